"""The fit of one link count: a :class:`~.segmenter.Segmenter`, then :data:`~.stages.STAGES`.

:func:`fit` runs every stage on one :class:`~.stages.FitState` (paper §5–§7; docs/method_notes.md §2–§5,
docs/method_notes_model.md §6–§10):

1. ``segment``    cut to k, split along every seam, merge on Λ with motion centroids (§5.2);
   Green's scans use two levels: per block column, then across all columns (§7.2, A-9);
2. ``motions``    link motions: robust medoid or least squares (§6);
3. ``relabel``    tracked scans: faces to the link dominating their skin, link swaps (docs/method_notes_model.md §6);
4. ``skin``       seam-blended weights, or the refined skin decomposition (§7, docs/method_notes_model.md §8);
   ``split``      tracked scans, refined skin: links holding two bones cut in two (:mod:`splits`);
5. ``joints``     joint centres (§4, §6), the minimum spanning tree over joint cost, ground /
   world joint;
6. ``bones``      bone heads, tails and rest frames;
7. ``pose``       pose parameters per field and the rig's motions (§7);
8. ``residuals``  rest-space residual, per-link RMS, articulation error (§7, docs/metrics.md).

``FitResult.timings`` holds seconds per stage; the segment stage appears as its parts
``features``, ``cluster`` (paid once per Segmenter) and ``merge``.
"""
from __future__ import annotations

import time

import numpy as np

from . import linkcheck as _linkcheck
from . import quality as _quality
from . import segmenter as _segmenter
from .blas import single_threaded
from .options import FitOptions
from .result import FitResult, report as _report
from .scan import Scan, ScanError
from .segmenter import Segmenter, select_fields
from .stages import FitState, STAGES, new_state, relabelled, to_result, run_stages


def fit_until(seg: Segmenter, links: int, stage: str, progress=None, labels: np.ndarray | None = None):
    """The stages of :func:`fit` (its defaults) before ``stage``: ``(state, seconds per stage)``,
    which ``fit(seg.scan, links, segmenter=seg, resume=...)`` finishes into the same fit.

    ``labels (T,)``: start from those face labels (``links`` links 0..L−1, each owning a clustered
    triangle) instead of the Segmenter's cut: the links' robust motions of those labels (their
    medoid units over the Segmenter's fields, §6), then the stages from the relabelling. The
    link-count search fits the counts it climbs through from the links grown on the count below
    (:func:`linkcount.grow_link`): their relabelling starts with the missing bone's link in place
    instead of finding it again by swaps from a new cut of the tree."""
    skin = "seam" if seg.scan.kind == "greens" else "refined"
    t0, merge0 = time.perf_counter(), seg.timings.get("merge", 0.0)
    st = new_state(seg, int(links), "robust", skin)
    names = [name for name, _ in STAGES]
    first = 0
    secs = {}
    if labels is not None:
        labels = np.asarray(labels)
        if labels.shape != (seg.scan.n_faces,) or labels.min() < 0 or labels.max() != st.links - 1 or \
                np.any(np.bincount(labels[seg.valid][seg.unit_tri], minlength=st.links) == 0):
            raise ValueError("fit_until: labels must give every face one of links 0..L-1, each owning a "
                             "clustered triangle")
        st.fields = select_fields(st.scan.fields(), st.field_idx)
        st.used_fields = seg.segment_fields(st.seg_fields)
        st.n_links = st.links
        first = names.index("relabel")
    with single_threaded():
        if labels is not None:
            _report(progress, "motions", 0.0)
            relabelled(st, labels)
            secs = {"segment": 0.0, "motions": time.perf_counter() - t0}
        secs.update(run_stages(st, progress, STAGES[first:names.index(stage)]))
    st.spent_total = time.perf_counter() - t0
    st.spent_merge = seg.timings.get("merge", 0.0) - merge0
    return st, secs


def fit(scan: Scan, links: int, options: FitOptions | None = None, progress=None,
        segmenter: Segmenter | None = None, resume=None) -> FitResult:
    """Fit an articulated deformable model to ``scan`` with ``links`` links (paper §5–§7): the
    :data:`STAGES` in order (``result.timings``: seconds per stage, the segment stage as its
    parts features, cluster and merge). The pipeline behind :func:`artdef_addon.fit`, which checks
    the scan and the options and keeps the segmentation; scripts call that one.

    ``options``: a :class:`FitOptions` (default: all defaults), taken as given (checked where it
    entered) and resolved for the scan's kind here. Its ``strategy`` chooses how fields are
    combined (see :class:`Segmenter`) and is ignored when a ready ``segmenter`` is passed; its
    ``skin`` is ``"seam"`` (the paper's linear blend across each seam's one-ring) or ``"refined"``
    (per-vertex convex weights, at most 4 influences, fitted by least squares over all fields to
    the rig's link motions), ``"auto"`` refining for tracked scans and keeping seam weights for
    Green's scans; ``mode``, ``motion`` and ``p_max`` are the model's. ``max_links``,
    ``memory_budget`` and ``reduce`` belong to :func:`artdef_addon.fit` (the link-count search and
    the segmenter it makes).

    Runs with one OpenBLAS thread (:func:`blas.single_threaded`): its products are small, and a
    second BLAS thread only spins — measured on the 2-core machine, quiet: the same wall time at
    half the CPU (CesiumMan 3.0 s at 3.0 s of CPU against 3.0–3.6 s at 5.9–7.0 s); loaded: 2.3–3.6 ×
    faster. The results are the same (weights within 1e-11).

    ``resume``: ``(state, seconds)``, a :class:`FitState` of this fit the first stages have run on
    and their seconds per stage (:mod:`linkcount` decides on them): the fit runs the rest; its
    ``timings`` (merge, total) include what :func:`fit_until` spent on the state.
    """
    with single_threaded():
        return _fit(scan, links, FitOptions() if options is None else options, progress, segmenter, resume)


def _fit(scan, links, options, progress, segmenter, resume=None) -> FitResult:
    try:
        links = int(links)
    except (TypeError, ValueError):
        raise ScanError(f"the number of links must be an integer, got {links!r}") from None
    t_start = time.perf_counter()
    seg = segmenter if segmenter is not None else _segmenter.Segmenter(scan, progress, strategy=options.strategy)
    seg.progress = progress
    merge_before = seg.timings.get("merge", 0.0)
    scan = seg.scan
    seg._check_k(links)
    o = options.resolved(scan.kind)
    mode, motion, skin, p_max = o.mode, o.motion, o.skin, o.p_max
    if resume is not None:
        state, done = resume
        t_start -= state.spent_total             # the fit's first stages ran in fit_until
        merge_before -= state.spent_merge
        stage_times = {**done, **run_stages(state, progress, STAGES[len(done):])}
    else:
        state = new_state(seg, links, motion, skin)
        stage_times = run_stages(state, progress)
    result = to_result(state, stage_times)
    result.skin = skin
    result.mode = mode
    result.p_max = p_max
    _quality.judge(result, scan.vertices, scan.fields())
    # the links' self-check (:mod:`linkcheck`): a link holding two bones, two links moving as one
    result.notes += _linkcheck.notes(_linkcheck.check(
        scan.vertices, scan.fields(), scan.faces, result.face_labels, result.parents, result.rotations,
        result.weights if skin == "refined" else None))
    if mode == "pseudo":
        result.pseudo = []
        for k, g in enumerate(seg.groups):
            _report(progress, "pseudo", k / len(seg.groups))
            sub_state = FitState(scan=scan, seg=seg, links=links, motion=motion, skin=skin,
                                 field_idx=list(g), seg_fields=g)
            sub = to_result(sub_state, run_stages(sub_state))   # one "pseudo" report per load point
            sub.mode = "pseudo"
            sub.p_max = p_max
            result.pseudo.append(sub)
    # features and trees are paid once per Segmenter (cached); merge is this fit's own share
    timings = {"features": seg.timings.get("features", 0.0), "cluster": seg.timings.get("cluster", 0.0),
               "merge": seg.timings.get("merge", 0.0) - merge_before}
    timings.update((k, v) for k, v in stage_times.items() if k != "segment")
    timings["total"] = time.perf_counter() - t_start
    result.timings = timings
    result.notes = list(seg.notes) + result.notes
    _report(progress, "done", 1.0)
    return result
