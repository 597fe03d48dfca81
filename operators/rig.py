# SPDX-License-Identifier: GPL-3.0-or-later
"""Build (and remove) the Blender rig of a fit.

Everything here runs on the main thread *after* the fit has been computed,
so a failed or cancelled fit never reaches this module.

What a fit creates, all recorded in ``Object.artdef`` so that Clear Rig and a
re-fit remove exactly this:

* vertex groups ``artdef_link_XX`` (the seam-blended weights);
* the armature object ``<mesh>_artdef_rig`` with one deform bone per link
  (same names as the groups), the mesh parented to it and an Armature
  modifier ``ArtDef Armature`` at the top of the stack;
* shape keys ``artdef_field_XXX`` holding the residual (and ``Basis`` if the
  mesh had none);
* Green's scans: load empties ``artdef_load_K`` (children of the armature)
  whose ``location`` is the load vector, and a load-sweep action per empty:
  load k along axis d (field c = 3k+d) rises from 0 to the probe load p̂ and
  back, rest at frame 2c·frames_per_field, +p̂ at (2c+1)·frames_per_field.
  The loads drive the shape keys and, per link, a hidden non-deforming helper
  bone ``artdef_link_XX_load`` (bone collection ``ArtDef Load Helpers``, same
  rest frame and parent as the link bone); the link bone's Copy Transforms
  constraint ``ArtDef Load`` puts the helper's local transform before its
  own, so animator keys on the link bones add to the load-driven motion;
* tracked scans: actions replaying the input fields on the link bones, field
  p at frame (p+1)·frames_per_field (frame 0 = rest).  Either way the scene's
  frame range is set to cover the animation (restored by Clear Rig if still
  unchanged);
* the face colour attribute ``artdef_links`` (active), the per-vertex
  articulation residual ``artdef_residual`` (FLOAT, POINT) and its colours
  ``artdef_residual_color`` (FLOAT_COLOR, POINT, blue = 0 → red = largest).
"""

import colorsys
import math

import bpy
import numpy as np
from mathutils import Matrix, Vector

from ..artdef_addon import model as _model
from . import compat, io

GROUP_FMT = "artdef_link_{:02d}"
HELPER_FMT = GROUP_FMT + "_load"   # Green's scans: the load-driven helper bone of a link
HELPER_COLLECTION = "ArtDef Load Helpers"
LOAD_CONSTRAINT = "ArtDef Load"
KEY_PREFIX = "artdef_field_"
LOAD_FMT = "artdef_load_{}"
MODIFIER_NAME = "ArtDef Armature"
COLOR_ATTR = "artdef_links"
RESIDUAL_ATTR = "artdef_residual"
RESIDUAL_COLOR_ATTR = "artdef_residual_color"
SLIDER_RANGE = 10.0          # Blender's hard limit for shape key sliders
#: Longest driver expression written (Blender keeps 255 characters).  Longer
#: sums are split into partial sums held in custom properties of the armature.
MAX_EXPRESSION = 250
#: a Green's rig's posing version, stored on its armature (``RIG_VERSION_PROP``): 2 = first-order
#: and bump residual keys (model.greens_keys); a Green's rig without it was built with the probe
#: residual scaled linearly and is told to be refitted (:func:`stale_greens_rig`)
RIG_VERSION = 2
RIG_VERSION_PROP = "artdef_rig_version"
_AXES = "xyz"


# --------------------------------------------------------------------------
# colours
# --------------------------------------------------------------------------

# Twelve clearly different sRGB colours for the first links, then golden-ratio hues.
_PALETTE = (
    (0.90, 0.45, 0.20), (0.25, 0.50, 0.90), (0.45, 0.78, 0.30), (0.85, 0.25, 0.55),
    (0.95, 0.82, 0.25), (0.35, 0.80, 0.85), (0.55, 0.35, 0.80), (0.80, 0.22, 0.22),
    (0.60, 0.48, 0.32), (0.20, 0.62, 0.55), (0.97, 0.62, 0.78), (0.70, 0.88, 0.55),
)


def link_colours(n):
    """(n, 4) sRGB colours, well separated, deterministic."""
    out = np.ones((n, 4))
    for i in range(n):
        if i < len(_PALETTE):
            out[i, :3] = _PALETTE[i]
        else:
            h = (0.05 + i * 0.618033988749895) % 1.0
            out[i, :3] = colorsys.hsv_to_rgb(h, 0.5 + 0.25 * (i % 2), 0.95 - 0.15 * ((i // 2) % 2))
    return out


def write_link_colours(mesh, tri_labels, tri_polygons):
    """Colour polygons by link in the CORNER byte colour attribute ``artdef_links``."""
    n_poly = len(mesh.polygons)
    poly_label = np.zeros(n_poly, dtype=np.int64)
    poly_label[np.asarray(tri_polygons)] = np.asarray(tri_labels)
    totals = np.empty(n_poly, dtype=np.int32)
    mesh.polygons.foreach_get("loop_total", totals)
    corner_label = np.repeat(poly_label, totals)
    colours = link_colours(int(poly_label.max()) + 1 if n_poly else 1)[corner_label]
    old = mesh.color_attributes.get(COLOR_ATTR)
    if old is not None:
        mesh.color_attributes.remove(old)
    attr = mesh.color_attributes.new(COLOR_ATTR, 'BYTE_COLOR', 'CORNER')
    attr.data.foreach_set("color_srgb", np.ascontiguousarray(colours, dtype=np.float32).ravel())
    set_active_colour(mesh, COLOR_ATTR)
    return mesh.color_attributes.get(COLOR_ATTR)


def remove_link_colours(mesh):
    attr = mesh.color_attributes.get(COLOR_ATTR)
    if attr is not None:
        mesh.color_attributes.remove(attr)


def set_active_colour(mesh, name):
    """Make colour attribute ``name`` the active and the rendered one."""
    attrs = mesh.color_attributes
    attr = attrs.get(name)
    if attr is None:
        return
    attrs.active_color = attr
    for i, a in enumerate(attrs):
        if a.name == name:
            attrs.render_color_index = i


def write_residual(mesh, values, scale):
    """Per-vertex residual magnitude as FLOAT ``artdef_residual`` and as colours
    ``artdef_residual_color`` (blue at 0 → red at ``scale``).  The active colour
    attribute is left as it was (the link colours after a fit)."""
    from .fitquality import ramp
    values = np.ascontiguousarray(values, dtype=np.float32)
    active = mesh.color_attributes.active_color
    active_name = active.name if active is not None else None
    remove_residual(mesh)
    attr = mesh.attributes.new(RESIDUAL_ATTR, 'FLOAT', 'POINT')
    attr.data.foreach_set("value", values)
    colours = ramp(values / scale if scale > 0 else np.zeros(len(values)))
    col = mesh.color_attributes.new(RESIDUAL_COLOR_ATTR, 'FLOAT_COLOR', 'POINT')
    col.data.foreach_set("color_srgb", np.ascontiguousarray(colours, dtype=np.float32).ravel())
    if active_name is not None:
        set_active_colour(mesh, active_name)


def remove_residual(mesh):
    for coll, name in ((mesh.color_attributes, RESIDUAL_COLOR_ATTR), (mesh.attributes, RESIDUAL_ATTR)):
        attr = coll.get(name)
        if attr is not None:
            coll.remove(attr)


# --------------------------------------------------------------------------
# animation helpers (the version-dependent part lives in compat.new_action)
# --------------------------------------------------------------------------

def _new_action(id_data, name):
    """Assign a new action to ``id_data``; return it and a function making F-Curves."""
    action, new_fcurve = compat.new_action(id_data, name)
    action["artdef_made"] = True
    return action, new_fcurve


def _key_curve(fcurve, frames, values):
    n = len(frames)
    fcurve.keyframe_points.add(n)
    co = np.empty((n, 2), dtype=np.float32)
    co[:, 0] = frames
    co[:, 1] = values
    fcurve.keyframe_points.foreach_set("co", co.ravel())
    for kp in fcurve.keyframe_points:
        kp.interpolation = 'LINEAR'
    fcurve.update()


# --------------------------------------------------------------------------
# drivers
# --------------------------------------------------------------------------

def _driver_fcurve(fcurve):
    """``fcurve`` with no keyframes, so its value is the driver's value itself.

    ``driver_add()`` gives the F-Curve two keyframes (0, 0) and (1, 1); with
    them Blender snaps a driver value within about 1e-4 of a key to the key
    (measured: 8.3e-5 became 0 and 1e-4 became 0), which zeroes small bone
    angles and shape key values at small loads.
    """
    points = fcurve.keyframe_points
    while len(points):
        points.remove(points[len(points) - 1], fast=True)
    return fcurve


def _num(x):
    return "%.9g" % float(x)


def _linear_terms(coeffs, var_names):
    return [f"{_num(c)}*{v}" for c, v in zip(coeffs, var_names) if c != 0.0]


def _join(terms):
    if not terms:
        return "0"
    return "+".join(terms).replace("+-", "-")


def _add_load_vars(driver, empties, which):
    """Driver variables ``x<k>``, ``y<k>``, ``z<k>`` reading load empty k's location."""
    for k, d in which:
        var = driver.variables.new()
        var.name = f"{_AXES[d]}{k}"
        var.type = 'SINGLE_PROP'
        var.targets[0].id = empties[k]
        var.targets[0].data_path = f"location[{d}]"


def _drive_linear(owner, path, index, coeffs, empties, arm_obj, tag):
    """Drive ``owner.path[index]`` = sum_c coeffs[c] * load_flat[c].

    One simple expression when it fits Blender's 255 characters, otherwise
    partial sums in custom properties of ``arm_obj`` added by a SUM driver.
    """
    names = [f"{_AXES[c % 3]}{c // 3}" for c in range(len(coeffs))]
    used = [c for c in range(len(coeffs)) if coeffs[c] != 0.0]
    chunks, current, length = [], [], 0
    for c in used:
        term = len(_num(coeffs[c])) + len(names[c]) + 2
        if current and length + term > MAX_EXPRESSION:
            chunks.append(current)
            current, length = [], 0
        current.append(c)
        length += term
    if current or not chunks:
        chunks.append(current)

    def fill(driver, cs):
        driver.type = 'SCRIPTED'
        _add_load_vars(driver, empties, [(c // 3, c % 3) for c in cs])
        driver.expression = _join(_linear_terms([coeffs[c] for c in cs], [names[c] for c in cs]))

    fcurve = _driver_fcurve(owner.driver_add(path, index) if index is not None
                            else owner.driver_add(path))
    if len(chunks) == 1:
        fill(fcurve.driver, chunks[0])
        return [fcurve.driver]
    drivers = []
    fcurve.driver.type = 'SUM'
    for i, cs in enumerate(chunks):
        prop = f"artdef_sum_{tag}_{i}"
        arm_obj[prop] = 0.0
        sub = _driver_fcurve(arm_obj.driver_add(f'["{prop}"]'))
        fill(sub.driver, cs)
        drivers.append(sub.driver)
        var = fcurve.driver.variables.new()
        var.name = f"s{i}"
        var.type = 'SINGLE_PROP'
        var.targets[0].id = arm_obj
        var.targets[0].data_path = f'["{prop}"]'
    drivers.append(fcurve.driver)
    return drivers


def shape_value_expression(k, d, probe_load, p_max):
    """Simple expression of first-order shape key value c = 3k+d from load k (x<k>, y<k>, z<k>):
    h(p_k)[d] / (p̂ σ), h the strain-hardening map and σ its slope at zero (identity and 1 when
    off; :func:`artdef_addon.model.greens_key_values`)."""
    x, y, z = (f"{a}{k}" for a in _AXES)
    v = f"{_AXES[d]}{k}"
    if p_max is None:
        return f"{_num(1.0 / probe_load)}*{v}"
    # s~ = p_max (1 - q^s), q = (p_max-1)/p_max, s = |p|/p̂  ->  q^s = exp(|p| ln(q)/p̂)
    rate = math.log((p_max - 1.0) / p_max) / probe_load
    n = f"sqrt({x}*{x}+{y}*{y}+{z}*{z})"
    return f"{_num(p_max / _model.hardening_slope(p_max))}*(1-exp({_num(rate)}*{n}))*{v}/max({n},1e-30)"


def bump_value_expression(k, d, probe_load):
    """Simple expression of bump shape key value c = 3k+d from load k: (p_kd/p̂)² s⁴ e^(6(1−s)),
    s = |p_k|/p̂ (:data:`artdef_addon.model.BUMP_POWER` = 6; :func:`artdef_addon.model.greens_key_values`)."""
    x, y, z = (f"{a}{k}" for a in _AXES)
    v = f"{_AXES[d]}{k}"
    n2 = f"({x}*{x}+{y}*{y}+{z}*{z})"
    i2 = _num(1.0 / probe_load ** 2)
    power = _model.BUMP_POWER
    return (f"{v}*{v}*{i2}*" + "*".join([f"{n2}*{i2}"] * ((power - 2) // 2))
            + f"*exp({_num(power)}-{_num(power / probe_load)}*sqrt({n2}))")


# --------------------------------------------------------------------------
# record keeping / clearing
# --------------------------------------------------------------------------

def has_rig(obj):
    st = obj.artdef
    return bool(st.rig or len(st.groups) or len(st.shape_keys) or obj.modifiers.get(MODIFIER_NAME))


def stale_greens_rig(obj) -> bool:
    """True when ``obj``'s rig is a Green's rig (load helper bones) built before
    :data:`RIG_VERSION`: it still poses as it did (its keys and drivers are in the file), but its
    residual keys were scaled linearly from the probe load, so it is wrong to first order between
    and below the probe loads; the panel says to refit it."""
    arm = obj.artdef.rig
    if arm is None or arm.type != 'ARMATURE' or arm.data.bones.get(HELPER_FMT.format(0)) is None:
        return False
    return int(arm.get(RIG_VERSION_PROP, 1)) < RIG_VERSION


def _remove_object(ob):
    data = ob.data
    ad = ob.animation_data
    actions = [ad.action] if ad is not None and ad.action is not None else []
    if ad is not None:  # a several-clip replay's NLA tracks
        actions += [s.action for t in ad.nla_tracks for s in t.strips
                    if s.action is not None and s.action not in actions]
    bpy.data.objects.remove(ob, do_unlink=True)
    if data is not None and data.users == 0:
        if isinstance(data, bpy.types.Armature):
            bpy.data.armatures.remove(data)
    for action in actions:
        if action.users == 0 and action.get("artdef_made"):
            bpy.data.actions.remove(action)


def _restore_frame_range(st, scene):
    """Put back the scene frame range the fit replaced, unless the user changed it since."""
    if st.set_frame_range and scene is not None:
        if (scene.frame_start, scene.frame_end) == tuple(st.replay_frame_range):
            start, end = st.old_frame_range
            scene.frame_start = start
            scene.frame_end = max(end, start)
    st.set_frame_range = False


def _remove_clip_tracks(keys):
    """NLA tracks of a several-clip replay on the shape keys (their actions are
    ArtDef's), and those actions; the armature's go with the armature."""
    ad = keys.animation_data if keys is not None else None
    if ad is None:
        return
    for track in list(ad.nla_tracks):
        if track.name.startswith(STASH_PREFIX):
            continue                # the previous rig's, set aside during a re-fit (stash_rig)
        actions = [s.action for s in track.strips]
        if actions and all(a is not None and a.get("artdef_made") for a in actions):
            ad.nla_tracks.remove(track)
            for a in actions:
                if a.users == 0:
                    bpy.data.actions.remove(a)


def owns_rig(obj, arm) -> bool:
    """Whether the ArtDef armature ``arm`` (``obj``'s recorded rig) is ``obj``'s own: a duplicate of a
    fitted mesh records the original's armature (``artdef_owner``), which stays the original's."""
    if arm is None or not arm.get("artdef_rig"):
        return False
    owner = arm.get("artdef_owner")
    return owner is None or owner == obj


def clear_rig(obj, scene=None):
    """Remove everything the last fit created on/around mesh object ``obj``.

    ``scene`` (default: the context's) gets its frame range back if the fit set it.
    """
    st = obj.artdef
    _restore_frame_range(st, scene if scene is not None else bpy.context.scene)
    mesh = obj.data
    world = obj.matrix_world.copy()
    arm = st.rig
    # Parent back as before the fit (keeping the mesh where it is).
    if arm is not None and obj.parent == arm:
        obj.parent = st.old_parent
        if st.old_parent is not None:
            obj.parent_type = st.old_parent_type or 'OBJECT'
            if st.old_parent_bone:
                obj.parent_bone = st.old_parent_bone
            obj.matrix_parent_inverse = Matrix([st.old_parent_inverse[i * 4:i * 4 + 4]
                                                for i in range(4)])
        else:
            obj.matrix_parent_inverse = Matrix.Identity(4)
        obj.matrix_world = world
    mod = obj.modifiers.get(MODIFIER_NAME)
    if mod is not None:
        obj.modifiers.remove(mod)
    if owns_rig(obj, arm):
        # a duplicate of a fitted mesh points at the original's rig: that one stays
        for child in list(arm.children):
            if child.get("artdef_load") is not None:
                _remove_object(child)
        _remove_object(arm)
    st.rig = None
    st.old_parent = None
    st.old_parent_bone = ""
    for item in st.groups:
        vg = obj.vertex_groups.get(item.name)
        if vg is not None:
            obj.vertex_groups.remove(vg)
    st.groups.clear()
    keys = mesh.shape_keys
    _remove_clip_tracks(keys)
    if keys is not None:
        ad = keys.animation_data
        if ad is not None:
            for item in st.shape_keys:
                path = f'key_blocks["{item.name}"].value'
                for fc in list(ad.drivers):
                    if fc.data_path == path:
                        ad.drivers.remove(fc)
            if st.key_action is not None and ad.action == st.key_action:
                ad.action = st.key_action_previous
        for item in st.shape_keys:
            kb = keys.key_blocks.get(item.name)
            if kb is not None:
                obj.shape_key_remove(kb)
        if st.made_basis and mesh.shape_keys is not None and len(mesh.shape_keys.key_blocks) == 1:
            obj.shape_key_clear()
    key_action = st.key_action
    st.key_action = None  # the pointer itself counts as a user
    st.key_action_previous = None
    if key_action is not None and key_action.users == 0 and key_action.get("artdef_made"):
        bpy.data.actions.remove(key_action)
    st.shape_keys.clear()
    st.made_basis = False
    remove_link_colours(mesh)
    remove_residual(mesh)
    st.has_fit = False


# --------------------------------------------------------------------------
# a re-fit: the previous rig is set aside while the new one is built
# --------------------------------------------------------------------------

#: Prefix of the temporary names of the previous rig's pieces while a new rig is built
#: (names starting with "." are hidden from most of Blender's lists).
STASH_PREFIX = ".artdef_prev_"

_RECORD = ("made_basis", "key_action", "key_action_previous", "old_parent", "old_parent_type",
           "old_parent_bone", "old_parent_inverse", "set_frame_range", "replay_frame_range",
           "old_frame_range", "has_fit")
_TRANSFORM = ("location", "rotation_mode", "rotation_euler", "rotation_quaternion",
              "rotation_axis_angle", "scale")


def _copy(value):
    if isinstance(value, (str, bpy.types.ID)) or value is None:
        return value
    return tuple(value) if hasattr(value, "__len__") else value


def _stash_name(name):
    return STASH_PREFIX + name


class RigStash:
    """What :func:`stash_rig` set aside: the previous rig (or Preview Links' colours), renamed
    out of the new build's way; :func:`restore_rig` puts it back, :func:`drop_stash` removes it."""

    def __init__(self, obj):
        self.obj = obj
        self.record = {}
        self.rig = None
        self.owned = False
        self.ids = []              # (ID, its name): the previous rig's datablocks, renamed
        self.groups = []           # (temporary name, name) of vertex groups
        self.keys = []             # (temporary name, name) of shape keys
        self.tracks = []           # (temporary name, name) of the shape keys' clip tracks
        self.attrs = []            # (temporary name, name) of colour / residual attributes
        self.modifier = None       # (temporary name, index)
        self.parent = None         # (parent, type, bone, parent inverse, transform)
        self.frames = None         # the scene and its (start, end)
        self.key_action = None     # (action, slot) the shape keys played
        self.key_animdata = False  # the shape keys had animation data
        self.active = None         # (active group, active shape key, active attribute,
                                   #  active colour, render colour index)


def _rig_ids(arm):
    """The datablocks of ArtDef armature ``arm``: itself, its data, its load empties and the
    actions they play (their own, as the Clear Rig removes them)."""
    out = [arm]
    if arm.data is not None:
        out.append(arm.data)
    for ob in [arm] + [c for c in arm.children if c.get("artdef_load") is not None]:
        if ob is not arm:
            out.append(ob)
        ad = ob.animation_data
        if ad is None:
            continue
        for action in [ad.action] + [s.action for t in ad.nla_tracks for s in t.strips]:
            if action is not None and action.get("artdef_made") and action not in out:
                out.append(action)    # once: the active action is also a clip's strip
    return out


def stash_rig(obj, scene):
    """Set aside what a fit of ``obj`` would replace — the previous rig, or the link colours of
    Preview Links — so that a failed build can put it back (:func:`restore_rig`) and a finished
    one removes it (:func:`drop_stash`). Afterwards ``obj`` looks unfitted to :func:`build_rig`:
    the previous rig's pieces are renamed out of the way (``STASH_PREFIX``), the mesh is parented
    as before the previous fit and the scene has its frame range back; nothing is deleted."""
    st, mesh = obj.artdef, obj.data
    stash = RigStash(obj)
    stash.record = {name: _copy(getattr(st, name)) for name in _RECORD}
    stash.record["groups"] = [item.name for item in st.groups]
    stash.record["shape_keys"] = [item.name for item in st.shape_keys]
    colours = mesh.color_attributes
    stash.active = (obj.vertex_groups.active_index, obj.active_shape_key_index,
                    mesh.attributes.active.name if mesh.attributes.active is not None else None,
                    colours.active_color.name if colours.active_color is not None else None,
                    colours.render_color_index)
    if scene is not None:
        stash.frames = (scene, scene.frame_start, scene.frame_end)
        _restore_frame_range(st, scene)
    # parent: as clear_rig leaves it (the new armature copies the mesh's parent and transform)
    arm = st.rig
    stash.rig = arm
    if arm is not None and obj.parent == arm:
        stash.parent = (obj.parent, obj.parent_type, obj.parent_bone, obj.matrix_parent_inverse.copy(),
                        {name: _copy(getattr(obj, name)) for name in _TRANSFORM})
        world = obj.matrix_world.copy()
        obj.parent = st.old_parent
        if st.old_parent is not None:
            obj.parent_type = st.old_parent_type or 'OBJECT'
            if st.old_parent_bone:
                obj.parent_bone = st.old_parent_bone
            obj.matrix_parent_inverse = Matrix([st.old_parent_inverse[i * 4:i * 4 + 4] for i in range(4)])
        else:
            obj.matrix_parent_inverse = Matrix.Identity(4)
        obj.matrix_world = world
    mod = obj.modifiers.get(MODIFIER_NAME)
    if mod is not None:
        index = list(obj.modifiers).index(mod)
        mod.name = _stash_name(MODIFIER_NAME)
        stash.modifier = (mod.name, index)
    stash.owned = owns_rig(obj, arm)
    if stash.owned:   # a duplicate's rig is the original's: it stays as it is
        for db in _rig_ids(arm):
            stash.ids.append((db, db.name))
            db.name = _stash_name(db.name)
    for name in stash.record["groups"]:
        vg = obj.vertex_groups.get(name)
        if vg is not None:
            vg.name = _stash_name(name)
            stash.groups.append((vg.name, name))
    keys = mesh.shape_keys
    if keys is not None:
        ad = keys.animation_data
        stash.key_animdata = ad is not None
        if ad is not None:
            stash.key_action = (ad.action, getattr(ad, "action_slot", None))
            if st.key_action is not None and ad.action == st.key_action:
                ad.action = st.key_action_previous   # the action the new replay will record
            made = [st.key_action] if st.key_action is not None else []
            for track in ad.nla_tracks:
                actions = [s.action for s in track.strips]
                if actions and all(a is not None and a.get("artdef_made") for a in actions):
                    name = track.name
                    track.name = _stash_name(name)
                    stash.tracks.append((track.name, name))
                    made += [a for a in actions if a not in made]
            for action in made:      # the replay's shape-key actions: out of the new ones' names
                if action.get("artdef_made") and all(action is not db for db, _ in stash.ids):
                    stash.ids.append((action, action.name))
                    action.name = _stash_name(action.name)
        for name in stash.record["shape_keys"]:
            kb = keys.key_blocks.get(name)
            if kb is not None:
                kb.name = _stash_name(name)     # Blender renames the drivers' and actions' paths too
                stash.keys.append((kb.name, name))
    for name in (COLOR_ATTR, RESIDUAL_COLOR_ATTR, RESIDUAL_ATTR):
        attr = mesh.attributes.get(name)
        if attr is not None:
            attr.name = _stash_name(name)
            stash.attrs.append((attr.name, name))
    st.rig = None
    st.old_parent = None
    st.old_parent_bone = ""
    st.groups.clear()
    st.shape_keys.clear()
    st.key_action = None
    st.key_action_previous = None
    st.made_basis = False
    st.has_fit = False
    return stash


def _names_back(collection, renamed):
    """Give the items of a Blender ``collection`` their names back: ``renamed`` holds (temporary
    name, name) pairs of :func:`stash_rig` (an item since removed is passed over)."""
    for tmp, name in renamed:
        item = collection.get(tmp)
        if item is not None:
            item.name = name


def restore_rig(stash):
    """Put back what :func:`stash_rig` set aside, after the new build's pieces were removed
    (:func:`clear_rig` and :func:`remove_new_datablocks`)."""
    obj = stash.obj
    st, mesh = obj.artdef, obj.data
    for db, name in stash.ids:
        db.name = name
    _names_back(obj.vertex_groups, stash.groups)
    keys = mesh.shape_keys
    if keys is not None:
        _names_back(keys.key_blocks, stash.keys)
        ad = keys.animation_data
        if ad is not None:
            _names_back(ad.nla_tracks, stash.tracks)
            if stash.key_action is not None:
                action, slot = stash.key_action
                ad.action = action
                if slot is not None and getattr(ad, "action_slot", None) != slot:
                    ad.action_slot = slot
            elif (not stash.key_animdata and ad.action is None and not len(ad.drivers)
                  and not len(ad.nla_tracks)):
                keys.animation_data_clear()
    _names_back(mesh.attributes, stash.attrs)
    if stash.modifier is not None:
        mod = obj.modifiers.get(stash.modifier[0])
        if mod is not None:
            mod.name = MODIFIER_NAME
            index = list(obj.modifiers).index(mod)
            target = min(stash.modifier[1], len(obj.modifiers) - 1)
            if index != target:
                obj.modifiers.move(index, target)
    if stash.parent is not None:
        parent, parent_type, bone, inverse, transform = stash.parent
        obj.parent = parent
        obj.parent_type = parent_type
        if bone:
            obj.parent_bone = bone
        obj.matrix_parent_inverse = inverse
        for name, value in transform.items():
            setattr(obj, name, value)
    st.rig = stash.rig
    for name in _RECORD:
        setattr(st, name, stash.record[name])
    st.groups.clear()
    for name in stash.record["groups"]:
        st.groups.add().name = name
    st.shape_keys.clear()
    for name in stash.record["shape_keys"]:
        st.shape_keys.add().name = name
    group, key, attribute, colour, render = stash.active
    obj.vertex_groups.active_index = group
    obj.active_shape_key_index = key
    if attribute is not None and mesh.attributes.get(attribute) is not None:
        mesh.attributes.active = mesh.attributes[attribute]
    if colour is not None:
        set_active_colour(mesh, colour)
    if render < len(mesh.color_attributes):
        mesh.color_attributes.render_color_index = render
    if stash.frames is not None:
        scene, start, end = stash.frames
        if start > scene.frame_end:
            scene.frame_end = end
            scene.frame_start = start
        else:
            scene.frame_start = start
            scene.frame_end = end


def drop_stash(stash):
    """Remove what :func:`stash_rig` set aside, once the new rig is built."""
    obj = stash.obj
    st, mesh = obj.artdef, obj.data
    if stash.modifier is not None:
        mod = obj.modifiers.get(stash.modifier[0])
        if mod is not None:
            obj.modifiers.remove(mod)
    if stash.owned and stash.rig is not None:
        arm = stash.rig
        for child in list(arm.children):
            if child.get("artdef_load") is not None:
                _remove_object(child)
        _remove_object(arm)
    for tmp, _ in stash.groups:
        vg = obj.vertex_groups.get(tmp)
        if vg is not None:
            obj.vertex_groups.remove(vg)
    keys = mesh.shape_keys
    actions = [stash.record["key_action"]] if stash.record.get("key_action") is not None else []
    if keys is not None:
        ad = keys.animation_data
        if ad is not None:
            for tmp, _ in stash.tracks:
                track = ad.nla_tracks.get(tmp)
                if track is not None:
                    actions += [s.action for s in track.strips if s.action is not None]
                    ad.nla_tracks.remove(track)
            paths = {f'key_blocks["{tmp}"].value' for tmp, _ in stash.keys}
            for fc in list(ad.drivers):
                if fc.data_path in paths:
                    ad.drivers.remove(fc)
        for tmp, _ in stash.keys:
            kb = keys.key_blocks.get(tmp)
            if kb is not None:
                obj.shape_key_remove(kb)
    if stash.record.get("made_basis"):
        st.made_basis = True      # the previous fit's Basis is the new rig's now
    for action in {a.session_uid: a for a in actions}.values():   # the previous replay's
        if action.users == 0 and action.get("artdef_made"):
            bpy.data.actions.remove(action)
    for tmp, _ in stash.attrs:
        attr = mesh.attributes.get(tmp)
        if attr is not None:
            mesh.attributes.remove(attr)


# --------------------------------------------------------------------------
# datablocks: a failed build leaves none behind
# --------------------------------------------------------------------------

#: ID collections of ``bpy.data`` that a rig build could never create and that
#: must not be touched (the UI's own).
_UI_COLLECTIONS = {"window_managers", "screens", "workspaces", "libraries"}


def id_collections():
    """Names of every ``bpy.data`` collection of datablocks (objects, meshes,
    armatures, actions, images, texts, shape_keys, ...), read from RNA so that
    a collection added by a later Blender is counted too."""
    names = []
    for prop in bpy.data.bl_rna.properties:
        if prop.type != 'COLLECTION':
            continue
        rna = prop.fixed_type
        while rna is not None and rna.identifier != "ID":
            rna = rna.base
        if rna is not None:
            names.append(prop.identifier)
    return names


def datablock_snapshot():
    """``{collection: set of session_uid}`` of every datablock now in ``bpy.data``."""
    return {name: {db.session_uid for db in getattr(bpy.data, name)}
            for name in id_collections() if name not in _UI_COLLECTIONS}


def remove_new_datablocks(before):
    """Remove every datablock not in snapshot ``before``; return their names."""
    new = []
    for name, uids in before.items():
        new += [db for db in getattr(bpy.data, name) if db.session_uid not in uids]
    names = [f"{db.__class__.__name__} '{db.name}'" for db in new]
    if new:
        bpy.data.batch_remove(new)
    return names


# --------------------------------------------------------------------------
# building
# --------------------------------------------------------------------------

def _fill_vertex_group(obj, name, weights):
    """Vertex group ``name`` with exact float weights (fast path: attribute_convert)."""
    mesh = obj.data
    old = mesh.attributes.get(name)
    if old is not None:
        mesh.attributes.remove(old)
    attr = mesh.attributes.new(name, 'FLOAT', 'POINT')
    ok = False
    if attr is not None and attr.name == name:
        attr.data.foreach_set("value", np.ascontiguousarray(weights, dtype=np.float32))
        mesh.attributes.active = attr
        try:
            with bpy.context.temp_override(object=obj, active_object=obj):
                ok = 'FINISHED' in bpy.ops.geometry.attribute_convert(mode='VERTEX_GROUP')
        except RuntimeError:
            ok = False
        left = mesh.attributes.get(name)
        if left is not None and left.domain == 'POINT' and left.data_type == 'FLOAT':
            mesh.attributes.remove(left)
    vg = obj.vertex_groups.get(name)
    if ok and vg is not None:
        return vg
    # Fallback (slower, still exact): one add() per distinct weight.
    if vg is None:
        vg = obj.vertex_groups.new(name=name)
    w = np.asarray(weights, dtype=np.float32)
    nz = np.nonzero(w > 0)[0]
    values, inverse = np.unique(w[nz], return_inverse=True)
    order = np.argsort(inverse, kind="stable")
    bounds = np.searchsorted(inverse[order], np.arange(len(values) + 1))
    for i, value in enumerate(values):
        vg.add(nz[order[bounds[i]:bounds[i + 1]]].tolist(), float(value), 'REPLACE')
    return vg


def _add_link_bones(arm_data, result):
    """One deform edit bone per link at the fitted joints, in the fitted tree."""
    edit = []
    for l in range(result.n_links):
        eb = arm_data.edit_bones.new(GROUP_FMT.format(l))
        head = Vector(result.heads[l])
        tail = Vector(result.tails[l])
        frame = np.asarray(result.frames[l])
        if (tail - head).length < 1e-6:  # Blender deletes zero-length bones
            tail = head + Vector(frame[:, 1]) * 1e-3
        eb.head = head
        eb.tail = tail
        eb.align_roll(Vector(frame[:, 2]))
        eb.use_connect = False
        eb.use_deform = True
        edit.append(eb)
    for l, p in enumerate(result.parents):
        if p >= 0:
            edit[l].parent = edit[int(p)]
    return edit


def _add_helper_bones(arm_data, links):
    """Hidden non-deforming copies (same head, tail, roll and parent) of the link
    edit bones ``links``, in the hidden bone collection ``ArtDef Load Helpers``.
    Not children of their link bones: those follow them (a dependency cycle)."""
    coll = arm_data.collections.new(HELPER_COLLECTION)
    coll.is_visible = False
    for l, eb in enumerate(links):
        hb = arm_data.edit_bones.new(HELPER_FMT.format(l))
        hb.head = eb.head
        hb.tail = eb.tail
        hb.roll = eb.roll
        hb.parent = eb.parent
        hb.use_connect = False
        hb.use_deform = False
        coll.assign(hb)


def _make_armature(context, obj, result, helpers=False):
    """The armature object of ``result`` (one deform bone per link; with
    ``helpers`` also the load helper bones).  Returns it and the link bone names."""
    name = f"{obj.name}_artdef_rig"
    arm_data = bpy.data.armatures.new(name)
    arm = bpy.data.objects.new(name, arm_data)
    arm["artdef_rig"] = True
    arm["artdef_owner"] = obj       # the mesh it was built for (a duplicate of the mesh shares the pointer)
    arm["artdef_source"] = obj.name
    for coll in obj.users_collection:
        coll.objects.link(arm)
    if not arm.users_collection:
        context.scene.collection.objects.link(arm)
    arm_data.display_type = 'OCTAHEDRAL'
    arm.show_in_front = True
    # Same parent and world transform as the mesh: armature space = mesh space.
    arm.parent = obj.parent
    if obj.parent is not None:
        arm.parent_type = obj.parent_type
        if obj.parent_type == 'BONE':
            arm.parent_bone = obj.parent_bone
    arm.matrix_parent_inverse = obj.matrix_parent_inverse.copy()
    arm.matrix_basis = obj.matrix_basis.copy()

    view_layer = context.view_layer
    prev_active = view_layer.objects.active
    selected = [o for o in view_layer.objects if o.select_get()]
    hidden = arm.hide_get(view_layer=view_layer)
    arm.hide_set(False)
    view_layer.objects.active = arm
    try:
        with context.temp_override(active_object=arm, object=arm, edit_object=None,
                                   selected_objects=[arm], selected_editable_objects=[arm]):
            bpy.ops.object.mode_set(mode='EDIT')
            if arm.mode != 'EDIT':
                raise RuntimeError("could not enter edit mode on the new armature "
                                   "(is its collection hidden or excluded?)")
            edit = _add_link_bones(arm_data, result)
            bone_names = [eb.name for eb in edit]
            if helpers:
                _add_helper_bones(arm_data, edit)
            bpy.ops.object.mode_set(mode='OBJECT')
    finally:
        if arm.mode != 'OBJECT':
            with context.temp_override(active_object=arm, object=arm):
                bpy.ops.object.mode_set(mode='OBJECT')
        view_layer.objects.active = prev_active
        for o in view_layer.objects:
            o.select_set(o in selected)
        arm.hide_set(hidden)
    if len(arm_data.bones) != result.n_links * (2 if helpers else 1):
        raise RuntimeError("Blender dropped a bone of the rig (zero length?)")
    for l in range(result.n_links):
        pb = arm.pose.bones[bone_names[l]]
        pb.rotation_mode = 'XYZ'
        free = result.parents[l] < 0 and not bool(result.grounded[l])
        pb.lock_location = (not free,) * 3
        if helpers:
            arm.pose.bones[HELPER_FMT.format(l)].rotation_mode = 'XYZ'
    return arm, bone_names


def _make_load_empties(obj, arm, result, load_names, size):
    mesh = obj.data
    empties = []
    for k, vert in enumerate(np.asarray(result.load_vertices)):
        name = LOAD_FMT.format(load_names[k])
        emp = bpy.data.objects.new(name, None)
        for coll in arm.users_collection:
            coll.objects.link(emp)
        emp["artdef_load"] = int(load_names[k])
        emp.parent = arm
        emp.matrix_parent_inverse = Matrix.Identity(4)
        emp.delta_location = mesh.vertices[int(vert)].co  # rest position: location = load
        emp.location = (0.0, 0.0, 0.0)
        emp.empty_display_type = 'SPHERE'
        emp.empty_display_size = size
        emp.show_in_front = True
        emp.hide_render = True
        emp.lock_rotation = (True, True, True)
        emp.lock_scale = (True, True, True)
        empties.append(emp)
    return empties


def build_rig(context, obj, result, tri_polygons, kind, load_names=None, frames_per_field=10):
    """Create the rig of ``result`` for mesh object ``obj`` (replacing its old rig).

    ``tri_polygons`` maps the scan's triangles to the mesh's polygons; ``kind``
    is the scan kind ('greens' drives from load empties, 'tracked' replays the
    fields in actions); ``load_names`` numbers the load empties (defaults to
    0..M-1; pseudo mode passes the original load index); tracked scans replay
    field p at frame (p+1)·``frames_per_field`` and the scene's frame range is
    set to cover the replay.
    """
    clear_rig(obj, context.scene)
    st = obj.artdef
    mesh = obj.data
    L = int(result.n_links)
    weights = np.asarray(result.weights, dtype=np.float64)
    residual = np.asarray(result.residual, dtype=np.float64)

    # 1. vertex groups
    for l in range(L):
        name = GROUP_FMT.format(l)
        old = obj.vertex_groups.get(name)
        if old is not None:
            obj.vertex_groups.remove(old)
        item = st.groups.add()  # recorded first: a failure while filling still clears it
        item.name = name
        item.name = _fill_vertex_group(obj, name, weights[:, l]).name

    # 2. armature, parenting, modifier
    greens = kind == "greens" and result.kappa is not None
    arm, bone_names = _make_armature(context, obj, result, helpers=greens)
    st.rig = arm
    st.old_parent = obj.parent
    st.old_parent_type = obj.parent_type
    st.old_parent_bone = obj.parent_bone
    st.old_parent_inverse = [v for row in obj.matrix_parent_inverse for v in row]
    basis = obj.matrix_basis.copy()
    obj.parent = arm
    obj.parent_type = 'OBJECT'
    obj.matrix_parent_inverse = basis.inverted_safe()
    mod = obj.modifiers.new(MODIFIER_NAME, 'ARMATURE')
    mod.object = arm
    mod.use_vertex_groups = True
    mod.use_bone_envelopes = False
    idx = list(obj.modifiers).index(mod)
    if idx != 0:
        obj.modifiers.move(idx, 0)

    # 3. residual shape keys
    if mesh.shape_keys is None:
        obj.shape_key_add(name="Basis", from_mix=False)
        st.made_basis = True
    keys = mesh.shape_keys
    n = len(mesh.vertices)
    ref_co = np.empty(3 * n, dtype=np.float32)
    io.key_points(keys.reference_key).foreach_get("co", ref_co)
    ref_co = ref_co.reshape(n, 3).astype(np.float64)
    if greens:     # first-order and bump keys (model.greens_keys): the rig's tangent at zero load is G
        residual = _model.greens_keys(result, ref_co)
    n_fields = residual.shape[0]
    width = max(3, len(str(n_fields - 1)))
    key_names = []
    for c in range(n_fields):
        kb = obj.shape_key_add(name=f"{KEY_PREFIX}{c:0{width}d}", from_mix=False)
        kb.slider_min = -SLIDER_RANGE
        kb.slider_max = SLIDER_RANGE
        kb.value = 0.0
        io.key_points(kb).foreach_set("co", np.ascontiguousarray(ref_co + residual[c], dtype=np.float32).ravel())
        st.shape_keys.add().name = kb.name
        key_names.append(kb.name)

    # 4. link colours
    write_link_colours(mesh, result.face_labels, tri_polygons)

    # 5. load controls (and their sweep) or replay
    if greens:
        empties = _build_load_controls(obj, arm, result, bone_names, key_names, load_names)
        end = _build_load_sweep(empties, float(result.probe_load), frames_per_field)
    else:
        end = _build_replay(obj, arm, result, bone_names, key_names, frames_per_field)
    if end is not None:  # None: the replay keeps the source's frames, the scene's range stays
        _set_frame_range(st, context.scene, end)
    return arm


def _set_frame_range(st, scene, end):
    """Scene frames 0..end (recorded, so Clear Rig can put the old range back)."""
    st.old_frame_range = (scene.frame_start, scene.frame_end)
    if end > scene.frame_start:
        scene.frame_end = end  # set the end first: frame_start may not pass frame_end
        scene.frame_start = 0
    else:
        scene.frame_start = 0
        scene.frame_end = end
    st.replay_frame_range = (scene.frame_start, scene.frame_end)
    st.set_frame_range = True


def sweep_frame(c, frames_per_field=10):
    """Frame at which the load sweep holds field c = 3k+d: load k = p̂ along axis d."""
    return (2 * int(c) + 1) * max(int(frames_per_field), 1)


def _build_load_sweep(empties, probe_load, frames_per_field=10):
    """One action per load empty sweeping its load along x, y, z in turn.

    Field c = 3k+d (empty k, axis d): location[d] is 0 at frame 2c·F, the probe
    load p̂ at (2c+1)·F and 0 again at (2c+2)·F (F = frames_per_field), so
    playing the scene shows every scanned load case once, one after the other,
    and any frame in between is a smaller load of the same case.  Returns the
    last frame.
    """
    step = max(int(frames_per_field), 1)
    n = 3 * len(empties)
    end = 2 * n * step
    for k, emp in enumerate(empties):
        action, new_fcurve = _new_action(emp, f"{emp.name}_sweep")
        action["artdef_made"] = True
        action.use_frame_range = True
        action.frame_start, action.frame_end = 0, end
        for d in range(3):
            c = 3 * k + d
            frames = [0.0, 2 * c * step, (2 * c + 1) * step, (2 * c + 2) * step, end]
            values = [0.0, 0.0, probe_load, 0.0, 0.0]
            # drop repeated frames (first and last case), keep the order
            keep = [i for i in range(len(frames)) if i == 0 or frames[i] != frames[i - 1]]
            _key_curve(new_fcurve("location", d, "Load Sweep"),
                       [frames[i] for i in keep], [values[i] for i in keep])
    return end


def _add_load_constraint(arm, pb, helper):
    """Copy Transforms ``ArtDef Load`` on link bone ``pb``: its local transform
    becomes helper's local transform (the load-driven one) followed by its own
    (the animator's keys), as if the helper were its parent."""
    con = pb.constraints.new('COPY_TRANSFORMS')
    con.name = LOAD_CONSTRAINT
    con.target = arm
    con.subtarget = helper
    con.target_space = 'LOCAL'
    con.owner_space = 'LOCAL'
    con.mix_mode = 'BEFORE_FULL'


def _build_load_controls(obj, arm, result, bone_names, key_names, load_names):
    """Load empties driving the helper bones (linearly through κ) and the shape
    keys (through the strain-hardening map); the link bones follow their helpers.
    Returns the empties."""
    kappa = np.asarray(result.kappa, dtype=np.float64)
    m = len(result.load_vertices)
    if load_names is None:
        load_names = list(range(m))
    co = np.empty(3 * len(obj.data.vertices), dtype=np.float32)
    obj.data.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3)
    extent = float(np.linalg.norm(co.max(0) - co.min(0))) or 1.0
    empties = _make_load_empties(obj, arm, result, load_names, 0.02 * extent)
    for l, bname in enumerate(bone_names):
        pb = arm.pose.bones[HELPER_FMT.format(l)]
        _add_load_constraint(arm, arm.pose.bones[bname], pb.name)
        for j in range(6):
            coeffs = kappa[l, j]
            if not np.any(coeffs):
                continue
            path = "rotation_euler" if j < 3 else "location"
            _drive_linear(pb, path, j % 3, coeffs, empties, arm, f"{l:02d}_{'rl'[j // 3]}{j % 3}")
    keys = obj.data.shape_keys
    probe = float(result.probe_load)
    p_max = None if result.p_max is None else float(result.p_max)
    first = len(key_names) // 2
    for c, kname in enumerate(key_names):
        k, d = divmod(c % first, 3)
        fc = _driver_fcurve(keys.driver_add(f'key_blocks["{kname}"].value'))
        drv = fc.driver
        drv.type = 'SCRIPTED'
        _add_load_vars(drv, empties, [(k, 0), (k, 1), (k, 2)])
        drv.expression = (shape_value_expression(k, d, probe, p_max) if c < first
                          else bump_value_expression(k, d, probe))
    arm[RIG_VERSION_PROP] = RIG_VERSION
    return empties


def _build_replay(obj, arm, result, bone_names, key_names, frames_per_field=10):
    """Actions replaying the fields: rest at frame 0, field p at (p+1)·frames_per_field,
    or, for a scan sampled from an animation or a sequence, every field at its
    source frame (:func:`.timing.clip_timings`).  A scan of several clips gets
    one armature action and one shape-key action per clip, each also in a
    muted NLA track named after the clip (the glTF exporter's NLA Tracks mode
    writes one animation per track name); the first clip is the active one.

    Returns the last frame of the replay, or None when the replay keeps the
    source's timing (the scene's frame range is then left alone).
    """
    from .timing import clip_timings
    angles = np.asarray(result.angles, dtype=np.float64)
    locations = np.asarray(result.locations, dtype=np.float64)
    p = angles.shape[0]
    clips = clip_timings(obj.data, p, frames_per_field)
    keys = obj.data.shape_keys
    st = obj.artdef
    ad = keys.animation_data
    st.key_action_previous = ad.action if ad is not None else None
    made = []
    for clip, frames, field, from_source in clips:
        pick = field + 1                # row 0 of np.r_[0, values]: the rest pose
        first, end = int(frames[0]), int(frames[-1])
        action, new_fcurve = _new_action(arm, clip or f"{arm.name}_replay")
        action["artdef_made"] = True
        action.use_frame_range = True
        action.frame_start, action.frame_end = first, max(end, first + 1)
        for l, bname in enumerate(bone_names):
            base = f'pose.bones["{bname}"]'
            for j in range(3):
                _key_curve(new_fcurve(f"{base}.rotation_euler", j, bname), frames,
                           np.r_[0.0, angles[:, l, j]][pick])
            if not all(arm.pose.bones[bname].lock_location) or np.any(locations[:, l]):
                for j in range(3):
                    _key_curve(new_fcurve(f"{base}.location", j, bname), frames,
                               np.r_[0.0, locations[:, l, j]][pick])
        kaction, new_kcurve = _new_action(keys, f"{clip}_shape_keys" if clip
                                          else f"{obj.name}_artdef_replay")
        kaction["artdef_made"] = True
        kaction.use_frame_range = True
        kaction.frame_start, kaction.frame_end = first, max(end, first + 1)
        for c, kname in enumerate(key_names):
            values = (field == c).astype(np.float64)
            _key_curve(new_kcurve(f'key_blocks["{kname}"].value', 0, "ArtDef"), frames, values)
        made.append((clip, action, kaction, first))
    if len(made) > 1:
        from . import compat
        for clip, action, kaction, first in made:
            compat.nla_clip_track(arm, clip, action, first)
            compat.nla_clip_track(keys, clip, kaction, first)
        compat.assign_action(arm, made[0][1])
        compat.assign_action(keys, made[0][2])
    st.key_action = made[0][2]
    if all(c[3] for c in clips):
        return None
    return int(max(c[1][-1] for c in clips))
