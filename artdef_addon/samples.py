"""Built-in sample scans with known answers.

* ``rod``        — the paper's Table 1 object: a 3-link rod along x, joints at x = 0, 12, 24
  (joint 1 to the fixed support), seams linearly blended, three tracked fields (docs/method_notes_model.md §11).
* ``branching``  — a hub with five two-segment arms (11 links, a branching tree), 12 fields,
  optionally with noise and local bulges; ``disconnected=True`` builds the arms as separate
  pieces that share no vertex with the hub.
* ``greens_rod`` — a Green's-matrix scan: unit loads at four vertices bend the rod (fixed at
  its support) through three rotational springs, plus a local dent at each load.
* ``elastic``    — not articulated: the rod's tube bent, twisted and bulged smoothly along its
  whole length (no rigid part, no joint), 12 fields; the fit's verdict must say so (docs/metrics.md).

``make(name)`` returns a :class:`Scan`; ``make_with_truth(name)`` also returns the truth:
``face_labels``, ``joints`` (per link, its joint with its parent or the support), ``parents``.
"""
from __future__ import annotations

import functools

import numpy as np
from scipy.spatial.transform import Rotation

from .options import FloatRange, IntRange
from .scan import Scan, validate_scan

NAMES = ("rod", "branching", "greens_rod", "elastic")
#: the ranges of the sample command's numeric settings (``python -m artdef_addon sample``), by name
RANGES = {"fields": IntRange(1, 1000), "noise": FloatRange(0.0, 100.0), "seed": IntRange(0, 2 ** 63 - 1)}
_SQUARE = np.array([(-1, -1), (0, -1), (1, -1), (1, 0), (1, 1), (0, 1), (-1, 1), (-1, 0)], dtype=float)


def _checked(build):
    """A sample builder whose scan is checked where it is made (:func:`scan.validate_scan`): the
    fit's modules take it as it is."""
    @functools.wraps(build)
    def checked(*args, **kw):
        scan, truth = build(*args, **kw)
        return validate_scan(scan), truth
    return checked


def _tube(length: int):
    """Square 2×2 tube along x from 0 to ``length``, 8 vertices a ring at unit spacing, capped at the end."""
    rings = np.arange(length + 1, dtype=float)
    v = np.zeros((len(rings), 8, 3))
    v[:, :, 0] = rings[:, None]
    v[:, :, 1:] = _SQUARE[None]
    v = v.reshape(-1, 3)
    i = np.arange(length)[:, None]
    j = np.arange(8)[None, :]
    a = i * 8 + j
    b = i * 8 + (j + 1) % 8
    c = (i + 1) * 8 + (j + 1) % 8
    d = (i + 1) * 8 + j
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    centre = len(v)
    v = np.vstack([v, [[length, 0, 0]]])
    ring = length * 8 + np.arange(8)
    cap = np.stack([ring, np.roll(ring, -1), np.full(8, centre)], -1)
    return v, _orient(v, np.concatenate([faces, cap]), lambda c: np.where(
        (c[:, 0] > length - 1e-9)[:, None], [[1.0, 0, 0]], c * [0, 1, 1]))


def _orient(v, f, outward):
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    c = v[f].mean(axis=1)
    flip = np.einsum("ij,ij->i", n, outward(c)) < 0
    f = f.copy()
    f[flip] = f[flip][:, [0, 2, 1]]
    return f


def _true_labels(faces, weights):
    """The true link of a face: the bone with the largest summed weight over its vertices
    (the convention of the shared ground-truth data)."""
    summed = weights[faces].sum(axis=1)
    return summed.argmax(axis=1), summed


def _ramp(x, lo, hi):
    return np.clip((x - lo) / (hi - lo), 0.0, 1.0)


def _skin(x0, weights, R, t):
    return np.einsum("nl,lij,nj->ni", weights, R, x0) + weights @ t


def _chain_fk(joints, rotations):
    """World transforms of a chain of links, link j rotating about joint j relative to link j−1."""
    R = np.eye(3)
    t = np.zeros(3)
    Rs, ts = [], []
    for c, Rj in zip(joints, rotations):
        # G = G_prev · Tr(c) Rj Tr(−c)
        t = R @ (c - Rj @ c) + t
        R = R @ Rj
        Rs.append(R)
        ts.append(t)
    return np.array(Rs), np.array(ts)


@_checked
def rod(blend: float = 1.0, n_fields: int = 3, seed: int = 0, max_deg: float = 25.0, min_deg: float = 5.0):
    """The paper's three-link rod (Table 1)."""
    x0, faces = _tube(36)
    joints = np.array([[0.0, 0, 0], [12.0, 0, 0], [24.0, 0, 0]])
    x = x0[:, 0]
    r = [_ramp(x, 0.0, blend), _ramp(x, 12 - blend, 12 + blend), _ramp(x, 24 - blend, 24 + blend)]
    w = np.stack([1 - r[0], r[0] - r[1], r[1] - r[2], r[2]], axis=1)  # ground, link 1..3
    rng = np.random.default_rng(seed)
    fields, rel = [], []
    for p in range(n_fields):
        ang = np.radians(rng.uniform(min_deg, max_deg, (3, 3)) * rng.choice([-1, 1], (3, 3)))
        Rj = Rotation.from_euler("ZYX", ang).as_matrix()
        R, t = _chain_fk(joints, Rj)
        Rall = np.concatenate([np.eye(3)[None], R])
        tall = np.concatenate([np.zeros((1, 3)), t])
        fields.append(_skin(x0, w, Rall, tall) - x0)
        rel.append(Rj)
    truth = dict(face_labels=np.maximum(_true_labels(faces, w)[0] - 1, 0), joints=joints,
                 parents=np.array([-1, 0, 1]), relative_rotations=np.array(rel), weights=w[:, 1:])
    scan = Scan(x0, faces, displacements=np.array(fields), support_vertices=np.arange(8))
    return scan, truth


def _branching_mesh(disconnected: bool):
    """Hub box [-3,3]³ with holes on five faces and a square tube arm of length 8 out of each."""
    keys: dict = {}
    pts: list = []

    def vid(p, piece):
        k = (piece if disconnected else 0,) + tuple(np.round(p, 6))
        if k not in keys:
            keys[k] = len(pts)
            pts.append(p)
        return keys[k]

    tris, outward, part, dist = [], [], [], []
    arm_dirs = [(0, 1), (0, -1), (1, 1), (1, -1), (2, 1)]
    for a in range(3):
        for s in (1, -1):
            u_ax, v_ax = [i for i in range(3) if i != a]
            hole = (a, s) in arm_dirs
            for u in range(-3, 3):
                for v in range(-3, 3):
                    if hole and -1 <= u <= 0 and -1 <= v <= 0:
                        continue
                    corners = []
                    for du, dv in ((0, 0), (1, 0), (1, 1), (0, 1)):
                        p = np.zeros(3)
                        p[a] = 3 * s
                        p[u_ax] = u + du
                        p[v_ax] = v + dv
                        corners.append(vid(p, 0))
                    n = np.zeros(3)
                    n[a] = s
                    for tri in ((0, 1, 2), (0, 2, 3)):
                        tris.append([corners[i] for i in tri])
                        outward.append(n)
                        part.append(0)
                        dist.append(0.0)
    for arm, (a, s) in enumerate(arm_dirs):
        n = np.zeros(3)
        n[a] = s
        base = 3 * s * np.eye(3)[a]
        u_ax, v_ax = [i for i in range(3) if i != a]
        ring = []
        for d in range(9):
            row = []
            for (pu, pv) in _SQUARE:
                p = base + d * n
                p = p.copy()
                p[u_ax] += pu
                p[v_ax] += pv
                row.append(vid(p, 1 + arm))
            ring.append(row)
        for d in range(8):
            for j in range(8):
                q = [ring[d][j], ring[d][(j + 1) % 8], ring[d + 1][(j + 1) % 8], ring[d + 1][j]]
                for tri in ((0, 1, 2), (0, 2, 3)):
                    tris.append([q[i] for i in tri])
                    outward.append(None)
                    part.append(1 + arm)
                    dist.append(d + 0.5)
        centre = vid(base + 8 * n, 1 + arm)
        for j in range(8):
            tris.append([ring[8][j], ring[8][(j + 1) % 8], centre])
            outward.append(n)
            part.append(1 + arm)
            dist.append(8.0)
    v = np.array(pts, dtype=float)
    f = np.array(tris, dtype=np.int64)
    part = np.array(part)
    dist = np.array(dist)
    c = v[f].mean(axis=1)
    out = np.zeros_like(c)
    for i, o in enumerate(outward):
        if o is not None:
            out[i] = o
        else:
            a, s = arm_dirs[part[i] - 1]
            r = c[i].copy()
            r[a] = 0
            out[i] = r
    nrm = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    flip = np.einsum("ij,ij->i", nrm, out) < 0
    f[flip] = f[flip][:, [0, 2, 1]]
    return v, f, part, dist, arm_dirs


def _vertex_normals(v, f):
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    vn = np.zeros_like(v)
    for i in range(3):
        np.add.at(vn, f[:, i], n)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)


@_checked
def branching(n_fields: int = 12, noise: float = 0.0, bulges: bool = False, disconnected: bool = False,
              seed: int = 1, max_deg: float = 40.0, blend: float = 1.0):
    """Hub + five two-segment arms: 11 links in a branching tree (hub is link 0, the root).

    ``blend``: width of the hub–arm blend and half-width of the elbow blend (arm units; an arm
    is 8 long, its elbow at 4). The default 1 blends narrowly; 2.5 blends most of each inner
    segment with its neighbours, like a character with very smooth skin weights."""
    v, f, part, dist, arm_dirs = _branching_mesh(disconnected)
    N = len(v)
    L = 11
    # per-vertex arm membership and distance along the arm
    vpart = np.zeros(N, dtype=int)
    vdist = np.zeros(N)
    for i in range(3):
        sel = part > 0
        vpart[f[sel, i]] = part[sel]
    for arm, (a, s) in enumerate(arm_dirs):
        m = vpart == arm + 1
        vdist[m] = v[m, a] * s - 3
    w = np.zeros((N, L))
    w[vpart == 0, 0] = 1
    joints = np.zeros((L, 3))
    joints[0] = np.nan
    parents = np.full(L, -1)
    for arm, (a, s) in enumerate(arm_dirs):
        m = vpart == arm + 1
        # a separate piece moves rigidly with its own link: no blend with the hub
        r1 = np.ones(m.sum()) if disconnected else _ramp(vdist[m], 0.0, blend)
        r2 = _ramp(vdist[m], 4.0 - blend, 4.0 + blend)
        w[m, 0] = 1 - r1
        w[m, 1 + 2 * arm] = r1 - r2
        w[m, 2 + 2 * arm] = r2
        n = np.zeros(3)
        n[a] = s
        joints[1 + 2 * arm] = 3 * n
        joints[2 + 2 * arm] = 7 * n
        parents[1 + 2 * arm] = 0
        parents[2 + 2 * arm] = 1 + 2 * arm
    rng = np.random.default_rng(seed)
    normals = _vertex_normals(v, f)
    fields = []
    for p in range(n_fields):
        R = np.zeros((L, 3, 3))
        t = np.zeros((L, 3))
        R[0] = Rotation.from_rotvec(rng.normal(size=3) * np.radians(15)).as_matrix()
        t[0] = rng.uniform(-2, 2, 3)
        for arm in range(5):
            for seg in (1, 2):
                l = 2 * arm + seg
                q = parents[l]
                Rj = Rotation.from_rotvec(_random_axis(rng) * np.radians(rng.uniform(10, max_deg))).as_matrix()
                c = joints[l]
                R[l] = R[q] @ Rj
                t[l] = R[q] @ (c - Rj @ c) + t[q]
        u = _skin(v, w, R, t) - v
        if bulges:
            for _ in range(2):
                centre = v[rng.integers(N)]
                g = np.exp(-np.sum((v - centre) ** 2, axis=1) / (2 * 0.8 ** 2))
                u += 0.15 * g[:, None] * normals
        if noise:
            scale = np.sqrt(np.mean(np.sum(u * u, axis=1)))
            u += rng.normal(size=u.shape) * noise * scale / np.sqrt(3)
        fields.append(u)
    fl, _ = _true_labels(f, w)
    truth = dict(face_labels=fl, joints=joints, parents=parents, weights=w)
    return Scan(v, f, displacements=np.array(fields)), truth


def _random_axis(rng):
    a = rng.normal(size=3)
    return a / np.linalg.norm(a)


@_checked
def greens_rod(loads_x=(8, 18, 30, 35), stiffness=(200.0, 150.0, 100.0), dent=0.2, probe_load: float = 1.0,
               blend: float = 1.0):
    """A Green's-matrix scan of the rod fixed at x = 0: springs at the joints plus local dents."""
    x0, faces = _tube(36)
    joints = np.array([[0.0, 0, 0], [12.0, 0, 0], [24.0, 0, 0]])
    x = x0[:, 0]
    r = [_ramp(x, 0.0, blend), _ramp(x, 12 - blend, 12 + blend), _ramp(x, 24 - blend, 24 + blend)]
    w = np.stack([1 - r[0], r[0] - r[1], r[1] - r[2], r[2]], axis=1)
    load_vertices = np.array([int(lx) * 8 + 5 for lx in loads_x])  # top middle (y=0, z=1) of ring
    N = len(x0)
    G = np.zeros((3 * N, 3 * len(load_vertices)))
    for k, lv in enumerate(load_vertices):
        xk = x0[lv]
        for d in range(3):
            F = np.zeros(3)
            F[d] = probe_load
            rots = []
            for j, c in enumerate(joints):
                if c[0] < xk[0]:
                    rots.append(Rotation.from_rotvec(np.cross(xk - c, F) / stiffness[j]).as_matrix())
                else:
                    rots.append(np.eye(3))
            R, t = _chain_fk(joints, rots)
            Rall = np.concatenate([np.eye(3)[None], R])
            tall = np.concatenate([np.zeros((1, 3)), t])
            u = _skin(x0, w, Rall, tall) - x0
            g = np.exp(-np.sum((x0 - xk) ** 2, axis=1) / 2.0)
            u += dent * g[:, None] * F[None, :]
            G[:, 3 * k + d] = (u / probe_load).reshape(-1)
    truth = dict(face_labels=np.maximum(_true_labels(faces, w)[0] - 1, 0), joints=joints,
                 parents=np.array([-1, 0, 1]))
    scan = Scan(x0, faces, greens=G, load_vertices=load_vertices, support_vertices=np.arange(8),
                probe_load=probe_load)
    return scan, truth


@_checked
def elastic(n_fields: int = 12, seed: int = 0, bend_deg: float = 0.0, bulge: float = 0.3, length: int = 36,
            move_deg: float = 30.0):
    """A tube wobbling like jelly: per field a smooth bend (bend angles cubic along the length, up to
    ``bend_deg`` at the end, in two planes; the centreline integrated from the bent tangent, so the
    axis does not stretch) and a smooth radial wobble of the cross-sections,
    r(s, θ) = 1 + Σ_{j ≤ 4, k ≤ 2} a_jk sin(π j s/ℓ) · (cos kθ or sin kθ), every a_jk random up to ``bulge``/4;
    then the whole tube moves rigidly (a rotation up to ``move_deg`` about its middle and a translation).
    No part moves rigidly on its own and there is no joint: truth has ``articulated=False``."""
    x0, faces = _tube(length)
    rng = np.random.default_rng(seed)
    s = np.clip(x0[:, 0], 0.0, length) / length                       # (N,) position along the tube, 0..1
    theta = np.arctan2(x0[:, 2], x0[:, 1])
    modes = np.stack([np.sin(np.pi * j * s) * ang for j in range(1, 5)
                      for ang in (np.ones_like(s), np.cos(theta), np.sin(theta), np.cos(2 * theta), np.sin(2 * theta))],
                     axis=1)                                           # (N, 20)
    fine = np.linspace(0.0, 1.0, 64 * length + 1)
    fields = []
    for _ in range(n_fields):
        c = rng.uniform(-1, 1, (2, 3))                                 # bend angle(s) = Σ c_i s^(i+1), 2 planes
        c *= np.radians(bend_deg) / max(np.abs(c.sum(axis=1)).max(), 1e-9) * rng.uniform(0.3, 1.0)

        def rotvec(u):
            pw = np.stack([u, u ** 2, u ** 3], axis=-1)
            return np.stack([np.zeros_like(u), pw @ c[0], pw @ c[1]], axis=-1)
        tangent = Rotation.from_rotvec(rotvec(fine)).apply([1.0, 0.0, 0.0])
        steps = 0.5 * (tangent[1:] + tangent[:-1]) * (length / (len(fine) - 1))
        line = np.concatenate([np.zeros((1, 3)), np.cumsum(steps, axis=0)])
        centre = np.stack([np.interp(s, fine, line[:, k]) for k in range(3)], axis=1)
        radius = 1.0 + modes @ rng.uniform(-0.25 * bulge, 0.25 * bulge, modes.shape[1])
        off = x0 * [0.0, 1.0, 1.0] * radius[:, None]
        x = centre + Rotation.from_rotvec(rotvec(s)).apply(off)
        mid = np.array([0.5 * length, 0.0, 0.0])
        whole = Rotation.from_rotvec(_random_axis(rng) * np.radians(rng.uniform(0, move_deg)))
        fields.append(whole.apply(x - mid) + mid + rng.uniform(-0.1, 0.1, 3) * length - x0)
    truth = dict(articulated=False)
    return Scan(x0, faces, displacements=np.array(fields)), truth


def make_with_truth(name: str, **kw):
    """(Scan, truth dict) for a sample name in :data:`NAMES`."""
    try:
        fn = {"rod": rod, "branching": branching, "greens_rod": greens_rod, "elastic": elastic}[name]
    except KeyError:
        raise ValueError(f"unknown sample {name!r}; choose from {', '.join(NAMES)}") from None
    return fn(**kw)


def make(name: str, **kw) -> Scan:
    """A built-in sample scan (see module docstring)."""
    return make_with_truth(name, **kw)[0]


def random_poses(vertices, weights, joints, parents, n_fields: int = 20, max_deg: float = 45.0,
                 seed: int = 0, root_motion: bool = True, motions: bool = False, min_deg: float = 0.0):
    """Displacements (P, N, 3) of random poses of a rigged mesh by linear blend skinning.

    Every bone rotates about its rest head by a random axis and an angle drawn uniformly between
    ``min_deg`` and ``max_deg``;
    roots also translate when ``root_motion``. Used to make fresh tracked scans with a known
    skeleton from the shared rigged models. With ``motions`` the bones' world motions
    ``R`` (P, J, 3, 3), ``t`` (P, J, 3) are returned too (x ↦ R x + t per bone and pose).
    """
    rng = np.random.default_rng(seed)
    J = len(parents)
    order = []
    seen = set()
    while len(order) < J:
        for j in range(J):
            if j not in seen and (parents[j] < 0 or parents[j] in seen):
                order.append(j)
                seen.add(j)
    diag = float(np.linalg.norm(np.ptp(vertices, axis=0)))
    out = np.zeros((n_fields,) + vertices.shape)
    Rs = np.zeros((n_fields, J, 3, 3))
    ts = np.zeros((n_fields, J, 3))
    for p in range(n_fields):
        R, t = Rs[p], ts[p]
        for j in order:
            Rj = Rotation.from_rotvec(_random_axis(rng) * np.radians(rng.uniform(min_deg, max_deg))).as_matrix()
            c = joints[j]
            q = parents[j]
            if q < 0:
                R[j] = Rj
                t[j] = c - Rj @ c + (rng.uniform(-0.1, 0.1, 3) * diag if root_motion else 0.0)
            else:
                R[j] = R[q] @ Rj
                t[j] = R[q] @ (c - Rj @ c) + t[q]
        out[p] = _skin(vertices, weights, R, t) - vertices
    return (out, Rs, ts) if motions else out
