"""The refined skin: alternating weight solves and link-motion updates (paper §7, docs/method_notes_model.md §8).

:func:`alternate` decomposes the fields into convex per-vertex weights (at most 4 influences) and
link motions; the weight solve of each round is :func:`.qp.simplex_least_squares` on each vertex's
candidate links (:mod:`.meshgraph`), the motion update a least-squares fit per link. The seam-blended
weights are :mod:`.seamblend`'s; the vertex and field samples :mod:`.subsample`'s. Their names are
also importable from here.
"""
from __future__ import annotations

import functools

import numpy as np

from .meshgraph import REACH_CACHE, candidate_links, link_incidence, vertex_candidates  # noqa: F401
from .qp import simplex_least_squares  # noqa: F401
from .seamblend import blend_weights  # noqa: F401
from .subsample import (SAMPLE_FIELDS, SAMPLE_PER_LINK, SAMPLE_SHARE, SAMPLE_VERTICES,  # noqa: F401
                        field_sample, vertex_sample)


def _homogeneous(vertices: np.ndarray, R: np.ndarray, t: np.ndarray):
    """Centred homogeneous rest points x̃ = [x − m, 1] (N, 4) and motions A = [R | R m + t − m] (P, L, 3, 4).

    Centring keeps the expanded squares below (‖A x̃‖² − 2 X·A x̃ + ‖X‖²) at round-off of the
    object's size rather than of its distance from the origin.
    """
    m = vertices.mean(axis=0)
    xh = np.empty((vertices.shape[0], 4))
    xh[:, :3] = vertices - m
    xh[:, 3] = 1.0
    A = np.concatenate([R, (t + R @ m - m)[..., None]], axis=-1)
    return m, xh, A


def _from_homogeneous(A: np.ndarray, m: np.ndarray):
    R = A[..., :3]
    return R.copy(), A[..., 3] - R @ m + m


#: bytes of one vertex block of the stacked fields in :func:`_data_pass`
PASS_BLOCK_BYTES = 64 * 2 ** 20


def _data_pass(xh, fields, A=None, Y=None):
    """One streamed pass over the fields (the only O(P·N) work of an iteration; BLAS products).

    With ``A`` (P, L, 3, 4): q (N, L) = Σ_p X_p(v)·(A_l^p x̃_v) and xx (N,) = Σ_p ‖X_p(v)‖².
    With ``Y`` (N, 4L) = w_vl x̃_v: M (P, L, 4, 3) = Σ_v w_vl x̃_v X_p(v)ᵀ.
    X_p = x̃ + u_p in centred coordinates. The fields are read in vertex blocks laid out as
    (n, 3P), so each block is one matrix product with an inner dimension of 3P over all fields
    at once (instead of P thin products).
    """
    N = xh.shape[0]
    P = fields.shape[0]
    x = xh[:, :3]
    out = {}
    flat = fields.X if isinstance(fields, _Flat) else None
    if A is not None:
        L = A.shape[1]
        Aflat = A.transpose(0, 2, 1, 3).reshape(3 * P, 4 * L)            # [(p,i), (l,j)]
        q = np.empty((N, L))
        xx = np.empty(N)
        out["q"], out["xx"] = q, xx
    if Y is not None:
        L = Y.shape[1] // 4
        Mflat = np.zeros((4 * L, 3 * P))                                  # [(l,j), (p,i)]
    step = N if flat is not None else max(256, int(PASS_BLOCK_BYTES // (8 * 3 * max(P, 1))))
    for s in range(0, N, step):
        e = min(N, s + step)
        # (n, 3P), a new array (the fields are never written: with one field the reshape is a view)
        Xb = flat[s:e] if flat is not None else \
            fields[:, s:e, :].transpose(1, 0, 2).reshape(e - s, 3 * P) + np.tile(x[s:e], P)
        if A is not None:
            S = (Xb @ Aflat).reshape(e - s, L, 4)
            q[s:e] = np.einsum("nlj,nj->nl", S, xh[s:e])
            xx[s:e] = np.einsum("ni,ni->n", Xb, Xb)
        if Y is not None:
            Mflat += Y[s:e].T @ Xb
    if Y is not None:
        out["M"] = Mflat.reshape(L, 4, P, 3).transpose(2, 0, 1, 3)
    return out


class _Flat:
    """Fields (P, N, 3) laid out once as the centred positions X_p = x̃ + u_p, (N, 3P), for every data
    pass of a decomposition (:func:`_data_pass` would otherwise lay them out again each round).
    Built only where that copy is one pass block (:data:`PASS_BLOCK_BYTES`)."""

    def __init__(self, vertices: np.ndarray, fields: np.ndarray):
        N, P = vertices.shape[0], fields.shape[0]
        x = vertices - vertices.mean(axis=0)
        self.X = fields.transpose(1, 0, 2).reshape(N, 3 * P) + np.tile(x, P)
        self.shape = fields.shape

    @staticmethod
    def of(vertices: np.ndarray, fields: np.ndarray):
        if isinstance(fields, _Flat) or 8 * fields.size > PASS_BLOCK_BYTES:
            return fields
        return _Flat(vertices, fields)


def _gram_links(A: np.ndarray) -> np.ndarray:
    """G[a, b] = Σ_p A_aᵀ A_b (L, L, 4, 4): Σ_p (A_a x̃)·(A_b x̃) = x̃ᵀ G[a, b] x̃ for every vertex."""
    P, L = A.shape[:2]
    Af = A.transpose(0, 2, 1, 3).reshape(P * 3, L * 4)                  # [(p, i), (l, j)]
    return (Af.T @ Af).reshape(L, 4, L, 4).transpose(0, 2, 1, 3)


def _pair_quadratic(xh: np.ndarray, G: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Q (N, m, m) with Q[v, a, b] = x̃_vᵀ G[cols[v,a], cols[v,b]] x̃_v, in vertex blocks."""
    N, m = cols.shape
    L = G.shape[0]
    Gf = G.transpose(2, 3, 0, 1).reshape(16, L * L)
    Q = np.empty((N, m, m))
    step = max(1024, int(2e7 // max(L * L, 1)))
    for s in range(0, N, step):
        x = xh[s:s + step]
        H = (np.einsum("nj,nk->njk", x, x).reshape(-1, 16) @ Gf).reshape(-1, L, L)
        c = cols[s:s + step]
        Q[s:s + step] = H[np.arange(len(x))[:, None, None], c[:, :, None], c[:, None, :]]
    return Q


#: vertices per block of the refined skin's weight solve (bounded memory at scale)
SOLVE_BLOCK = 32768
#: weight solves of at least this many vertices go to the fit's pool in vertex blocks (the full-mesh
#: skins of large scans): below it a pool worker's start-up (about 0.6 s of CPU) costs more than the
#: solve (CesiumMan's 3k vertices: tens of ms)
POOL_ROWS = 100_000

#: a vertex's candidate links: the ones whose own motion explains it best, among which its (at most
#: max_influences) skin links are chosen (see :func:`refined_weights`)
POOL = 8


def _refine(vertices, fields, faces, labels, R, t, max_influences=4, rings=3, ground=None,
            radius=None, cand=None, details=False, pool=None, w_init=None, w_free=None, free_out=None):
    """:func:`refined_weights` plus the total squared articulation error of the result.

    ``cand`` is the candidate matrix when the caller already has it (it depends on the labels
    only, so an alternation computes it once). With ``details`` a third value holds each
    vertex's candidate links ``cols`` (N, m), its normal equations ``Q`` (N, m, m), ``q`` (N, m),
    ``xx`` (N,), its weights on the candidates ``wc`` (N, m) and the single-link errors ``err``
    (L, N) (inf off the candidates) — what :mod:`swaps` needs to price removing a link.
    ``w_free`` (N, L): the previous round's convex optimum (no influence limit) to start the
    active set from instead of ``w_init`` (it differs from this round's by the motions' change
    only, so few links enter or leave); ``free_out``: a dict that receives this round's, "w" (N, L).
    """
    N = vertices.shape[0]
    P = R.shape[0]
    if ground is not None:
        R = np.concatenate([R, np.tile(np.eye(3), (P, 1, 1, 1))], axis=1)
        t = np.concatenate([t, np.zeros((P, 1, 3))], axis=1)
    L = R.shape[1]
    if cand is None:
        cand = vertex_candidates(vertices, faces, labels, L, rings, radius, ground)
    # every candidate's single-link squared error over all fields, from one data pass:
    # Σ_p ‖A_l x̃ − X_p‖² = x̃ᵀ G_ll x̃ − 2 q_l + Σ_p ‖X_p‖²
    m0, xh, A = _homogeneous(vertices, R, t)
    stats = _data_pass(xh, fields, A=A)
    q_all, xx = stats["q"], stats["xx"]
    G = _gram_links(A)
    Gd = G[np.arange(L), np.arange(L)]                                   # (L, 4, 4)
    err = np.einsum("nj,ljk,nk->ln", xh, Gd, xh, optimize=_single_path(xh.shape, Gd.shape)) - 2 * q_all.T + xx[None]
    err = np.where(cand.T, np.maximum(err, 0.0), np.inf)
    pool = POOL if pool is None else pool
    if L > pool:
        keep = np.argsort(err, axis=0)[:pool]                            # (m, N)
        mask = np.zeros((L, N), dtype=bool)
        mask[keep, np.arange(N)[None, :]] = True
        mask &= np.isfinite(err)
    else:
        mask = np.isfinite(err)
    m = min(pool, L)
    order = np.argsort(~mask, axis=0, kind="stable")[:m]                # candidate link ids (m, N)
    valid = np.take_along_axis(mask, order, axis=0).T                   # (N, m)
    cols = order.T                                                       # (N, m)
    # Gram systems of the candidates (no pass over the fields), solved in vertex blocks so that
    # the O(N m²) systems and the solver's work arrays stay bounded at scale (rows are independent:
    # the same weights as one batch); kept whole only when the details are asked for (swaps, which
    # run on small scans only)
    q = np.take_along_axis(q_all, cols, axis=1)
    start = w_init if w_free is None else w_free
    w0 = None if start is None else np.take_along_axis(start, cols, axis=1) * valid
    out = np.zeros((N, L))
    wc = np.zeros((N, m))
    block = N if details else SOLVE_BLOCK
    Q = _pair_quadratic(xh, G, cols) if details else None
    row_err = np.empty(N)

    def solve(se):
        """The weights of rows s:e (independent of every other row) into ``wc``, their errors into
        ``row_err``; returns their convex optimum with ``free_out``, else None."""
        s, e = se
        Qb = Q[s:e] if details else _pair_quadratic(xh[s:e], G, cols[s:e])
        wb, wf, row_err[s:e] = solve_rows(Qb, q[s:e], valid[s:e], None if w0 is None else w0[s:e],
                                          xx[s:e], max_influences, free_out is not None)
        wc[s:e] = wb
        return wf

    parts = [(s, min(N, s + block)) for s in range(0, N, block)]
    from .parallel import weight_blocks
    pooled = None if details or N < POOL_ROWS else weight_blocks(
        xh, G, cols, q, valid, w0, xx, max_influences, free_out is not None, parts)
    if pooled is None:
        convex = [solve(se) for se in parts]
    else:
        convex = []
        for (s, e), (wb, wf, err_b) in zip(parts, pooled):
            wc[s:e], row_err[s:e] = wb, err_b
            convex.append(wf)
    total = 0.0                          # summed a SOLVE_BLOCK at a time
    for s in range(0, N, block):
        total += float(np.sum(row_err[s:min(N, s + block)]))
    np.put_along_axis(out, cols, wc, axis=1)
    if free_out is not None:
        wf = np.zeros((N, L))
        np.put_along_axis(wf, cols, np.concatenate(convex), axis=1)
        free_out["w"] = wf
    if details:
        return out, max(total, 0.0), {"cols": cols, "valid": valid, "Q": Q, "q": q, "xx": xx, "wc": wc, "err": err}
    return out, max(total, 0.0)


@functools.lru_cache(maxsize=64)
def _single_path(xshape, gshape):
    """The contraction order ``np.einsum(..., optimize=True)`` picks for the single-link errors
    x̃ᵀ G_ll x̃ of ``_refine`` (N, 4), (L, 4, 4), remembered per shape (the search costs more than
    the contraction on a vertex sample)."""
    x, g = np.empty(xshape), np.empty(gshape)
    return np.einsum_path("nj,ljk,nk->ln", x, g, x, optimize=True)[0]


def refined_weights(vertices: np.ndarray, fields: np.ndarray, faces: np.ndarray, labels: np.ndarray,
                    R: np.ndarray, t: np.ndarray, max_influences: int = 4,
                    rings: int = 3, ground=None, radius: float | None = None,
                    pool: int | None = None) -> np.ndarray:
    """Per-vertex convex skin weights fitted by least squares over all fields (SSDR-style).

    For each vertex v, with candidate links C(v) — the links of the triangles within ``rings``
    rings of v (or the ``radius``, :func:`candidate_links`), at most ``pool`` (default ``POOL``) of
    them, those whose own motion explains v best —
    solve   min_w Σ_p ‖Σ_{l∈C(v)} w_l (R_l^p x0(v) + t_l^p) − x^p(v)‖²   s.t. w ≥ 0, Σ w = 1,
    with at most ``max_influences`` non-zero weights (:func:`simplex_least_squares`). The pool is
    wider than the influences because a vertex blended over four bones is often explained better,
    one link at a time, by a neighbouring bone it does not use (figures:
    ``benchmarks/results/core_constants.md``).
    given the link motions (R, t) (P, L, 3, 3) / (P, L, 3). The normal equations are sums
    over fields that factor into per-link-pair 4×4 matrices (Σ_p A_aᵀA_b, independent of the
    vertex) and one streamed pass of small matrix products over the fields (Le & Deng's SSDR
    trick), so the cost is O(N·P·L) in BLAS plus O(N·m²) — no per-vertex or per-field Python
    loop over vertices. Rows with one candidate get weight 1. Returns (N, L) rows summing to 1. With ``ground`` (N,) bool, the fixed world (identity
    motion) is one more candidate for those vertices and their ``rings`` rings, returned as
    column L.
    """
    return _refine(vertices, fields, faces, labels, R, t, max_influences, rings, ground, radius, pool=pool)[0]


def update_motions(vertices: np.ndarray, fields: np.ndarray, weights: np.ndarray, R: np.ndarray,
                   t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One pass of link-motion updates for fixed skin weights (the bone update of SSDR).

    For each link j and field p, with the other links fixed, minimise
    Σ_v ‖w_vj (R_j x_v + t_j) − r_v‖², r_v = x^p_v − Σ_{k≠j} w_vk (R_k x_v + t_k): a weighted
    Kabsch problem. Its cross-covariance is M_j^p − Σ_{k≠j} A_k C_kj with
    M^p = Σ_v w_v x̃_v X_p(v)ᵀ (one streamed product per field) and C_kj = Σ_v w_vk w_vj x̃ x̃ᵀ
    (once), so the links are updated one after another (Gauss–Seidel, as before) for all
    fields at once without touching the vertices again.
    """
    P, L = R.shape[:2]
    N = vertices.shape[0]
    m0, xh, A = _homogeneous(vertices, R, t)
    Y = (weights[:, :, None] * xh[:, None, :]).reshape(N, L * 4)
    C = (Y.T @ Y).reshape(L, 4, L, 4).transpose(0, 2, 1, 3)             # C[k, j] (4, 4)
    M = _data_pass(xh, fields, Y=Y)["M"]                             # (P, L, 4, 3)
    count = np.count_nonzero(weights > 1e-6, axis=0)
    D = np.tile(np.eye(3), (P, 1, 1))
    Ct = np.ascontiguousarray(C.transpose(1, 0, 2, 3)).reshape(L, L * 4, 4)   # Ct[j] = [C[k, j]]_k
    Af = np.ascontiguousarray(A.transpose(0, 2, 1, 3))                         # (P, 3, L, 4), a view below
    Af2 = Af.reshape(P * 3, L * 4)
    for j in range(L):
        if count[j] < 3:
            continue
        Cjj = C[j, j]
        s0 = Cjj[3, 3]
        sx = Cjj[:3, 3]
        # Σ_v w_vj r_v x̃_vᵀ, (P, 3, 4): Σ_k A_k C_kj as one product over (k, a)
        Nj = (np.swapaxes(M[:, j], -1, -2) - (Af2 @ Ct[j]).reshape(P, 3, 4)
              + Af[:, :, j] @ Cjj)
        n1 = Nj[:, :, 3]
        H = Nj[:, :, :3] - n1[:, :, None] * sx[None, None, :] / s0
        U, _, Vt = np.linalg.svd(H)
        d = np.sign(np.linalg.det(U @ Vt))
        D[:, 2, 2] = np.where(d == 0, 1.0, d)
        Rj = U @ D @ Vt
        Af[:, :, j, :3] = Rj
        Af[:, :, j, 3] = (n1 - Rj @ sx) / s0
    return _from_homogeneous(Af.transpose(0, 2, 1, 3), m0)


#: geodesic reach of a link's skin, as a fraction of the bounding-box diagonal (refined skin): as
#: far as the rigged models' true weights reach (``benchmarks/results/core_constants.md``)
SKIN_RADIUS = 0.2


def alternate(vertices, fields, faces, labels, R, t, iterations: int = 30,
              tol: float = 1e-4, radius: float | None = SKIN_RADIUS, **kw):
    """Skinning decomposition from the fitted links: alternate refined weights and link motions.

    Starts from the rig's link motions and refines both, as the skinning-decomposition methods
    (SSDR / Dem Bones) do, keeping artdef's links as the candidate structure. Stops after
    ``iterations`` rounds or when a round lowers the squared articulation error by less than a
    fraction ``tol``. Returns ``(weights, R, t)``; the error never increases from one step to
    the next (each step is an exact minimiser given the other). ``w_init`` (N, L): feasible weights
    to warm-start the first weight solve from (the active set's start; see :func:`simplex_least_squares`).
    """
    rows = kw.pop("rows", None)
    if rows is not None:
        # most rounds on the vertex sample, then the last ones on every vertex from its motions
        w, R, t, _ = alternate_scored(vertices, fields, faces, labels, R, t, iterations, tol, radius,
                                      rows=rows, **kw)
        w_full = np.zeros((vertices.shape[0], w.shape[1]))
        w_full[rows] = w
        kw["w_init"] = w_full
        iterations = POLISH_ROUNDS
    return alternate_scored(vertices, fields, faces, labels, R, t, iterations, tol, radius, **kw)[:3]


#: rounds of the refined skin on every vertex after its decomposition on a vertex sample
POLISH_ROUNDS = 3


#: a decomposition given a ``target`` error (a swap trial, :mod:`swaps`) stops once its error, less
#: this many times its last round's drop for every round left, is still above the target. On
#: CesiumMan's fit the drop per round shrinks (rising at most 1.7x in a round), so a
#: trial stopped this way would not have reached the target in its rounds; on CesiumMan the six
#: rejected trials stop after 3-4 of their 10 rounds (126 weight solves in the fit instead of 164,
#: the same result).
GIVE_UP_SLACK = 2.0


def alternate_scored(vertices, fields, faces, labels, R, t, iterations=30, tol=1e-4, radius=SKIN_RADIUS,
                     details=False, **kw):
    """:func:`alternate` returning ``(weights, R, t, error)``: error is the total squared
    articulation error Σ_p Σ_v ‖x̂ − x‖² of the returned skin. With ``details`` a fifth value
    holds :func:`_refine`'s details of the returned skin (what :mod:`swaps` prices links from).
    ``target``: stop early when the error cannot fall below it in the rounds left
    (:data:`GIVE_UP_SLACK`), or (``far``, pairs ``(rounds, factor)``) when after ``rounds`` rounds it
    is still ``factor`` times above it; the returned error is then above it. ``rows`` (S,): decompose on
    those vertices only (:func:`vertex_sample`; candidates still from the whole mesh): weights,
    error and details are then the sample's, (S, L); :func:`full_skin` extends them to every vertex.
    The rounds are :class:`Alternation`'s."""
    run = Alternation(vertices, fields, faces, labels, R, t, iterations, tol, radius, details=details, **kw)
    run.start()
    while not run.finished:
        run.step()
    return run.result()


def solve_rows(Qb, q, valid, w0, xx, max_influences, convex):
    """One vertex block of :func:`_refine`'s weight solve: ``(weights (n, m), convex optimum or
    None, squared errors (n,))`` from the block's normal equations ``Qb (n, m, m)``, ``q (n, m)``,
    ``xx (n,)`` (rows are independent: any split into blocks gives the same rows)."""
    wb = simplex_least_squares(Qb, q, valid, max_support=max_influences, w0=w0, convex=convex)
    wf = None
    if convex:
        wb, wf = wb
    wb[wb < 1e-6] = 0.0
    wb /= wb.sum(axis=1, keepdims=True)
    err = np.einsum("na,nab,nb->n", wb, Qb, wb) - 2 * np.einsum("na,na->n", q, wb) + xx
    return wb, wf, err


def weight_task(arrays, params, report):
    """In a pool's worker: :func:`solve_rows` of one vertex block (:func:`parallel.weight_blocks`)."""
    from .procs import shared as sh
    s, e = params["rows"]
    cols = np.asarray(sh(params["cols"])[s:e])
    Qb = _pair_quadratic(np.asarray(sh(params["xh"])[s:e]), np.asarray(sh(params["G"])), cols)
    w0 = np.asarray(sh(params["w0"])[s:e]) if "w0" in params else None
    wb, wf, err = solve_rows(Qb, np.asarray(sh(params["q"])[s:e]), np.asarray(sh(params["valid"])[s:e]),
                             w0, np.asarray(sh(params["xx"])[s:e]), params["max_influences"],
                             params["convex"])
    return {}, {"w": wb, "err": err, **({} if wf is None else {"free": wf})}


class Alternation:
    """One skin decomposition (:func:`alternate_scored`) advanced a round at a time, so that several
    of them — the split trials of a round (:func:`splits.split_links`) — can run in lockstep, be
    compared round by round. :meth:`start` solves the weights for the
    starting motions (round 0); each :meth:`step` updates the motions and then the weights (one
    round); ``finished`` is set once the rounds are used up, the error falls by less than ``tol``,
    the ``target`` is out of reach, or :meth:`stop` was called. ``e`` is the current error,
    ``rounds`` the rounds done."""

    def __init__(self, vertices, fields, faces, labels, R, t, iterations=30, tol=1e-4, radius=SKIN_RADIUS,
                 details=False, target=None, far=None, w_init=None, rows=None, **kw):
        kw["radius"] = radius
        kw["details"] = details
        self.args = (vertices, fields, faces, labels, R, t)
        self.kw, self.iterations, self.tol = kw, iterations, tol
        self.target, self.far, self.w_init, self.rows = target, far, w_init, rows
        self.rounds, self.finished, self.e = 0, False, np.inf

    def start(self) -> None:
        """Candidates, the vertex sample's arrays and the first weight solve (round 0)."""
        vertices, fields, faces, labels, R, t = self.args
        kw, rows, w_init = self.kw, self.rows, self.w_init
        L = R.shape[1] + (1 if kw.get("ground") is not None else 0)
        kw["cand"] = vertex_candidates(vertices, faces, labels, L, kw.get("rings", 3), kw["radius"], kw.get("ground"))
        if rows is not None:
            # the decomposition on a vertex sample (:func:`vertex_sample`): candidates from the whole mesh
            vertices, fields, kw["cand"] = vertices[rows], fields[:, rows], kw["cand"][rows]
            w_init = None if w_init is None else w_init[rows]
            if kw.get("ground") is not None:
                kw["ground"] = kw["ground"][rows]
        self.vertices, self.fields, self.faces, self.labels = vertices, _Flat.of(vertices, fields), faces, labels
        self.free = {}
        self.w, self.e, *self.info = _refine(vertices, self.fields, faces, labels, R, t, w_init=w_init,
                                             free_out=self.free, **kw)
        self.R, self.t = R, t
        self.finished = self.iterations <= 0

    def step(self) -> None:
        """One round: the motions for the weights (:func:`update_motions`), then the weights for the
        motions, warm-started from the last round's convex optimum (fewer active-set steps)."""
        if self.finished:
            return
        i, e, target = self.rounds, self.e, self.target
        R1, t1 = update_motions(self.vertices, self.fields, self.w, self.R, self.t)
        free1 = {}
        w1, e1, *info1 = _refine(self.vertices, self.fields, self.faces, self.labels, R1, t1, w_init=self.w,
                                 w_free=self.free["w"], free_out=free1, **self.kw)
        if e1 > e:      # round-off only: keep the better pair
            self.finished = True
            return
        done = e - e1 <= self.tol * e
        # a trial that cannot reach ``target`` in its remaining rounds: the alternation's drops
        # shrink from round to round (measured on the real sets; GIVE_UP_SLACK for the odd rise)
        hopeless = target is not None and e1 - GIVE_UP_SLACK * (e - e1) * (self.iterations - 1 - i) > target
        if self.far is not None and target is not None:
            # still far above the target after so many rounds (splits.FAR)
            bars = [f for r, f in self.far if i + 1 >= r]
            hopeless |= bool(bars) and e1 > min(bars) * target
        self.w, self.R, self.t, self.e, self.info, self.free = w1, R1, t1, e1, info1, free1
        self.rounds = i + 1
        self.finished = done or hopeless or self.rounds >= self.iterations

    def stop(self) -> None:
        """Give the run up where it stands (a lockstep comparison found it far behind)."""
        self.finished = True

    def result(self) -> tuple:
        """``(weights, R, t, error)`` and, with ``details``, :func:`_refine`'s details."""
        return (self.w, self.R, self.t, self.e, *self.info)


def full_skin(vertices, fields, faces, labels, R, t, radius=SKIN_RADIUS, details=False, rows=None,
              w_rows=None, **kw):
    """The weights of every vertex for given link motions ``R (P, L, 3, 3)``, ``t (P, L, 3)``: one
    weight solve (:func:`_refine`), warm-started on ``rows`` from their weights ``w_rows (S, L)``
    (a decomposition on a :func:`vertex_sample`). Returns ``(weights (N, L), error)`` and, with
    ``details``, the details dict."""
    L = R.shape[1] + (1 if kw.get("ground") is not None else 0)
    cand = vertex_candidates(vertices, faces, labels, L, kw.get("rings", 3), radius, kw.get("ground"))
    w_init = None
    if rows is not None and w_rows is not None:
        w_init = np.zeros((vertices.shape[0], w_rows.shape[1]))
        w_init[rows] = w_rows
    return _refine(vertices, fields, faces, labels, R, t, cand=cand, radius=radius, details=details,
                   w_init=w_init, **kw)

