# SPDX-License-Identifier: GPL-3.0-or-later
"""When a tracked scan's replay keys each field.

A scan sampled from an animation (Fields from Animation, an animated file) or
read from a numbered mesh sequence remembers the frames it came from
(``artdef_frames``: one per field; ``artdef_sampled_frames``: every frame
sampled, the ones equal to the rest included).  Its replay then keys every
field at its own frame and the rest pose at the sampled frames that were equal
to the rest - the source's timing, so an exported clip plays like the source.
Other scans replay field p at (p+1)·frames_per_field after a rest key at 0.
"""

import numpy as np


def replay_timing(mesh, n_fields, frames_per_field=10):
    """``(frames, field, from_source)`` of a replay of ``n_fields`` fields.

    frames: (K,) float, increasing key frames; field: (K,) int, the field keyed
    there, -1 for the rest pose; from_source: True when the frames are the
    source's (then the scene's frame range is left as it is).
    """
    frames = mesh.get("artdef_frames") if mesh is not None else None
    if frames is not None and len(frames) == n_fields and n_fields > 0:
        frames = [int(f) for f in frames]
        sampled = mesh.get("artdef_sampled_frames")
        sampled = set(int(f) for f in sampled) if sampled is not None else set()
        at = {f: p for p, f in enumerate(frames)}
        if len(at) == n_fields:  # one field per frame
            keys = np.array(sorted(sampled | set(frames)), dtype=np.float64)
            field = np.array([at.get(int(f), -1) for f in keys], dtype=np.int64)
            return keys, field, True
    step = max(int(frames_per_field), 1)
    keys = np.arange(n_fields + 1, dtype=np.float64) * step
    return keys, np.arange(-1, n_fields, dtype=np.int64), False


def clip_timings(mesh, n_fields, frames_per_field=10):
    """``[(clip name or None, frames, field, from_source)]``: one entry per clip.

    A scan sampled from several clips (``artdef_field_clips``: the clip of each
    field, ``artdef_clip_names``, ``artdef_clip_sampled``: every frame sampled
    per clip) replays each clip at its own frames, ``field`` indexing the whole
    scan; any other scan is one clip as :func:`replay_timing` times it.
    """
    clips = mesh.get("artdef_field_clips") if mesh is not None else None
    names = mesh.get("artdef_clip_names") if mesh is not None else None
    frames = mesh.get("artdef_frames") if mesh is not None else None
    if clips is None or names is None or frames is None or len(clips) != n_fields \
            or len(frames) != n_fields:
        return [(None, *replay_timing(mesh, n_fields, frames_per_field))]
    clips = np.asarray(clips, dtype=np.int64)
    frames = np.asarray(frames, dtype=np.int64)
    sampled = mesh.get("artdef_clip_sampled") or {}
    out = []
    for c, name in enumerate(names):
        fields = np.flatnonzero(clips == c)
        at = {int(frames[p]): int(p) for p in fields}
        extra = set(int(f) for f in sampled.get(str(c), []))
        keys = np.array(sorted(extra | set(at)), dtype=np.float64)
        if len(keys) == 0:
            continue
        field = np.array([at.get(int(f), -1) for f in keys], dtype=np.int64)
        out.append((str(name), keys, field, True))
    return out
