"""Swap links: drop the least useful link, re-seed it where the skin fits worst.

An addition to the paper for tracked scans. The greedy merge of §5.2 never revisits a decision,
so with a fixed link count a smoothly skinned character can end with a link spent on a sliver of
blended triangles (the palm side of a finger seam) while two short true bones (two finger
segments) share one link. Those links then feed the skinning decomposition
(:func:`skinning.alternate`, SSDR-style), whose error E = Σ_p Σ_v ‖Σ_l w_vl (R_l^p x_v + t_l^p) − x_v^p‖²
measures what the rig cannot explain. As Dem Bones re-initialises its weakest bones, a swap

1. prices removing each link l from the decomposition's own normal equations: every vertex that
   uses l falls back to the better of its other weights renormalised and its best other single
   candidate link (an upper bound on the re-solved error);
2. re-seeds the cheapest link at a clustered triangle whose three vertices the skin fits worst
   (the worst triangle of each of the worst-fitted links; the 2 cheapest links × 3 places are
   tried in turn), with the least-squares motion (Kabsch/Arun, docs/method_notes_model.md §6;
   ``joints.lsq_motions``) of that triangle's one-ring; the removed link's faces go to their best
   other candidate link;
3. re-runs the decomposition and keeps the swap only if E falls by at least ``MIN_GAIN``.

The link count never changes and E falls at every kept swap. Green's scans keep the paper's
segmentation (this pass is not used for them).
"""
from __future__ import annotations

import numpy as np

from .joints import lsq_motions
from .quality import vertex_spread

#: a swap is kept when it lowers the decomposition error by at least this fraction
MIN_GAIN = 0.005
#: below this Karni–Gotsman ratio ‖X − X̂‖/‖X − X̄‖ the fields count as explained (no swaps)
EXACT = 1e-4
#: vertices × fields (those the trials use, at most ``skinning.SAMPLE_FIELDS``) up to which swaps and
#: the split stage run (each trial is a ``TRIAL_ROUNDS`` decomposition on a vertex sample, each kept
#: one a weight solve of every vertex; ``benchmarks/results/core_constants.md``). 1M because at
#: 500k the cow (11,666 vertices) at 87 fresh poses lost both stages that it keeps at 40, its rig
#: falling from 9 to 3-4 of 11 joints within 2 % and 0.34 to 0.55-0.69 x Dem Bones' error; with them
#: 9 of 11 and 0.36-0.42 x, in 12.5-13.8 s against 5.3 s (Dem Bones 6.4-7.7 s)
SWAP_BUDGET = 1_000_000


def within_budget(n_vertices: int, trial_fields: int) -> bool:
    """Whether a scan of ``n_vertices`` runs the swap and split trials (:data:`SWAP_BUDGET`), its
    trials decomposing ``trial_fields`` fields: the one rule of the relabelling
    (:func:`merge.dominant_labels`), the split stage (``fit._split_links``) and the estimate
    (``cost.articulation_cost``)."""
    return n_vertices * trial_fields <= SWAP_BUDGET
#: rounds of the decomposition per trial (the final refined skin runs to convergence)
TRIAL_ROUNDS = 10


def _quad(w, Q, q, xx):
    return np.einsum("na,nab,nb->n", w, Q, w) - 2 * np.einsum("na,na->n", q, w) + xx


def removal_costs(info: dict, L: int):
    """Rise of the decomposition error if each link were dropped (see module docstring, step 1),
    and each vertex's current error (N,). ``info`` is :func:`skinning._refine`'s detail dict."""
    cols, valid, Q, q, xx, wc, err = (info[k] for k in ("cols", "valid", "Q", "q", "xx", "wc", "err"))
    cur = np.maximum(_quad(wc, Q, q, xx), 0.0)
    cost = np.zeros(L)
    for j in range(cols.shape[1]):
        v = np.flatnonzero(valid[:, j] & (wc[:, j] > 0))
        if v.size == 0:
            continue
        l = cols[v, j]
        w2 = wc[v].copy()
        w2[:, j] = 0.0
        s = w2.sum(axis=1)
        ok = s > 1e-9
        blend = np.full(v.size, np.inf)
        w2[ok] /= s[ok, None]
        blend[ok] = _quad(w2[ok], Q[v[ok]], q[v[ok]], xx[v[ok]])
        single = err[:L, v].copy()
        single[l, np.arange(v.size)] = np.inf
        new = np.minimum(blend, single.min(axis=0))
        np.add.at(cost, l, np.where(np.isfinite(new), new - cur[v], np.inf))
    return cost, cur


def reassign_faces(labels, l, faces, err, fallback=None, x0=None):
    """``labels`` (T,) with link ``l``'s faces given to the other link whose own motion fits their
    corners best (``err`` (L, N): each link's single-link squared error per vertex, inf off its
    candidates). A face with no other candidate link goes to ``fallback``, or (``x0`` given) to the
    link of the nearest face of another link. Returns a new array."""
    new = labels.copy()
    mine = np.flatnonzero(labels == l)
    ferr = err[:, faces[mine]].sum(axis=2)                              # (L, n) summed over corners
    ferr[l] = np.inf
    pick = np.argmin(ferr, axis=0)
    lost = ~np.isfinite(ferr.min(axis=0))
    if lost.any() and fallback is not None and fallback != l:
        pick[lost] = fallback
    elif lost.any() and x0 is not None:   # no other candidate link nearby: the nearest face of another link
        from scipy.spatial import cKDTree
        other = np.flatnonzero(labels != l)
        cen = x0[faces].mean(axis=1)
        pick[lost] = labels[other[cKDTree(cen[other]).query(cen[mine[lost]])[1]]]
    new[mine] = pick
    return new


def _one_ring(faces, f, labels):
    """Faces sharing a vertex with face ``f`` and carrying its label."""
    touch = np.isin(faces, faces[f]).any(axis=1) & (labels == labels[f])
    return np.flatnonzero(touch)


def swap_links(x0: np.ndarray, fields: np.ndarray, faces: np.ndarray, labels: np.ndarray,
               R: np.ndarray, t: np.ndarray, units: np.ndarray | None = None,
               max_swaps: int | None = None, candidates: int = 2, seed_links: int = 3, error: bool = False,
               rows: np.ndarray | None = None):
    """Skinning decomposition with link swaps (see module docstring).

    ``labels`` (T,) link of every face; ``R`` (P, L, 3, 3), ``t`` (P, L, 3) the links' motions;
    ``units`` the faces that carry the links' robust motions (clustered triangles; default all),
    where seeds are taken. Returns ``(weights (N, L), labels, swaps)``: the decomposition's
    weights and the labels the swaps left (each face's link before the caller re-labels by skin).
    With ``error`` the decomposition's squared error E and the vertex sample are appended. ``rows``
    (S,): the decompositions run on that vertex sample (:func:`skinning.vertex_sample`; E is the
    sample's); each trial adds its seed's vertices to it, and the kept one's weights and prices are
    extended to every vertex (:func:`skinning.full_skin`).
    """
    from .skinning import alternate_scored, full_skin
    labels = np.array(labels, copy=True)
    L = R.shape[1]
    P = fields.shape[0]
    units = np.arange(len(labels)) if units is None else np.asarray(units)
    max_swaps = L if max_swaps is None else max_swaps

    def decompose(labels, R, t, rows, **kw):
        w, R, t, e, *info = alternate_scored(x0, fields, faces, labels, R, t, iterations=TRIAL_ROUNDS,
                                             details=rows is None, rows=rows, **kw)
        return w, R, t, e, (info[0] if info else None)

    def extend(labels, R, t, w, rows):
        w, _, info = full_skin(x0, fields, faces, labels, R, t, details=True, rows=rows, w_rows=w)
        return w, info

    w, R, t, e, info = decompose(labels, R, t, rows)
    if rows is not None:
        w, info = extend(labels, R, t, w, rows)
    spread = vertex_spread(fields if rows is None else fields[:, rows])
    if e <= EXACT ** 2 * spread:      # the skin already explains the fields: nothing to swap
        return (w, R, t, labels, 0) + ((e, rows) if error else ())
    swaps = 0
    tried = set()
    while swaps < max_swaps and L > 2 and P > 0:
        cost, cur = removal_costs(info, L)
        face_err = cur[faces].sum(axis=1)
        kept = False
        # the worst-fitted clustered triangle of each link, the worst links first
        worst = np.full(L, -1)
        order = units[np.argsort(-face_err[units], kind="stable")]
        lab_o = labels[order]
        first = np.unique(lab_o, return_index=True)
        worst[first[0]] = order[first[1]]
        seeds = worst[np.argsort(-np.where(worst >= 0, face_err[np.maximum(worst, 0)], -np.inf))]
        trials = [(int(l), int(sd)) for l in np.argsort(cost)[:candidates] if np.isfinite(cost[l])
                  for sd in seeds[:seed_links] if sd >= 0 and labels[sd] != l]
        for l, seed in trials:
            if (l, seed) in tried:
                continue
            tried.add((l, seed))
            new = reassign_faces(labels, l, faces, info["err"][:L], x0=x0)
            ring = _one_ring(faces, seed, labels)
            new[ring] = l
            if np.any(np.bincount(new[units], minlength=L) == 0):
                continue
            R1, t1 = R.copy(), t.copy()
            Rr, tr = lsq_motions(x0, fields, faces[ring], np.zeros(len(ring), dtype=np.int64), 1, corner_weights=True)
            R1[:, l], t1[:, l] = Rr[:, 0], tr[:, 0]
            rows1, base = rows, e
            if rows is not None:
                # the new link's seed keeps its vertices in the sample; the current skin's error on
                # the grown sample is the per-vertex error of its extension to every vertex
                rows1 = np.union1d(rows, faces[ring].reshape(-1))
                base = float(cur[rows1].sum())
            w1, R1, t1, e1, info1 = decompose(new, R1, t1, rows1, w_init=w, target=(1.0 - MIN_GAIN) * base)
            if e1 < (1.0 - MIN_GAIN) * base:
                rows = rows1
                if rows is not None:
                    w1, info1 = extend(new, R1, t1, w1, rows)
                labels, w, R, t, e, info = new, w1, R1, t1, e1, info1
                swaps += 1
                kept = True
                break
        if not kept:
            break
    return (w, R, t, labels, swaps) + ((e, rows) if error else ())

