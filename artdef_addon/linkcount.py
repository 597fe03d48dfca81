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

Whole fits, upward (tracked scans without a fixed ground). The re-cut tree is cheap but a poor
segmentation for short, blended bones, so its curve flattens before they all have a link: it
undershoots on rigs with fingers and tail segments. The error of the whole fit (link swaps and
refined skin, :func:`fit.fit`) instead drops to the data's floor once every bone has its link. So
from the tree's choice k grows by the same slope rule on the whole fits' errors with
s = ``WHOLE_FIT_SLOPE`` (one fit per count, the scan's segmenter reused). It only
adds links; a scan with support vertices keeps the tree's choice (the fit's skin has no ground
candidate, so a link would be spent on the ground seam).

Links that are not bones, downward (the same scans). Where the true skin weights are smooth
(many influences per vertex), the error keeps falling past the true count, because under the
4-influence limit a few more links explain a wide blend better than the true bones do. The
extra links are of two kinds (:func:`spurious_links`):

- *interpolating*: on its own vertices and over all fields, a convex blend of its neighbours'
  motions reproduces the link's motion with less than ``INTERPOLATING`` of the squared error of
  its best single neighbour (:func:`interpolating_links`); a true bone turns on its own;
- *blend handles*: the link owns a few triangles but its skin weights sum to more than
  ``HANDLE`` times the vertices of its own triangles, i.e. its motion serves mostly as an
  ingredient of other vertices' blends.

While the chosen fit has such links, k drops by their number and the scan is fitted again.

The measurements that set τ, s, ``WHOLE_FIT_SLOPE``, ``INTERPOLATING`` and ``HANDLE`` (shared
rigged and CraGL sets): ``benchmarks/results/core_constants.md``; the method: docs/method.md,
"Automatic link count".
"""
from __future__ import annotations

import dataclasses

import numpy as np

from . import skinning
from .model import skin


@dataclasses.dataclass
class LinkChoice:
    links: int
    errors: np.ndarray       # e(k) for k = 1..len(errors), percent
    tau: float
    reason: str
    tree_links: int = 0      # the re-cut tree's pick, before the whole fits
    upward_links: int = 0    # after the whole fits upward, before links that are not bones are dropped
    result: object = None    # the whole fit at ``links`` (fit.fit's defaults), when one was made

    def reusable(self, mode: str = "global", motion: str = "robust", skin: str | None = "auto"):
        """The chooser's own fit at the chosen count if it is what ``fit.fit(scan, links, mode,
        motion, skin=skin)`` would return (same segmenter), else None — so callers need not fit it
        again."""
        if self.result is None or mode != "global" or motion != "robust" or skin not in (None, "auto", "refined"):
            return None
        return self.result if getattr(self.result, "skin", None) == "refined" else None


def articulation_error_curve(seg, max_links: int, progress=None) -> np.ndarray:
    """e(k) for k = 1..max_links (see module docstring), percent."""
    scan = seg.scan
    fields_all = scan.fields()
    ground = None
    if scan.support_vertices is not None:
        ground = np.zeros(scan.n_vertices, dtype=bool)
        ground[scan.support_vertices] = True
    out = []
    for k in range(1, max_links + 1):
        if progress is not None and progress("links", (k - 1) / max_links):
            from .fit import FitCancelled
            raise FitCancelled("cancelled while choosing the link count")
        lab, med, used = seg.segment(k)
        labels = seg.full_labels(lab)
        R = np.stack([seg.features[p].R[med[:, i]] for i, p in enumerate(used)])
        t = np.stack([seg.features[p].t[med[:, i]] for i, p in enumerate(used)])
        fields = fields_all[used]
        X = scan.vertices[None] + fields
        den = np.linalg.norm(X - X.mean(axis=0))
        # candidates: each vertex's 4 best single links. The curve and its rule were set on these;
        # the wider pool of the fit's skin lowers e(k) by a few 0.01 % at large k only, but moves
        # the slope rule's choice on flat tails (cylinder 4 → 7 links, RiggedFigure 20 → 23)
        w = skinning.refined_weights(scan.vertices, fields, scan.faces, labels, R, t, ground=ground, rings=2,
                                     pool=4)
        if ground is not None:  # the fixed world is one more "link" with the identity motion
            R = np.concatenate([R, np.tile(np.eye(3), (len(used), 1, 1, 1))], axis=1)
            t = np.concatenate([t, np.zeros((len(used), 1, 3))], axis=1)
        err = sum(np.sum((skin(w, R[i], t[i], scan.vertices) - X[i]) ** 2) for i in range(len(used)))
        out.append(100.0 * np.sqrt(err) / den if den > 0 else 0.0)
    return np.array(out)


#: log-log slope below which the whole fits' error counts as levelled off (see module docstring)
WHOLE_FIT_SLOPE = 2.0


def choose_links(seg, max_links: int = 30, tau: float = 0.15, progress=None, slope: float = 0.7,
                 window: int = 4, whole_fits: bool | None = None) -> LinkChoice:
    """Pick the link count for a :class:`fit.Segmenter` (see module docstring). ``whole_fits``
    (default: for tracked scans without support vertices) continues upward with whole fits."""
    max_links = int(max(1, min(max_links, len(seg.valid))))
    e = articulation_error_curve(seg, max_links, progress=progress)
    floor = max(float(e.min()), 1e-3)
    top = max(float(e[0]), floor)
    if top <= floor * 1.0001:
        k = 1
        why = f"one rigid motion explains every field (error {e[0]:.3g}%)"
    else:
        frac = np.log(np.maximum(e, floor) / floor) / np.log(top / floor)
        k0 = int(np.flatnonzero(frac <= tau)[0]) + 1
        env = np.minimum.accumulate(np.maximum(e, floor))  # best error with at most k links
        k = k0
        while k < max_links:
            j = min(max_links, k + window)
            if np.log(env[k - 1] / env[j - 1]) / np.log(j / k) <= slope:
                break
            k += 1
        why = (f"articulation error {e[0]:.2f}% with 1 link, {e[k0 - 1]:.2f}% with {k0} (within tau={tau:g} of the "
               f"floor {e.min():.2f}% by {max_links} on a log scale)")
        if k > k0:
            why += (f", still falling faster than k^-{slope:g} over the next {window} link counts up to {k} "
                    f"({e[k - 1]:.2f}%)")
        else:
            why += f"; beyond it the error falls slower than k^-{slope:g}"
    tree_links = k
    scan = seg.scan
    if whole_fits is None:
        whole_fits = scan.kind != "greens" and scan.support_vertices is None
    if whole_fits:
        fits = {}
        k1 = k
        if k < max_links:
            k1, ef = _whole_fits_upward(seg, k, max_links, window, progress, fits)
            why += f". Whole fits from {k} links: error {ef[k]:.3g}%"
            if k1 > k:
                why += f", {ef[k1]:.3g}% with {k1}"
            why += f"; beyond it the error falls slower than k^-{WHOLE_FIT_SLOPE:g} over {window} more links"
        k, steps = _drop_non_bones(seg, k1, fits, progress)
        if k < k1:
            why += (". Links that are not bones (moving as a blend of their neighbours, or lending their motion "
                    "to blends far beyond their own triangles): " + ", ".join(f"{n} of {j}" for j, n in steps)
                    + f", so {k}")
    result = fits.get(k) if whole_fits else None
    return LinkChoice(k, e, tau, f"links auto: chose {k}. {why}", tree_links, k1 if whole_fits else k, result)


#: blend-to-single squared-error ratio below which a link is interpolating (see module docstring)
INTERPOLATING = 0.2
#: skin weight mass per owned vertex above which a link is a blend handle (see module docstring)
HANDLE = 3.0


def spurious_links(x0: np.ndarray, faces: np.ndarray, result) -> np.ndarray:
    """(L,) bool: the links of a fit that are not bones — interpolating (ρ < ``INTERPOLATING``,
    :func:`interpolating_links`) or blend handles (Σ_v w_vl > ``HANDLE`` × the vertices of the
    link's own triangles). ``result``: a :class:`fit.FitResult`."""
    L = result.rotations.shape[1]
    rho = interpolating_links(x0, faces, result.face_labels, result.rotations, result.translations)
    n_owned = np.diff(skinning.link_incidence(x0.shape[0], faces, result.face_labels, L).indptr)
    mass = result.weights[:, :L].sum(axis=0)
    return (rho < INTERPOLATING) | (mass > HANDLE * np.maximum(n_owned, 1))


def interpolating_links(x0: np.ndarray, faces: np.ndarray, labels: np.ndarray, R: np.ndarray,
                        t: np.ndarray) -> np.ndarray:
    """Per link, how well its neighbours' motions explain its own (the ratio ρ of the module
    docstring; links with no neighbour or a motion equal to a neighbour's get 1).

    For link j with vertices V_j (those of its triangles) and neighbours K_j (links sharing a
    vertex with it), d_k(v, p) = (R_k^p x0(v) + t_k^p) − (R_j^p x0(v) + t_j^p) and
    ρ_j = min_{c ≥ 0, Σc = 1} ‖Σ_k c_k d_k‖² / min_k ‖d_k‖²  over v ∈ V_j and all fields p.
    ``labels`` (T,) face labels (−1: none), R (P, L, 3, 3), t (P, L, 3).
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
    many links off and fit again. Returns (k, [(count, such links), ...])."""
    from .fit import fit
    scan = seg.scan
    steps = []
    while k > 1:
        if k not in fits:
            report = None
            if progress is not None:
                def report(stage, frac):
                    return progress("links", min(1.0, frac))
            fits[k] = fit(scan, k, segmenter=seg, progress=report)
        r = fits[k]
        n = int(np.count_nonzero(spurious_links(scan.vertices, scan.faces, r)))
        steps.append((k, n))
        if n == 0:
            break
        k = max(1, k - n)
    return k, steps


def _whole_fits_upward(seg, k: int, max_links: int, window: int, progress=None, fits=None):
    """From ``k``, add links while the whole fits' articulation error (running minimum) over the
    next ``window`` counts falls faster than k^(−WHOLE_FIT_SLOPE). Returns (k, {count: error %})."""
    from .fit import fit
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
            fits[j] = fit(seg.scan, j, segmenter=seg, progress=report)
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
