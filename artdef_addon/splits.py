"""Split links that hold two bones (issue 19): every joint the data support stays in the tree.

An addition to the paper for tracked scans. With a fixed link count the segmentation can end with
two short, fully blended true bones (two finger segments, or a finger segment and its hand) in one
link while a sliver elsewhere holds a link of its own (RobotExpressive, fresh poses of new seeds:
2 of 30 joints missing). The skin then explains the merged pair by blending its neighbours, so the
decomposition error is low (0.02 %) but above what the true structure reaches (< 0.001 %), and
the swaps of :mod:`swaps`, which seed where the skin fits *worst*, do not find the pair: the
merged link is not where the skin fails, it is where the link's own motion is not rigid.

A split trial, for each of the ``CANDIDATES`` links whose own rigid motion leaves the largest RMS
residual on their own vertices (over all fields; the merged pair's motion is not one rigid motion):

1. cut the link's faces in two by their motions: start from its face worst fitted by the link's
   motion, take the least-squares motion (Kabsch/Arun, METHOD §6) of that face's one-ring, and
   alternate a few times between giving every face of the link to the motion (the link's or the
   seed's) that moves its three vertices best over all fields and refitting the seed's motion to
   its faces; both parts must hold at least ``MIN_FACES`` faces;
2. the second part takes the place of the link the decomposition misses least
   (:func:`swaps.removal_costs`, the cheapest of the ``DROP`` cheapest, never the split link),
   whose faces go to their best other candidate link — so the link count never changes
   (``--links k`` keeps k; links auto chooses the count over fits that already split);
3. the skinning decomposition (:func:`skinning.alternate`, ``swaps.TRIAL_ROUNDS`` rounds) is run
   on the new links; the split is kept only if its squared error falls by at least
   ``MIN_GAIN`` (a fraction). Cutting a smoothly blended true bone in two and dropping another
   true bone raises that error, so it is refused.

Splits repeat (at most ``MAX_SPLITS``) while one is kept. The scan sizes are those of the swaps
(``swaps.SWAP_BUDGET`` vertex-fields); Green's scans keep the paper's segmentation.
"""
from __future__ import annotations

import numpy as np

#: off by default: on RobotExpressive's fresh poses (seed 4) the first version kept a split whose 10-round
#: trial error fell but whose final fit lost two more joints (26 of 30, error 0.019 % → 0.065 %); see the
#: branch report. ``True`` runs it inside every tracked fit with the refined skin.
SPLIT_LINKS = False
#: links tried per round, by their own rigid residual (largest first)
CANDIDATES = 6
#: links offered to be dropped per candidate (the cheapest by removal cost)
DROP = 2
#: a split is kept when it lowers the decomposition error by at least this fraction
MIN_GAIN = 0.05
#: at most this many kept splits per fit
MAX_SPLITS = 4
#: the smaller part of a split must hold at least this many faces
MIN_FACES = 4


def _motion_errors(x0, fields, tri, R, t):
    """(P-summed) squared error of moving the vertices ``tri`` (n, 3) by motions R (P, 3, 3), t (P, 3):
    per face, Σ_p Σ_corners ‖R^p x + t^p − x^p‖². Returns (n,)."""
    x = x0[tri]                                             # (n, 3, 3)
    moved = np.einsum("pij,ncj->pnci", R, x) + t[:, None, None, :]
    target = x[None] + fields[:, tri]
    return np.sum((moved - target) ** 2, axis=(0, 2, 3))


def cut_link(x0, fields, faces, labels, l, R, t, iterations: int = 4):
    """Cut link ``l``'s faces into the part its motion R (P, 3, 3), t (P, 3) explains and the part a
    second rigid motion explains better (module docstring, step 1). Returns (faces of the second part,
    its motion (R2, t2)) or None when a part would be smaller than ``MIN_FACES``."""
    from .fit import _lsq_motions
    mine = np.flatnonzero(labels == l)
    if mine.size < 2 * MIN_FACES:
        return None
    e_own = _motion_errors(x0, fields, faces[mine], R, t)
    seed = mine[int(np.argmax(e_own))]
    touch = np.isin(faces[mine], faces[seed]).any(axis=1)
    part = mine[touch]
    R2 = t2 = None
    for _ in range(iterations):
        if part.size < MIN_FACES or part.size > mine.size - MIN_FACES:
            return None
        R2, t2 = _lsq_motions(x0, fields, faces[part], np.zeros(part.size, dtype=np.int64), 1, corner_weights=True)
        R2, t2 = R2[:, 0], t2[:, 0]
        e2 = _motion_errors(x0, fields, faces[mine], R2, t2)
        new = mine[e2 < e_own]
        if np.array_equal(new, part):
            break
        part = new
    if part.size < MIN_FACES or part.size > mine.size - MIN_FACES:
        return None
    return part, (R2, t2)


def own_residuals(x0, fields, faces, labels, R, t) -> np.ndarray:
    """(L,) RMS over a link's own vertices and all fields of its own rigid motion's error."""
    L = R.shape[1]
    out = np.zeros(L)
    for l in range(L):
        vid = np.unique(faces[labels == l])
        if vid.size == 0:
            continue
        d = np.einsum("pij,nj->pni", R[:, l], x0[vid]) + t[:, l, None, :] - (x0[vid][None] + fields[:, vid])
        out[l] = np.sqrt(np.mean(np.sum(d * d, axis=-1)))
    return out


def split_merged(x0: np.ndarray, fields: np.ndarray, faces: np.ndarray, labels: np.ndarray,
                 R: np.ndarray, t: np.ndarray, units: np.ndarray | None = None):
    """Split links that hold two rigid parts, each paired with dropping the least useful link (module
    docstring). ``labels`` (T,) link of every face, ``R`` (P, L, 3, 3), ``t`` (P, L, 3) the links' motions,
    ``units`` the faces that carry link motions (each link must keep one). Returns ``(labels, R, t, splits)``:
    the links' motions as given except for the links a kept split changed (their decomposition motions)."""
    from .skinning import _alternate
    from .swaps import EXACT, SWAP_BUDGET, TRIAL_ROUNDS, removal_costs
    L = R.shape[1]
    P = fields.shape[0]
    if not SPLIT_LINKS or L < 3 or P == 0 or x0.shape[0] * P > SWAP_BUDGET:
        return labels, R, t, 0
    units = np.arange(len(labels)) if units is None else np.asarray(units)
    labels = np.array(labels, copy=True)
    R, t = R.copy(), t.copy()
    w, Rd, td, e, info = _alternate(x0, fields, faces, labels, R, t, iterations=TRIAL_ROUNDS, details=True)
    mean = fields.mean(axis=0)
    spread = sum(float(np.sum((fields[i] - mean) ** 2)) for i in range(P))
    if e <= EXACT ** 2 * spread:      # the skin already explains the fields: nothing to split
        return labels, R, t, 0
    splits = 0
    tried = set()
    while splits < MAX_SPLITS:
        res = own_residuals(x0, fields, faces, labels, Rd, td)
        cost, _ = removal_costs(info, L)
        kept = False
        for l in np.argsort(-res)[:CANDIDATES]:
            l = int(l)
            cut = cut_link(x0, fields, faces, labels, l, Rd[:, l], td[:, l])
            if cut is None:
                continue
            part, (R2, t2) = cut
            for j in [int(j) for j in np.argsort(cost) if j != l and np.isfinite(cost[j])][:DROP]:
                key = (l, j, part.size)
                if key in tried:
                    continue
                tried.add(key)
                new = labels.copy()
                gone = np.flatnonzero(labels == j)
                ferr = info["err"][:L][:, faces[gone]].sum(axis=2)     # (L, n) summed over corners
                ferr[j] = np.inf
                pick = np.argmin(ferr, axis=0)
                lost = ~np.isfinite(ferr.min(axis=0))
                if lost.any():  # no other candidate link nearby: the nearest face of another link
                    from scipy.spatial import cKDTree
                    other = np.flatnonzero(labels != j)
                    cen = x0[faces].mean(axis=1)
                    pick[lost] = labels[other[cKDTree(cen[other]).query(cen[gone[lost]])[1]]]
                new[gone] = pick
                new[part] = j
                if np.any(np.bincount(new[units], minlength=L) == 0):
                    continue
                R1, t1 = Rd.copy(), td.copy()
                R1[:, j], t1[:, j] = R2, t2
                w1, R1, t1, e1, info1 = _alternate(x0, fields, faces, new, R1, t1, iterations=TRIAL_ROUNDS,
                                                   details=True)
                if e1 < (1.0 - MIN_GAIN) * e:
                    changed = [l, j] + np.unique(pick).tolist()
                    labels, Rd, td, e, info = new, R1, t1, e1, info1
                    R[:, changed], t[:, changed] = Rd[:, changed], td[:, changed]
                    splits += 1
                    kept = True
                    break
            if kept:
                break
        if not kept:
            break
    return labels, R, t, splits
