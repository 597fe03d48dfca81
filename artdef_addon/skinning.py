"""Seam-blended skin weights (paper Eq. 2, "blended linearly" at the seams; METHOD §8, choice A-15)."""
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


def simplex_least_squares(Q: np.ndarray, q: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Exact minimiser of wᵀQw − 2qᵀw over the simplex {w ≥ 0, Σw = 1} on each row's ``valid`` entries.

    Batched over rows (Q (N,m,m), q (N,m), m small): every support subset S of the m candidates
    is tried at once for all rows — the equality-constrained optimum on S from its KKT system —
    and the best feasible one is kept. The convex optimum is one of them, so this is exact
    (2^m − 1 tiny solves per row; m ≤ 4 gives 15).
    """
    N, m = q.shape
    best = np.full(N, np.inf)
    out = np.zeros((N, m))
    for mask in range(1, 1 << m):
        S = [i for i in range(m) if mask >> i & 1]
        ok = np.all(valid[:, S], axis=1)
        if not ok.any():
            continue
        n = len(S)
        K = np.zeros((N, n + 1, n + 1))
        K[:, :n, :n] = 2 * Q[:, S][:, :, S]
        K[:, :n, n] = 1.0
        K[:, n, :n] = 1.0
        rhs = np.zeros((N, n + 1))
        rhs[:, :n] = 2 * q[:, S]
        rhs[:, n] = 1.0
        try:
            sol = np.linalg.solve(K, rhs[..., None])[..., 0]
        except np.linalg.LinAlgError:
            sol = np.einsum("nij,nj->ni", np.linalg.pinv(K), rhs)
        w = sol[:, :n]
        feas = ok & np.all(w >= -1e-12, axis=1) & np.all(np.isfinite(w), axis=1)
        if not feas.any():
            continue
        w = np.maximum(w, 0.0)
        full = np.zeros((N, m))
        full[:, S] = w
        obj = np.einsum("na,nab,nb->n", full, Q, full) - 2 * np.einsum("na,na->n", q, full)
        better = feas & (obj < best)
        best[better] = obj[better]
        out[better] = full[better]
    return out


def refined_weights(vertices: np.ndarray, fields: np.ndarray, faces: np.ndarray, labels: np.ndarray,
                    R: np.ndarray, t: np.ndarray, seam_weights: np.ndarray, max_influences: int = 4,
                    rings: int = 3, ground=None) -> np.ndarray:
    """Per-vertex convex skin weights fitted by least squares over all fields (issue 5; SSDR-style).

    For each vertex v, with candidate links C(v) — the links of the triangles within ``rings``
    rings of v, at most ``max_influences`` of them, those whose own motion explains v best —
    solve   min_w Σ_p ‖Σ_{l∈C(v)} w_l (R_l^p x0(v) + t_l^p) − x^p(v)‖²   s.t. w ≥ 0, Σ w = 1,
    given the link motions (R, t) (P, L, 3, 3) / (P, L, 3). All vertices are solved together and
    exactly by :func:`simplex_least_squares` on their small Gram systems (no per-vertex Python
    loop). ``seam_weights`` (N, L) is kept where a vertex has a single candidate. Returns (N, L)
    rows summing to 1. With ``ground`` (N,) bool, the fixed world (identity motion) is one more
    candidate for those vertices and their ``rings`` rings, returned as column L.
    """
    N = vertices.shape[0]
    if ground is not None:
        P = R.shape[0]
        R = np.concatenate([R, np.tile(np.eye(3), (P, 1, 1, 1))], axis=1)
        t = np.concatenate([t, np.zeros((P, 1, 3))], axis=1)
        seam_weights = np.concatenate([seam_weights, np.zeros((N, 1))], axis=1)
    L = R.shape[1]
    # candidate links: dilate the vertex-link incidence over the vertex graph
    rows = faces.reshape(-1)
    inc = np.asarray(coo_matrix((np.ones(rows.size), (rows, np.repeat(labels, 3))), shape=(N, L)).todense()) > 0
    if ground is not None:
        inc[:, L - 1] = ground
    f = faces
    a = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    A = coo_matrix((np.ones(len(a)), (a[:, 0], a[:, 1])), shape=(N, N)).tocsr()
    A = ((A + A.T) > 0).astype(np.float64)
    cand = inc.astype(np.float64)
    for _ in range(max(rings - 1, 0)):
        cand = cand + A @ cand
    cand = cand > 0
    # single-link error of every candidate, accumulated field by field: err (L, N)
    P = R.shape[0]
    err = np.zeros((L, N))
    for p in range(P):
        Xp = vertices + fields[p]
        for l in range(L):
            d = vertices @ R[p, l].T + t[p, l] - Xp
            err[l] += np.sqrt(np.einsum("ni,ni->n", d, d))
    err = np.where(cand.T, err, np.inf)
    if L > max_influences:
        keep = np.argsort(err, axis=0)[:max_influences]                  # (m, N)
        mask = np.zeros((L, N), dtype=bool)
        mask[keep, np.arange(N)[None, :]] = True
        mask &= np.isfinite(err)
    else:
        mask = np.isfinite(err)
    m = max_influences if L > max_influences else L
    order = np.argsort(~mask, axis=0, kind="stable")[:m]                # candidate link ids (m, N)
    valid = np.take_along_axis(mask, order, axis=0).T                   # (N, m)
    cols = order.T                                                       # (N, m)
    # Gram systems of the candidates, accumulated field by field (memory O(N m²))
    Q = np.zeros((N, m, m))
    q = np.zeros((N, m))
    for p in range(P):
        Yc = np.einsum("nmij,nj->nmi", R[p][cols], vertices) + t[p][cols]   # (N, m, 3)
        Q += np.einsum("nai,nbi->nab", Yc, Yc)
        q += np.einsum("nai,ni->na", Yc, vertices + fields[p])
    w = simplex_least_squares(Q, q, valid)
    out = np.zeros((N, L))
    np.put_along_axis(out, cols, w, axis=1)
    out[out < 1e-6] = 0.0
    return out / out.sum(axis=1, keepdims=True)


def update_motions(vertices: np.ndarray, fields: np.ndarray, weights: np.ndarray, R: np.ndarray,
                   t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One pass of link-motion updates for fixed skin weights (the bone update of SSDR).

    For each link j and field p, with the other links fixed, minimise
    Σ_v ‖w_vj (R_j x_v + t_j) − r_v‖², r_v = x^p_v − Σ_{k≠j} w_vk (R_k x_v + t_k): a weighted
    Kabsch problem with weights w_vj² and targets r_v / w_vj, solved for all fields at once.
    """
    R = R.copy()
    t = t.copy()
    P, L = R.shape[:2]
    X = vertices[None] + fields                                          # (P, N, 3)

    def moved(Rl, tl, x):                                                # (P, n, 3), BLAS matmuls
        return np.matmul(x[None], np.swapaxes(Rl, -1, -2)) + tl[:, None, :]

    blended = np.zeros_like(X)
    for l in range(L):
        vid = np.flatnonzero(weights[:, l])
        if vid.size:
            blended[:, vid] += weights[vid, l][None, :, None] * moved(R[:, l], t[:, l], vertices[vid])
    for j in range(L):
        vid = np.flatnonzero(weights[:, j] > 1e-6)
        if vid.size < 3:
            continue
        w = weights[vid, j]
        x = vertices[vid]
        own = moved(R[:, j], t[:, j], x)
        rest = blended[:, vid] - w[None, :, None] * own
        y = (X[:, vid] - rest) / w[None, :, None]
        om = w * w
        xs = om @ x / om.sum()
        ys = np.einsum("n,pni->pi", om, y) / om.sum()
        H = np.matmul(((x - xs) * om[:, None]).T[None], y - ys[:, None, :])
        U, _, Vt = np.linalg.svd(H)
        V = np.swapaxes(Vt, -1, -2)
        d = np.sign(np.linalg.det(V @ np.swapaxes(U, -1, -2)))
        D = np.tile(np.eye(3), (P, 1, 1))
        D[:, 2, 2] = d
        Rj = V @ D @ np.swapaxes(U, -1, -2)
        tj = ys - np.einsum("pij,j->pi", Rj, xs)
        blended[:, vid] += w[None, :, None] * (moved(Rj, tj, x) - own)
        R[:, j] = Rj
        t[:, j] = tj
    return R, t


def alternate(vertices, fields, faces, labels, R, t, seam_weights, iterations: int = 5, **kw):
    """Skinning decomposition from the fitted links: alternate refined weights and link motions.

    Starts from the rig's link motions and refines both, as the skinning-decomposition methods
    (SSDR / Dem Bones) do, keeping artdef's links as the candidate structure. Returns
    ``(weights, R, t)``; the articulation error never increases from one step to the next.
    """
    w = refined_weights(vertices, fields, faces, labels, R, t, seam_weights, **kw)
    for _ in range(iterations):
        R, t = update_motions(vertices, fields, w, R, t)
        w = refined_weights(vertices, fields, faces, labels, R, t, w, **kw)
    return w, R, t
