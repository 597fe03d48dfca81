# SPDX-License-Identifier: GPL-3.0-or-later
"""Finalize: turn a fitted rig into a plain armature + mesh an animator can take anywhere.

``artdef.finalize`` on a fitted mesh (or its armature):

1. bakes what drivers compute (a Green's rig: load empties drive hidden helper
   bones, which the link bones copy, and the residual shape keys) into keys on
   the link bones and the shape keys, at every frame of the scene's range;
2. removes the helpers: load empties, helper bones and their bone collection,
   the link bones' ``ArtDef Load`` constraints, every driver and the partial-sum
   properties on the armature;
3. removes the ArtDef records: the stored scan, the fit record and summary
   (``Object.artdef``), the ``artdef_*`` custom properties, the debug colour
   attributes (links, residual);
4. input data, the same on every input path: shape keys and vertex groups
   that the fit did not make (the source's, e.g. after Fields from Shape Keys)
   are removed, and a source object the scan was sampled from (Fields from
   Animation, an animated file) is hidden, so it no longer sits under the rig.
   The operator reports what it removed.

The rig then no longer counts as an ArtDef rig (Clear Rig does not touch it).
"""

import bpy

from . import compat, io, rig


def _link_bones(arm):
    return [b.name for b in arm.data.bones if b.use_deform]


def _bake(context, obj, arm):
    """Key the evaluated local transform of every link bone and every driven
    shape key value at each frame of the scene's range (only when drivers
    move the rig).  Returns the number of frames baked."""
    arm_drivers = arm.animation_data is not None and len(arm.animation_data.drivers) > 0
    keys = obj.data.shape_keys
    key_drivers = keys is not None and keys.animation_data is not None and \
        len(keys.animation_data.drivers) > 0
    if not (arm_drivers or key_drivers):
        return 0
    scene = context.scene
    frames = list(range(scene.frame_start, scene.frame_end + 1))
    bones = _link_bones(arm)
    local = {b: [] for b in bones}
    driven_keys = sorted({fc.data_path.split('"')[1] for fc in keys.animation_data.drivers}) \
        if key_drivers else []
    values = {k: [] for k in driven_keys}
    frame_before = scene.frame_current
    for f in frames:
        scene.frame_set(f)
        for b in bones:
            pb = arm.pose.bones[b]
            local[b].append(arm.convert_space(pose_bone=pb, matrix=pb.matrix,
                                              from_space='POSE', to_space='LOCAL').copy())
        for k in driven_keys:
            values[k].append(keys.key_blocks[k].value)
    scene.frame_set(frame_before)
    # the drivers and constraints go; then the values become keys
    _remove_drivers(arm)
    if keys is not None and keys.animation_data is not None:
        for fc in list(keys.animation_data.drivers):
            keys.animation_data.drivers.remove(fc)
    for b in bones:
        pb = arm.pose.bones[b]
        con = pb.constraints.get(rig.LOAD_CONSTRAINT)
        if con is not None:
            pb.constraints.remove(con)
    ad = arm.animation_data or arm.animation_data_create()
    if ad.action is None:
        compat.assign_action(arm, bpy.data.actions.new(f"{arm.name}_baked"))
    for b in bones:
        pb = arm.pose.bones[b]
        pb.rotation_mode = 'QUATERNION'
        for f, m in zip(frames, local[b]):
            loc, rot, _scale = m.decompose()
            pb.location, pb.rotation_quaternion = loc, rot
            pb.keyframe_insert("location", frame=f, group=b)
            pb.keyframe_insert("rotation_quaternion", frame=f, group=b)
    for k in driven_keys:
        kb = keys.key_blocks[k]
        for f, v in zip(frames, values[k]):
            kb.value = v
            kb.keyframe_insert("value", frame=f)
    # unkeyed channels from before (Euler rotations of the fit) no longer apply
    for fc in compat.action_fcurves(ad.action):
        if fc.data_path.endswith("rotation_euler"):
            fc.mute = True
    return len(frames)


def _remove_drivers(arm):
    ad = arm.animation_data
    if ad is not None:
        for fc in list(ad.drivers):
            ad.drivers.remove(fc)
    for key in [k for k in arm.keys() if k.startswith("artdef_sum_")]:
        del arm[key]


def _remove_helper_bones(context, arm):
    helpers = [b.name for b in arm.data.bones if not b.use_deform]
    if not helpers:
        return 0
    view_layer = context.view_layer
    prev = view_layer.objects.active
    hidden = arm.hide_get(view_layer=view_layer)
    arm.hide_set(False)
    view_layer.objects.active = arm
    try:
        with context.temp_override(active_object=arm, object=arm, selected_objects=[arm],
                                   selected_editable_objects=[arm]):
            bpy.ops.object.mode_set(mode='EDIT')
            for name in helpers:
                eb = arm.data.edit_bones.get(name)
                if eb is not None:
                    arm.data.edit_bones.remove(eb)
            bpy.ops.object.mode_set(mode='OBJECT')
    finally:
        view_layer.objects.active = prev
        arm.hide_set(hidden)
    coll = arm.data.collections.get(rig.HELPER_COLLECTION)
    if coll is not None:
        arm.data.collections.remove(coll)
    return len(helpers)


def finalize(context, obj):
    """Finalize the rig of mesh ``obj``; return a list of what was done (words)."""
    from .export import rig_parts
    mesh_obj, arm = rig_parts(obj)
    if mesh_obj is None:
        raise RuntimeError(f"'{obj.name}' has no ArtDef rig")
    st = mesh_obj.artdef
    done = []
    baked = _bake(context, mesh_obj, arm)
    if baked:
        done.append(f"baked drivers into keys over {baked} frames")
    _remove_drivers(arm)
    n_helpers = _remove_helper_bones(context, arm)
    empties = [c for c in arm.children if c.get("artdef_load") is not None]
    for emp in empties:
        action = emp.animation_data.action if emp.animation_data else None
        bpy.data.objects.remove(emp, do_unlink=True)
        if action is not None and action.users == 0:
            bpy.data.actions.remove(action)
    if n_helpers or empties:
        done.append(f"removed {len(empties)} load empties and {n_helpers} helper bones")
    # input data
    ours_keys = {item.name for item in st.shape_keys}
    keys = mesh_obj.data.shape_keys
    dropped_keys = []
    if keys is not None:
        for kb in list(keys.key_blocks)[1:]:
            if kb.name not in ours_keys:
                dropped_keys.append(kb.name)
                mesh_obj.shape_key_remove(kb)
    bones = set(_link_bones(arm))
    dropped_groups = [vg.name for vg in mesh_obj.vertex_groups if vg.name not in bones]
    for name in dropped_groups:
        mesh_obj.vertex_groups.remove(mesh_obj.vertex_groups[name])
    if dropped_keys:
        done.append(f"removed the source's shape keys {', '.join(dropped_keys[:4])}"
                    + (", ..." if len(dropped_keys) > 4 else ""))
    if dropped_groups:
        done.append(f"removed the source's vertex groups {', '.join(dropped_groups[:4])}"
                    + (", ..." if len(dropped_groups) > 4 else ""))
    source = bpy.data.objects.get(str(mesh_obj.data.get("artdef_source", "")))
    if source is not None and source != mesh_obj and not source.hide_get():
        source.hide_set(True)
        done.append(f"hid the source '{source.name}'")
    # records
    mesh = mesh_obj.data
    rig.remove_link_colours(mesh)
    rig.remove_residual(mesh)
    io.clear_scan(mesh)
    for id_data in (mesh_obj, mesh, arm, arm.data):
        for key in [k for k in id_data.keys() if k.startswith("artdef")]:
            del id_data[key]
    for id_data in (arm, keys):
        ad = getattr(id_data, "animation_data", None) if id_data is not None else None
        if ad is not None and ad.action is not None and ad.action.get("artdef_made") is not None:
            del ad.action["artdef_made"]    # the animator's action now: Clear Rig won't delete it
    mod = mesh_obj.modifiers.get(rig.MODIFIER_NAME)
    if mod is not None:
        mod.name = "Armature"
    mesh_obj.property_unset("artdef")
    done.append("removed the ArtDef records (scan, fit record, debug colours)")
    return done


class ARTDEF_OT_finalize(bpy.types.Operator):
    """Make the fitted rig a plain armature and mesh: bake drivers into keys, remove load empties, helper bones, the scan, the fit record, debug colours and the source's shape keys and vertex groups (the source object is hidden). ArtDef no longer manages the rig afterwards"""
    bl_idname = "artdef.finalize"
    bl_label = "Finalize Rig"
    bl_options = {'REGISTER', 'UNDO'}

    @classmethod
    def poll(cls, context):
        from .export import poll_rig
        return poll_rig(cls, context) is not None

    def execute(self, context):
        obj = context.active_object
        try:
            done = finalize(context, obj)
        except RuntimeError as err:
            self.report({'ERROR'}, str(err))
            return {'CANCELLED'}
        from . import ops
        ops.LAST_RESULTS.pop(obj.name, None)
        self.report({'INFO'}, f"'{obj.name}' finalized: " + "; ".join(done))
        return {'FINISHED'}


classes = (ARTDEF_OT_finalize,)


# Blender's own helper: registers in order, unregisters in reverse
register, unregister = bpy.utils.register_classes_factory(classes)
