# SPDX-License-Identifier: GPL-3.0-or-later
"""The rig's actions: keyed F-Curves, the tracked scans' replay of the fields, the frame range.

Tracked scans: actions replaying the input fields on the link bones, field p at frame
(p+1)·frames_per_field (frame 0 = rest), or at the source's frames for a scan sampled from an
animation; the scene's frame range is set to cover the animation (restored by Clear Rig if still
unchanged).
"""

import numpy as np

from . import compat


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


def _build_replay(obj, arm, result, bone_names, key_names, frames_per_field=10, key_values=None):
    """Actions replaying the fields: rest at frame 0, field p at (p+1)·frames_per_field,
    or, for a scan sampled from an animation or a sequence, every field at its
    source frame (:func:`.timing.clip_timings`).  A scan of several clips gets
    one armature action and one shape-key action per clip, each also in a
    muted NLA track named after the clip (the glTF exporter's NLA Tracks mode
    writes one animation per track name); the first clip is the active one.

    ``key_values (P, C)``: shape key c's value at field p (a tracked fit's principal residual
    shapes); None: field p sets key p to 1, the others 0.

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
            values = (field == c).astype(np.float64) if key_values is None else np.r_[0.0, key_values[:, c]][pick]
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
