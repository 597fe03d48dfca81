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
  mesh had none): one per field, or a tracked fit's principal residual shapes
  (``artdef_addon.residuals``) keyed at their weight per field;
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
* a mesh joined from several source meshes (:mod:`.parts`): one object per source mesh
  ``<source>_rigged`` with that mesh's vertices, groups, residual keys, modifier and parent (the
  joined mesh keeps the scan and is hidden);
* the face colour attribute ``artdef_links`` (active), the per-vertex
  articulation residual ``artdef_residual`` (FLOAT, POINT) and its colours
  ``artdef_residual_color`` (FLOAT_COLOR, POINT, blue = 0 → red = largest).

The pieces live in their own modules: the names in :mod:`.names`, the mesh attributes in
:mod:`.attributes`, the Green's scans' loads and drivers in :mod:`.loads` (expressions:
:mod:`artdef_addon.drivers`), the tracked scans' replay in :mod:`.replay`, and the re-fit's
transaction (stash / restore / drop, datablock snapshots) in :mod:`.stash`; their names are also
importable from here. :func:`build_rig` runs :data:`BUILD_STAGES` in order and checks each
stage's work before the next one starts.
"""

import bpy
import numpy as np
from mathutils import Matrix, Vector

from ..artdef_addon import model as _model
from . import io, loads, replay
from ..artdef_addon.drivers import MAX_EXPRESSION, number as _num, join as _join  # noqa: F401
from ..artdef_addon.drivers import (linear_terms as _linear_terms,  # noqa: F401
                                    shape_value_expression)
from .attributes import (_PALETTE, link_colours, remove_link_colours, remove_residual,  # noqa: F401
                         set_active_colour, write_link_colours, write_residual)
from .loads import (_add_load_constraint, _add_load_vars, _build_load_controls, _build_load_sweep,  # noqa: F401
                    _drive_linear, _driver_fcurve, _make_load_empties, sweep_frame)
from .names import (COLOR_ATTR, GROUP_FMT, HELPER_COLLECTION, HELPER_FMT, KEY_PREFIX, LOAD_CONSTRAINT,  # noqa: F401
                    LOAD_FMT, MODIFIER_NAME, RESIDUAL_ATTR, RESIDUAL_COLOR_ATTR, RIG_VERSION, RIG_VERSION_PROP,
                    STASH_PREFIX)
from ..artdef_addon.residuals import rig_shapes
from .replay import _build_replay, _key_curve, _new_action, _set_frame_range  # noqa: F401

SLIDER_RANGE = 10.0          # Blender's hard limit for shape key sliders

#: the re-fit's transaction, in :mod:`.stash` (which imports this module: looked up when asked for)
_STASH_NAMES = ("RigStash", "stash_rig", "restore_rig", "drop_stash", "id_collections",
                "datablock_snapshot", "remove_new_datablocks", "_rig_ids", "_names_back", "_copy",
                "_stash_name", "_RECORD", "_TRANSFORM", "_UI_COLLECTIONS")


def __getattr__(name):
    if name in _STASH_NAMES:
        from . import stash
        return getattr(stash, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


# --------------------------------------------------------------------------
# record keeping / clearing
# --------------------------------------------------------------------------

def has_rig(obj):
    st = obj.artdef
    return bool(st.rig or len(st.groups) or len(st.shape_keys) or obj.modifiers.get(MODIFIER_NAME))


def stale_greens_rig(obj) -> bool:
    """True when ``obj``'s rig is a Green's rig (load helper bones) built before
    :data:`RIG_VERSION`: it still poses as it did (its keys and drivers are in the file), but it
    either scaled its residual keys linearly from the probe load (wrong to first order between and
    below the probe loads) or turns its joints linearly in the load (overshooting a dead load at
    large loads, and summing loads on several links linearly where their torques do not add so);
    the panel says to refit it."""
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
    from . import parts            # a joined mesh's rigged objects, one per source mesh
    rigged = parts.parts_of(obj)
    parts.remove_parts(rigged)
    if rigged and obj.name in bpy.context.view_layer.objects:
        obj.hide_set(False)
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
            arm.pose.bones[HELPER_FMT.format(l)].rotation_mode = 'QUATERNION'   # the spring turn's quaternion
    return arm, bone_names


class RigBuild:
    """What :func:`build_rig`'s stages hand on: the inputs, then what each stage made."""

    def __init__(self, context, obj, result, tri_polygons, kind, load_names, frames_per_field):
        self.context, self.obj, self.result = context, obj, result
        self.tri_polygons, self.kind = tri_polygons, kind
        self.load_names, self.frames_per_field = load_names, frames_per_field
        self.n_links = int(result.n_links)
        self.weights = np.asarray(result.weights, dtype=np.float64)
        # a tracked fit's principal residual shapes and their weight per field, else one per field
        self.residual, self.key_values = rig_shapes(result)
        self.n_keys = 0              # residual shape keys (a Green's rig: two per field)
        self.greens = kind == "greens" and result.kappa is not None
        self.arm = None              # armature
        self.bone_names = []         # the link bones' names
        self.key_names = []          # the residual shape keys' names


def _stage_groups(b):
    """1. vertex groups, one per link (the skin weights)."""
    st, obj = b.obj.artdef, b.obj
    for l in range(b.n_links):
        name = GROUP_FMT.format(l)
        old = obj.vertex_groups.get(name)
        if old is not None:
            obj.vertex_groups.remove(old)
        item = st.groups.add()  # recorded first: a failure while filling still clears it
        item.name = name
        item.name = _fill_vertex_group(obj, name, b.weights[:, l]).name


def _stage_armature(b):
    """2. the armature, the mesh parented to it, the Armature modifier first in the stack."""
    obj, st = b.obj, b.obj.artdef
    arm, b.bone_names = _make_armature(b.context, obj, b.result, helpers=b.greens)
    b.arm = arm
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


def _stage_shape_keys(b):
    """3. the residual shape keys (and ``Basis`` if the mesh had none); a Green's rig has one a field."""
    obj, st, mesh = b.obj, b.obj.artdef, b.obj.data
    if mesh.shape_keys is None:
        obj.shape_key_add(name="Basis", from_mix=False)
        st.made_basis = True
    keys = mesh.shape_keys
    n = len(mesh.vertices)
    ref_co = np.empty(3 * n, dtype=np.float32)
    io.key_points(keys.reference_key).foreach_get("co", ref_co)
    ref_co = ref_co.reshape(n, 3).astype(np.float64)
    residual = b.residual
    if b.greens:   # first-order keys (model.greens_keys): the rig's tangent at zero load is G
        residual = _model.greens_keys(b.result, ref_co)
    b.n_keys = residual.shape[0]
    width = max(3, len(str(b.n_keys - 1)))
    for c in range(b.n_keys):
        kb = obj.shape_key_add(name=f"{KEY_PREFIX}{c:0{width}d}", from_mix=False)
        kb.slider_min = -SLIDER_RANGE
        kb.slider_max = SLIDER_RANGE
        kb.value = 0.0
        io.key_points(kb).foreach_set("co", np.ascontiguousarray(ref_co + residual[c], dtype=np.float32).ravel())
        st.shape_keys.add().name = kb.name
        b.key_names.append(kb.name)


def _stage_colours(b):
    """4. the link colours."""
    write_link_colours(b.obj.data, b.result.face_labels, b.tri_polygons)


def _stage_animation(b):
    """5. Green's scans: the load controls and their sweep; tracked scans: the replay."""
    obj, arm = b.obj, b.arm
    if b.greens:
        empties = loads._build_load_controls(obj, arm, b.result, b.bone_names, b.key_names, b.load_names)
        end = loads._build_load_sweep(empties, float(b.result.probe_load), b.frames_per_field)
    else:
        end = replay._build_replay(obj, arm, b.result, b.bone_names, b.key_names, b.frames_per_field,
                                   b.key_values)
    if end is not None:  # None: the replay keeps the source's frames, the scene's range stays
        replay._set_frame_range(obj.artdef, b.context.scene, end)


def _check(b, stage):
    """What ``stage`` left is what the next stages build on; a RuntimeError naming what is missing
    otherwise (the caller then removes the half-built rig, as for any failed build)."""
    obj, st = b.obj, b.obj.artdef
    missing = None
    if stage == "groups":
        if len(st.groups) != b.n_links or any(obj.vertex_groups.get(i.name) is None for i in st.groups):
            missing = "a link's vertex group"
    elif stage == "armature":
        mod = obj.modifiers.get(MODIFIER_NAME)
        if b.arm is None or st.rig != b.arm or obj.parent != b.arm or mod is None or mod.object != b.arm \
                or len(b.bone_names) != b.n_links:
            missing = "the armature, its bones or the mesh's Armature modifier"
    elif stage == "shape_keys":
        keys = obj.data.shape_keys
        if len(b.key_names) != b.n_keys or keys is None or \
                any(keys.key_blocks.get(n) is None for n in b.key_names):
            missing = "a residual shape key"
    elif stage == "colours":
        if obj.data.attributes.get(COLOR_ATTR) is None:
            missing = "the link colours"
    if missing is not None:
        raise RuntimeError(f"the rig build's {stage} stage did not make {missing}")


#: the rig build's stages in order: (name, function of a :class:`RigBuild`); :func:`build_rig`
#: runs :func:`_check` after each one
BUILD_STAGES = (
    ("groups", _stage_groups),
    ("armature", _stage_armature),
    ("shape_keys", _stage_shape_keys),
    ("colours", _stage_colours),
    ("animation", _stage_animation),
)


def build_rig(context, obj, result, tri_polygons, kind, load_names=None, frames_per_field=10):
    """Create the rig of ``result`` for mesh object ``obj`` (replacing its old rig).

    ``tri_polygons`` maps the scan's triangles to the mesh's polygons; ``kind``
    is the scan kind ('greens' drives from load empties, 'tracked' replays the
    fields in actions); ``load_names`` numbers the load empties (defaults to
    0..M-1; pseudo mode passes the original load index); tracked scans replay
    field p at frame (p+1)·``frames_per_field`` and the scene's frame range is
    set to cover the replay. Runs :data:`BUILD_STAGES`, each checked before the next.
    """
    clear_rig(obj, context.scene)
    b = RigBuild(context, obj, result, tri_polygons, kind, load_names, frames_per_field)
    for name, stage in BUILD_STAGES:
        stage(b)
        _check(b, name)
    return b.arm
