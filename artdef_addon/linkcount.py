"""Choosing the number of links from the data (``--links auto``).

The paper names the link count as its only parameter. Here it is chosen from the articulation
error curve: for every candidate k the segmentation is re-cut from the cached tree (no new
distances), each link moves with its robust motion, every vertex gets its best convex blend of
nearby link motions (:func:`skinning.refined_weights`), and e(k) is the Karni–Gotsman error
100·‖X − X̂‖/‖X − X̄‖ of that articulation (X̄ each vertex's mean over the fields; the rules below
read ratios of one scan's errors, which the choice of X̄ scales alike — docs/metrics.md). With too few links some part of the object cannot
follow; once every articulated part has its link the curve drops to a floor (noise, local
deformation). Where the scan has support vertices the fixed world is one more candidate motion
(the paper's ground link). The choice is the smallest k with

    log(e(k) / e_floor) ≤ τ · log(e(1) / e_floor),    e_floor = min_k e(k),

i.e. k gets within a fraction τ (default 0.15) of the whole drop, on a log scale. That k₀ is
where the big drop ends; past it the curve keeps falling slowly because extra links only
re-cut seams (roughly like a power of k), while a still-missing small link (a finger, a tail
segment) makes it fall faster. So from k₀ on, k grows while the error over the next h = 4 link
counts falls faster than k^(−s), s = 0.7 (log-log slope of the running minimum of e,
log(ê(k)/ê(k+h)) / log((k+h)/k) > s); the first k where it does not is the tree's choice.

The curve is read where the rule reads it (:func:`descending_curve`): e(1), then from Max Links
down until two counts in a row are above the τ bar; the counts under them (the big drop, and the
dearest segmentations) are left out, which gave the same picks as the whole curve on every shared
set.

Whole fits, upward (tracked scans without a fixed ground). The re-cut tree is cheap but a poor
segmentation for short, blended bones, so its curve flattens before they all have a link: it
undershoots on rigs with fingers and tail segments. The error of the whole fit (link swaps and
refined skin, :func:`pipeline.fit`) instead drops to the data's floor once every bone has its link. So
from the tree's choice k grows by the same slope rule on the whole fits' errors with
s = ``WHOLE_FIT_SLOPE`` (the scan's segmenter reused). It only adds links; a scan with support
vertices keeps the tree's choice (the fit's skin has no ground candidate, so a link would be
spent on the ground seam). The whole fits are spared where cheaper work gives the same decision
(:func:`_grown_upward`): each count is first fitted up to its split stage (:func:`partial_fit`,
finished with ``pipeline.fit(resume=...)`` only if it may be chosen), and the counts ahead are priced
by links grown one at a time on it (:func:`grow_link`, Dem Bones' way of adding a bone). Grown
links well below the slope rule's bar pass the count without a whole fit, well above it they stop
the search; in between whole fits decide, unless the count's own whole fit already has links that
are not bones (below): the search stops there. A count passed on to this way is fitted from the
links grown there (:func:`pipeline.fit_until`'s ``labels``), so its relabelling starts with the missing bone's
link in place. The chosen count's fit is the one handed back.
``benchmarks/results/links_auto.md`` has the counts against the whole-fit rule's.

Links that are not bones, downward (the same scans). Where the true skin weights are smooth
(many influences per vertex), the error keeps falling past the true count, because under the
4-influence limit a few more links explain a wide blend better than the true bones do. The
extra links are of two kinds (:func:`spurious_links`):

- *interpolating*: on its own vertices and over all fields, a convex blend of its neighbours'
  motions reproduces the link's motion with less than ``INTERPOLATING`` of the squared error of
  its best single neighbour (:func:`interpolating_links`); a true bone turns on its own;
- *blend handles*: the link owns a few triangles but its skin weights sum to more than
  ``HANDLE`` times the vertices of its own triangles, i.e. its motion serves mostly as an
  ingredient of other vertices' blends;
- *unused*: no vertex's skin follows the link by ``UNUSED`` or more (a sliver of a few triangles
  the search kept above the true count on new rigs, weighing 0.01-0.09 at most).

While the chosen fit has such links, k drops by their number and the scan is fitted again.

The measurements that set τ, s, ``WHOLE_FIT_SLOPE``, ``INTERPOLATING``, ``HANDLE`` and ``UNUSED`` (shared
rigged and CraGL sets): ``benchmarks/results/core_constants.md``; the method: docs/method.md,
"Automatic link count".
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np

from . import cost as _cost
from . import skinning
from .blas import single_threaded
from .merge import dominant_faces
from .model import skin_errors
from .quality import frame_spread


@dataclasses.dataclass
class LinkChoice:
    links: int
    errors: np.ndarray       # e(k) for k = 1..len(errors), percent
    tau: float
    reason: str
    tree_links: int = 0      # the re-cut tree's pick, before the whole fits
    upward_links: int = 0    # after the whole fits upward, before links that are not bones are dropped
    result: object = None    # the whole fit at ``links`` (pipeline.fit's defaults; a count climbed to from the
    #                          links grown below it: from those, see start_fit), when one was made
    timings: dict = dataclasses.field(default_factory=dict)   # seconds: curve, upward, drop
    whole_errors: dict = dataclasses.field(default_factory=dict)   # {count: whole-fit error %} upward
    grown_errors: dict = dataclasses.field(default_factory=dict)   # {count: grown error %} (grow_link)
    decisions: list = dataclasses.field(default_factory=list)      # [(count, how the rule decided)]
    # what the search did: {"whole_fits": n (finished fits), "partial_fits": n (fits run up to their split
    # stage, finished or not), "climbed_fits": n (of those, started from grown links), "grown_links": n,
    # "low_over_bar": [(count, grown links' lowest error / bar)]}
    # (the lowest of the links grown: a continue stops growing at the first under its bar)
    work: dict = dataclasses.field(default_factory=dict)

    def reusable(self, mode: str = "global", motion: str = "robust", skin: str | None = "auto"):
        """The chooser's own fit at the chosen count if it is the kind of fit ``pipeline.fit(scan, links,
        mode, motion, skin=skin)`` would return (same segmenter; a count climbed to is fitted from
        the links grown below it), else None — so callers need not fit it
        again."""
        if self.result is None or mode != "global" or motion != "robust" or skin not in (None, "auto", "refined"):
            return None
        return self.result if getattr(self.result, "skin", None) == "refined" else None


class SearchProgress:
    """The link-count search reported as one stage, ``"links"``, whose fraction only grows, from 0
    at the start of the tree's error curve to 1 when the count is chosen (the Segmenter's own
    stages before it and the final fit's after it are reported as usual).

    Work is counted in whole fits (:data:`cost.CURVE_FITS_PER_COUNT` a count of the curve, 1 a
    whole fit, :data:`cost.GROW_FITS` a link added to a decomposition); the search plans what it
    knows it will do and extends the plan when it needs more, so the fraction is done / planned,
    held from falling. ``progress(stage, fraction) -> bool`` as in :func:`pipeline.fit` (True cancels:
    :class:`fit.FitCancelled`)."""

    def __init__(self, progress, planned: float):
        self.progress = progress
        self.done = 0.0
        self.planned = float(planned)
        self.last = 0.0

    def plan(self, more: float) -> None:
        """At least ``more`` fits' work is still to come."""
        self.planned = max(self.planned, self.done + more)

    def report(self, extra: float = 0.0, final: bool = False) -> None:
        if self.progress is None:
            return
        frac = 1.0 if final else min(0.99, (self.done + extra) / max(self.planned, 1e-12))
        self.last = max(self.last, frac)
        if self.progress("links", self.last):
            from .result import FitCancelled
            raise FitCancelled("cancelled while choosing the link count")

    def step(self, units: float) -> None:
        self.done += units
        self.report()

    def fit_callback(self, units: float = 1.0):
        """A fit's ``progress``: its stages as parts of ``units`` of the search."""
        if self.progress is None:
            return None

        def report(stage, frac):
            at = _FIT_STAGE_AT.get(stage)
            if at is None:          # the segmentation's merge (fraction of its share)
                at = 0.1 * min(max(float(frac), 0.0), 1.0)
            self.report(units * at)
            return False
        return report


#: where each stage of a fit starts, as a fraction of the fit's time (tracked scans: the relabelling's
#: decompositions are most of it, the refined skin most of the rest)
_FIT_STAGE_AT = {"segment": 0.0, "motions": 0.1, "relabel": 0.1, "skin": 0.6, "split": 0.75, "joints": 0.95,
                 "bones": 0.96, "pose": 0.97, "residuals": 0.97, "done": 1.0}


def articulation_error_curve(seg, max_links: int, progress=None, counts=None) -> np.ndarray:
    """e(k) for k = 1..max_links (see module docstring), percent; with ``counts`` only at those
    counts (NaN elsewhere). ``progress``: a ``progress(stage, fraction)`` callback (the stage
    "links", fraction (k − 1)/max_links) or a :class:`SearchProgress` (one step per count)."""
    out = np.full(max_links, np.nan)
    for k in (range(1, max_links + 1) if counts is None else counts):
        if isinstance(progress, SearchProgress):
            progress.step(_cost.CURVE_FITS_PER_COUNT if k > 1 else 0.0)
        elif progress is not None and progress("links", (k - 1) / max_links):
            from .result import FitCancelled
            raise FitCancelled("cancelled while choosing the link count")
        out[k - 1] = curve_error(seg, k)
    if isinstance(progress, SearchProgress):
        progress.step(_cost.CURVE_FITS_PER_COUNT)
    return out


def curve_error(seg, k: int) -> float:
    """e(k) of the tree curve (see module docstring), percent."""
    scan = seg.scan
    ground = None
    if scan.support_vertices is not None:
        ground = np.zeros(scan.n_vertices, dtype=bool)
        ground[scan.support_vertices] = True
    lab, med, used = seg.segment(k)
    labels = seg.full_labels(lab)
    R = np.stack([seg.features[p].R[med[:, i]] for i, p in enumerate(used)])
    t = np.stack([seg.features[p].t[med[:, i]] for i, p in enumerate(used)])
    fields = scan.fields()[used]
    X = scan.vertices[None] + fields
    den = np.linalg.norm(X - X.mean(axis=0))
    # candidates: each vertex's 4 best single links. The curve and its rule were set on these;
    # the wider pool of the fit's skin lowers e(k) by a few 0.01 % at large k only, but moves
    # the slope rule's choice on flat tails (cylinder 4 → 7 links, RiggedFigure 20 → 23)
    w = skinning.refined_weights(scan.vertices, fields, scan.faces, labels, R, t, ground=ground, rings=2, pool=4)
    if ground is not None:  # the fixed world is one more "link" with the identity motion
        R = np.concatenate([R, np.tile(np.eye(3), (len(used), 1, 1, 1))], axis=1)
        t = np.concatenate([t, np.zeros((len(used), 1, 3))], axis=1)
    err = float(skin_errors(w, R, t, scan.vertices, fields).sum())
    return 100.0 * np.sqrt(err) / den if den > 0 else 0.0


def descending_curve(seg, max_links: int, tau: float = 0.15, progress=None) -> np.ndarray:
    """The tree curve where the rule reads it: e(1), then e(k) from ``max_links`` down until two
    counts in a row are above the tau bar e_floor·(e(1)/e_floor)^τ of the counts so far (NaN below
    them). The counts left out are under that pair, where a rig's curve is still in its big drop:
    the rule's first count within tau (k₀) and everything above it are read as from the whole curve
    unless a count under the pair were within tau again (the same tree picks on the 23 curves of
    the shared sets, 15-20 of CesiumMan's 30 counts computed; ``cost.CURVE_SHARE``).
    The low counts are the dear ones (a few large clusters' medoids and seams)."""
    out = np.full(max_links, np.nan)
    search = progress if isinstance(progress, SearchProgress) else SearchProgress(None, 1.0)
    search.step(0.0)                 # the search has begun: 0
    out[0] = curve_error(seg, 1)
    for k in range(max_links, 1, -1):
        search.step(_cost.CURVE_FITS_PER_COUNT)
        out[k - 1] = curve_error(seg, k)
        floor, top = _floor_top(out)
        bar = floor * (top / floor) ** tau
        if k < max_links and out[k - 1] > bar and out[k] > bar:
            break
    search.step(_cost.CURVE_FITS_PER_COUNT)
    return out


def _floor_top(e: np.ndarray) -> tuple:
    """The tree curve's floor e_floor = min_k e(k) (at least 1e-3 %) and top e(1) (at least the
    floor), over the counts computed (NaN elsewhere): the ends of the tau rule's log scale."""
    floor = max(float(np.nanmin(e)), 1e-3)
    return floor, max(float(e[0]), floor)


#: log-log slope below which the whole fits' error counts as levelled off (see module docstring)
WHOLE_FIT_SLOPE = 2.0
#: the upward search continues on grown links (:func:`_grown_upward`) when their errors fall below
#: this many times the bar (whole fits: 0.12-0.17 x at CesiumMan's continues, grown links 0.23-0.39 x)
GROWN_CONTINUE = 0.5
#: ... but not where the count's error (percent) is below this, where a bone is no longer clearly
#: missing: near the floor grown links and whole fits part ways (RiggedFigure's own poses at 20 links,
#: 0.021 %: the links grown on the whole fit 0.23 x the bar, the whole fits of 21-24 3.1-4.3 x, as
#: whole fits get worse with more links on its 130 vertices; a noiseless scan's grown errors fall
#: by ratios of rounding, the 11-link branching sample 2e-13 % at 11, 0 at 12). The counts passed
#: on grown links on the shared sets stood at 0.24-0.74 % (CesiumMan, the Fox)
GROWN_FLOOR = 0.1
#: ... and only from counts at most this many grown links above the chain's fit: further up the
#: chain's own error stands in for the count's, and the bar with it. A chain started far below the
#: truth kept falling past it at depth 5 (the Fox's fresh poses from 17 links: passed 22, the true
#: count, and stopped at 24), and at depth 1 on the 11-link branching sample (its grown 11th link
#: short of the exact segment the whole fit finds, the next ones at 0: passed 11). With the floor
#: below, depth 1 still passed the Fox's true count (22 → 23, both pose sets) and climbed CesiumMan's
#: fresh seed 9 to 20
CONTINUE_DEPTH = 0
#: the upward search stops on grown links (:func:`_grown_upward`) only when their errors stay above
#: this many times the bar. A whole fit re-segments, swaps and splits links, so from a chain grown on
#: the first whole fit it could end far below the grown error of its count (0.23-1.2 x; the Fox's own
#: poses at 23 links: grown 1.92 x the bar, whole fits 0.43 x), which would need a margin of 2.5. Grown
#: on the count's own fit (the chain starts again at every fit), the links land within 0.6-1.3 x of the next
#: count's whole fit on CesiumMan, and its stops stood at 1.34-3.2 x (whole fits 1.27-2.1 x): at 1.25
#: every grown stop on the shared sets is the whole fits' too (``links_auto.py --verify``, links_auto.md)
GROWN_MARGIN = 1.25
#: ... and from this many times the bar where the count's error is below ``GROWN_FLOOR``. There
#: the whole fits measure their own optimisation more than a missing bone: past the true count
#: they rise and fall by 1.5-2 x from one count to the next (CesiumMan fresh seed 7: 0.025 % at 19,
#: 0.050 % at 20; RiggedFigure 0.021 % at 20, 0.046 % at 21) and end above the links grown on the
#: fit (1.5-13 x), so the slope rule on them continued past the truth on RobotExpressive (36 → 37,
#: both pose sets) and cost CesiumMan's fresh seed 2 four more whole fits for its stop. A missing
#: bone still shows at the floor as a drop of the grown links to below half the bar (Robot's 36th
#: link: whole fits 0.075 % → 0.019 %, the grown 0.22 x the bar from 35)
FLOOR_MARGIN = 0.5
#: whole-fit error (percent) at which nothing is left to explain: the search stops, as
#: :func:`_whole_fits_upward` does (a floor of 0.01 % would spare the rigid sets their window's
#: whole fits, but is not the whole-fit rule)
EXPLAINED = 1e-9


def choose_links(seg, max_links: int = 30, tau: float = 0.15, progress=None, slope: float = 0.7,
                 window: int = 4, whole_fits: bool | None = None) -> LinkChoice:
    """Pick the link count for a :class:`fit.Segmenter` (see module docstring). ``whole_fits``
    (default: for tracked scans without support vertices) continues upward with whole fits.
    ``progress(stage, fraction)``: the search is reported as the stage ``"links"`` (see
    :class:`SearchProgress`)."""
    max_links = int(max(1, min(max_links, len(seg.valid))))
    scan = seg.scan
    if whole_fits is None:
        whole_fits = scan.kind != "greens" and scan.support_vertices is None
    search = progress if isinstance(progress, SearchProgress) else SearchProgress(
        progress, _cost.CURVE_FITS_PER_COUNT * max_links + (1.0 + window * _cost.GROW_FITS if whole_fits else 0.0))
    with seg.remembering():
        return _choose_links(seg, max_links, tau, search, slope, window, whole_fits)


def _choose_links(seg, max_links, tau, search, slope, window, whole_fits) -> LinkChoice:
    """:func:`choose_links` after its arguments are settled."""
    t0 = time.perf_counter()
    with single_threaded():      # thousands of small distance products (see :mod:`blas`)
        e = descending_curve(seg, max_links, tau, progress=search)
    timings = {"curve": time.perf_counter() - t0}
    floor, top = _floor_top(e)
    if top <= floor * 1.0001:
        k = 1
        why = f"one rigid motion explains every field (error {e[0]:.3g}%)"
    else:
        frac = np.log(np.maximum(e, floor) / floor) / np.log(top / floor)     # NaN where not computed
        k0 = int(np.flatnonzero(frac <= tau)[0]) + 1
        # best error with at most k links (of the counts computed)
        env = np.minimum.accumulate(np.where(np.isnan(e), np.inf, np.maximum(e, floor)))
        k = k0
        while k < max_links:
            j = min(max_links, k + window)
            if np.log(env[k - 1] / env[j - 1]) / np.log(j / k) <= slope:
                break
            k += 1
        why = (f"articulation error {e[0]:.2f}% with 1 link, {e[k0 - 1]:.2f}% with {k0} (within tau={tau:g} of the "
               f"floor {np.nanmin(e):.2f}% by {max_links} on a log scale)")
        if k > k0:
            why += (f", still falling faster than k^-{slope:g} over the next {window} link counts up to {k} "
                    f"({e[k - 1]:.2f}%)")
        else:
            why += f"; beyond it the error falls slower than k^-{slope:g}"
    tree_links = k
    fits = {}
    work = {"whole_fits": 0, "partial_fits": 0, "grown_links": 0}
    k1 = k
    ef, eg, decisions = {}, {}, []
    if whole_fits:
        t0 = time.perf_counter()
        if k < max_links:
            k1, ef, eg, decisions = _grown_upward(seg, k, max_links, window, search, fits, work)
            why += f". Whole fits from {k} links" + (f": error {ef[k]:.3g}%" if k in ef
                                                     else " (passed on links grown on its fit)")
            if k1 > k:
                why += f", {ef[k1]:.3g}% with {k1}"
            why += f"; beyond it the error falls slower than k^-{WHOLE_FIT_SLOPE:g} over {window} more links"
        timings["upward"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        k, steps = _drop_non_bones(seg, k1, fits, search)
        timings["drop"] = time.perf_counter() - t0
        if k < k1:
            why += (". Links that are not bones (moving as a blend of their neighbours, lending their motion "
                    "to blends far beyond their own triangles, or followed by no vertex): " + ", ".join(f"{n} of {j}" for j, n in steps)
                    + f", so {k}")
    if np.isnan(e[k - 1]):           # chosen below the counts the rule read (the drop of non-bones)
        with single_threaded():
            e[k - 1] = curve_error(seg, k)
    search.report(final=True)
    work["whole_fits"] = len(fits)
    return LinkChoice(k, e, tau, f"links auto: chose {k}. {why}", tree_links, k1, fits.get(k), timings,
                      ef, eg, decisions, work)


#: blend-to-single squared-error ratio below which a link is interpolating (see module docstring)
INTERPOLATING = 0.2
#: skin weight mass per owned vertex above which a link is a blend handle (see module docstring)
HANDLE = 3.0
#: a link no vertex's skin follows by at least this weight is unused (not a bone): on twelve rigs built
#: outside the shared data (``benchmarks/results/fidelity.md``, "Rigs outside the shared data") the slivers
#: the search kept over the true count (4-9 faces) weighed at most 0.09 anywhere, where the smallest true
#: bones of the shared sets reach 0.47 or more (the Fox's 2-face and RiggedFigure's 1-face bones)
UNUSED = 0.25


def spurious_links(x0: np.ndarray, faces: np.ndarray, result) -> np.ndarray:
    """(L,) bool: the links of a fit that are not bones — interpolating (ρ < ``INTERPOLATING``,
    :func:`interpolating_links`), blend handles (Σ_v w_vl > ``HANDLE`` × the vertices of the
    link's own triangles) or unused (max_v w_vl < ``UNUSED``). ``result``: a :class:`fit.FitResult`."""
    L = result.rotations.shape[1]
    unused = result.weights[:, :L].max(axis=0) < UNUSED
    # an unused link is no motion of the object: blends are made of the links the skin follows only
    rho = interpolating_links(x0, faces, result.face_labels, result.rotations, result.translations,
                              ingredients=~unused)
    n_owned = np.diff(skinning.link_incidence(x0.shape[0], faces, result.face_labels, L).indptr)
    mass = result.weights[:, :L].sum(axis=0)
    return (rho < INTERPOLATING) | (mass > HANDLE * np.maximum(n_owned, 1)) | unused


def interpolating_links(x0: np.ndarray, faces: np.ndarray, labels: np.ndarray, R: np.ndarray,
                        t: np.ndarray, ingredients: np.ndarray | None = None) -> np.ndarray:
    """Per link, how well its neighbours' motions explain its own (the ratio ρ of the module
    docstring; links with no neighbour or a motion equal to a neighbour's get 1).

    For link j with vertices V_j (those of its triangles) and neighbours K_j (links sharing a
    vertex with it), d_k(v, p) = (R_k^p x0(v) + t_k^p) − (R_j^p x0(v) + t_j^p) and
    ρ_j = min_{c ≥ 0, Σc = 1} ‖Σ_k c_k d_k‖² / min_k ‖d_k‖²  over v ∈ V_j and all fields p.
    ``labels`` (T,) face labels (−1: none), R (P, L, 3, 3), t (P, L, 3). ``ingredients`` (L,) bool:
    the links a blend may use (default all). :func:`spurious_links` leaves out the unused links: a
    sliver no vertex follows has a motion fitted to a few faces, which can lie anywhere between its
    neighbours', and blends of such motions reproduced a true bone beside them (the hand-off tests'
    three-bone leg at 8 links: slivers between hip and knee gave the hip ρ = 0.12, and the drop of
    non-bones went to 2 links instead of 3).
    """
    L = R.shape[1]
    inc = skinning.link_incidence(x0.shape[0], faces, labels, L)
    adj = (inc.T @ inc).toarray() > 0
    xh = np.concatenate([x0, np.ones((x0.shape[0], 1))], axis=1)
    A = np.concatenate([R, t[..., None]], axis=-1)        # (P, L, 3, 4): x ↦ R x + t on x̃ = (x, 1)
    out = np.ones(L)
    for j in range(L):
        nb = np.flatnonzero(adj[j])
        nb = nb[nb != j]
        if ingredients is not None:
            nb = nb[ingredients[nb]]
        if nb.size == 0:
            continue
        vj = inc.indices[inc.indptr[j]:inc.indptr[j + 1]]
        S = xh[vj].T @ xh[vj]                             # Σ_v x̃ x̃ᵀ over the link's vertices
        dA = A[:, nb] - A[:, j:j + 1]                     # d_k(v, p) = dA_k^p x̃_v
        Q = np.einsum("pkab,bc,plac->kl", dA, S, dA, optimize=True)   # Σ_p Σ_v d_k · d_l
        single = float(np.min(np.diag(Q)))
        if single <= 1e-12 * max(float(np.max(np.diag(Q))), 1e-300):
            continue
        c = skinning.simplex_least_squares(Q[None], np.zeros((1, nb.size)), np.ones((1, nb.size), dtype=bool))[0]
        out[j] = max(float(c @ Q @ c), 0.0) / single
    return out


def _drop_non_bones(seg, k: int, fits: dict, progress=None):
    """From ``k``, while the fit has links that are not bones (:func:`spurious_links`), take that
    many links off and fit again. Returns (k, [(count, such links), ...]). ``progress``: a
    callback or a :class:`SearchProgress`."""
    from .pipeline import fit
    scan = seg.scan
    search = progress if isinstance(progress, SearchProgress) else SearchProgress(progress, 1.0)
    steps = []
    while k > 1:
        if k not in fits:
            search.plan(1.0)
            fits[k] = fit(scan, k, None, search.fit_callback(), segmenter=seg)
            search.step(1.0)
        r = fits[k]
        n = int(np.count_nonzero(spurious_links(scan.vertices, scan.faces, r)))
        steps.append((k, n))
        if n == 0:
            break
        k = max(1, k - n)
        search.plan(1.0)
    return k, steps


def grow_link(x0: np.ndarray, fields: np.ndarray, faces: np.ndarray, labels: np.ndarray, w: np.ndarray,
              R: np.ndarray, t: np.ndarray, units: np.ndarray, spread: float):
    """One more link where the skin fits worst, and the skin decomposition from there (Dem Bones'
    way of adding a bone; the seeding of :mod:`swaps`).

    The skin ``w (N, L)`` with motions ``R (P, L, 3, 3)``, ``t (P, L, 3)`` explains vertex v with
    error e_v = Σ_p ‖Σ_l w_vl (R_l^p x_v + t_l^p) − x_v^p‖². The clustered triangle (``units``) of
    largest Σ e over its corners, with the triangles of its link that share a vertex with it,
    becomes link L, moving with the least-squares rigid motion of those triangles (Kabsch/Arun,
    docs/method_notes_model.md §6); the decomposition (:func:`skinning.alternate_scored`, ``swaps.TRIAL_ROUNDS``
    rounds as a swap trial, on the relabelling's vertex sample :func:`skinning.vertex_sample`,
    extended to every vertex by :func:`skinning.full_skin`) then starts from ``w`` (the new link
    at weight 0) and every face goes to the link of its largest summed weight.
    A seed whose ring would leave its link without a clustered triangle is passed over.
    ``labels (T,)``; ``spread`` ‖X − X̄‖² (the Karni–Gotsman denominator).

    Returns ``(labels (T,), w (N, L+1), R (P, L+1, 3, 3), t (P, L+1, 3), error %)``.
    """
    from .joints import lsq_motions
    from .swaps import TRIAL_ROUNDS
    L = R.shape[1]
    face_err = skin_errors(w, R, t, x0, fields)[faces].sum(axis=1)
    order = units[np.argsort(-face_err[units], kind="stable")]
    unit_count = np.bincount(labels[units], minlength=L)
    new = None
    for seed in order[:16]:
        ring = np.flatnonzero(np.isin(faces, faces[seed]).any(axis=1) & (labels == labels[seed]))
        lost = np.bincount(labels[np.intersect1d(ring, units, assume_unique=True)], minlength=L)
        if np.all(unit_count - lost > 0):
            new = labels.copy()
            new[ring] = L
            break
    if new is None:                       # every link is a single ring: nothing to split
        return None
    Rr, tr = lsq_motions(x0, fields, faces[ring], np.zeros(len(ring), dtype=np.int64), 1, corner_weights=True)
    R1 = np.concatenate([R, Rr], axis=1)
    t1 = np.concatenate([t, tr], axis=1)
    w0 = np.concatenate([w, np.zeros((w.shape[0], 1))], axis=1)
    rows = skinning.vertex_sample(faces, new, x0.shape[0])   # as the relabelling: None on small meshes
    w1, R1, t1, e1 = skinning.alternate_scored(x0, fields, faces, new, R1, t1, iterations=TRIAL_ROUNDS, w_init=w0,
                                               rows=rows)
    if rows is not None:
        w1, e1 = skinning.full_skin(x0, fields, faces, new, R1, t1, rows=rows, w_rows=w1)[:2]
    grown = dominant_faces(w1, faces, new, units)
    return grown, w1, R1, t1, (100.0 * np.sqrt(max(e1, 0.0) / spread) if spread > 0 else 0.0)


def _grown_upward(seg, k: int, max_links: int, window: int, search: SearchProgress, fits: dict,
                  work: dict | None = None):
    """:func:`_whole_fits_upward`'s choice with fewer whole fits.

    At count k the rule asks whether one of the next ``window`` counts has a whole-fit error below
    ``bar`` = best·(k/(k+window))^s (best: the lowest error up to k, s = ``WHOLE_FIT_SLOPE``);
    :func:`_whole_fits_upward` fits all of them to know. Here the question goes first to links
    grown one at a time (:func:`grow_link`) on the latest whole fit, a chain started again at every
    new whole fit (a link grown on a whole fit lands within 0.6-1.3 x of the next count's whole
    fit on CesiumMan; grown on grown links it drifts up, to 4 x where a whole fit's swaps find the
    bone):

    - the chain falls below ``GROWN_CONTINUE`` × the bar: continue to k+1 without fitting it (its
      error, until it is fitted, the chain's);
    - otherwise k gets its whole fit first (when it has none yet, the chain is grown again on it);
      then, when that fit already has links that are not bones (:func:`spurious_links`), stop at k:
      the count is past the bones and the drop of non-bones that follows would take the counts above
      it down again, so neither a second chain on k nor the whole fits of a close call above it are
      made (dembones_bone's search 57 -> 19 s, RiggedFigure's 15.0 -> 4.1-4.8 s, the same counts on
      every row of ``benchmarks/results/links_auto.md``);
      when the chain stays above ``GROWN_MARGIN`` × the bar, stop at k too;
    - otherwise whole fits decide, k+1 first, then the others in the order of their grown errors,
      until one is below the bar (continue) or none is (stop), as :func:`_whole_fits_upward`.

    The count stopped at always has its whole fit (kept in ``fits``; the other fitted counts too).
    Returns (k, {count: whole-fit error %}, {count: grown error %, the last chain's}, [(k, how),
    ...] with how "grown" / "whole" / "non-bones" (stops), "explained", "continue" (whole fits), "grown
    continue"); the figures and the whole fits' agreement: ``benchmarks/results/links_auto.md``.
    ``work["grown_links"]`` counts the links grown."""
    from .pipeline import fit
    work = {} if work is None else work
    scan = seg.scan
    x0, faces, fields = scan.vertices, scan.faces, scan.fields()
    spread = frame_spread(x0, fields)   # ‖X − X̄‖², X̄ a frame's centroid
    units = seg.valid[seg.unit_tri]
    start = k
    errors: dict[int, float] = {}       # whole fits
    known: dict[int, float] = {}        # each count passed: its whole fit's error, else the chain's
    grown: dict[int, float] = {}        # the chain's errors, from its base
    chain: dict[int, object] = {}       # count -> (labels, w, R, t) of the chain, or None (nothing to grow)
    partial: dict[int, tuple] = {}      # count -> (FitState, seconds) of a fit run up to its split stage
    decisions = []

    def whole(j):
        if j not in errors:
            if j not in fits:
                share = 1.0 - PARTIAL_SHARE if j in partial else 1.0
                search.plan(share)
                fits[j] = fit(scan, j, None, search.fit_callback(share), segmenter=seg, resume=partial.pop(j, None))
                search.step(share)
            e = float(fits[j].articulation_error_percent)
            errors[j] = e if np.isfinite(e) else 0.0   # undefined (one field): nothing to explain
        known[j] = errors[j]
        return errors[j]

    def start_fit(j):
        """The whole fit at j run up to its split stage (:func:`partial_fit`): the chain's base, and
        the error of that skin as the count's until the fit is finished. A count the chain passed
        on (grown continue) starts from the chain's links at j (:func:`partial_fit`'s ``start``: the
        grown link in place) instead of a new cut of the tree, whose swaps would look for the missing
        bone again (CesiumMan's seed 9: 1.6 s a climbed count against 2.6-3.4 s, the same counts and
        rigs as good on every row of ``benchmarks/results/links_auto.md``). Not for the whole fits that
        decide close calls: from a chain they climb past the truth (the Fox to 23 and 24)."""
        search.plan(PARTIAL_SHARE)
        work["partial_fits"] = work.get("partial_fits", 0) + 1
        grown_state = chain.get(j)
        if grown_state is not None:
            work["climbed_fits"] = work.get("climbed_fits", 0) + 1
        st, secs, e = partial_fit(seg, j, search.fit_callback(PARTIAL_SHARE),
                                  start=None if grown_state is None else grown_state[0])
        search.step(PARTIAL_SHARE)
        partial[j] = (st, secs)
        known[j] = e
        chain.clear()
        grown.clear()
        chain[j] = (st.labels, st.weights, st.Rs, st.ts)
        grown[j] = e

    def rebase(j):
        """The chain from the whole fit at j."""
        base = fits[j]
        L = base.rotations.shape[1]
        chain.clear()
        grown.clear()
        chain[j] = (base.face_labels, base.weights[:, :L], base.rotations, base.translations)
        grown[j] = errors[j]

    def grow_to(j, k=None, below=None):
        """The chain grown to count j; with ``below``, only until a count above k has a grown
        error under it (the continue decision is then made: the rest would not change it)."""
        top = max(chain)
        search.plan(_cost.GROW_FITS * max(j - top, 0))
        while top < j:
            if below is not None and any(grown[i] < below for i in range(k + 1, top + 1)):
                break
            work["grown_links"] = work.get("grown_links", 0) + 1
            with single_threaded():      # a proxy: its small products need no BLAS threads either
                g = grow_link(x0, fields, faces, *chain[top], units, spread) if chain[top] is not None else None
            grown[top + 1] = grown[top] if g is None else float(g[4])
            chain[top + 1] = None if g is None else g[:4]
            top += 1
            search.step(_cost.GROW_FITS)

    verdicts: dict[int, bool] = {}      # count -> its whole fit has links that are not bones

    def past_bones(j):
        """Whether j's whole fit has links that are not bones; asked once a count."""
        if j not in verdicts:
            verdicts[j] = bool(np.any(spurious_links(x0, faces, fits[j])))
        return verdicts[j]

    start_fit(start)
    while k < max_links:
        j = min(max_links, k + window)
        best_k = min(known[i] for i in range(start, k + 1))
        if best_k <= EXPLAINED and k in errors:
            decisions.append((k, "explained"))
            break
        bar = best_k * (k / j) ** WHOLE_FIT_SLOPE   # log(best/e)/log(j/k) > s  <=>  e < bar
        if k - min(chain) > CONTINUE_DEPTH and k not in errors and k not in partial:
            start_fit(k)                 # the chain is too long to pass more counts on: start again at k
            continue
        may_continue = best_k > GROWN_FLOOR and k - min(chain) <= CONTINUE_DEPTH
        grow_to(j, k, GROWN_CONTINUE * bar if may_continue else None)
        low = min(grown[i] for i in range(k + 1, j + 1) if i in grown)   # all of them unless it continues
        work.setdefault("low_over_bar", []).append((k, low / bar if bar > 0 else float("inf")))
        if low < GROWN_CONTINUE * bar and may_continue:
            decisions.append((k, "grown continue"))
            k += 1
            known.setdefault(k, grown[k])
            continue
        if k not in errors:              # a stop or a close call: k's own whole fit first
            based = k in partial         # the chain grew from this fit's skin before its split stage
            whole(k)
            if past_bones(k):
                decisions.append((k, "non-bones"))   # k is already past the bones: the drop takes it down
                break
            if not (based and fits[k].n_links == known_links(chain[k]) and errors[k] >= grown[k] * (1 - 1e-6)):
                rebase(k)                # the split stage changed the fit: grow the chain again
            continue
        if low >= (GROWN_MARGIN if best_k > GROWN_FLOOR else FLOOR_MARGIN) * bar:
            decisions.append((k, "grown"))
            break
        if past_bones(k):
            decisions.append((k, "non-bones"))
            break
        order = [k + 1] + sorted(range(k + 2, j + 1), key=grown.get)
        if not any(whole(i) < bar for i in order):
            decisions.append((k, "whole"))
            break
        decisions.append((k, "continue"))
        k += 1
        rebase(k)                        # k + 1 was fitted first
    whole(k)
    return k, errors, grown, decisions


#: the share of a whole fit's time up to its split stage (CesiumMan: 0.6-0.7), for the progress
PARTIAL_SHARE = 0.65


def known_links(state) -> int:
    """The link count of a chain state (labels, w, R, t)."""
    return -1 if state is None else int(state[2].shape[1])


def partial_fit(seg, k: int, progress=None, start=None):
    """The whole fit (:func:`pipeline.fit`, its defaults) at ``k`` links run up to, not including, its
    split stage: ``(state, seconds per stage, error %)``, the error the Karni–Gotsman error of
    the refined skin (weights with the skin's own motions), which the split stage only lowers
    (the whole fit's error is that of its final skin: ``fit.stage_residuals``).
    ``pipeline.fit(..., resume=(state, seconds))`` finishes the same fit. ``start``: face labels (T,)
    of ``k`` links to start from instead of the Segmenter's cut (:func:`pipeline.fit_until`: a count the
    search climbed to, from the links grown on the count below)."""
    from .pipeline import fit_until
    scan = seg.scan
    x0, fields = scan.vertices, scan.fields()
    st, secs = fit_until(seg, k, "split", progress, labels=start)
    err = float(skin_errors(st.weights, st.Rs, st.ts, x0, fields).sum())
    spread = frame_spread(x0, fields)
    return st, secs, (100.0 * np.sqrt(err / spread) if spread > 0 else 0.0)


def _whole_fits_upward(seg, k: int, max_links: int, window: int, progress=None, fits=None):
    """From ``k``, add links while the whole fits' articulation error (running minimum) over the
    next ``window`` counts falls faster than k^(−WHOLE_FIT_SLOPE). Returns (k, {count: error %})."""
    from .pipeline import fit
    errors: dict[int, float] = {}
    fits = {} if fits is None else fits
    start = k

    def error(j):
        if j not in errors:
            span = max(max_links - start, 1)
            report = None
            if progress is not None:
                def report(stage, frac, j=j):
                    return progress("links", min(1.0, (j - start + frac) / span))
            fits[j] = fit(seg.scan, j, None, report, segmenter=seg)
            e = float(fits[j].articulation_error_percent)
            errors[j] = e if np.isfinite(e) else 0.0   # undefined (one field): nothing to explain
        return errors[j]

    while k < max_links:
        j = min(max_links, k + window)
        best_k = min(error(i) for i in range(start, k + 1))
        best_j = min(best_k, min(error(i) for i in range(k + 1, j + 1)))
        if best_k <= 1e-9 or np.log(best_k / max(best_j, 1e-300)) / np.log(j / k) <= WHOLE_FIT_SLOPE:
            break
        k += 1
    error(k)
    return k, errors
