# SPDX-License-Identifier: GPL-3.0-or-later
"""Engine-friendly motion: rotation-only joints with fixed bone lengths.

A fitted link moves rigidly; its bone's replay keys a rotation and, where the
fitted joint is not exact, a small translation.  Many engines (and animation
retargeting) want joints that only rotate, bones that keep their length, and
only the root translating.  ``artdef.rotation_only`` removes the location
channels of every bone that has a parent (the root keeps its translation; no
bone has scale keys) and measures what that costs: the largest and the RMS
vertex distance, over the replay's keyed frames, between the rig before and
after, as a percentage of the bounding-box diagonal.  The figures are reported
and stored on the mesh (``artdef_rotation_only_error``).
"""

import bpy
import numpy as np

from . import compat


def _keyed_frames(mesh_obj, arm):
    frames = set()
    for id_data in (arm, mesh_obj.data.shape_keys):
        ad = getattr(id_data, "animation_data", None) if id_data is not None else None
        if ad is not None and ad.action is not None:
            frames.update(round(f) for f in compat.keyed_frames(ad.action))
    return sorted(frames)


def _positions(context, obj, frames):
    """(F, N, 3) evaluated object-space positions at ``frames``."""
    scene = context.scene
    before = scene.frame_current
    out = np.empty((len(frames), len(obj.data.vertices), 3), dtype=np.float32)
    try:
        for i, f in enumerate(frames):
            scene.frame_set(int(f))
            dg = context.evaluated_depsgraph_get()
            ev = obj.evaluated_get(dg)
            me = ev.to_mesh()
            try:
                me.vertices.foreach_get("co", out[i].reshape(-1))
            finally:
                ev.to_mesh_clear()
    finally:
        scene.frame_set(before)
    return out.astype(np.float64)


def rotation_only(context, mesh_obj, arm):
    """Remove the child bones' location channels (and zero their pose
    locations); return (max %, rms %) of the added error over the keyed frames."""
    frames = _keyed_frames(mesh_obj, arm)
    ad = arm.animation_data
    if ad is None or ad.action is None:
        raise RuntimeError(f"'{arm.name}' has no action to make rotation-only")
    children = {b.name for b in arm.data.bones if b.parent is not None}
    before = _positions(context, mesh_obj, frames)
    removed = 0
    for fc in list(compat.action_fcurves(ad.action)):
        path = fc.data_path
        if path.startswith('pose.bones["') and path.endswith((".location", ".scale")):
            if path.split('"')[1] in children:
                compat.remove_fcurve(ad.action, fc)
                removed += 1
    for name in children:
        pb = arm.pose.bones[name]
        pb.location = (0.0, 0.0, 0.0)
        pb.scale = (1.0, 1.0, 1.0)
        pb.lock_location = (True, True, True)
        pb.lock_scale = (True, True, True)
    after = _positions(context, mesh_obj, frames)
    rest = np.empty(3 * len(mesh_obj.data.vertices), dtype=np.float32)
    mesh_obj.data.vertices.foreach_get("co", rest)
    diag = float(np.linalg.norm(np.ptp(rest.reshape(-1, 3), axis=0))) or 1.0
    err = np.linalg.norm(after - before, axis=-1) if len(frames) else np.zeros((1, 1))
    worst = 100.0 * float(err.max()) / diag
    rms = 100.0 * float(np.sqrt(np.mean(err ** 2))) / diag
    mesh_obj.data["artdef_rotation_only_error"] = [worst, rms]
    return worst, rms, removed


class ARTDEF_OT_rotation_only(bpy.types.Operator):
    """Make the fitted rig's motion engine-friendly: joints only rotate, bones keep their length, only the root bone translates. Removes the small joint translations of the fit and reports the error this adds (largest and RMS vertex distance over the keyed frames, % of the bounding-box diagonal)"""
    bl_idname = "artdef.rotation_only"
    bl_label = "Rotation-Only Joints"
    bl_options = {'REGISTER', 'UNDO'}

    @classmethod
    def poll(cls, context):
        from .export import poll_rig
        parts = poll_rig(cls, context)
        if parts is None:
            return False
        arm = parts[1]
        if arm.animation_data is None or arm.animation_data.action is None:
            cls.poll_message_set("The rig has no action (a Green's rig: Finalize it first)")
            return False
        return True

    def execute(self, context):
        from .export import rig_parts
        mesh, arm = rig_parts(context.active_object)
        try:
            worst, rms, removed = rotation_only(context, mesh, arm)
        except RuntimeError as err:
            self.report({'ERROR'}, str(err))
            return {'CANCELLED'}
        self.report({'INFO'}, f"'{arm.name}': rotation-only joints ({removed} translation "
                              f"channels removed); added error max {worst:.3f}%, "
                              f"RMS {rms:.3f}% of the diagonal")
        return {'FINISHED'}


classes = (ARTDEF_OT_rotation_only,)


# Blender's own helper: registers in order, unregisters in reverse
register, unregister = bpy.utils.register_classes_factory(classes)
