"""Merge split clusters into links (paper §5.2 second half; docs/method_notes.md §5.2–5.5).

Every cluster C has, in every field p, a motion centroid m_C^p = argmin_{i∈C} Σ_{j∈C} ε_p(i,j)
(its medoid triangle, choice A-6). Clusters are merged greedily on

    Λ(A, B) = |A||B| / (|A| + |B|) · Σ_p w_p ε_p(m_A^p, m_B^p),

with w_p = 1 / max_t z_p(t) putting each field on a unit scale (A-7), until ``k`` remain. The
row sums Σ_{j∈C} ε_p(i,j) are kept per triangle and updated on every merge with the cross block
of the two merged clusters only, so the medoids stay exact at a total cost bounded by one
pass over the pairwise distances. Clusters larger than ``MEDOID_SAMPLE`` estimate these sums
from an evenly spaced subsample (a documented approximation that keeps big links affordable).
"""
from __future__ import annotations

import numpy as np

from .metric import (FieldFeatures, cross_sums, digest, distance_block, distance_row_sums, distances_to_one,
                     row_medians)


def field_weights(features: list[FieldFeatures]) -> np.ndarray:
    """w_p = 1 / max_t |r(I→t) − r(ν_t→t)| (0 for a field without motion, which is dropped)."""
    w = np.zeros(len(features))
    for p, f in enumerate(features):
        z = f.zero_distance().max() if f.n else 0.0
        w[p] = 1.0 / z if z > 1e-300 else 0.0
    return w


class MergeCancelled(Exception):
    """The progress callback asked to stop the merge (the fit turns it into FitCancelled)."""


def member_key(m: np.ndarray) -> bytes:
    """A digest of a member array (order included): the key of its cached sums."""
    return digest(np.asarray(m, dtype=np.int64))


class SumCache:
    """Per-cluster distance sums kept across merges of one :class:`fit.Segmenter`.

    Sweeping the link count (``--links auto``, Preview Links) re-merges mostly the same clusters:
    each cut of a tree differs from the next by a split or two. Every cached value is a pure
    function of its key (the fields, and the member arrays in order), so a cached fit is
    bit-identical to a fresh one. When the values exceed ``max_bytes`` the cache starts over. A
    Segmenter fills it from its second segmentation on (a single fit keeps no extra memory).
    """

    def __init__(self, max_bytes: int = 256 * 2 ** 20):
        self.max_bytes = max_bytes
        self._d: dict = {}
        self.nbytes = 0
        self.hits = 0

    def get(self, key):
        v = self._d.get(key)
        if v is not None:
            self.hits += 1
        return v

    def put(self, key, value):
        nb = sum(a.nbytes for a in (value if isinstance(value, tuple) else (value,)))
        if self.nbytes + nb > self.max_bytes:
            self._d.clear()
            self.nbytes = 0
        self._d[key] = value
        self.nbytes += nb
        return value


#: clusters larger than this estimate their medoid sums from this many members
MEDOID_SAMPLE = 1024


def merge_clusters(features: list[FieldFeatures], weights: np.ndarray, init: np.ndarray,
                   k: int, progress=None, sample: int | None = MEDOID_SAMPLE, unit_size=None,
                   cache: SumCache | None = None, tag: bytes = b""):
    """Agglomerate the clusters of ``init`` (T,) down to ``k`` on Λ.

    ``unit_size`` (T,) is how many triangles each clustered unit stands for (the patch sizes of
    the reduced method; default 1): the |A| of Λ counts triangles, not patches. ``cache`` keeps
    the initial clusters' row sums and each merge's cross sums for later calls with the same
    features (``tag`` names them). Returns ``(labels (T,), medoids (k, P), row_sums (P, T))``
    with labels 0..k−1 ordered by the smallest triangle index of each link, and the medoid
    triangle of each link per field.
    """
    T = init.shape[0]
    P = len(features)
    _, init = np.unique(init, return_inverse=True)
    nc = int(init.max()) + 1
    members = _groups(init, nc)
    us = (lambda m: None) if unit_size is None else (lambda m: unit_size[m])  # noqa: E731
    sums = np.zeros((P, T))
    for m in members:
        if len(m) < 2:
            continue
        key = (tag, b"rows", member_key(m))
        block = None if cache is None else cache.get(key)
        if block is None:
            block = np.zeros((P, len(m)))
            for p, f in enumerate(features):
                if weights[p]:
                    block[p] = distance_row_sums(f, m, m, sample=sample, col_weights=us(m))
            if cache is not None:
                cache.put(key, block)
        sums[:, m] = block
    medoid = np.zeros((nc, P), dtype=np.int64)
    for c, m in enumerate(members):
        medoid[c] = m[np.argmin(sums[:, m], axis=1)]
    if unit_size is None:
        size = np.array([len(m) for m in members], dtype=np.float64)
    else:
        size = np.array([float(np.sum(unit_size[m])) for m in members])
    D = np.zeros((nc, nc))
    for p, f in enumerate(features):
        if weights[p]:
            D += weights[p] * distance_block(f, medoid[:, p], medoid[:, p])
    rows = _MedoidRows(features, weights, medoid)
    active = np.ones(nc, dtype=bool)
    lam = _lambda(D, size)
    n_active = nc
    total = max(nc - k, 1)
    while n_active > k:
        if progress is not None and progress((nc - n_active) / total):
            raise MergeCancelled()
        flat = int(np.argmin(lam))
        a, b = divmod(flat, nc)
        if a > b:
            a, b = b, a
        A, B = members[a], members[b]
        key = (tag, b"cross", member_key(A), member_key(B))
        cross = None if cache is None else cache.get(key)
        if cross is None:
            cross = (np.zeros((P, len(A))), np.zeros((P, len(B))))
            for p, f in enumerate(features):
                if weights[p]:
                    cross[0][p], cross[1][p] = cross_sums(f, A, B, sample=sample, wA=us(A), wB=us(B))
            if cache is not None:
                cache.put(key, cross)
        sums[:, A] += cross[0]
        sums[:, B] += cross[1]
        m = np.concatenate([A, B])
        members[a] = m
        members[b] = np.zeros(0, dtype=np.int64)
        active[b] = False
        n_active -= 1
        size[a] += size[b]
        size[b] = 0
        medoid[a] = m[np.argmin(sums[:, m], axis=1)]
        rows.move(a, medoid[a])
        row = rows.distances(a)
        D[a, :] = row
        D[:, a] = row
        lam[b, :] = np.inf
        lam[:, b] = np.inf
        new = size[a] * size / np.maximum(size[a] + size, 1e-300) * row
        new[~active] = np.inf
        new[a] = np.inf
        lam[a, :] = new
        lam[:, a] = new
    keep = np.flatnonzero(active)
    order = keep[np.argsort([members[c].min() for c in keep])]
    labels = np.empty(T, dtype=np.int64)
    for new_label, c in enumerate(order):
        labels[members[c]] = new_label
    return labels, medoid[order], sums


class _MedoidRows:
    """The ε features of every cluster's medoid in every weighted field, stacked (fields first), so
    that one merge's new row of medoid distances is two batched products instead of two per field
    (:func:`metric.distances_to_one`).

    ``medoid (nc, P)`` unit indices. :meth:`distances` gives Σ_p w_p ε_p(m_a^p, m_j^p) for every
    cluster j, as :func:`metric.distance_block` of each field would, summed in field order."""

    def __init__(self, features: list[FieldFeatures], weights: np.ndarray, medoid: np.ndarray):
        self.fields = [p for p in range(len(features)) if weights[p]]
        self.w = weights[self.fields]
        self.features = [features[p] for p in self.fields]
        m = medoid[:, self.fields].T                                          # (Pa, nc)
        self.g = np.stack([f.g[m[i]] for i, f in enumerate(self.features)])    # (Pa, nc, 17)
        self.f = np.stack([f.f[m[i]] for i, f in enumerate(self.features)])
        self.r = np.stack([f.r_self[m[i]] for i, f in enumerate(self.features)])   # (Pa, nc)

    def move(self, a: int, medoid_a: np.ndarray) -> None:
        """Cluster ``a``'s medoids are now ``medoid_a`` (P,)."""
        for i, f in enumerate(self.features):
            u = medoid_a[self.fields[i]]
            self.g[i, a], self.f[i, a], self.r[i, a] = f.g[u], f.f[u], f.r_self[u]

    def distances(self, a: int) -> np.ndarray:
        """(nc,) Σ_p w_p ε_p(medoid of a, medoid of j) over the clusters j (paper Eq. 5, |·| variant)."""
        eps = distances_to_one(self.g, self.f, self.r, a)
        row = np.zeros(eps.shape[1])
        for i in range(len(self.fields)):
            row += self.w[i] * eps[i]
        return row


def _groups(labels: np.ndarray, n: int):
    order = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order], np.arange(n + 1))
    return [order[bounds[i]:bounds[i + 1]] for i in range(n)]


def _lambda(D: np.ndarray, size: np.ndarray) -> np.ndarray:
    lam = size[:, None] * size[None, :] / (size[:, None] + size[None, :]) * D
    np.fill_diagonal(lam, np.inf)
    return lam


#: residual entries :func:`refine_seams` takes at once (32 MB of float64)
SEAM_BLOCK = 4_000_000


def refine_seams(x0: np.ndarray, fields: np.ndarray, faces: np.ndarray, R: np.ndarray, t: np.ndarray,
                 weights: np.ndarray, labels: np.ndarray, adjacency: np.ndarray,
                 iterations: int = 10, margin: float = 1.0 + 1e-9, fixed=None, cache: SumCache | None = None,
                 tag: bytes = b"") -> np.ndarray:
    """Give each seam triangle to the side of the seam that holds most of its skin weight.

    A triangle on a linearly blended seam moves in between its neighbours, so the clustering
    may put it on either side. For every vertex and candidate link l (the triangle's own link
    and its neighbours') the weighted error e_l(v) = Σ_p w_p ‖G_l^p x0(v) − x^p(v)‖ of the link's
    robust motion is measured; ŵ_l(v) ∝ 1/e_l(v) recovers the blend weight of a vertex blended
    between two links exactly, and the triangle goes to the link with the largest summed ŵ
    over its three vertices — the definition of a face's true link in rigged data. A triangle
    moves only when the new side holds ``margin`` times the weight of its current side (so
    smoothly blended regions, where the medoid motions are themselves blended, stay as the
    clustering put them). Triangles in ``fixed`` (the links' medoids) never move, so no link
    empties. Iterated until no seam moves. An addition to the paper (docs/method.md, "Deviations from the paper").
    ``cache`` / ``tag`` as in :func:`merge_clusters`: a link's errors e_l depend on its motions only, so
    a link whose robust motions another segmentation of the same fields had (the link-count search's
    counts share most of their links) takes them from there.
    """
    labels = labels.copy()
    k = R.shape[1]
    T = labels.shape[0]
    E = np.zeros((k, x0.shape[0]))
    todo, keys = np.arange(k), None
    if cache is not None:
        keys = [(tag, b"seam", digest(R[:, l], t[:, l], weights)) for l in range(k)]
        hits = [cache.get(key) for key in keys]
        for l, hit in enumerate(hits):
            if hit is not None:
                E[l] = hit
        todo = np.array([l for l, hit in enumerate(hits) if hit is None], dtype=np.int64)
    links = max(1, SEAM_BLOCK // max(3 * x0.shape[0], 1))     # links whose residuals are taken at once
    for p in range(fields.shape[0]):
        if weights[p]:
            X = x0 + fields[p]
            for l0 in range(0, len(todo), links):
                ls = todo[l0:l0 + links]
                # (links, N, 3) residuals of field p
                d = np.matmul(x0, np.swapaxes(R[p, ls], -1, -2))
                d += t[p, ls, None, :]
                d -= X
                E[ls] += weights[p] * np.sqrt(np.einsum("lni,lni->ln", d, d))
    if cache is not None:
        for l in todo:
            cache.put(keys[l], E[l].copy())
    scale = E.max() if E.size else 1.0
    # every residual zero (fields that are one rigid motion): equal costs, not 1/1e-312 = inf
    inv = 1.0 / (E + (1e-12 * max(scale, 1e-300) if scale > 0 else 1.0))
    a, b = adjacency[:, 0], adjacency[:, 1]
    for _ in range(iterations):
        # only triangles on a seam can move: those with a neighbour in another link
        seam = np.zeros(T, dtype=bool)
        diff = labels[a] != labels[b]
        seam[a[diff]] = True
        seam[b[diff]] = True
        idx = np.flatnonzero(seam)
        if idx.size == 0:
            break
        pos = np.full(T, -1)
        pos[idx] = np.arange(idx.size)
        allowed = np.zeros((k, idx.size), dtype=bool)
        allowed[labels[idx], np.arange(idx.size)] = True
        ea = diff & seam[a]
        allowed[labels[b[ea]], pos[a[ea]]] = True
        eb = diff & seam[b]
        allowed[labels[a[eb]], pos[b[eb]]] = True
        w = np.where(allowed[:, :, None], inv[:, faces[idx]], 0.0)     # (k, S, 3)
        w /= w.sum(axis=0, keepdims=True)
        score = w.sum(axis=2)
        best = score.argmax(axis=0)
        cols = np.arange(idx.size)
        change = score[best, cols] > score[labels[idx], cols] * margin
        if fixed is not None:
            change[np.isin(idx, fixed)] = False
        if not change.any():
            break
        labels[idx[change]] = best[change]
    return labels


def link_medoids(features: list[FieldFeatures], weights: np.ndarray, labels: np.ndarray, k: int,
                 sample: int | None = 512, unit_size=None, cache: SumCache | None = None,
                 tag: bytes = b"") -> np.ndarray:
    """The motion centroid of every link in every field, with a 50% breakdown point.

    m_l^p = argmin_{i∈l} median_{j∈l} ε_p(i, j): the member whose motion agrees exactly with at
    least half of the link. On a link with a rigid core larger than its blended seams this is a
    core triangle, so the link's robust motion is exact however wide the blends are (the
    plain sum of §5.2 drifts toward the seams once they are about a third of the link). Used
    for the final link motions; the merge keeps the sum, which it can update incrementally.
    With ``unit_size`` (patch sizes of the reduced method) the median is weighted by the
    triangles each unit stands for. ``cache`` / ``tag`` as in :func:`merge_clusters` (a link's
    medoids depend on its members only). Returns (k, P) indices into the clustered units.
    """
    from .metric import subsample

    def reference(m):
        """Members the median runs over: an even subsample, or, with unit sizes, ``sample``
        members drawn evenly along the cumulative triangle count (a unit appears about in
        proportion to its size, so the plain median is the size-weighted one)."""
        if unit_size is None:
            return subsample(m, sample)
        cum = np.cumsum(np.asarray(unit_size, dtype=np.float64)[m])
        n = min(sample, len(m)) if sample else len(m)
        at = np.searchsorted(cum, (np.arange(n) + 0.5) / n * cum[-1])
        return m[np.minimum(at, len(m) - 1)]

    P = len(features)
    out = np.zeros((k, P), dtype=np.int64)
    groups = _groups(labels, k)
    for l, m in enumerate(groups):
        key = (tag, b"medoid", sample, member_key(m))
        hit = None if cache is None else cache.get(key)
        if hit is not None:
            out[l] = hit
            continue
        ref = reference(m)
        # candidates: every member of a small link, an even subsample of twice ``sample`` of a
        # big one (a rigid core is most of a link, so the subsample holds core members)
        pool = subsample(m, None if sample is None else 2 * sample)
        for p, f in enumerate(features):
            if len(m) == 1:
                out[l, p] = m[0]
                continue
            med = np.empty(len(pool))
            step = max(1, 2_000_000 // max(len(ref), 1))
            for i0 in range(0, len(pool), step):
                med[i0:i0 + step] = row_medians(distance_block(f, pool[i0:i0 + step], ref))
            # ties (a whole rigid core at zero) go to the smallest sum, i.e. deepest in the core
            cand = np.flatnonzero(med <= med.min() + 1e-12 * max(med.max(), 1e-300))
            if len(cand) > 1:
                sums = distance_block(f, pool[cand], ref).sum(axis=1)
                out[l, p] = pool[cand[np.argmin(sums)]]
            else:
                out[l, p] = pool[cand[0]]
        if cache is not None:
            cache.put(key, out[l].copy())
    return out


#: decompositions re-run on the argmax labels at most (see :func:`dominant_labels`)
RELABEL_ROUNDS = 5
#: rounds of each of those decompositions: each goes on from the last one's motions and weights, so
#: it continues one alternation rather than redoing it (half the weight solves of 10 rounds each; 4
#: lost two finger joints on one of 77 fresh RobotExpressive seeds, 2-3 on another; 5 keeps every
#: joint on all 154 fidelity seeds, ``benchmarks/results/fidelity.md``)
RELABEL_TRIAL_ROUNDS = 5


def dominant_faces(w, faces, labels, units=None, k=None, keep_units_only=False):
    """Each face's link of largest summed skin weight ``w (N, L)`` over its corners (the first ``k``
    columns, default all); where a link would be left without a face (or without a face of ``units``)
    its faces keep their ``labels (T,)`` — with ``keep_units_only`` only its faces of ``units`` (the
    rest go by the skin). The relabelling's, the splits' and the grown links' rule."""
    k = w.shape[1] if k is None else k
    new = w[faces, :k].sum(axis=1).argmax(axis=1)
    mine = np.ones(len(labels), dtype=bool)       # faces a starved link takes back
    if units is not None and keep_units_only:
        mine[:] = False
        mine[units] = True
    for _ in range(k):
        owned = np.bincount(new if units is None else new[units], minlength=k) > 0
        if owned.all():
            break
        keep = ~owned[labels] & mine
        new[keep] = labels[keep]
    return new


def dominant_labels(x0: np.ndarray, fields: np.ndarray, faces: np.ndarray, labels: np.ndarray,
                    R: np.ndarray, t: np.ndarray, units: np.ndarray | None = None):
    """Give every face to the link that dominates its skin (an addition to the paper).

    On a smoothly skinned character the motion of a triangle between two bones is a blend of
    theirs, so the clustering (and the link's robust motion, a medoid) can sit anywhere along the
    blend: the seams end up shifted by up to half a bone, and a short bone whose every triangle is
    blended can lose its link to its neighbours. Here the skin is decomposed from the links' own
    motions (:func:`skinning.alternate`: per-vertex convex weights over the nearby links and the
    link motions, alternated as in SSDR), and each face goes to the link with the largest summed
    weight over its three vertices — the usual definition of a face's bone in rigged data. The
    decomposition (on a vertex sample, :func:`skinning.vertex_sample`) first moves links that
    explain little to where the skin fits worst (:func:`swaps.swap_links`), so a sliver link at a seam can become a short bone
    (scans of up to ``swaps.SWAP_BUDGET`` vertex-fields). Moving the seams changes which links
    each vertex may blend, so the decomposition is run again on the new labels, from the motions
    it found, and the faces relabelled, while that lowers its error (at most ``RELABEL_ROUNDS``
    times; figures: ``benchmarks/results/core_constants.md``). A link
    that would own no face — or none of the faces ``units`` that carry the link motions (the
    clustered triangles, or the patch representatives of the reduced method) — keeps its faces.
    ``labels`` (T,) over all faces, ``R`` (P, k, 3, 3), ``t`` (P, k, 3). Returns the new (T,) labels
    and the number of swaps kept (None when the scan is above the swaps' budget).
    """
    from .skinning import alternate_scored, full_skin, vertex_sample
    from .swaps import TRIAL_ROUNDS, swap_links, within_budget
    k = R.shape[1]
    rows = vertex_sample(faces, labels, x0.shape[0])

    def decompose(labels, R, t, rounds=TRIAL_ROUNDS, **kw):
        w, R, t, e = alternate_scored(x0, fields, faces, labels, R, t, iterations=rounds, rows=rows, **kw)
        if rows is not None:
            w = full_skin(x0, fields, faces, labels, R, t, rows=rows, w_rows=w)[0]
        return w, R, t, e

    # a rough skin is enough for the argmax: fewer rounds than the final refined skin
    if within_budget(x0.shape[0], fields.shape[0]):
        w, R, t, labels, swaps, e, rows = swap_links(x0, fields, faces, labels, R, t, units=units, error=True,
                                                     rows=rows)
    else:
        swaps = None if k > 2 else 0   # None: skipped, the scan is above the budget
        w, R, t, e = decompose(labels, R, t)
    new = dominant_faces(w, faces, labels, units, k)
    # the argmax moves seams, which changes the links' candidate reach: decompose again on the
    # new labels (from the motions just found) while that lowers the error and moves faces
    for _ in range(RELABEL_ROUNDS):
        if np.array_equal(new, labels):
            break
        w1, R1, t1, e1 = decompose(new, R, t, rounds=RELABEL_TRIAL_ROUNDS, w_init=w)
        if not e1 < e:
            break
        labels, w, R, t, e = new, w1, R1, t1, e1
        new = dominant_faces(w, faces, labels, units, k)
    return new, swaps
