# SPDX-License-Identifier: GPL-3.0-or-later
"""Per-object ArtDef data: fit settings, what the last fit made, its summary.

Registered as ``Object.artdef``.  The record of what a fit created lets
*Clear Rig* and a re-fit remove exactly that and nothing of the user's.
"""

import bpy
from bpy.props import (BoolProperty, CollectionProperty, EnumProperty, FloatProperty,
                       FloatVectorProperty, IntProperty, IntVectorProperty, PointerProperty,
                       StringProperty)
from bpy.types import PropertyGroup

from ..artdef_addon.options import FitOptions


def enum_id(value: str) -> str:
    """Blender enum identifier of a canonical option value (the one spelling, upper-cased)."""
    return value.upper()


#: how far above an exclusive lower bound a Blender property's minimum sits
EXCLUSIVE_STEP = 1e-6


def _option_property(default, opt):
    """A ``bpy.props`` property for one :class:`FitOptions` field, from its declaration."""
    description = opt.description + (f" [{opt.unit}]" if opt.unit else "")
    if opt.choices:
        items = tuple((enum_id(c.value), c.label, c.description) for c in opt.choices)
        return EnumProperty(name=opt.label, items=items, default=enum_id(default), description=description)
    bounds = {k: getattr(opt, k) for k in ("soft_min", "soft_max", "max") if getattr(opt, k) is not None}
    if opt.auto:            # the count when its Auto switch (auto_property) is off
        return IntProperty(name=opt.label, default=int(opt.min or 0), min=int(opt.min or 0),
                           description=description + "; used when Auto is off",
                           **{k: int(v) for k, v in bounds.items()})
    if opt.optional:        # None ("off") is 0 in Blender, the lower bound is checked on use
        description += "; 0 turns it off"
        bounds["min"] = 0.0
    elif opt.min is not None:
        # a bound the value may not reach (memory budget > 0): Blender stops just above it, so that
        # no value the panel accepts fails the options' check
        bounds["min"] = opt.min + EXCLUSIVE_STEP if opt.min_exclusive else opt.min
    if opt.type is int:
        return IntProperty(name=opt.label, default=int(default), description=description,
                           **{k: int(v) for k, v in bounds.items()})
    return FloatProperty(name=opt.label, default=0.0 if default is None else float(default),
                         description=description, precision=2, **bounds)


def auto_name(name: str) -> str:
    """The switch property of an option that may be "auto" (``Option.auto``): on, chosen from the data."""
    return name + "_auto"


def _auto_property(opt):
    return BoolProperty(name=f"Auto {opt.label}", default=True,
                        description=f"Choose {opt.label} from the data; turn off to set the count yourself")


#: Settings of the Blender layer only (how the rig is made from a result, how the count is set)
_RIG_SETTINGS = {
    "links": IntProperty(name="Links", default=3, min=1, soft_max=64,
                         description="Number of rigid links (bones) to fit"),
    "auto_links": BoolProperty(name="Auto Links", default=False,
                               description="Choose the number of links from the data (where the "
                                           "articulation error stops dropping), up to Max Links; "
                                           "the reason is reported. Turn off to set Links yourself"),
    "load_index": IntProperty(name="Load Index", default=0, min=0,
                              description="Pseudo mode: the load point whose model becomes the rig"),
    "frames_per_field": IntProperty(
        name="Frames per Field", default=10, min=1, soft_max=100,
        description="Tracked scans: the replay action keys field p at frame (p+1) x this and the "
                    "rest pose at frame 0. Green's scans: the load sweep takes 2 x this frames per "
                    "load point and axis (0, probe load, 0). The scene's frame range is set to cover it"),
}

#: Every fit setting as a property: the rig settings above and one per FitOptions field
SETTING_NAMES = tuple(_RIG_SETTINGS) + tuple(FitOptions.declaration()) + tuple(
    auto_name(name) for name, (_, opt) in FitOptions.declaration().items() if opt.auto)


class FitSettings:
    """Mixin holding every fit setting as ``bpy.props`` annotations, shared by the Fit operator
    and the object's settings (the glTF add-on's pattern); the :class:`FitOptions` ones are made
    from the core's declaration by :func:`_option_property`."""
    __annotations__ = {**_RIG_SETTINGS,
                       **{name: _option_property(default, opt)
                          for name, (default, opt) in FitOptions.declaration().items()},
                       **{auto_name(name): _auto_property(opt)
                          for name, (_, opt) in FitOptions.declaration().items() if opt.auto}}


def options_from(settings) -> FitOptions:
    """The core's :class:`FitOptions` from a :class:`FitSettings` holder (operator or object
    settings); :class:`OptionsError` names a value out of range."""
    values = {}
    for name, (default, opt) in FitOptions.declaration().items():
        v = getattr(settings, name)
        if opt.choices:
            v = v.lower()
        elif opt.auto and getattr(settings, auto_name(name)):
            v = None
        elif opt.optional and v == 0:
            v = None
        values[name] = v
    return FitOptions(**values)


def store_options(settings, options: FitOptions) -> None:
    """Write ``options`` into a :class:`FitSettings` holder (the inverse of :func:`options_from`)."""
    for name, (default, opt) in FitOptions.declaration().items():
        v = getattr(options, name)
        if opt.auto:
            setattr(settings, auto_name(name), v is None)
            if v is None:
                continue
        if opt.choices:
            v = enum_id(v)
        elif v is None:
            v = 0.0
        setattr(settings, name, v)


class ARTDEF_PG_name(PropertyGroup):
    """A name recorded in a list (``name`` is built into PropertyGroup)."""


class ARTDEF_PG_file_mesh(PropertyGroup):
    """One mesh of the animated file a scan was sampled from (``name``: its object's name)."""
    fit: BoolProperty(name="Fit", default=True,
                      description="Sample this mesh into the scan (Resample Meshes), together with the "
                                  "other ticked meshes")
    vertices: IntProperty(name="Vertices", description="Vertices of the mesh as the file stores them")
    reason: StringProperty(name="Left Out",
                           description="Why the mesh cannot be fitted (static, no faces, a bone's custom "
                                       "shape); empty when it can")


class ARTDEF_PG_link_stats(PropertyGroup):
    """Fit quality of one link (``name`` is the bone/group name)."""
    link: IntProperty(name="Link")
    parent: IntProperty(name="Parent", default=-1,
                        description="Parent link (-1: root)")
    grounded: BoolProperty(name="Grounded",
                           description="The link is jointed to the fixed world")
    has_joint: BoolProperty(name="Has Joint",
                            description="The link has a joint (to its parent or the world)")
    joint_error: FloatProperty(name="Joint Error", precision=6,
                               description="RMS distance between where the two links of this "
                                           "joint move its centre, over the fields")
    rigid_residual: FloatProperty(name="Rigid Residual", precision=6,
                                  description="RMS over fields of the link's own rigid-motion "
                                              "residual on its vertices")
    triangles: IntProperty(name="Triangles")


class ARTDEF_PG_object(FitSettings, PropertyGroup):
    """Fit settings (shown in the panel, defaults for the operators), what the last fit made, its
    summary."""

    # ---- what the last fit created (used by Clear Rig / re-fit) ----
    rig: PointerProperty(type=bpy.types.Object, name="Rig",
                         description="Armature created by the last fit")
    made_basis: BoolProperty(default=False, description="The fit added the Basis shape key")
    shape_keys: CollectionProperty(type=ARTDEF_PG_name)
    groups: CollectionProperty(type=ARTDEF_PG_name)
    key_action: PointerProperty(type=bpy.types.Action,
                                description="Shape-key replay action made by the fit")
    key_action_previous: PointerProperty(type=bpy.types.Action,
                                         description="Shape-key action before the fit")
    old_parent: PointerProperty(type=bpy.types.Object)
    # ---- the meshes of the animated file the scan came from (Fields from File) ----
    file_meshes: CollectionProperty(type=ARTDEF_PG_file_mesh)
    file_meshes_index: IntProperty(name="Active File Mesh")
    old_parent_type: StringProperty(default='OBJECT')
    old_parent_bone: StringProperty()
    old_parent_inverse: FloatVectorProperty(size=16)
    set_frame_range: BoolProperty(default=False,
                                  description="The fit set the scene's frame range to its replay")
    replay_frame_range: IntVectorProperty(size=2, description="Frame range the fit set")
    old_frame_range: IntVectorProperty(size=2, description="Scene frame range before the fit")

    # ---- last fit summary (panel) ----
    has_fit: BoolProperty(default=False)
    fit_links: IntProperty(name="Links")
    fit_mode: StringProperty(name="Mode")
    fit_motion: StringProperty(name="Motion")
    fit_kind: StringProperty(name="Kind")
    fit_load_index: IntProperty(default=-1)
    fit_p_max: FloatProperty()
    fit_rms_articulation: FloatProperty(name="RMS articulation", precision=6,
                                        description="RMS error of the articulated motion alone")
    fit_rms_total: FloatProperty(name="RMS total", precision=6,
                                 description="RMS error of articulation plus residual shape keys")
    fit_seconds: FloatProperty(name="Time", unit='TIME_ABSOLUTE',
                               description="Wall time of the fit")
    fit_timings: StringProperty(description="Seconds per fitting stage")
    fit_summary: StringProperty(description="The core's summary of the fit")
    fit_articulation_percent: FloatProperty(
        name="Articulation error", precision=3, subtype='PERCENTAGE',
        description="Articulation-only reconstruction error, the Karni-Gotsman distortion "
                    "100 |X - X_art| / |X - X_centroid| over all fields, X_centroid each frame's centroid")
    fit_e_rms: FloatProperty(name="E_RMS", precision=6,
                             description="|X - X_art| / sqrt(3 N F): RMS error per coordinate, scene units")
    fit_rigid_percent: FloatProperty(name="One rigid motion", precision=3, subtype='PERCENTAGE',
                                     description="Distortion left by one rigid motion per frame")
    fit_linear_percent: FloatProperty(name="Linear model", precision=3, subtype='PERCENTAGE',
                                      description="Distortion left by the fields' best rank-k linear model "
                                                  "of about the rig's size")
    fit_linear_rank: IntProperty(name="Linear rank")
    fit_articulated: BoolProperty(default=True,
                                  description="False when the data do not look articulated (see the notes)")
    fit_residual_max: FloatProperty(
        name="Residual colour scale", precision=6,
        description="Per-vertex articulation residual shown red in 'artdef_residual_color' "
                    "(the largest one; blue = 0)")
    fit_residual_mean: FloatProperty(name="Mean vertex residual", precision=6)
    fit_diagonal: FloatProperty(name="Bounding-box diagonal", precision=6,
                                description="Scale of the scan, to read the errors against")
    fit_replay: StringProperty(description="Frames of the replay action (tracked scans) or of the load sweep (Green's scans)")
    fit_link_stats: CollectionProperty(type=ARTDEF_PG_link_stats)
    fit_link_reason: StringProperty(description="Why Auto Links chose this link count")
    fit_skin: StringProperty(name="Skin", description="Skin weights of the fit")
    fit_notes: StringProperty(description="The core's notes on the fit, one a line (for example "
                                          "why and how the reduced method was used)")
    fit_reduced: BoolProperty(description="The fit used the reduced method on patches")
    show_link_stats: BoolProperty(name="Per Link", default=False,
                                  description="Show the fit quality of every link")


classes = (ARTDEF_PG_name, ARTDEF_PG_file_mesh, ARTDEF_PG_link_stats, ARTDEF_PG_object)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)
    bpy.types.Object.artdef = PointerProperty(type=ARTDEF_PG_object)


def unregister():
    del bpy.types.Object.artdef
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
