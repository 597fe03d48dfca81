"""Residual shapes of a tracked rig as a low-rank basis (paper §7's residual, docs/method_notes_model.md §8).

The fit's residual ``δ (P, N, 3)`` is, per field, the rest-space offset that makes the skin
reproduce that field exactly (shape keys act before skinning: ``x = Σ_l w_l G_l (x0 + δ)``).
For a Green's scan those P shapes are the paper's linear shape space, driven by the loads. For a
tracked scan (an animation) one shape per frame would store the animation a second time, so the
rig keeps the K principal shapes of the residual instead,

    δ_p ≈ Σ_k c_pk S_k,      S (K, N, 3) shapes,  c (P, K) one weight per shape and frame,

the best rank-K approximation in the least-squares sense (Eckart–Young: the truncated SVD of δ
as a P × 3N matrix). K is asked for, or chosen as the fewest shapes whose replay error reaches
:data:`options.RESIDUAL_TARGET_MAX` (worst vertex of any frame) and
:data:`options.RESIDUAL_TARGET_RMS` (RMS) in % of the bounding-box diagonal, at most
:data:`options.RESIDUAL_FRAME_SHARE` of the frames. The choice reads the rest-space error of the
truncation, an upper bound of the replay's: the blended transform Σ_l w_l R_l of convex weights
has norm ≤ 1. The errors reported are the replay's own (the rig's bone motions and the skin), with
the shapes and without them. The rig's keys hold the shapes with weights in [0, 1] (a constant
offset key takes what keeping them non-negative shifts, :func:`_keys`).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from . import model as _model
from .options import (MAX_RESIDUAL_SHAPES, RESIDUAL_FRAME_SHARE, RESIDUAL_TARGET_MAX,
                      RESIDUAL_TARGET_RMS)

#: entries of the work block (fields × vertex coordinates) the error sweeps take at once: about 32 MB
BLOCK = 4_000_000

#: singular values below this share of the largest are numerical zeros (no shape is made of them):
#: through the Gram matrix a singular value is known to about √ε ≈ 1.5e-8 of the largest
RANK_TOL = 1e-6


@dataclasses.dataclass
class ResidualBasis:
    """The rig's residual shapes of a tracked scan (see the module's docstring)."""
    shapes: np.ndarray          # (K, N, 3) rest-space shapes, scaled so that their weights span [0, 1]
    values: np.ndarray          # (P, K) each shape's weight per field, in [0, 1]
    rank: int                   # principal shapes (K: these, and one constant offset key if any)
    asked: int | None           # the shapes asked for; None: chosen from the data ("auto")
    cap: int                    # the most "auto" could choose
    skin_error: tuple           # (max, rms) replay error with no shape, % of the diagonal
    replay_error: tuple         # (max, rms) with the K shapes
    reached: bool               # the replay error reaches the targets

    @property
    def keys(self) -> int:
        """Shape keys: the ``rank`` principal shapes, and one constant offset when a weight had to be
        shifted to stay ≥ 0 (:func:`_keys`)."""
        return int(self.shapes.shape[0])

    def describe(self) -> str:
        """One line: the rank, how it was chosen and the replay errors with and without it."""
        how = (f"the fewest reaching max {RESIDUAL_TARGET_MAX:g}% / RMS {RESIDUAL_TARGET_RMS:g}% of the "
               f"diagonal, at most {self.cap}" if self.asked is None else "as asked")
        if self.asked is None and not self.reached:
            how += ": the target is not reached"
        extra = " and a constant offset key" if self.keys > self.rank else ""
        return (f"residual shapes: {self.rank} of {self.values.shape[0]} frames{extra} ({how}); replay error "
                f"skin alone max {self.skin_error[0]:.3g}% RMS {self.skin_error[1]:.3g}%, with the shapes "
                f"max {self.replay_error[0]:.3g}% RMS {self.replay_error[1]:.3g}% of the bounding-box diagonal")


def principal_shapes(residual: np.ndarray, k_max: int):
    """The ``k_max`` leading singular triplets of ``residual (P, N, 3)`` as a P × 3N matrix:
    ``(U (P, r), s (r,), V (r, 3N))`` with r ≤ k_max, singular values below :data:`RANK_TOL` of
    the largest dropped. Through the Gram matrix of the smaller side (one P × P or 3N × 3N
    eigenproblem), so a long capture of a small mesh and a big mesh of a few frames both stay cheap."""
    P = residual.shape[0]
    A = residual.reshape(P, -1)
    if P <= A.shape[1]:
        lam, U = np.linalg.eigh(A @ A.T)
        order = np.argsort(lam)[::-1][:k_max]
        s = np.sqrt(np.maximum(lam[order], 0.0))
        U = U[:, order]
        keep = _significant(s)
        U, s = U[:, keep], s[keep]
        V = (U.T @ A) / s[:, None]
    else:
        lam, W = np.linalg.eigh(A.T @ A)
        order = np.argsort(lam)[::-1][:k_max]
        s = np.sqrt(np.maximum(lam[order], 0.0))
        keep = _significant(s)
        V, s = W[:, order][:, keep].T, s[keep]
        U = (A @ V.T) / s[None, :]
    return U, s, V


def _significant(s: np.ndarray) -> np.ndarray:
    """Which of the descending singular values ``s`` are above :data:`RANK_TOL` of the largest."""
    return s > RANK_TOL * s[0] if s.size and s[0] > 0 else np.zeros(s.size, dtype=bool)


def truncation_errors(residual: np.ndarray, U: np.ndarray, diag: float) -> np.ndarray:
    """Rest-space error of every truncation: ``(r + 1, 2)``, row k the (max, RMS) over vertices
    and fields of ‖δ − Σ_{j<k} u_j u_jᵀ δ‖ in % of ``diag`` (row 0: no shape). ``U (P, r)``
    orthonormal columns (:func:`principal_shapes`); swept over blocks of vertices."""
    P, N = residual.shape[:2]
    r = U.shape[1]
    worst = np.zeros(r + 1)
    total = np.zeros(r + 1)
    step = max(1, BLOCK // max(3 * P, 1))
    for v0 in range(0, N, step):
        E = residual[:, v0:v0 + step].reshape(P, -1).copy()
        C = U.T @ E
        for k in range(r + 1):
            d = np.einsum("pvi,pvi->pv", E.reshape(P, -1, 3), E.reshape(P, -1, 3))
            worst[k] = max(worst[k], float(d.max()) if d.size else 0.0)
            total[k] += float(d.sum())
            if k < r:
                E -= np.outer(U[:, k], C[k])
    scale = 100.0 / diag if diag > 0 else 0.0
    return np.column_stack([np.sqrt(worst) * scale, np.sqrt(total / max(P * N, 1)) * scale])


def replay_error(result, x0: np.ndarray, fields: np.ndarray, shapes: np.ndarray, values: np.ndarray,
                 diag: float) -> tuple:
    """(max, RMS) distance in % of ``diag`` between the fields' positions ``x0 + fields (P, N, 3)``
    and the rig's replay of ``result``: its bones' motions (forward kinematics of the pose
    parameters, §7) skinning ``x0`` plus the residual shapes ``shapes (K, N, 3)`` at ``values
    (P, K)`` (K = 0: the skin alone). Blocks of fields at once."""
    P, N = fields.shape[:2]
    R, t = _model.forward_kinematics(result.parents, result.heads, result.frames, result.params)
    w = np.asarray(result.weights, dtype=np.float64)
    worst, total = 0.0, 0.0
    step = max(1, BLOCK // max(12 * N, 1))
    for p0 in range(0, P, step):
        c = slice(p0, p0 + step)
        rest = x0[None] + np.einsum("pk,knd->pnd", values[c], shapes) if shapes.shape[0] else x0[None]
        moved = np.einsum("pnij,pnj->pni", _model.blended_linear(w, R[c]), np.broadcast_to(rest, fields[c].shape))
        moved += np.matmul(w, t[c])
        d = np.einsum("pni,pni->pn", moved - x0 - fields[c], moved - x0 - fields[c])
        worst = max(worst, float(d.max()))
        total += float(d.sum())
    scale = 100.0 / diag if diag > 0 else 0.0
    return math.sqrt(worst) * scale, math.sqrt(total / max(P * N, 1)) * scale


def frame_cap(n_fields: int) -> int:
    """The most shapes ``auto`` chooses for ``n_fields`` frames (:data:`RESIDUAL_FRAME_SHARE`, at
    least 1, at most :data:`MAX_RESIDUAL_SHAPES`)."""
    return int(min(MAX_RESIDUAL_SHAPES, max(1, math.floor(RESIDUAL_FRAME_SHARE * n_fields))))


def choose_rank(errors: np.ndarray, cap: int) -> tuple:
    """``(k, reached)``: the fewest shapes k ≤ ``cap`` whose row of ``errors`` (:func:`truncation_errors`)
    is within both targets, else ``cap`` (the most allowed) and False."""
    ok = np.flatnonzero((errors[:cap + 1, 0] <= RESIDUAL_TARGET_MAX) & (errors[:cap + 1, 1] <= RESIDUAL_TARGET_RMS))
    if ok.size:
        return int(ok[0]), True
    return int(min(cap, errors.shape[0] - 1)), False


def low_rank_basis(result, x0: np.ndarray, fields: np.ndarray, asked: int | None) -> ResidualBasis:
    """The :class:`ResidualBasis` of a tracked fit ``result`` (its ``residual (P, N, 3)``, skin and
    pose) of the scan ``x0 (N, 3)``, ``fields (P, N, 3)``: ``asked`` shapes (at most the residual's
    rank), or with ``asked=None`` the rank :func:`choose_rank` takes, at most :func:`frame_cap`."""
    residual = np.asarray(result.residual, dtype=np.float64)
    P, N = residual.shape[:2]
    diag = float(np.linalg.norm(np.ptp(x0, axis=0))) if N else 0.0
    cap = frame_cap(P)
    k_max = min(P, cap if asked is None else int(asked))
    U, s, V = principal_shapes(residual, k_max) if k_max > 0 else (np.zeros((P, 0)), np.zeros(0), None)
    reached = True
    if asked is None:
        k, reached = choose_rank(truncation_errors(residual, U, diag), min(cap, U.shape[1]))
    else:
        k = U.shape[1]
    shapes, values = _keys(U[:, :k], s[:k], V[:k] if k else None, N)
    empty = (np.zeros((0, N, 3)), np.zeros((P, 0)))
    skin = replay_error(result, x0, fields, *empty, diag)
    replay = replay_error(result, x0, fields, shapes, values, diag) if k else skin
    if asked is None:
        reached = replay[0] <= RESIDUAL_TARGET_MAX and replay[1] <= RESIDUAL_TARGET_RMS
    return ResidualBasis(shapes=shapes, values=values, rank=k, asked=asked, cap=cap, skin_error=skin,
                         replay_error=replay, reached=reached)


def _keys(U, s, V, N):
    """Shape keys of the truncation ``U (P, k)``, ``s (k,)``, ``V (k, 3N)``: ``(shapes (C, N, 3),
    values (P, C))`` with Σ_c values[p, c] shapes[c] = (U s V)_p and every value in [0, 1]. Blender's
    glTF importer clamps a negative morph weight to 0 where it leaves the key's slider at 0, and
    engines' weight sliders start at 0: each shape's weights are shifted and scaled into [0, 1]
    (c = lo + (hi − lo) c', lo = min(0, min_p c)), and what the shift moves, Σ_k lo_k s_k v_k, is one
    more key at value 1 in every field (C = k + 1; none when no weight is negative)."""
    P, k = U.shape
    if k == 0:
        return np.zeros((0, N, 3)), np.zeros((P, 0))
    lo = np.minimum(U.min(axis=0), 0.0)
    span = U.max(axis=0) - lo
    span = np.where(span > 0, span, 1.0)
    values = (U - lo) / span
    shapes = ((s * span)[:, None] * V).reshape(k, N, 3)
    if np.any(lo < 0):
        offset = ((s * lo) @ V).reshape(1, N, 3)
        shapes = np.concatenate([shapes, offset])
        values = np.column_stack([values, np.ones(P)])
    return shapes, values


#: the result file's keys of a :class:`ResidualBasis` (docs/formats.md)
BASIS_KEYS = ("residual_shapes", "residual_values", "residual_basis_numbers")


def basis_arrays(b: ResidualBasis | None) -> dict:
    """The result file's arrays of ``b`` (none when there is no basis): the shapes, their values
    and ``(rank, asked or -1, cap, skin max, skin RMS, replay max, replay RMS, reached)``."""
    if b is None:
        return {}
    numbers = [b.rank, -1 if b.asked is None else b.asked, b.cap, *b.skin_error, *b.replay_error, float(b.reached)]
    return {"residual_shapes": b.shapes, "residual_values": b.values,
            "residual_basis_numbers": np.asarray(numbers, dtype=np.float64)}


def basis_from_arrays(d: dict) -> ResidualBasis | None:
    """The :class:`ResidualBasis` of a result file's arrays (None when it has none, or older files);
    ValueError when the arrays do not fit together."""
    if "residual_shapes" not in d:
        return None
    shapes, values = np.asarray(d["residual_shapes"], dtype=np.float64), np.asarray(d["residual_values"], dtype=np.float64)
    n = np.asarray(d["residual_basis_numbers"], dtype=np.float64).reshape(-1)
    if shapes.ndim != 3 or shapes.shape[2] != 3 or values.ndim != 2 or values.shape[1] != shapes.shape[0] or n.size != 8:
        raise ValueError("the residual shapes, their values and numbers do not fit together")
    return ResidualBasis(shapes=shapes, values=values, rank=int(n[0]), asked=None if n[1] < 0 else int(n[1]),
                         cap=int(n[2]), skin_error=(float(n[3]), float(n[4])), replay_error=(float(n[5]), float(n[6])),
                         reached=bool(n[7]))


def rig_shapes(result):
    """What a rig of ``result`` keys: ``(shapes (C, N, 3), values (P, C) or None)``. A tracked fit
    with a :class:`ResidualBasis` gives its shapes and their weights per field; otherwise the
    residual of every field is its own shape (None: field p sets shape p to 1; a Green's rig
    drives them by its loads, §7)."""
    basis = getattr(result, "residual_basis", None)
    if basis is None:
        return np.asarray(result.residual, dtype=np.float64), None
    return np.asarray(basis.shapes, dtype=np.float64), np.asarray(basis.values, dtype=np.float64)
