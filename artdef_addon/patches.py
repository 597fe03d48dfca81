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
from .metric import FieldFeatures


def pair_distances(f: FieldFeatures, pairs: np.ndarray) -> np.ndarray:
    """ε(i, j) for each row (i, j) of ``pairs`` (no matrix: one dot product a pair)."""
    a, b = pairs[:, 0], pairs[:, 1]
    r_ba = np.sqrt(np.maximum(np.einsum("ij,ij->i", f.g[b], f.f[a]), 0.0))
    r_ab = np.sqrt(np.maximum(np.einsum("ij,ij->i", f.g[a], f.f[b]), 0.0))
    return np.abs(r_ba - f.r_self[a]) + np.abs(r_ab - f.r_self[b])


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
