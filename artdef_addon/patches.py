"""The reduced method for large meshes: patches of triangles that move together.

A documented deviation from the paper, used when the all-pairs distance of the full method
would not fit the memory budget:

1. for every pair of edge-adjacent triangles, the largest weighted distance over all fields,
   a_ij = max_p w_p ε_p(i, j) (Eq. 5 on neighbours only: O(T) per field, streamed);
2. patches by heavy-edge matching (graph coarsening): in every round each patch proposes
   the neighbour it agrees with most (smallest a), mutual proposals merge while the merged
   patch stays within ``max_size`` triangles; the distance between two patches is the
   largest a over their shared edges, so seams are merged last. Rounds repeat until at most
   ``target`` patches remain (or nothing can merge);
3. each patch is represented by its most central triangle; the method (distances, clustering,
   merge, motion centroids) runs on these representatives;
4. labels go back to every triangle of each patch and the seams are refined at triangle
   resolution (:func:`merge.refine_seams`).
"""
from __future__ import annotations

import numpy as np

from .clustering import split
from .metric import FieldFeatures, RestGeometry, field_features


def pair_distances(f: FieldFeatures, pairs: np.ndarray) -> np.ndarray:
    """ε(i, j) for each row (i, j) of ``pairs`` (no matrix: one dot product a pair)."""
    return _pair_distances(f.g, f.f, f.r_self, pairs)


def _pair_distances(g, fa, r_self, pairs):
    a, b = pairs[:, 0], pairs[:, 1]
    r_ba = np.sqrt(np.maximum(np.einsum("ij,ij->i", g[b], fa[a]), 0.0))
    r_ab = np.sqrt(np.maximum(np.einsum("ij,ij->i", g[a], fa[b]), 0.0))
    return np.abs(r_ba - r_self[a]) + np.abs(r_ab - r_self[b])


#: triangles, and neighbour pairs, a block of :func:`neighbour_distances` takes at once
STREAM_BLOCK = 65536


def neighbour_distances(x0: np.ndarray, u: np.ndarray, faces: np.ndarray, rest: RestGeometry,
                        pairs: np.ndarray, block: int = STREAM_BLOCK):
    """One field's ε(i, j) for each row of ``pairs`` (E,) and its largest zero-velocity distance
    max_t z(t) (:meth:`metric.FieldFeatures.zero_distance`): what the patch stream needs of a field.

    The same numbers as :func:`metric.field_features` and :func:`pair_distances` on the whole mesh,
    computed ``block`` triangles (and pairs) at a time: of a field's features only the residual
    product's rows and columns (T, 17) and the own residuals are whole-mesh arrays, so a million
    triangles' temporaries stay a few MB instead of several GB a field in flight."""
    T = len(faces)
    g = np.empty((T, 17))
    fa = np.empty((T, 17))
    r_self = np.empty(T)
    z = 0.0
    u_mean = u.mean(axis=0)
    for s in range(0, T, block):
        e = min(T, s + block)
        f = field_features(x0, u, faces[s:e],
                           RestGeometry(rest.m0, rest.R0[s:e], rest.c0[s:e], rest.d0[s:e], rest.s0[s:e]), u_mean)
        g[s:e], fa[s:e], r_self[s:e] = f.g, f.f, f.r_self
        z = max(z, float(f.zero_distance().max()))
    d = np.empty(len(pairs))
    for s in range(0, len(pairs), block):
        d[s:s + block] = _pair_distances(g, fa, r_self, pairs[s:s + block])
    return d, z


def _coarsen(n: int, adjacency: np.ndarray, agree: np.ndarray, target: int, max_size: int) -> np.ndarray:
    """Heavy-edge matching rounds (see module docstring); returns patch labels (n,).

    The rounds work on the patch graph: one edge a pair of neighbouring patches, weighted by the
    largest a over their shared triangle edges. When patches merge, their edges to a neighbour
    are one edge of the largest of those weights (the same maximum over the shared triangle
    edges), so a round's work shrinks with the patches instead of passing over every triangle
    edge each time."""
    labels = np.arange(n)                # triangle -> patch
    size = np.ones(n, dtype=np.int64)    # triangles a patch
    u, w = adjacency.astype(np.int64), agree   # edges as patch ids (pairs keyed below), and their weights
    for _ in range(200):
        cross = u[:, 0] != u[:, 1]
        if not cross.any() or len(size) <= target:
            break
        n_p = len(size)
        uc = u[cross]
        key = np.minimum(uc[:, 0], uc[:, 1]) * n_p + np.maximum(uc[:, 0], uc[:, 1])   # the pair, in order
        order = np.argsort(key, kind="stable")
        key, w = key[order], w[cross][order]
        # patch-level distance: the largest over the shared triangle edges
        first = np.ones(len(key), dtype=bool)
        first[1:] = key[1:] != key[:-1]
        starts = np.flatnonzero(first)
        key = key[starts]
        u = np.stack([key // n_p, key % n_p], axis=1)   # the patch graph: each pair once
        w = np.maximum.reduceat(w, starts)
        ok = size[u[:, 0]] + size[u[:, 1]] <= max_size
        if not ok.any():
            break
        pe, pw = u[ok], w[ok]
        # each patch's best partner
        # (the least a; of equal ones, the edge met first with the patch first, then second)
        src = np.concatenate([pe[:, 0], pe[:, 1]])
        dst = np.concatenate([pe[:, 1], pe[:, 0]])
        bw = np.concatenate([pw, pw])
        least = np.full(n_p, np.inf)
        np.minimum.at(least, src, bw)
        hit = np.flatnonzero(bw == least[src])
        pick = np.full(n_p, len(src))
        np.minimum.at(pick, src[hit], hit)
        has = pick < len(src)
        best = np.full(n_p, -1)
        best[has] = dst[pick[has]]
        a = np.flatnonzero(best >= 0)
        mutual = a[(best[best[a]] == a) & (a < best[a])]
        if mutual.size == 0:
            break
        new = np.arange(n_p)
        new[best[mutual]] = mutual
        inv = (np.cumsum(new == np.arange(n_p)) - 1)[new]           # patch -> merged patch, compact
        labels = inv[labels]
        u = inv[u]
        size = np.bincount(inv, weights=size, minlength=int(inv.max()) + 1).astype(np.int64)
    return labels


def make_patches(neighbour_iter, n_triangles: int, adjacency: np.ndarray, centroids: np.ndarray,
                 max_size: int, target: int):
    """Patches (T,) and their representative triangles (U,) from per-field neighbour distances.

    ``neighbour_iter`` yields, one field at a time, w_p ε_p(i, j) for the rows of ``adjacency``
    (:func:`pair_distances` times the field's weight), so no field's features need to outlive
    its own distances; a = max_p of them.
    """
    agree = np.zeros(len(adjacency))
    for d in neighbour_iter:
        np.maximum(agree, d, out=agree)
    labels = _coarsen(n_triangles, adjacency, agree, target, max_size)
    labels = split(labels[None], adjacency)
    n = labels.max() + 1
    cnt = np.bincount(labels, minlength=n).astype(np.float64)
    centre = np.stack([np.bincount(labels, centroids[:, d], minlength=n) for d in range(3)], axis=1) / cnt[:, None]
    dist = np.linalg.norm(centroids - centre[labels], axis=1)
    order = np.lexsort((dist, labels))
    first = np.searchsorted(labels[order], np.arange(n))
    reps = order[first]
    return labels, reps
