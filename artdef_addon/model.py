"""The articulated deformable model (paper Eqs. 1–3, §7; docs/method_notes_model.md §7.3, §8–§10).

Pose parameters are per link six numbers: the bone-local Euler angles in Blender's 'XYZ'
order (R = R_z R_y R_x) and a bone-local location (the translation the fitted joint does not
explain: zero for exact joints, the whole translation of a free root). A link's bone has its head h at the joint
and rest rotation B (columns: bone X, Y, Z in world space). Forward kinematics is Blender's
armature formula:

    G_child = G_parent · [B R_loc Bᵀ,  h + B loc − B R_loc Bᵀ h]

and a vertex moves by linear blend skinning of the seam weights, applied to its rest position
plus the residual shape offsets (shape keys act before the Armature modifier, as glTF morph
targets act before skinning):

    x(v) = Σ_l w_l(v) G_l (x0(v) + Σ_c δ_c(v) value_c).

Calibration fields are reproduced exactly: δ_c is solved in that rest space (docs/method_notes_model.md §8, with
the residual stored before skinning — see docs/method.md, "Deviations from the paper").
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from . import springs
from .springs import cross_matrices


def euler_to_matrix(angles: np.ndarray) -> np.ndarray:
    """Blender 'XYZ' Euler (x, y, z) → rotation matrix R_z(z) R_y(y) R_x(x); any leading shape."""
    a = np.asarray(angles, dtype=np.float64)
    return Rotation.from_euler("xyz", a.reshape(-1, 3)).as_matrix().reshape(a.shape[:-1] + (3, 3))


def matrix_to_euler(R: np.ndarray) -> np.ndarray:
    """Inverse of :func:`euler_to_matrix` (docs/method_notes_model.md §7.3; gimbal lock handled by scipy)."""
    R = np.asarray(R, dtype=np.float64)
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # gimbal lock: scipy sets the third angle to 0
        return Rotation.from_matrix(R.reshape(-1, 3, 3)).as_euler("xyz").reshape(R.shape[:-2] + (3,))


def topological_order(parents: np.ndarray) -> list[int]:
    order, seen = [], set()
    children = {i: [] for i in range(len(parents))}
    for i, p in enumerate(parents):
        if p >= 0:
            children[int(p)].append(i)
    stack = [i for i, p in enumerate(parents) if p < 0][::-1]
    while stack:
        i = stack.pop()
        if i in seen:
            continue
        seen.add(i)
        order.append(i)
        stack.extend(children[i][::-1])
    if len(order) != len(parents):
        raise ValueError("parents do not form a forest")
    return order


def forward_kinematics(parents, heads, frames, params) -> tuple[np.ndarray, np.ndarray]:
    """Link transforms (R (..., L, 3, 3), t (..., L, 3)) for pose ``params`` (..., L, 6)."""
    params = np.asarray(params, dtype=np.float64)
    Rloc = euler_to_matrix(params[..., :3])
    B = frames
    Rw = np.einsum("lij,...ljk,lmk->...lim", B, Rloc, B)
    tw = heads + np.einsum("lij,...lj->...li", B, params[..., 3:]) - np.einsum("...lij,lj->...li", Rw, heads)
    R = np.empty_like(Rw)
    t = np.empty_like(tw)
    for l in topological_order(parents):
        p = parents[l]
        if p < 0:
            R[..., l, :, :] = Rw[..., l, :, :]
            t[..., l, :] = tw[..., l, :]
        else:
            R[..., l, :, :] = R[..., p, :, :] @ Rw[..., l, :, :]
            t[..., l, :] = np.einsum("...ij,...j->...i", R[..., p, :, :], tw[..., l, :]) + t[..., p, :]
    return R, t


def params_from_motions(parents, heads, frames, grounded, R, t) -> np.ndarray:
    """Pose parameters (..., L, 6) that reproduce the link motions (R, t) exactly.

    Rotation: the relative rotation to the parent, in the bone frame, as Blender 'XYZ' Euler
    angles (docs/method_notes_model.md §7.3). Location: whatever translation the joint does not explain,
    loc = Bᵀ(R_pᵀ(t_l − t_p) − h + R_rel h) — zero when the fitted joint is exact, a small
    bone offset otherwise (and the whole translation of a free root), so the rig follows the
    estimated link motions even where the joint fit is imperfect. ``grounded`` is accepted for
    symmetry with the result file; a grounded root gets the same formula with the world as parent.
    """
    L = len(parents)
    Rrel = np.array(R, copy=True)
    trel = np.array(t, copy=True)
    for l in range(L):
        p = parents[l]
        if p >= 0:
            Rpt = np.swapaxes(R[..., p, :, :], -1, -2)
            Rrel[..., l, :, :] = Rpt @ R[..., l, :, :]
            trel[..., l, :] = np.einsum("...ij,...j->...i", Rpt, t[..., l, :] - t[..., p, :])
    Rloc = np.einsum("lji,...ljk,lkm->...lim", frames, Rrel, frames)
    out = np.zeros(R.shape[:-2] + (6,))
    out[..., :3] = matrix_to_euler(Rloc)
    moved = trel - heads + np.einsum("...lij,lj->...li", Rrel, heads)
    out[..., 3:] = np.einsum("lji,...lj->...li", frames, moved)
    return out


def skin(weights, R, t, x, links=None) -> np.ndarray:
    """Linear blend skinning Σ_l w_l (R_l x + t_l) for one pose; ``x`` (N,3), ``R`` (L,3,3), ``t`` (L,3).
    ``links``: :func:`skin_links` of ``weights`` when skinning many poses with them."""
    out = np.zeros_like(x)
    for l, (nz, w) in enumerate(skin_links(weights) if links is None else links):
        if nz.size:
            out[nz] += w[:, None] * (x[nz] @ R[l].T + t[l])
    return out


def skin_links(weights) -> list:
    """Each link's (vertex ids (n_l,), their weights (n_l,)) of ``weights`` (N, L): what it moves."""
    out = []
    for l in range(weights.shape[1]):
        nz = np.flatnonzero(weights[:, l])
        out.append((nz, weights[nz, l]))
    return out


def skin_errors(weights, R, t, x0, fields) -> np.ndarray:
    """Σ_p ‖skin(weights, R_p, t_p, x0) − (x0 + u_p)‖² per vertex, (N,): how far the skin with the
    motions ``R (P, L, 3, 3)``, ``t (P, L, 3)`` stays from the fields ``fields (P, N, 3)``
    (``weights`` (N, L') with L' ≤ L: the first L' links). The skin of a block of fields at once
    as blended transforms (:func:`blended_linear`, :data:`SKIN_BLOCK_BYTES` of them)."""
    N, L = weights.shape
    err = np.zeros(N)
    step = max(1, int(SKIN_BLOCK_BYTES // (8 * 12 * max(N, 1))))
    for c0 in range(0, fields.shape[0], step):
        c = slice(c0, c0 + step)
        d = np.einsum("bnij,nj->bni", blended_linear(weights, R[c, :L]), x0)
        d += np.matmul(weights, t[c, :L])
        d -= x0 + fields[c]
        err += np.einsum("bni,bni->n", d, d)
    return err


#: bytes of the blended transforms (12 numbers a vertex and field) one block of :func:`skin_errors` takes
SKIN_BLOCK_BYTES = 32 * 2 ** 20


def blended_linear(weights, R) -> np.ndarray:
    """Σ_l w_l R_l per vertex: ``weights`` (N, L), ``R`` (..., L, 3, 3) (one pose or a block of them)
    → (..., N, 3, 3), one matrix product."""
    N, L = weights.shape
    return np.matmul(weights, R.reshape(R.shape[:-3] + (L, 9))).reshape(R.shape[:-3] + (N, 3, 3))


def blended_residual(B, rhs) -> np.ndarray:
    """δ (..., 3) with B δ = rhs for blended transforms ``B`` (..., 3, 3) (:func:`blended_linear`):
    a solve where B is invertible, the pseudo-inverse where it is not (|det| ≤ 1e-10).

    The solve is Cramer's rule in closed form, element-wise over all the matrices at once: with
    B's rows b₀, b₁, b₂ the cofactor columns c₀ = b₁ × b₂, c₁ = b₂ × b₀, c₂ = b₀ × b₁ give
    det B = b₀ · c₀ and δ = Σ_j c_j rhs_j / det B, refined once with its own residual (to the
    accuracy of LAPACK's pivoted LU, whose 3 × 3 solves one matrix at a time took two thirds of
    the residual stage at a million vertices)."""
    b = [[B[..., i, j] for j in range(3)] for i in range(3)]
    # cof[j][i]: component i of the cofactor column c_j (the adjugate's row i, column j)
    cof = [[b[(j + 1) % 3][(i + 1) % 3] * b[(j + 2) % 3][(i + 2) % 3]
            - b[(j + 1) % 3][(i + 2) % 3] * b[(j + 2) % 3][(i + 1) % 3] for i in range(3)] for j in range(3)]
    det = b[0][0] * cof[0][0] + b[0][1] * cof[0][1] + b[0][2] * cof[0][2]
    ok = np.abs(det) > 1e-10
    inv_det = 1.0 / np.where(ok, det, 1.0)

    def cramer(r):
        r0, r1, r2 = r[..., 0], r[..., 1], r[..., 2]
        return np.stack([(cof[0][i] * r0 + cof[1][i] * r1 + cof[2][i] * r2) * inv_det for i in range(3)], axis=-1)

    def times_B(x):
        x0, x1, x2 = x[..., 0], x[..., 1], x[..., 2]
        return np.stack([b[i][0] * x0 + b[i][1] * x1 + b[i][2] * x2 for i in range(3)], axis=-1)
    d = cramer(rhs)
    d += cramer(rhs - times_B(d))          # one step of refinement: LU's accuracy
    if not np.all(ok):
        bad = ~ok
        d[bad] = np.einsum("nij,nj->ni", np.linalg.pinv(B[bad]), rhs[bad])
    return d


def harden(s, p_max):
    """Strain hardening of a normalised load magnitude (paper §7.1; docs/method_notes_model.md §10).

    s̃ = p_max (1 − ((p_max − 1)/p_max)^s): s̃(0)=0, s̃(1)=1, s̃ → p_max. ``p_max=None`` is off.
    """
    s = np.asarray(s, dtype=np.float64)
    if p_max is None:
        return s
    if p_max <= 1:
        raise ValueError(f"p_max must be greater than 1, got {p_max}")
    return p_max * (1.0 - ((p_max - 1.0) / p_max) ** s)


def linear_displacement(parents, heads, frames, weights, params, x) -> np.ndarray:
    """The rig's first-order (linearised) motion: d/dε of the skinned positions of ``x`` (N, 3)
    at pose ε·``params`` (..., L, 6), at ε = 0 → (..., N, 3) (paper Eq. 2 linearised;
    docs/method_notes_model.md §7.3).

    At the rest pose every link transform is the identity and R_z R_y R_x has derivative
    [e_x]× dx + [e_y]× dy + [e_z]× dz, so link l's local transform moves by A_l = [B_l ω_l]×,
    b_l = B_l loc_l − A_l h_l, and a child's world motion is its parent's plus its own:
    u(v) = Σ_l w_l(v) (A_l x(v) + b_l), the A_l and b_l summed along the tree."""
    params = np.asarray(params, dtype=np.float64)
    A = cross_matrices(np.einsum("lij,...lj->...li", frames, params[..., :3]))
    b = np.einsum("lij,...lj->...li", frames, params[..., 3:]) - np.einsum("...lij,lj->...li", A, heads)
    Aw, bw = np.empty_like(A), np.empty_like(b)
    for l in topological_order(parents):
        p = parents[l]
        Aw[..., l, :, :] = A[..., l, :, :] + (Aw[..., p, :, :] if p >= 0 else 0.0)
        bw[..., l, :] = b[..., l, :] + (bw[..., p, :] if p >= 0 else 0.0)
    return np.einsum("...nij,nj->...ni", blended_linear(weights, Aw), x) + np.matmul(weights, bw)


def hardening_slope(p_max) -> float:
    """d s̃/ds at s = 0 of :func:`harden` (1 when off): p_max ln(p_max/(p_max − 1)) (docs/method_notes_model.md §10)."""
    return 1.0 if p_max is None else float(p_max * np.log(p_max / (p_max - 1.0)))


def greens_keys(result, rest) -> np.ndarray:
    """The residual shape keys of a Green's rig, (P, N, 3), one a field (paper Eq. 6, §7.1; docs/greens.md).

    The fit's residual δ_c makes the rig reproduce field c at the probe load p̂ (x0 + p̂ Ξ e_c =
    skin(κ_c p̂, x0 + δ_c)). Scaled linearly in the load it would carry the articulation's
    second-order terms at p̂ along linearly, so the rig's tangent at zero load would not be G. The
    key is measured against the articulation's linearised motion instead
    (:func:`linear_displacement`): Δ_c = p̂ Ξ e_c − J κ_c p̂, which, with the hardening's slope σ
    at zero (:func:`hardening_slope`) dividing its value (:func:`greens_key_values`), gives the rig
    G as its derivative at zero load. ``rest`` (N, 3): the rest positions."""
    ph = float(result.probe_load)
    params = np.transpose(np.asarray(result.kappa, dtype=np.float64), (2, 0, 1)) * ph    # (P, L, 6)
    R, t = forward_kinematics(result.parents, result.heads, result.frames, params)
    B = blended_linear(result.weights, R)
    art = np.einsum("pnij,nj->pni", B, rest) + np.matmul(result.weights, t)
    delta = np.asarray(result.residual, dtype=np.float64)
    field = art + np.einsum("pnij,pnj->pni", B, delta) - rest
    return field - linear_displacement(result.parents, result.heads, result.frames, result.weights, params, rest)


#: load (in probe loads) at which the first-order keys' value is 1/√2 of linear (:func:`greens_key_values`):
#: they saturate so that what they leave of a link's stretch stays small at large loads
#: (benchmarks/results/greens_posing.md: 10 probe loads, 0.5 % without it, under 0.3 % with it)
KEY_SATURATION = 6.0


def greens_key_values(result, loads) -> np.ndarray:
    """Values (P,) of :func:`greens_keys` for the loads (M, 3) the links carrying them feel:
    key 3k+d at h(p_k)_d / (p̂ σ) / √(1 + (s/S)²) (hardening h on the residual only, A-17; S =
    :data:`KEY_SATURATION`, a change of third order in the load; s = |p_k|/p̂)."""
    loads = np.asarray(loads, dtype=np.float64).reshape(-1, 3)
    s = np.linalg.norm(loads, axis=1) / result.probe_load
    first = shape_values_for_loads(result, loads) / hardening_slope(result.p_max)
    return first / np.repeat(np.sqrt(1.0 + (s / KEY_SATURATION) ** 2), 3)


def pose_params_for_turns(result, turns, carried) -> np.ndarray:
    """Pose parameters (L, 6) of the joint turns ω (L, 3) (rotation vectors in rest coordinates,
    :func:`artdef_addon.springs.spring_turns`): the bone-local rotation Bᵀ Rot(ω) B as Euler
    angles, and the bone-local location κ's translation rows times the ``carried`` loads (M, 3)."""
    Rrel = Rotation.from_rotvec(np.asarray(turns, dtype=np.float64)).as_matrix()
    out = np.zeros((len(result.parents), 6))
    out[:, :3] = matrix_to_euler(np.einsum("lji,ljk,lkm->lim", result.frames, Rrel, result.frames))
    out[:, 3:] = np.einsum("ljc,c->lj", np.asarray(result.kappa, dtype=np.float64)[:, 3:],
                           np.asarray(carried, dtype=np.float64).reshape(-1))
    return out


def pose_params_for_loads(result, loads) -> np.ndarray:
    """Joint angles linear in load (rotational springs, paper §7): params = κ · p, (L, 6)."""
    loads = np.asarray(loads, dtype=np.float64).reshape(-1)
    return np.einsum("ljc,c->lj", result.kappa, loads)


def shape_values_for_loads(result, loads) -> np.ndarray:
    """Residual shape-key values for loads (M,3): value_{3k+d} = h(p_k)_d / p̂ (hardening on Δ only, A-17)."""
    loads = np.asarray(loads, dtype=np.float64).reshape(-1, 3)
    ph = result.probe_load
    n = np.linalg.norm(loads, axis=1)
    if result.p_max is None:
        h = loads
    else:
        s_t = harden(n / ph, result.p_max)
        h = np.where(n[:, None] > 0, ph * s_t[:, None] * loads / np.maximum(n, 1e-300)[:, None], 0.0)
    return (h / ph).reshape(-1)


def deform(result, rest, params, shape_values) -> np.ndarray:
    """Vertex positions of the rig in pose ``params`` (L,6) with shape-key ``shape_values`` (P,)."""
    R, t = forward_kinematics(result.parents, result.heads, result.frames, params)
    x = rest + np.einsum("c,cnd->nd", np.asarray(shape_values, dtype=np.float64), result.residual)
    return skin(result.weights, R, t, x)


def evaluate_loads(result, rest, loads) -> np.ndarray:
    """Positions of the load-driven model (global or pseudo) for loads (M,3) in force units: the
    joints' spring turns (:mod:`artdef_addon.springs`), and the residual keys of the loads the links
    carrying them feel."""
    loads = np.asarray(loads, dtype=np.float64).reshape(-1, 3)
    if result.pseudo:
        out = np.array(rest, dtype=np.float64, copy=True)
        for k, sub in enumerate(result.pseudo):
            if np.any(loads[k]):
                out += evaluate_loads(sub, rest, loads[k:k + 1]) - rest
        return out
    if result.kappa is None:
        raise ValueError("this fit has no loads (tracked scan): pose it with deform()")
    sp = springs.joint_springs(result, rest)
    turns, felt = springs.spring_turns(sp, loads)
    carried = springs.carried_loads(sp, felt)
    R, t = forward_kinematics(result.parents, result.heads, result.frames, pose_params_for_turns(result, turns, carried))
    x = rest + np.einsum("c,cnd->nd", greens_key_values(result, carried), greens_keys(result, rest))
    return skin(result.weights, R, t, x)
