# SPDX-License-Identifier: GPL-3.0-or-later
"""A fit's result made into a rig on a mesh, and the object's record of it (main thread only)."""

import numpy as np

from . import fitquality, parts, rig
from .jobs import model_of
from .props import enum_id, store_options
from .state import LAST_RESULTS


def apply_result(context, obj, result, scan, tri_polygons, *, load_index=0, frames_per_field=10,
                 auto_links=None, seconds=0.0, model=None, vertex_residual=None):
    """Build the rig of ``result`` (a fit of ``scan``) on mesh ``obj`` and record it: vertex
    groups, armature, residual shape keys, load controls or replay, residual colours, the
    object's settings and summary. The one way a rig is made from a fit — the Fit operator after
    its job and the command line (``operators/headless.py``) both call it. Main thread only;
    on failure what the build made is removed, the previous rig (or the link colours of Preview
    Links) is put back as it was, and the error raised."""
    if model is None:
        model, vertex_residual = model_of(result, scan, load_index)
    if model is None:
        raise ValueError("The fit returned no pseudo-articulation for that load point")
    pseudo = result.mode == "pseudo"
    before = rig.datablock_snapshot()
    # the previous rig (or Preview Links' colours) is set aside, not removed, until the new rig
    # is built: a build that fails puts it back as it was
    old_parts = parts.detach_parts(obj)   # the previous fit's objects per source mesh, likewise
    stash = rig.stash_rig(obj, context.scene)
    try:
        rig.build_rig(context, obj, model, tri_polygons, scan.kind, [load_index] if pseudo else None,
                      frames_per_field)
        scale = float(vertex_residual.max()) if len(vertex_residual) else 0.0
        rig.write_residual(obj.data, vertex_residual, scale)
        parts.write_parts(context, obj)      # a joined mesh: the rig on each source mesh's object
    except Exception:
        try:
            rig.clear_rig(obj, context.scene)
        finally:
            try:
                # whatever the build made and clear_rig did not know of yet
                # (an action, armature or empty made just before the failure)
                rig.remove_new_datablocks(before)
            finally:
                try:
                    rig.restore_rig(stash)
                finally:
                    parts.attach_parts(obj, old_parts)
        raise
    rig.drop_stash(stash)
    parts.remove_parts(old_parts)
    parts.settle_names(obj)
    LAST_RESULTS[obj.name] = model
    store_summary(obj, result, model, scan, vertex_residual, load_index=load_index,
                  frames_per_field=frames_per_field, seconds=seconds, auto_links=auto_links)
    return model


def store_summary(obj, result, model, scan, vertex_residual, *, load_index=0, frames_per_field=10,
                  seconds=0.0, auto_links=None):
    """The object's record of the fit (panel) and the settings that made it."""
    st = obj.artdef
    o = result.options
    pseudo = result.mode == "pseudo"
    st.has_fit = True
    st.fit_links = int(model.n_links)
    st.fit_mode = enum_id(result.mode)
    st.fit_motion = enum_id(result.motion)
    st.fit_kind = scan.kind
    st.fit_load_index = load_index if pseudo else -1
    st.fit_p_max = result.p_max or 0.0
    st.fit_rms_articulation = float(model.rms_articulation)
    st.fit_rms_total = float(model.rms_total)
    st.fit_seconds = seconds
    timings = getattr(model, "timings", None) or getattr(result, "timings", None) or {}
    st.fit_timings = ", ".join(f"{k} {v:.2f}s" for k, v in timings.items())
    e = float(model.articulation_error_percent)
    st.fit_articulation_percent = e if e == e else -1.0   # −1: undefined (degenerate frames), shown "n/a"
    # the fidelity figures (NaN/absent on a pseudo model or a result file without them: shown as unknown)
    st.fit_e_rms = float(getattr(model, "e_rms", float("nan")))
    st.fit_rigid_percent = float(getattr(model, "rigid_error_percent", float("nan")))
    st.fit_linear_percent = float(getattr(model, "linear_error_percent", float("nan")))
    st.fit_linear_rank = int(getattr(model, "linear_rank", 0))
    st.fit_articulated = bool(getattr(model, "articulated", True))
    res = vertex_residual
    st.fit_residual_max = float(res.max()) if len(res) else 0.0
    st.fit_residual_mean = float(res.mean()) if len(res) else 0.0
    st.fit_diagonal = float(np.linalg.norm(np.ptp(scan.vertices, axis=0)))
    st.fit_link_stats.clear()
    for item in fitquality.link_stats(model):
        rec = st.fit_link_stats.add()
        rec.name = rig.GROUP_FMT.format(item["link"])
        for key, value in item.items():
            setattr(rec, key, value)
    if st.set_frame_range:
        start, end = st.replay_frame_range
        if scan.kind == "greens":
            st.fit_replay = (f"load sweep: load k along axis d at the probe load at frame "
                             f"(2(3k+d)+1)x{frames_per_field}, scene frames set to {start}-{end}")
        else:
            st.fit_replay = (f"replay: field p at frame (p+1)x{frames_per_field}, "
                             f"scene frames set to {start}-{end}")
    else:
        st.fit_replay = ""
    st.fit_summary = str(model.summary())
    if st.fit_replay:
        st.fit_summary += ("\n" if st.fit_summary else "") + st.fit_replay
    st.fit_link_reason = result.link_reason
    obj["artdef_link_errors"] = [float(e) for e in (result.link_errors or [])]  # panel's curve
    st.fit_skin = str(getattr(model, "skin", "") or "")
    st.fit_notes = "\n".join(str(n) for n in (result.notes or []))
    st.fit_reduced = bool(result.reduced)
    # Remember the settings that made this rig (Links: the count used, also when chosen)
    if o is not None:
        store_options(st, o)
    st.links = int(model.n_links)
    st.load_index = load_index
    st.frames_per_field = frames_per_field
    if auto_links is not None:
        st.auto_links = auto_links
