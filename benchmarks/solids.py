"""Tetrahedral solids with soft joints, their linear Green's scans and a nonlinear truth.

The solids (``finger``, ``T``, ``fork``) are voxel shapes of stiff links joined by layers of soft
material and clamped at their base; each cube of the voxel grid is cut into the six Kuhn
tetrahedra (the same cut in every cube, so the mesh is conforming). The scan a fit sees is the
solid's boundary surface: its vertices, its triangles, and the Green's matrix G of linear
elasticity at the load vertices (paper §3: column 3k+d is the surface displacement under a unit
load along axis d at load vertex k, the supports clamped).

The truth for large loads is total-Lagrangian compressible neo-Hookean elasticity of the same
mesh, P1 tetrahedra, dead point loads at the load vertices, Newton's method with load stepping:

    Ψ(F) = μ/2 (tr FᵀF − 3) − μ ln J + λ/2 (ln J)²,   P = μ (F − F⁻ᵀ) + λ ln J F⁻ᵀ.

Its tangent at F = I is isotropic linear elasticity with the same Lamé constants, so its
stiffness at zero load is the stiffness that made G (:func:`linear_stiffness` assembles that
one independently, from the classical formula). Everything is vectorised over the tetrahedra.
Used by the tests and benchmarks only (the add-on itself never builds a solid).
"""
from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from artdef_addon.scan import Scan

NAMES = ("finger", "T", "fork")
#: voxel edge length (model units)
CELL = 0.5
#: Kuhn's six tetrahedra of a unit cube: corner offsets (bits x, y, z) along each axis permutation
_KUHN = np.array([[0, 1 << a, (1 << a) | (1 << b), 7] for a, b, _ in itertools.permutations(range(3))])


@dataclasses.dataclass
class Solid:
    """A clamped tetrahedral solid. ``nodes`` (n, 3); ``tets`` (T, 4); ``mu``, ``lam`` (T,) Lamé
    constants; ``fixed`` clamped node ids; ``surface`` node ids of the boundary (the scan's
    vertices, in order); ``faces`` (F, 3) boundary triangles in scan-vertex numbering, outward;
    ``loads`` (M,) node ids loaded; ``link`` (n,) the link of each node (−1 soft material or
    ground), ``joints`` (L, 3) the centre of each link's joint layer, ``parents`` (L,)."""
    name: str
    nodes: np.ndarray
    tets: np.ndarray
    mu: np.ndarray
    lam: np.ndarray
    fixed: np.ndarray
    surface: np.ndarray
    faces: np.ndarray
    loads: np.ndarray
    link: np.ndarray
    joints: np.ndarray
    parents: np.ndarray

    @property
    def n_dof(self) -> int:
        return 3 * len(self.nodes)


# --------------------------------------------------------------------------------------------
# geometry
# --------------------------------------------------------------------------------------------

def _voxel_solid(name, occ, region, origin, joints, parents, load_cells, stiff, soft, nu):
    """Tetrahedral solid of the cells ``occ`` (nx, ny, nz bool); ``region`` (same shape) the link
    of a cell (−1: soft); nodes on the plane of the lowest cell layer along y are clamped."""
    nx, ny, nz = occ.shape
    cells = np.argwhere(occ)
    corner = np.array([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)])
    grid = cells[:, None, :] + corner[None]                                    # (C, 8, 3)
    key = (grid[..., 0] * (ny + 1) + grid[..., 1]) * (nz + 1) + grid[..., 2]
    uniq, inv = np.unique(key.ravel(), return_inverse=True)
    inv = inv.reshape(-1, 8)
    ijk = np.stack([uniq // ((ny + 1) * (nz + 1)), (uniq // (nz + 1)) % (ny + 1), uniq % (nz + 1)], 1)
    nodes = origin + CELL * ijk.astype(float)
    tets = inv[:, _KUHN].reshape(-1, 4)
    creg = np.repeat(region[cells[:, 0], cells[:, 1], cells[:, 2]], 6)
    E = np.where(creg >= 0, stiff, soft)
    mu = E / (2 * (1 + nu))
    lam = E * nu / ((1 + nu) * (1 - 2 * nu))
    # orient every tetrahedron positively
    D = nodes[tets[:, 1:]] - nodes[tets[:, :1]]
    neg = np.linalg.det(D) < 0
    tets[neg] = tets[neg][:, [0, 2, 1, 3]]
    # boundary: triangles of one tetrahedron only, outward (away from the tet's fourth node)
    tri = np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 3, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 1]]])
    s = np.sort(tri, axis=1)
    _, first, count = np.unique(s, axis=0, return_index=True, return_counts=True)
    btri = tri[first[count == 1]]
    surface, faces = np.unique(btri, return_inverse=True)
    faces = faces.reshape(-1, 3)
    fixed = np.flatnonzero(ijk[:, 1] == 0)
    # node links: the link of every cell touching it when they agree, else −1
    nl = np.full((len(nodes), 2), [np.iinfo(np.int64).max, np.iinfo(np.int64).min])
    creg8 = np.repeat(region[cells[:, 0], cells[:, 1], cells[:, 2]], 8)
    np.minimum.at(nl[:, 0], inv.ravel(), creg8)
    np.maximum.at(nl[:, 1], inv.ravel(), creg8)
    link = np.where(nl[:, 0] == nl[:, 1], nl[:, 0], -1)
    link[fixed] = -1
    loads = np.array([int(np.flatnonzero((ijk == c).all(axis=1))[0]) for c in load_cells])
    return Solid(name, nodes, tets, mu, lam, fixed, surface, faces, loads, link, np.asarray(joints, float),
                 np.asarray(parents))


def _box(occ, region, lo, hi, link, origin):
    """Fill cells of [lo, hi) (model units) with ``link``."""
    a = np.round((np.asarray(lo, float) - origin) / CELL).astype(int)
    b = np.round((np.asarray(hi, float) - origin) / CELL).astype(int)
    occ[a[0]:b[0], a[1]:b[1], a[2]:b[2]] = True
    region[a[0]:b[0], a[1]:b[1], a[2]:b[2]] = link


def make_solid(name: str, seed: int = 0) -> Solid:
    """The solid ``name`` of :data:`NAMES` with link lengths, stiffnesses and load vertices drawn
    from ``seed`` (clamped at y = 0, links along +y, 2 × 2 cross-sections, 1-thick soft joints).

    * ``finger``: a chain of three links (support joint, two knuckles); loads on the links' tops.
    * ``T``: a stem and two arms off its top (a branching tree); loads near the arms' ends and on the stem.
    * ``fork``: a stem with a palm and two prongs on soft bases; loads on the prongs and the palm."""
    rng = np.random.default_rng(seed)
    nu = float(rng.uniform(0.25, 0.35))
    stiff = 1000.0
    soft = stiff / float(rng.uniform(60.0, 150.0))
    q = lambda lo, hi: CELL * int(rng.integers(int(lo / CELL), int(hi / CELL) + 1))   # noqa: E731
    if name == "finger":
        lens = [q(3.0, 4.5), q(2.5, 3.5), q(2.0, 3.0)]
        total = 1.0 + sum(lens) + 2.0
        origin = np.array([-1.0, 0.0, -1.0])
        shape = (4, int(round(total / CELL)), 4)
        occ = np.zeros(shape, bool)
        reg = np.full(shape, -1)
        y = 0.0
        joints, boxes = [], []
        for l, ln in enumerate(lens):
            joints.append([0.0, y + 0.5, 0.0])
            _box(occ, reg, (-1, y, -1), (1, y + 1, 1), -1, origin)
            _box(occ, reg, (-1, y + 1, -1), (1, y + 1 + ln, 1), l, origin)
            boxes.append((y + 1, y + 1 + ln))
            y += 1 + ln
        occ = occ[:, :int(round(y / CELL))]
        reg = reg[:, :int(round(y / CELL))]
        # load cells (grid corners): the top (+z) face, middle of x, near each link's far end
        loads = [(2, int(round((b - 0.5 - origin[1]) / CELL)), 4) for a, b in boxes]
        loads.append((int(rng.integers(0, 5)), int(round(y / CELL)), int(rng.integers(0, 5))))
        return _voxel_solid(name, occ, reg, origin, joints, [-1, 0, 1], loads, stiff, soft, nu)
    if name == "T":
        stem = q(4.0, 6.0)
        arm_l, arm_r = q(3.0, 4.5), q(3.0, 4.5)
        half = 1.0
        x0, x1 = -half - 1.0 - arm_l, half + 1.0 + arm_r
        origin = np.array([x0, 0.0, -1.0])
        top = 1.0 + stem + 2.0
        shape = (int(round((x1 - x0) / CELL)), int(round(top / CELL)), 4)
        occ = np.zeros(shape, bool)
        reg = np.full(shape, -1)
        _box(occ, reg, (-1, 0, -1), (1, 1, 1), -1, origin)                         # support joint
        _box(occ, reg, (-1, 1, -1), (1, top, 1), 0, origin)                        # stem and its head
        _box(occ, reg, (-half - 1, top - 2, -1), (-half, top, 1), -1, origin)      # left joint
        _box(occ, reg, (x0, top - 2, -1), (-half - 1, top, 1), 1, origin)          # left arm
        _box(occ, reg, (half, top - 2, -1), (half + 1, top, 1), -1, origin)        # right joint
        _box(occ, reg, (half + 1, top - 2, -1), (x1, top, 1), 2, origin)           # right arm
        ix = lambda x: int(round((x - origin[0]) / CELL))                          # noqa: E731
        iy = lambda y: int(round((y - origin[1]) / CELL))                          # noqa: E731
        loads = [(ix(x0 + 0.5), iy(top), 2), (ix(x1 - 0.5), iy(top), 2), (ix(x0 + 1.0), iy(top - 1.0), 4),
                 (ix(1.0), iy(1.0 + stem * float(rng.uniform(0.4, 0.8))), 4)]
        joints = [[0, 0.5, 0], [-half - 0.5, top - 1, 0], [half + 0.5, top - 1, 0]]
        return _voxel_solid(name, occ, reg, origin, joints, [-1, 0, 0], loads, stiff, soft, nu)
    if name == "fork":
        stem = q(3.0, 5.0)
        prong = [q(3.0, 5.0), q(3.0, 5.0)]
        origin = np.array([-3.0, 0.0, -1.0])
        palm = 1.0 + stem
        top = palm + 2.0 + 1.0 + max(prong)
        shape = (12, int(round(top / CELL)), 4)
        occ = np.zeros(shape, bool)
        reg = np.full(shape, -1)
        _box(occ, reg, (-1, 0, -1), (1, 1, 1), -1, origin)
        _box(occ, reg, (-1, 1, -1), (1, palm, 1), 0, origin)
        _box(occ, reg, (-3, palm, -1), (3, palm + 2, 1), 0, origin)
        joints = []
        loads = []
        iy = lambda y: int(round((y - origin[1]) / CELL))                          # noqa: E731
        for p, (xa, xb) in enumerate(((-3, -1), (1, 3))):
            b = palm + 2.0
            _box(occ, reg, (xa, b, -1), (xb, b + 1, 1), -1, origin)
            _box(occ, reg, (xa, b + 1, -1), (xb, b + 1 + prong[p], 1), 1 + p, origin)
            joints.append([0.5 * (xa + xb), b + 0.5, 0])
            loads.append((int(round((0.5 * (xa + xb) - origin[0]) / CELL)), iy(b + 1 + prong[p]), 2))
        loads.append((int(round((-2 - origin[0]) / CELL)), iy(palm + 2.0 + 1.0 + 0.5 * prong[0]), 4))
        loads.append((int(round((1.0 - origin[0]) / CELL)), iy(palm + 1.0), 4))
        occ = occ[:, :iy(top)]
        reg = reg[:, :iy(top)]
        return _voxel_solid(name, occ, reg, origin, [[0, 0.5, 0]] + joints, [-1, 0, 0], loads, stiff, soft, nu)
    raise ValueError(f"unknown solid {name!r}; choose from {', '.join(NAMES)}")


# --------------------------------------------------------------------------------------------
# finite elements
# --------------------------------------------------------------------------------------------

def shape_gradients(solid: Solid):
    """Rest volumes (T,) and shape-function gradients ∇N (T, 4, 3) of the P1 tetrahedra."""
    X = solid.nodes[solid.tets]                                     # (T, 4, 3)
    Dm = np.swapaxes(X[:, 1:] - X[:, :1], 1, 2)                     # columns: edges from node 0
    inv = np.linalg.inv(Dm)                                         # rows: ∇N_1..3
    grad = np.concatenate([-inv.sum(axis=1, keepdims=True), inv], axis=1)
    return np.linalg.det(Dm) / 6.0, grad


def _assemble(solid: Solid, ke):
    """Sparse (3n, 3n) matrix of element blocks ``ke`` (T, 4, 3, 4, 3)."""
    dof = 3 * solid.tets[:, :, None] + np.arange(3)                 # (T, 4, 3)
    rows = np.broadcast_to(dof[:, :, :, None, None], ke.shape).ravel()
    cols = np.broadcast_to(dof[:, None, None, :, :], ke.shape).ravel()
    return sp.csr_matrix((ke.ravel(), (rows, cols)), shape=(solid.n_dof, solid.n_dof))


def linear_stiffness(solid: Solid) -> sp.csr_matrix:
    """K (3n, 3n) of isotropic linear elasticity: K_ab = V (λ ∇N_a ∇N_bᵀ + μ ∇N_b ∇N_aᵀ + μ ∇N_a·∇N_b I)."""
    V, g = shape_gradients(solid)
    lam, mu = solid.lam[:, None, None, None, None], solid.mu[:, None, None, None, None]
    ke = (lam * np.einsum("tai,tbk->taibk", g, g) + mu * np.einsum("tak,tbi->taibk", g, g)
          + mu * np.einsum("taj,tbj->tab", g, g)[:, :, None, :, None] * np.eye(3)[None, None, :, None, :])
    return _assemble(solid, V[:, None, None, None, None] * ke)


def _deformation(solid, u, g):
    """Deformation gradients F (T, 3, 3) of nodal displacements ``u`` (n, 3)."""
    return np.eye(3) + np.einsum("tai,taJ->tiJ", u[solid.tets], g)


def internal_forces(solid: Solid, u, V=None, g=None):
    """Nodal internal forces (n, 3) of the neo-Hookean solid displaced by ``u`` (n, 3)."""
    if g is None:
        V, g = shape_gradients(solid)
    F = _deformation(solid, u, g)
    J = np.linalg.det(F)
    if np.any(J <= 0):
        raise FloatingPointError("a tetrahedron inverted")
    Finv_T = np.swapaxes(np.linalg.inv(F), 1, 2)
    P = solid.mu[:, None, None] * (F - Finv_T) + (solid.lam * np.log(J))[:, None, None] * Finv_T
    fe = V[:, None, None] * np.einsum("tiJ,taJ->tai", P, g)
    out = np.zeros_like(u)
    np.add.at(out, solid.tets, fe)
    return out


def tangent_stiffness(solid: Solid, u, V=None, g=None) -> sp.csr_matrix:
    """The tangent ∂f_int/∂u (3n, 3n) at ``u``:
    A_iJkL = μ δ_ik δ_JL + (μ − λ ln J) F⁻¹_Li F⁻¹_Jk + λ F⁻¹_Ji F⁻¹_Lk."""
    if g is None:
        V, g = shape_gradients(solid)
    F = _deformation(solid, u, g)
    J = np.linalg.det(F)
    Fi = np.linalg.inv(F)                                           # Fi[t, J, i] = F⁻¹_Ji
    mu, lam = solid.mu, solid.lam
    c = mu - lam * np.log(J)
    ga = np.einsum("taJ,tJi->tai", g, Fi)                           # Σ_J ∇N_aJ F⁻¹_Ji
    ke = (mu[:, None, None, None, None] * np.einsum("taJ,tbJ->tab", g, g)[:, :, None, :, None]
          * np.eye(3)[None, None, :, None, :]
          + c[:, None, None, None, None] * np.einsum("tak,tbi->taibk", ga, ga)
          + lam[:, None, None, None, None] * np.einsum("tai,tbk->taibk", ga, ga))
    return _assemble(solid, V[:, None, None, None, None] * ke)


def _free(solid):
    free = np.ones(solid.n_dof, bool)
    free[(3 * solid.fixed[:, None] + np.arange(3)).ravel()] = False
    return np.flatnonzero(free)


def _load_vector(solid, loads):
    f = np.zeros((len(solid.nodes), 3))
    np.add.at(f, solid.loads, np.asarray(loads, float).reshape(-1, 3))
    return f


def linear_solve(solid: Solid, loads) -> np.ndarray:
    """Nodal displacements (n, 3) of linear elasticity under ``loads`` (M, 3) at the load nodes."""
    free = _free(solid)
    K = linear_stiffness(solid)[free][:, free]
    u = np.zeros(solid.n_dof)
    u[free] = spla.spsolve(K.tocsc(), _load_vector(solid, loads).ravel()[free])
    return u.reshape(-1, 3)


def greens_scan(solid: Solid, probe: float = 0.04) -> Scan:
    """The solid's Green's scan: boundary vertices and triangles, G (3N, 3M) of linear elasticity,
    load and support vertices; the probe load is the force whose largest displacement is
    ``probe`` of the solid's size (so scans of different solids deform alike)."""
    free = _free(solid)
    K = linear_stiffness(solid)[free][:, free].tocsc()
    lu = spla.splu(K)
    M = len(solid.loads)
    rhs = np.zeros((solid.n_dof, 3 * M))
    for k, node in enumerate(solid.loads):
        rhs[3 * node + np.arange(3), 3 * k + np.arange(3)] = 1.0
    U = np.zeros((solid.n_dof, 3 * M))
    U[free] = lu.solve(rhs[free])
    rows = (3 * solid.surface[:, None] + np.arange(3)).ravel()
    G = U[rows]
    size = float(np.linalg.norm(np.ptp(solid.nodes, axis=0)))
    reach = np.abs(G).max()
    probe_load = float(probe * size / reach)
    where = {int(v): i for i, v in enumerate(solid.surface)}
    loads = np.array([where[int(v)] for v in solid.loads])
    support = np.array([where[int(v)] for v in solid.fixed if int(v) in where])
    return Scan(solid.nodes[solid.surface].copy(), solid.faces.copy(), greens=G, load_vertices=loads,
                support_vertices=support, probe_load=probe_load)


def nonlinear_solve(solid: Solid, loads, steps: int | None = None, tol: float = 1e-10,
                    max_iter: int = 30) -> np.ndarray:
    """Nodal displacements (n, 3) of the neo-Hookean solid under dead ``loads`` (M, 3): Newton's
    method on f_int(u) = λ f over load steps λ = 1/s … 1 (``steps``: chosen from the linear
    response when None), each step converged to ‖r‖ ≤ ``tol`` ‖f‖ or a Newton update below 1e-10 of the displacement
    (the round-off floor of the stiff links' forces at small loads), halving a step that fails."""
    V, g = shape_gradients(solid)
    free = _free(solid)
    f = _load_vector(solid, loads)
    fn = float(np.linalg.norm(f))
    u = np.zeros_like(f)
    if fn == 0.0:
        return u
    if steps is None:
        lin = linear_solve(solid, loads)
        size = float(np.linalg.norm(np.ptp(solid.nodes, axis=0)))
        steps = int(np.clip(np.ceil(np.abs(lin).max() / (0.05 * size)), 1, 200))
    lam, dlam = 0.0, 1.0 / steps
    while lam < 1.0 - 1e-14:
        target = min(1.0, lam + dlam)
        trial = u.copy()
        ok = False
        try:
            for _ in range(max_iter):
                r = (target * f - internal_forces(solid, trial, V, g)).ravel()[free]
                if np.linalg.norm(r) <= tol * fn:
                    ok = True
                    break
                K = tangent_stiffness(solid, trial, V, g)[free][:, free].tocsc()
                du = np.zeros(solid.n_dof)
                du[free] = spla.spsolve(K, r)
                trial = trial + du.reshape(-1, 3)
                if np.abs(du).max() <= 1e-10 * max(np.abs(trial).max(), 1e-300):
                    ok = True        # round-off floor of the stiff links' forces reached
                    break
        except FloatingPointError:
            ok = False
        if ok:
            u, lam = trial, target
            dlam = min(dlam * 1.5, 1.0 - lam) if lam < 1.0 else dlam
        else:
            dlam *= 0.5
            if dlam < 1e-6:
                raise RuntimeError("Newton's method did not converge at load factor %.4g" % target)
    return u


def surface_truth(solid: Solid, loads, **kw) -> np.ndarray:
    """Displacements (N, 3) of the scan's vertices (the boundary) under dead ``loads`` (M, 3)."""
    return nonlinear_solve(solid, loads, **kw)[solid.surface]
