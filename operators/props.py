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

from ..artdef_addon.files import MAX_AUTO_LINKS  # bounded work: the command line's --max-links limit

MODE_ITEMS = (
    ('GLOBAL', "Global", "One articulated model for all fields (the main path)"),
    ('PSEUDO', "Pseudo", "Fit each load point separately and build the rig of one load "
                         "point's model (Load Index)"),
)
SKIN_ITEMS = (
    ('AUTO', "Auto", "Refined for tracked scans, seam-blended for Green's scans"),
    ('SEAM', "Seam", "Weights blended across the seams between links"),
    ('REFINED', "Refined", "Per-vertex convex weights (at most 4 nearby links) solved by least "
                           "squares over all fields: reproduces the capture closely with few bones"),
)
REDUCE_ITEMS = (
    ('AUTO', "Auto", "Use the reduced method on patches only when the full method would need more "
                     "memory than the Memory Budget (the fit then says so)"),
    ('ON', "On", "Always use the reduced method: the method on small patches of triangles whose "
                 "motions agree, seams refined per triangle (fast, bounded memory)"),
    ('OFF', "Off", "Always use the paper's full method over all triangle pairs (memory grows "
                   "with the square of the triangle count)"),
)
#: Memory Budget: the UI drags down to ``soft_min``; a script may go lower (tests, tiny scans).
BUDGET_MIN, BUDGET_SOFT_MIN = 0.001, 0.1
MEMORY_BUDGET_DESCRIPTION = (
    "Most memory the fit may use, in GB (2^30 bytes). With Reduced Method 'Auto' a scan whose "
    "full method would need more switches to the reduced method on patches instead of running "
    "out of memory; it also sets how many patches the reduced method uses")
MOTION_ITEMS = (
    ('ROBUST', "Robust", "Each link moves with its motion centroid: the member triangle whose "
                         "motion agrees exactly with at least half of the link (a medoid that "
                         "stays correct with up to 50% outlying triangles)"),
    ('LSQ', "Least Squares", "Least-squares rigid motion fitted to all the link's triangles "
                             "(for comparison)"),
)


class ARTDEF_PG_name(PropertyGroup):
    """A name recorded in a list (``name`` is built into PropertyGroup)."""


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


class ARTDEF_PG_object(PropertyGroup):
    # ---- fit settings (shown in the panel, defaults for the operators) ----
    links: IntProperty(
        name="Links", default=3, min=1, soft_max=64,
        description="Number of rigid links (bones) to fit")
    mode: EnumProperty(name="Mode", items=MODE_ITEMS, default='GLOBAL',
                       description="Global fit, or per-load-point pseudo-articulation")
    motion: EnumProperty(name="Motion", items=MOTION_ITEMS, default='ROBUST',
                         description="How each link's rigid motion is estimated")
    p_max: FloatProperty(
        name="Max Hardening", default=0.0, min=0.0, soft_max=20.0,
        description="Strain hardening limit p_max (in units of the probe load, must be > 1); "
                    "0 turns hardening off (linear response)")
    load_index: IntProperty(
        name="Load Index", default=0, min=0,
        description="Pseudo mode: which load point's model becomes the rig")
    auto_links: BoolProperty(
        name="Auto Links", default=False,
        description="Choose the number of links from the data (where the articulation error "
                    "stops dropping), up to Max Links; turn off to set Links yourself")
    max_links: IntProperty(name="Max Links", default=30, min=1, max=MAX_AUTO_LINKS, soft_max=64,
                           description="Auto Links: the largest link count tried")
    skin: EnumProperty(name="Skin", items=SKIN_ITEMS, default='AUTO',
                       description="How the skin weights are made")
    frames_per_field: IntProperty(
        name="Frames per Field", default=10, min=1, soft_max=100,
        description="Tracked scans: the replay action keys field p at frame "
                    "(p+1) x this, the rest pose at frame 0. Green's scans: the load sweep "
                    "takes 2 x this frames per load point and axis (0, probe load, 0)")
    reduce: EnumProperty(name="Reduced Method", items=REDUCE_ITEMS, default='AUTO',
                         description="Segment small patches of triangles instead of every "
                                     "triangle (large scans)")
    memory_budget: FloatProperty(name="Memory Budget", default=2.0, min=BUDGET_MIN,
                                 soft_min=BUDGET_SOFT_MIN, soft_max=64.0, precision=2,
                                 description=MEMORY_BUDGET_DESCRIPTION)

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


classes = (ARTDEF_PG_name, ARTDEF_PG_link_stats, ARTDEF_PG_object)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)
    bpy.types.Object.artdef = PointerProperty(type=ARTDEF_PG_object)


def unregister():
    del bpy.types.Object.artdef
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
