"""Seam-blended skin weights (paper Eq. 2, "blended linearly" at the seams; docs/method_notes_model.md §8,
choice A-15)."""
from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix, diags


def blend_weights(vertices: np.ndarray, faces: np.ndarray, labels: np.ndarray, n_links: int,
                  rings: int = 1) -> np.ndarray:
    """w_l(v) = area of v's incident triangles in link l / total incident area, (N, L), rows sum to 1.

    Pure link vertices get weight 1; vertices on a seam are blended over its one-ring. With
    ``rings`` > 1 the weights are further averaged over vertex neighbourhoods (a band of
    ``rings`` rings around each seam). A vertex in no triangle (or only in degenerate ones) takes
    the weights of its incident faces by count, else of link 0.
    """
    n = vertices.shape[0]
    e1 = vertices[faces[:, 1]] - vertices[faces[:, 0]]
    e2 = vertices[faces[:, 2]] - vertices[faces[:, 0]]
    area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)
    rows = faces.reshape(-1)
    cols = np.repeat(labels, 3)

    def incidence(values):
        return np.asarray(coo_matrix((values, (rows, cols)), shape=(n, n_links)).todense())

    W = incidence(np.repeat(area, 3))
    tot = W.sum(axis=1)
    empty = tot <= 0
    if np.any(empty):
        Wc = incidence(np.ones(rows.shape[0]))
        W[empty] = Wc[empty]
        tot = W.sum(axis=1)
        still = tot <= 0
        W[still, 0] = 1.0
        tot = W.sum(axis=1)
    W /= tot[:, None]
    if rings > 1:
        f = faces
        a = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        A = coo_matrix((np.ones(len(a)), (a[:, 0], a[:, 1])), shape=(n, n)).tocsr()
        A = ((A + A.T) > 0).astype(np.float64) + diags(np.ones(n))
        A = diags(1.0 / np.asarray(A.sum(axis=1)).ravel()) @ A
        for _ in range(rings - 1):
            W = A @ W
        W /= W.sum(axis=1, keepdims=True)
    return W
