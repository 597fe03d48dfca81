"""The public entry points: ``artdef_addon.fit``, ``artdef_addon.load_scan``, ``artdef_addon.segment``.

>>> import artdef_addon
>>> scan = artdef_addon.load_scan("scan.npz")                      # doctest: +SKIP
>>> result = artdef_addon.fit(scan, links="auto")                  # doctest: +SKIP
>>> result.save("result.npz"); artdef_addon.FitResult.load("result.npz")   # doctest: +SKIP

The command line, the Blender operators and scripts all call :func:`fit`. What it does with the
scan's pairwise distances is its own business: the segmentation of a scan (its features and
clustering trees, the expensive O(T²) part) is kept for the next call on the same scan data and
method settings, so a second fit or a preview with another link count does not recompute it.
The cache holds the last :data:`CACHE_SIZE` segmentations; an entry is taken out while a call
uses it and put back only when the call succeeds (a cancelled or failed call may leave it half
merged). In Blender the cache lives in the add-on's worker process (:mod:`jobs`).
"""
from __future__ import annotations

import hashlib
import time
from collections import OrderedDict

import numpy as np

from . import cost as _cost
from . import linkcount as _linkcount
from . import pipeline as _pipeline
from . import procs as _procs
from . import residuals as _residuals
from . import seams as _seams
from . import segmenter as _segmenter
from .options import FitOptions, OptionsError
from .files import read_scan as load_scan
from .scan import Scan, ScanError, validate_scan

__all__ = ["fit", "load_scan", "segment", "plan", "FitOptions", "OptionsError", "ScanError"]

#: segmentations kept (each holds the per-field features and trees of one scan)
CACHE_SIZE = 2
_SEGMENTERS: OrderedDict = OrderedDict()


def fingerprint(scan: Scan) -> str:
    """sha256 of the scan's arrays: names the scan data for the segmentation cache."""
    h = hashlib.sha256()
    for a in (scan.vertices, scan.faces, scan.greens, scan.displacements, scan.load_vertices,
              scan.support_vertices):
        h.update(b"-" if a is None else np.ascontiguousarray(a).view(np.uint8).reshape(-1))
    h.update(np.float64(scan.probe_load).tobytes())
    return h.hexdigest()


def plan(triangles: int, fields: int, vertices: int, kind: str, options: FitOptions | None = None,
         **price):
    """What a fit with ``options`` will do, from counts only (no fit): ``(estimate, reduce_arg)``,
    the :class:`cost.Estimate` of the method that will run (``estimate.reduced``) and the
    segmenter's switch (None: decided by the budget, and noted). ``price``: ``links=`` /
    ``auto=`` of :func:`cost.estimate` (the whole fit's time for that count or the search)."""
    o = (options or FitOptions()).resolved(kind)
    budget = o.budget_bytes
    price.setdefault("jobs", o.processes)
    if price.get("auto"):
        price.setdefault("max_links", min(o.max_links, triangles))   # the search's range
    if o.reduce == "off":
        return _cost.estimate(triangles, fields, vertices, o.strategy, float("inf"), **price), False
    if o.reduce == "on":
        units = min(triangles, _cost.reduced_units(budget, fields))
        return _cost.estimate(triangles, fields, vertices, o.strategy, 0.0, units=units, **price), True
    return _cost.estimate(triangles, fields, vertices, o.strategy, budget, **price), None


def _key(scan: Scan, o: FitOptions, reduced: bool):
    """What a segmentation depends on: the scan, the strategy and, for the reduced method only,
    the budget (through the patch count; under 'auto' its note quotes the budget)."""
    base = (fingerprint(scan), o.strategy)
    if not reduced:
        return base + (False,)
    if o.reduce == "auto":
        return base + (True, "auto", round(o.memory_budget, 6))
    return base + (True, o.reduce, _cost.reduced_units(o.budget_bytes))


def _checkout(scan: Scan, o: FitOptions, progress):
    """A segmenter for ``scan`` (checked by the caller, :func:`fit` / :func:`segment`) and ``o``
    (resolved), from the cache or new; ``(key, seg)``."""
    est, reduce_arg = plan(scan.n_faces - len(scan.degenerate_faces), scan.n_fields, scan.n_vertices,
                           scan.kind, o)
    key = _key(scan, o, est.reduced)
    seg = _SEGMENTERS.pop(key, None)
    if seg is None:
        seg = _segmenter.Segmenter(scan, progress, strategy=o.strategy, reduce=reduce_arg, budget=o.budget_bytes)
        key = _key(scan, o, seg.reduced)     # what the core built (the plan predicts it)
    seg.progress = progress
    return key, seg


def _checkin(key, seg, keep: bool = True) -> None:
    """Put a segmenter back after a call; one that a cancelled or failed call used is dropped
    (it may hold half a merge), so a fresh one is made next time."""
    seg.progress = None                      # don't keep a caller's callback alive
    if not keep:
        return
    _SEGMENTERS.pop(key, None)
    _SEGMENTERS[key] = seg
    while len(_SEGMENTERS) > CACHE_SIZE:
        _SEGMENTERS.popitem(last=False)


def clear_cache() -> None:
    """Forget every kept segmentation (frees their memory)."""
    _SEGMENTERS.clear()


def _as_scan(scan) -> Scan:
    """``scan`` as this core's :class:`Scan`; a scan made by another copy of the core (the
    installed extension's, e.g. sampled in Blender for the command line) is taken by its fields."""
    if isinstance(scan, Scan):
        return scan
    names = ("vertices", "faces", "greens", "displacements", "load_vertices", "support_vertices", "probe_load")
    if not all(hasattr(scan, n) for n in names):
        raise ScanError(f"scan must be an artdef_addon Scan (see load_scan), got {type(scan).__name__}")
    return Scan(**{n: getattr(scan, n) for n in names})


def _checked(scan):
    """The boundary of the public calls: ``(checked scan, its welded scan, the weld)`` — ``scan`` as
    this core's :class:`Scan`, checked once (:func:`scan.validate_scan`; a checked scan is not
    checked again), copies at seams one point to the fit (:func:`seams.weld_scan`). Everything
    behind :func:`fit`, :func:`segment` and :func:`cached` takes the welded scan as it is."""
    stored = validate_scan(_as_scan(scan))
    welded, weld = _seams.weld_scan(stored)
    return stored, welded, weld


def _options(options, overrides) -> FitOptions:
    if options is None:
        options = FitOptions()
    elif isinstance(options, dict):
        options = FitOptions(**options)
    elif not isinstance(options, FitOptions):
        raise OptionsError(f"options must be a FitOptions, got {type(options).__name__}")
    return options.replace(**overrides) if overrides else options


def fit(scan: Scan, links, options: FitOptions | None = None, progress=None, **overrides) -> "_pipeline.FitResult":
    """Fit an articulated deformable model to ``scan`` (paper §5–§7).

    ``links``: the number of links, or ``"auto"`` to choose it from the data (up to
    ``options.max_links``; the reason is in ``result.link_reason``). ``options``: a
    :class:`FitOptions` (default: all defaults); keyword arguments override single settings
    (``fit(scan, 5, skin="seam")``). ``progress(stage, fraction) -> bool``: called as the fit
    goes; returning True cancels it (:class:`FitCancelled`, nothing produced).

    Vertices the scan stores more than once (copies at seams: the same rest position and motion,
    :mod:`seams`) are one point to the fit; the result is on the scan's own vertices, every copy
    with its point's values.

    Returns a :class:`FitResult`: links ``face_labels (T,)``, tree ``parents (L,)``, joints
    ``(L, 3)``, skin ``weights (N, L)``, pose parameters ``angles, locations (P, L, 3)``, rest-space
    residual ``(P, N, 3)`` … and ``save(path)`` / ``FitResult.load(path)``. Independent work runs
    on ``options.jobs`` processes (:mod:`parallel`; 1: in this process alone, the same rig).
    """
    o = _options(options, overrides)
    with _procs.pooled(o.processes):
        return _fit_pooled(scan, links, o, progress)


def _fit_pooled(scan, links, o: FitOptions, progress):
    """:func:`fit` inside its pool."""
    auto = isinstance(links, str) and links.strip().lower() == "auto"
    if not auto:
        if isinstance(links, bool) or not isinstance(links, (int, np.integer)):
            raise ScanError(f"links must be a whole number or 'auto', got {links!r}")
        links = int(links)
    stored, scan, weld = _checked(scan)      # copies at seams are one point to the fit
    requested, o = o, o.resolved(scan.kind)
    if o.mode == "pseudo" and scan.greens is None:
        raise OptionsError("pseudo-articulation needs a Green's-matrix scan (one model per load column)",
                           option="mode")
    key, seg = _checkout(scan, o, progress)
    seg_ok = False
    try:
        reason = ""
        result = None
        if auto:
            t_search = time.perf_counter()
            choice = _linkcount.choose_links(seg, max_links=o.max_links, progress=progress)
            search = time.perf_counter() - t_search
            links, reason = int(choice.links), str(choice.reason)
            errors = [float(e) for e in choice.errors]
            result = choice.reusable(o.mode, o.motion, o.skin)   # the chooser fitted this count already
            if result is not None:
                result.p_max = o.p_max
                result.timings = _search_timings(search, result.timings, 0.0)
        if result is None:
            result = _pipeline.fit(scan, links, o, progress, segmenter=seg)
            if auto:
                result.timings = _search_timings(search, result.timings, result.timings.get("total", 0.0))
        result.link_reason = reason
        result.link_errors = errors if auto else []
        result.options = requested     # as asked ("auto" kept); o.resolved(kind) is what ran
        result.reduced = bool(seg.reduced)
        result.estimate = seg.estimate
        result.groups = [list(g) for g in seg.groups]
        seg_ok = True
    finally:
        _checkin(key, seg, keep=seg_ok)
    # on the file's own vertices, the residual shapes of the rig on them
    return with_residual_shapes(_seams.expand_result(result, weld, stored), stored, o.residuals)


def with_residual_shapes(result, scan: Scan, residuals: int | None):
    """A tracked fit with its rig's residual shapes (:func:`residuals.low_rank_basis`: ``residuals``
    principal shapes, None: as many as the replay needs; its summary says how many and the replay
    error with and without them); a Green's fit as it is (one shape per field, driven by the loads)."""
    if scan.kind != "greens":
        result.residual_basis = _residuals.low_rank_basis(result, scan.vertices, scan.fields(), residuals)
    return result


def _search_timings(search: float, fit_timings: dict, after: float) -> dict:
    """A ``links auto`` fit's seconds per stage: ``"links"``, the link-count search (the fits it
    made included, the chosen count's among them when it is reused), then the chosen fit's own
    stages; ``"total"`` is the search and the fit made ``after`` it."""
    t = {"links": search, **fit_timings}
    t["total"] = search + after
    return t


def segment(scan: Scan, links: int, options: FitOptions | None = None, progress=None):
    """The links alone (Preview Links): ``(labels (T,), reduced, notes)`` — the link of every
    triangle for ``links`` links, whether the reduced method ran and the core's notes — from the
    same segmentation a :func:`fit` with these options makes (and keeps)."""
    o = _options(options, {})
    _, scan, _ = _checked(scan)
    o = o.resolved(scan.kind)
    with _procs.pooled(o.processes):
        key, seg = _checkout(scan, o, progress)
    seg_ok = False
    try:
        labels = seg.labels(int(links))
        seg_ok = True
        return labels, bool(seg.reduced), list(seg.notes)
    finally:
        _checkin(key, seg, keep=seg_ok)


def cached(scan: Scan, options: FitOptions | None = None):
    """The kept segmentation that a fit of ``scan`` with ``options`` would reuse, or None
    (nothing computed; for front ends that show whether a preview will be instant)."""
    o = _options(options, {})
    _, scan, _ = _checked(scan)
    o = o.resolved(scan.kind)
    est, _ = plan(scan.n_faces - len(scan.degenerate_faces), scan.n_fields, scan.n_vertices, scan.kind, o)
    return _SEGMENTERS.get(_key(scan, o, est.reduced))
