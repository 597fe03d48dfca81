"""Choosing the number of links from the data (``--links auto``; issue 5).

The paper names the link count as its only parameter. Here it is chosen from the articulation
error curve: for every candidate k the segmentation is re-cut from the cached tree (no new
distances), each link moves with its robust motion, every vertex gets its best convex blend of
nearby link motions (:func:`skinning.refined_weights`), and e(k) is the Karni–Gotsman error
100·‖X − X̂‖/‖X − X̄‖ of that articulation. With too few links some part of the object cannot
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
undershoots on rigs with fingers and tail segments (Fox 17 of 22 links, RobotExpressive 26 of 36).
The error of the whole fit (link swaps and refined skin, :func:`fit.fit`) instead drops to the
data's floor once every bone has its link: on fresh RobotExpressive poses 0.075 % with 35 links,
0.019 % with 36, no lower up to 40. So from the tree's choice k grows by the same slope rule on
the whole fits' errors with s = 2 (one fit per count, the scan's segmenter reused). It only
adds links; a scan with support vertices keeps the tree's choice (the fit's skin has no ground
candidate, so a link would be spent on the ground seam).
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
    if whole_fits and k < max_links:
        k1, ef = _whole_fits_upward(seg, k, max_links, window, progress)
        why += f". Whole fits from {k} links: error {ef[k]:.3g}%"
        if k1 > k:
            why += f", {ef[k1]:.3g}% with {k1}"
        why += f"; beyond it the error falls slower than k^-{WHOLE_FIT_SLOPE:g} over {window} more links"
        k = k1
    return LinkChoice(k, e, tau, f"links auto: chose {k}. {why}", tree_links)


def _whole_fits_upward(seg, k: int, max_links: int, window: int, progress=None):
    """From ``k``, add links while the whole fits' articulation error (running minimum) over the
    next ``window`` counts falls faster than k^(−WHOLE_FIT_SLOPE). Returns (k, {count: error %})."""
    from .fit import fit
    errors: dict[int, float] = {}
    start = k

    def error(j):
        if j not in errors:
            span = max(max_links - start, 1)
            report = None
            if progress is not None:
                def report(stage, frac, j=j):
                    return progress("links", min(1.0, (j - start + frac) / span))
            errors[j] = float(fit(seg.scan, j, segmenter=seg, progress=report).articulation_error_percent)
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
