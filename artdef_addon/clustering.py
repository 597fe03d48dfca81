"""Per-field average-linkage clustering and the seam split (paper §5.2; docs/method_notes.md §4, §5.1)."""
from __future__ import annotations

import numpy as np
from scipy.cluster.hierarchy import fcluster, linkage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from .metric import FieldFeatures, condensed_distance  # noqa: F401  (re-exported)


def field_linkage(f: FieldFeatures) -> np.ndarray:
    """Average-linkage (UPGMA) tree of the triangles of one field under ε (scipy ``linkage``)."""
    if f.n < 2:
        return np.zeros((0, 4))
    return linkage(condensed_distance(f), method="average")


def cut(Z: np.ndarray, n: int, k: int) -> np.ndarray:
    """Cut a tree to ``k`` clusters by undoing its last k−1 merges (choice A-3); labels from 0."""
    if n == 1 or k <= 1:
        return np.zeros(n, dtype=np.int64)
    return fcluster(Z, t=min(k, n), criterion="maxclust").astype(np.int64) - 1


def face_adjacency(faces: np.ndarray) -> np.ndarray:
    """Pairs (E,2) of triangles that share an edge."""
    t = faces.shape[0]
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e.sort(axis=1)
    owner = np.tile(np.arange(t), 3)
    order = np.lexsort((e[:, 1], e[:, 0]))
    e = e[order]
    owner = owner[order]
    same = np.all(e[1:] == e[:-1], axis=1)
    pairs = np.stack([owner[:-1][same], owner[1:][same]], axis=1)
    return pairs[pairs[:, 0] != pairs[:, 1]]


def split(labels: np.ndarray, adjacency: np.ndarray) -> np.ndarray:
    """Cut the surface along every seam of every field (choice A-5).

    ``labels`` is (G, T): one labelling per field (or per level-1 segmentation). Returns the
    connected components (T,) of the triangle graph after removing every adjacency whose two
    triangles differ in any labelling.
    """
    t = labels.shape[1]
    keep = np.all(labels[:, adjacency[:, 0]] == labels[:, adjacency[:, 1]], axis=0)
    a = adjacency[keep]
    g = coo_matrix((np.ones(len(a)), (a[:, 0], a[:, 1])), shape=(t, t))
    return connected_components(g, directed=False)[1].astype(np.int64)
