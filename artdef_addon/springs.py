"""Joint springs of a Green's rig: how loads become joint turns (paper §7; docs/greens.md).

The paper drives each joint's angles linearly by the loads (κ, §7.2): right to first order, but a
dead load keeps its world direction while its link turns, and its moment arm about every joint
above it changes with the turns of the links between. Here each joint j is a rotational spring
that turns by its torque: with R_j the world rotation of link j, x_k the load point k, c_j the
joint's head and f the loads (M, 3),

    ω_j = C_j τ_j(ω) + (E f)_j,    τ_j = R_p(j)ᵀ Σ_k (x_k − c_j) × f_k   (k on link j or below),

ω_j the turn of link j relative to its parent (a rotation vector in rest coordinates, R_j =
R_p(j) Rot(ω_j)), τ_j the torque about its head in its parent's frame. C_j (3, 3) is joint j's
compliance, the least-squares (ridge :data:`SPRING_RIDGE`) fit of the probe angles Ω_j (κ's rotation
rows in rest coordinates) to the rest torques, Ω_j ≈ C_j T_j; E = Ω − C T keeps the rest, so at
zero load ω = Ω f: the spring rig's first order is the fitted κ, and with it G.

Each term is written the way the Blender drivers compute it, without forward kinematics: the load
as link j feels it, g_jk = R_jᵀ f_k, goes down the tree (g_jk = Rot(−ω_j) g_p(j)k); the lever
arm in link j's frame goes up (λ_jk = s_jk + Rot(ω_n) λ_nk, n the next link towards load k's link,
s the rest segment: head to next head, or head to load point on that link); τ_j = Rot(ω_j) Σ_k
λ_jk × g_jk. The balance is solved by :data:`SPRING_STEPS` damped fixed-point steps from the
linear turn ω = Ω f, so every step keeps the first order. For a rigid link on a rotational spring
under a load across it this is k θ = F L cos θ.

Array in, array out; L links, M load points.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: damped fixed-point steps of :func:`spring_turns`, the drivers' as well, and their damping:
#: from the linear turn, four steps of ω ← 0.4 ω + 0.6 (C τ(ω) + E f) (benchmarks/results/greens_posing.md)
SPRING_STEPS = 4
SPRING_DAMPING = 0.6
#: ridge of the compliance fit, relative to the mean eigenvalue of T_j T_jᵀ: a joint whose loads
#: all lie along one line has no twist torque to fit its twist compliance to
SPRING_RIDGE = 1e-3


@dataclass
class Springs:
    """The joint springs of one Green's rig (:func:`joint_springs`)."""
    parents: np.ndarray      # (L,) parent link, −1 for a root
    order: list              # links, parents before children
    carrier: np.ndarray      # (M,) the link carrying load point k (its largest skin weight)
    down: np.ndarray         # (L, M) bool: load k acts on link j or below it
    next: np.ndarray         # (L, M) the next link from j towards load k's link, −1 on that link
    segment: np.ndarray      # (L, M, 3) rest segment s_jk (head to next head, or to the load point)
    turns: np.ndarray        # (L, 3, 3M) Ω: rotation vector of each link per unit flat load, rest coordinates
    compliance: np.ndarray   # (L, 3, 3) C_j
    linear: np.ndarray       # (L, 3, 3M) E = Ω − C T


def cross_matrices(a) -> np.ndarray:
    """[a]× (..., 3, 3) with [a]× b = a × b, for a (..., 3)."""
    a = np.asarray(a, dtype=np.float64)
    A = np.zeros(a.shape[:-1] + (3, 3))
    A[..., 0, 1], A[..., 0, 2], A[..., 1, 2] = -a[..., 2], a[..., 1], -a[..., 0]
    A[..., 1, 0], A[..., 2, 0], A[..., 2, 1] = a[..., 2], -a[..., 1], a[..., 0]
    return A


def _depth_order(parents) -> list:
    """Links by depth in the forest ``parents`` (L,): every parent before its children."""
    parents = np.asarray(parents)
    depth = np.zeros(len(parents), int)
    up = parents.copy()
    for _ in range(len(parents)):
        live = up >= 0
        if not live.any():
            break
        depth += live
        up = np.where(live, parents[np.maximum(up, 0)], -1)
    return [int(l) for l in np.argsort(depth, kind="stable")]


def rotate(w, v) -> np.ndarray:
    """Rodrigues: v (..., 3) turned by the rotation vectors w (..., 3), written as the drivers write it
    (cos θ v + sin θ/θ w × v + (1 − cos θ)/θ² w (w·v), θ = |w|)."""
    th = np.linalg.norm(w, axis=-1, keepdims=True)
    c = np.cos(th)
    sinc = np.sin(th) / np.maximum(th, 1e-30)
    vers = (1.0 - c) / np.maximum(th * th, 1e-60)
    return c * v + sinc * np.cross(w, v) + vers * w * np.sum(w * v, axis=-1, keepdims=True)


def joint_springs(result, rest) -> Springs:
    """The springs of a Green's fit ``result`` (with κ) on rest positions ``rest`` (N, 3)."""
    parents = np.asarray(result.parents)
    L = len(parents)
    lv = np.asarray(result.load_vertices)
    M = len(lv)
    heads = np.asarray(result.heads, dtype=np.float64)
    points = np.asarray(rest, dtype=np.float64)[lv]
    carrier = np.argmax(np.asarray(result.weights)[lv], axis=1)
    down = np.zeros((L, M), bool)
    nxt = -np.ones((L, M), int)
    for k in range(M):                       # up the tree from each load's link (L steps at most)
        l, prev = int(carrier[k]), -1
        while l >= 0:
            down[l, k], nxt[l, k] = True, prev
            prev, l = l, int(parents[l])
    ends = np.where(nxt >= 0, 0, 1)[..., None]
    segment = np.where(ends, points[None] - heads[:, None], heads[np.maximum(nxt, 0)] - heads[:, None])
    segment = np.where(down[..., None], segment, 0.0)
    kappa = np.asarray(result.kappa, dtype=np.float64)
    turns = np.einsum("lij,ljc->lic", result.frames, kappa[:, :3])
    # rest torque maps T_j (3, 3M): τ_j = Σ_k [x_k − c_j]× f_k over the loads at or below j
    T = cross_matrices(points[None] - heads[:, None]) * down[..., None, None]      # (L, M, 3, 3)
    T = np.transpose(T, (0, 2, 1, 3)).reshape(L, 3, 3 * M)
    A = np.einsum("lic,ljc->lij", T, T)
    lam = SPRING_RIDGE * np.trace(A, axis1=1, axis2=2) / 3.0
    ok = lam > 0
    C = np.zeros((L, 3, 3))
    C[ok] = np.einsum("lic,ljc->lij", turns[ok], T[ok]) @ np.linalg.inv(A[ok] + lam[ok, None, None] * np.eye(3))
    linear = turns - C @ T
    return Springs(parents, _depth_order(parents), carrier, down, nxt, segment, turns, C, linear)


def felt_loads(sp: Springs, w, loads) -> np.ndarray:
    """g (L, M, 3): load k as link j feels it at turns ``w`` (L, 3), R_jᵀ f_k (zero where k is not at or below j)."""
    f = np.asarray(loads, dtype=np.float64).reshape(-1, 3)
    g = np.zeros(sp.down.shape + (3,))
    for j in sp.order:
        p = sp.parents[j]
        g[j] = rotate(-w[j], f if p < 0 else g[p])
    return g * sp.down[..., None]


def levers(sp: Springs, w) -> np.ndarray:
    """λ (L, M, 3): from joint j's head to load point k in link j's frame, at turns ``w`` (L, 3)."""
    lev = np.array(sp.segment, copy=True)
    for j in reversed(sp.order):
        ks = np.flatnonzero(sp.down[j] & (sp.next[j] >= 0))
        if ks.size:
            n = sp.next[j, ks]
            lev[j, ks] += rotate(w[n], lev[n, ks])
    return lev


def torques(sp: Springs, w, g) -> np.ndarray:
    """τ (L, 3): each joint's torque in its parent's frame, Rot(ω_j) Σ_k λ_jk × g_jk."""
    own = np.einsum("lki->li", np.cross(levers(sp, w), g))
    return rotate(w, own)


def spring_turns(sp: Springs, loads, steps: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The joints' turns ω (L, 3) under ``loads`` (M, 3) by ``steps`` (default :data:`SPRING_STEPS`)
    damped fixed-point steps from ω = Ω f, and the felt loads g (L, M, 3) at them (:func:`felt_loads`)."""
    f = np.asarray(loads, dtype=np.float64).reshape(-1)
    w = np.einsum("lic,c->li", sp.turns, f)
    lin = np.einsum("lic,c->li", sp.linear, f)
    d = SPRING_DAMPING
    for _ in range(SPRING_STEPS if steps is None else steps):
        g = felt_loads(sp, w, f)
        w = (1.0 - d) * w + d * (np.einsum("lij,lj->li", sp.compliance, torques(sp, w, g)) + lin)
    return w, felt_loads(sp, w, f)


def carried_loads(sp: Springs, g) -> np.ndarray:
    """(M, 3): each load as the link carrying it feels it, g[carrier_k, k]."""
    return g[sp.carrier, np.arange(len(sp.carrier))]
