"""Least squares over the probability simplex: the refined skin's per-vertex weight solve.

Each vertex's weights minimise a small quadratic wᵀQw − 2qᵀw with Σw = 1 (and, ``convex``, w ≥ 0)
on its candidate links; :func:`simplex_least_squares` solves a batch of them by an active set on
one KKT system a row (docs/method_notes_model.md §8).
"""
from __future__ import annotations

import numpy as np


def _kkt_solve(Q, q, P):
    """Minimiser of wᵀQw − 2qᵀw subject to Σw = 1 and w = 0 off the rows' sets ``P`` (B, m).

    Q (B, m, m), q (B, m) → (B, m): one (m+1)-square KKT system a row, [[2Q, 1], [1ᵀ, 0]] on the
    set and an identity row off it (LAPACK; the pseudo-inverse if a system is singular)."""
    B, m = q.shape
    Pf = P.astype(np.float64)
    K = np.empty((B, m + 1, m + 1))
    np.multiply(Q, (2.0 * Pf)[:, :, None] * Pf[:, None, :], out=K[:, :m, :m])
    idx = np.arange(m)
    K[:, idx, idx] += 1.0 - Pf          # w = 0 off the set
    K[:, :m, m] = Pf
    K[:, m, :m] = Pf
    K[:, m, m] = 0.0
    rhs = np.empty((B, m + 1, 1))
    rhs[:, :m, 0] = 2.0 * q * Pf
    rhs[:, m, 0] = 1.0
    try:
        z = np.linalg.solve(K, rhs)[..., 0]
    except np.linalg.LinAlgError:
        z = np.einsum("nij,nj->ni", np.linalg.pinv(K), rhs[..., 0])
    return np.where(P, z[:, :m], 0.0)


def _active_set(Q, q, valid, max_rounds, w0=None):
    """Convex optimum on the simplex by a batched Lawson–Hanson active-set method (no support
    limit). Starts from each row's best single candidate, or from the feasible weights ``w0``
    (B, m) where they have support on valid candidates (a warm start: the previous round's skin).
    Returns (w, done): ``done`` marks rows whose KKT conditions hold at the end."""
    B, m = q.shape
    rows = np.arange(B)
    diagQ = np.einsum("nii->ni", Q)
    scale = np.abs(diagQ).max(axis=1) + np.abs(q).max(axis=1) + 1e-300
    single = np.where(valid, diagQ - 2 * q, np.inf)
    j0 = single.argmin(axis=1)
    w = np.zeros((B, m))
    w[rows, j0] = 1.0
    P = np.zeros((B, m), dtype=bool)
    P[rows, j0] = True
    if w0 is not None:
        w0 = np.where(valid, np.maximum(w0, 0.0), 0.0)
        tot = w0.sum(axis=1)
        warm = tot > 0
        w[warm] = w0[warm] / tot[warm, None]
        P[warm] = w[warm] > 0

    def settle(a):
        """Optimum on each row's set P, dropping the weights that turn negative (inner loop)."""
        for _ in range(m):
            z = _kkt_solve(Q[a], q[a], P[a])
            wa, Pa = w[a], P[a]
            neg = Pa & (z <= 0)
            bad = neg.any(axis=1)
            ok = ~bad
            w[a[ok]] = z[ok]
            if not bad.any():
                break
            b = a[bad]
            wb, zb, nb = wa[bad], z[bad], neg[bad]
            ratio = np.where(nb, wb / np.maximum(wb - zb, 1e-300), np.inf)
            alpha = np.clip(ratio.min(axis=1), 0.0, 1.0)
            wb = wb + alpha[:, None] * (zb - wb)
            drop = Pa[bad] & (wb <= 1e-14)
            wb[drop] = 0.0
            P[b] = Pa[bad] & ~drop
            w[b] = wb
            a = b

    if w0 is not None:
        several = np.flatnonzero(P.sum(axis=1) > 1)
        if several.size:
            settle(several)
    done = np.zeros(B, dtype=bool)
    live = rows                         # rows still adding links (a row that stops is done for good)
    for r in range(max_rounds):
        Ql, ql, Pl, wl = (Q, q, P, w) if r == 0 else (Q[live], q[live], P[live], w[live])
        g = 2 * (np.einsum("nab,nb->na", Ql, wl) - ql)
        lam = np.einsum("na,na->n", g, wl)
        viol = np.where(valid[live] & ~Pl, g - lam[:, None], np.inf)
        j = viol.argmin(axis=1)
        act = viol[np.arange(live.size), j] < -1e-10 * scale[live]
        done[live[~act]] = True
        live = live[act]
        if live.size == 0:
            break
        P[live, j[act]] = True
        settle(live)
    return w, done


def simplex_least_squares(Q: np.ndarray, q: np.ndarray, valid: np.ndarray,
                          max_support: int | None = None, w0: np.ndarray | None = None,
                          convex: bool = False):
    """Minimiser of wᵀQw − 2qᵀw over the simplex {w ≥ 0, Σw = 1} on each row's ``valid`` entries,
    with at most ``max_support`` non-zero weights (default: no limit).

    Batched over rows (Q (N,m,m), q (N,m), m small). The convex optimum comes from a batched
    Lawson–Hanson active-set method (:func:`_active_set`): exact, and where it uses at most
    ``max_support`` links it is also the optimum under the limit. Where it uses more, as the
    skinning-decomposition methods do, the largest ``max_support`` of its weights are re-solved on
    their own — or the ``max_support`` candidates that fit best alone, whichever is better (so
    never worse than choosing the links by their single fit). Rows with a single valid candidate
    get weight 1 on it without a solve. ``w0`` (N, m): feasible weights to start the active set
    from (the result does not depend on it where the optimum is unique). With ``convex`` the
    return is ``(w, w_convex)``: also the convex optimum (N, m) (no support limit) — the next
    round's best start.
    """
    N, m = q.shape
    out = np.zeros((N, m))
    nvalid = valid.sum(axis=1)
    one = nvalid == 1
    out[one] = valid[one]
    multi = np.flatnonzero(nvalid > 1)
    if multi.size == 0:
        return (out, out.copy()) if convex else out
    top = m if max_support is None else max(1, min(m, int(max_support)))
    Qm, qm, vm = Q[multi], q[multi], valid[multi]
    w, done = _active_set(Qm, qm, vm, max_rounds=3 * m, w0=None if w0 is None else w0[multi])
    if convex:
        wf = out.copy()
        wf[multi] = w
    over = np.flatnonzero(~done | (np.count_nonzero(w > 0, axis=1) > top))
    if over.size:
        Qo, qo, vo, wo = Qm[over], qm[over], vm[over], w[over]
        alone = np.where(vo, np.einsum("nii->ni", Qo) - 2 * qo, np.inf)
        subs = []
        for score in (-wo, alone):
            keep = np.argsort(score, axis=1, kind="stable")[:, :top]
            sub = np.zeros((over.size, m), dtype=bool)
            np.put_along_axis(sub, keep, True, axis=1)
            subs.append(sub & vo)
        # both choices solved in one batch (rows are independent); a row whose two choices keep
        # the same links is solved once (the same problem from the same start)
        other = np.flatnonzero((subs[0] != subs[1]).any(axis=1))
        pick = np.concatenate([np.arange(over.size), other])
        sub = np.concatenate([subs[0], subs[1][other]])
        Qs, qs = Qo[pick], qo[pick]
        # warm start from the convex optimum's weights on the kept links (feasible there, and
        # usually the limited optimum's support already): fewer active-set steps, same optimum
        ws, _ = _active_set(Qs, qs, sub, max_rounds=3 * top, w0=np.where(sub, wo[pick], 0.0))
        ws = np.maximum(ws, 0.0)
        ws /= ws.sum(axis=1, keepdims=True)
        obj = np.einsum("na,nab,nb->n", ws, Qs, ws) - 2 * np.einsum("na,na->n", qs, ws)
        best = ws[:over.size]
        better = obj[over.size:] < obj[other]
        best[other[better]] = ws[over.size:][better]
        w[over] = best
    w = np.maximum(w, 0.0)
    out[multi] = w / w.sum(axis=1, keepdims=True)
    return (out, wf) if convex else out

