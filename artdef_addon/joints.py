"""Joint centres between links and the kinematic tree (paper §4, §6; O'Brien et al. 2000;
docs/method_notes_model.md §7.1–7.2).

A joint at rest position c moves identically with both links in every field:
R_a^p c + t_a^p = R_b^p c + t_b^p. Stacked over the fields this is M c = y (3P×3), solved by a
truncated SVD around a reference point c_ref (choice A-12), so hinge-like data puts the joint on
the hinge axis nearest the seam instead of collapsing it toward the origin.
"""
from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree


def fit_joint(Ra, ta, Rb, tb, c_ref, tau: float = 1e-6):
    """Least-squares joint of two motion sequences (P,3,3)/(P,3). Returns ``(c, rms, rank)``."""
    M = (Ra - Rb).reshape(-1, 3)
    y = (tb - ta).reshape(-1)
    c_ref = np.asarray(c_ref, dtype=np.float64)
    U, s, Vt = np.linalg.svd(M, full_matrices=False)
    smax = s[0] if s.size else 0.0
    keep = s > tau * max(smax, 1e-300)
    if smax <= 1e-12:
        keep[:] = False
    r = y - M @ c_ref
    coef = (U[:, keep].T @ r) / s[keep]
    c = c_ref + Vt[keep].T @ coef
    rms = float(np.linalg.norm(M @ c - y) / np.sqrt(max(len(Ra), 1)))
    return c, rms, int(keep.sum())


def spanning_tree(n: int, edges: np.ndarray, cost: np.ndarray, preferred: np.ndarray, root: int):
    """Minimum spanning tree over joint costs, oriented away from ``root``; returns parents (n,).

    ``preferred`` marks edges between mesh-adjacent links (choice A-13): they always win over
    non-adjacent ones, which only join pieces the adjacent edges cannot connect. A constant is
    added to every weight so that exact (zero-cost) joints are not taken for missing edges by
    scipy's sparse MST; a constant shift does not change which tree is minimal.
    """
    if n == 1:
        return np.array([-1])
    big = 1.0 + 2.0 * (float(cost.max()) if cost.size else 0.0) * n
    w = 1.0 + cost + np.where(preferred, 0.0, big)
    g = coo_matrix((w, (edges[:, 0], edges[:, 1])), shape=(n, n)).tocsr()
    mst = minimum_spanning_tree(g)
    order, pred = breadth_first_order(mst, root, directed=False, return_predecessors=True)
    parents = np.where(pred < 0, -1, pred).astype(np.int64)
    parents[root] = -1
    if len(order) != n:
        raise ValueError("the links do not form a connected tree")
    return parents


def lsq_motions(x0, fields, faces, labels, L, corner_weights: bool = False):
    """Least-squares rigid motion of each link per field (Kabsch/Arun SVD fit, docs/method_notes_model.md §6).

    Each link vertex counts once, or with ``corner_weights`` once per face corner it is.
    """
    P = fields.shape[0]
    R = np.zeros((P, L, 3, 3))
    t = np.zeros((P, L, 3))
    for l in range(L):
        vid, count = np.unique(faces[labels == l], return_counts=True)
        w = count / count.sum() if corner_weights else np.full(len(vid), 1.0 / len(vid))
        a = x0[vid]
        b = a[None] + fields[:, vid]
        am = w @ a
        bm = np.einsum("n,pnj->pj", w, b)
        H = np.einsum("n,ni,pnj->pij", w, a - am, b - bm[:, None])
        U, _, Vt = np.linalg.svd(H)
        d = np.sign(np.linalg.det(np.swapaxes(Vt, -1, -2) @ np.swapaxes(U, -1, -2)))
        D = np.zeros((P, 3, 3))
        D[:, 0, 0] = 1
        D[:, 1, 1] = 1
        D[:, 2, 2] = d
        Rl = np.swapaxes(Vt, -1, -2) @ D @ np.swapaxes(U, -1, -2)
        R[:, l] = Rl
        t[:, l] = bm - np.einsum("pij,j->pi", Rl, am)
    return R, t
