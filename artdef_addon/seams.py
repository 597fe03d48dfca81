"""Seams closed for the fit, kept in the output: a file's copies of one surface point.

Animated files store a vertex once per UV island and hard edge (glTF and FBX split a position wherever
a normal or texture coordinate changes; a triangle soup stores every corner on its own). To the fit a
split vertex is two vertices: the triangle adjacency, the patches of the reduced method, the seams
between links (§5.2), the joints' seam references (§6) and the skin's one-rings (§7) would all see a
cut where the surface is whole. So the fit runs on the *distinct* points, and everything it writes per
vertex is taken back onto the file's own vertices, every copy of a point getting the same values
(the seam cannot open when the rig moves).

Two stored vertices are copies when their rest positions and their displacements in every field agree
to :data:`WELD_TOLERANCE` of the mesh's bounding-box diagonal; chains of such pairs are one point.
Points that touch at rest but move apart in some field (lips, fingers, a cut that opens) stay apart.

:func:`weld` finds the copies (a k-d tree on the rest position and a summary of the motion, then every
candidate pair checked on each field; no loop over vertices), :func:`weld_scan` makes the scan of the
distinct points, :func:`expand_result` takes a fit of it back onto the stored vertices. The public
:func:`artdef_addon.fit` and :func:`artdef_addon.segment` apply both, so every input (scan files,
animated files, sequences, shape keys) gets them.
"""
from __future__ import annotations

import dataclasses

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .scan import Scan, validate_scan

#: two vertices are copies of one point when rest position and every field's displacement agree to
#: this fraction of the bounding-box diagonal. Files store copies bit-identical or within float32
#: rounding (about 1e-7 of a coordinate); the finest meshes fitted here have edges of 1e-3 of the
#: diagonal (1M triangles), so 1e-5 joins the former and never the latter
WELD_TOLERANCE = 1e-5


@dataclasses.dataclass
class Weld:
    """The stored vertices of a mesh as distinct points.

    ``index (N,)``: the distinct point of every stored vertex (0..D−1, numbered in the order of their
    first copy); ``first (D,)``: the first stored vertex of every distinct point (``index[first] ==
    arange(D)``)."""
    index: np.ndarray
    first: np.ndarray

    @property
    def n_stored(self) -> int:
        return int(self.index.shape[0])

    @property
    def n_distinct(self) -> int:
        return int(self.first.shape[0])

    @property
    def copies(self) -> int:
        """Stored vertices beyond the first of their point (N − D)."""
        return self.n_stored - self.n_distinct

    def note(self) -> str:
        """What the fit says of it: "796 vertices, 494 distinct (302 copies at seams) …"."""
        return (f"{self.n_stored:,} vertices, {self.n_distinct:,} distinct ({self.copies:,} copies at seams): "
                f"the fit ran on the distinct points; weights, residual shapes and the rig are on all "
                f"{self.n_stored:,}, every copy of a point with the same values")


def identity(n: int) -> Weld:
    """The weld of a mesh without copies."""
    ids = np.arange(n, dtype=np.int64)
    return Weld(ids, ids)


def _field(scan: Scan, c: int) -> np.ndarray:
    return np.asarray(scan.field(c), dtype=np.float64)


def _mix(a: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(N,) ``a (N, 3)`` · ``w (3,)``."""
    return np.asarray(a, dtype=np.float64) @ w


def weld(scan: Scan, tolerance: float = WELD_TOLERANCE) -> Weld:
    """The copies of ``scan``'s vertices (a checked :class:`Scan`; N vertices, P fields): vertices whose
    rest positions and displacements in every field differ by at most ``tolerance`` × the bounding-box
    diagonal, joined transitively.

    Copies stored bit for bit (what exporters write) are gathered by one number a vertex, a fixed
    random combination of its rest position and of its displacement in every field: each group is a star of candidate pairs (not all pairs of a
    point's many copies). Copies that differ by rounding are found among the groups by a k-d tree on
    the rest position and checked on the rest position and on every field, so points that touch at
    rest but move apart are never joined."""
    x0 = np.asarray(scan.vertices, dtype=np.float64)
    n = x0.shape[0]
    diag = float(np.linalg.norm(np.ptp(x0, axis=0))) if n else 0.0
    tol = tolerance * diag
    if n < 2 or not tol > 0:
        return identity(n)
    rng = np.random.default_rng(0x5EA3)
    P = scan.n_fields
    # one number a vertex from its rest position and its motion: copies stored bit for bit get the
    # same number, gathered by one sort of N numbers (two equal rows rounded apart by a BLAS kernel
    # would only go to the k-d tree's near pairs below, which join them as well)
    code = _mix(x0, rng.standard_normal(3))
    for c in range(P):
        code += _mix(_field(scan, c), rng.standard_normal(3))
    _, first_of, inverse = np.unique(code, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    star = np.flatnonzero(first_of[inverse] != np.arange(n))
    # copies within the tolerance but not bit for bit: near rest positions among the groups' first
    reps = x0[first_of]
    pairs = cKDTree(reps, balanced_tree=False, compact_nodes=False).query_pairs(
        tol * (1 + 1e-9), output_type="ndarray")
    # a star pair has equal numbers: its rest positions are checked (the fields' share of the number
    # ties only where they agree, but for a chance of about 2^-52); a near pair on every field
    si, sj = star, first_of[inverse[star]]
    d = x0[si] - x0[sj]
    keep = np.einsum("ij,ij->i", d, d) <= tol * tol
    si, sj = si[keep], sj[keep]
    ni, nj = first_of[pairs[:, 0]], first_of[pairs[:, 1]]
    d = x0[ni] - x0[nj]
    keep = np.einsum("ij,ij->i", d, d) <= tol * tol
    for c in range(P):
        f = _field(scan, c)
        d = f[ni] - f[nj]
        keep &= np.einsum("ij,ij->i", d, d) <= tol * tol
    i = np.concatenate([si, ni[keep]]).astype(np.int64)
    j = np.concatenate([sj, nj[keep]]).astype(np.int64)
    if i.size == 0:
        return identity(n)
    graph = coo_matrix((np.ones(i.size, dtype=np.int8), (i, j)), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    # points numbered by their first copy: the first occurrence of each component, in stored order
    _, lowest = np.unique(comp, return_index=True)
    order = np.argsort(lowest, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    return Weld(rank[comp].astype(np.int64), lowest[order].astype(np.int64))


def weld_scan(scan: Scan, tolerance: float = WELD_TOLERANCE) -> tuple[Scan, Weld]:
    """``(scan of the distinct points, weld)`` of a checked ``scan``; ``scan`` itself when no vertex
    has a copy. The distinct scan keeps every triangle in its order, its corners renumbered (a
    triangle two of whose corners are copies had zero area already and stays degenerate: the fit
    gives it its neighbours' link), the fields of each point's first copy, load and support vertices
    renumbered. Kept on ``scan`` while it holds the same checked arrays, so Preview Links, the fit
    and the panel's checks weld it once."""
    memo = scan._welded
    if memo is not None and memo[0] is scan._checked and memo[1] == tolerance:
        return memo[2], memo[3]
    w = weld(scan, tolerance)
    if w.copies == 0:
        out = scan
    else:
        first, index = w.first, w.index
        greens = disp = None
        if scan.greens is not None:
            g = np.asarray(scan.greens)
            greens = g.reshape(scan.n_vertices, 3, -1)[first].reshape(3 * w.n_distinct, -1)
        else:
            disp = np.asarray(scan.displacements)[:, first]
        lv = None if scan.load_vertices is None else index[np.asarray(scan.load_vertices)]
        sv = None if scan.support_vertices is None else np.unique(index[np.asarray(scan.support_vertices)])
        out = validate_scan(Scan(np.asarray(scan.vertices)[first], index[np.asarray(scan.faces)], greens, disp,
                                 lv, sv, scan.probe_load))
    if scan._checked is not None:
        scan._welded = (scan._checked, tolerance, out, w)
    return out, w


def expand_result(result, w: Weld, stored: Scan):
    """A fit of the distinct points taken back onto the stored vertices: a copy of ``result`` whose
    per-vertex arrays — ``weights (N, L)``, ``residual (P, N, 3)``, those of its pseudo-articulated
    models — are indexed by the stored vertices (every copy the values of its point), its
    ``load_vertices`` the stored scan's and the weld's note first among its notes. Triangles, links, joints and motions need nothing: the distinct scan keeps every triangle."""
    if w.copies == 0:
        return result
    index = w.index

    def onto_stored(r, note: bool):
        out = dataclasses.replace(r, weights=r.weights[index], residual=r.residual[:, index])
        if r.load_vertices is not None and stored.load_vertices is not None:
            welded_lv = index[np.asarray(stored.load_vertices)]
            order = np.argsort(welded_lv, kind="stable")
            at = order[np.searchsorted(welded_lv[order], np.asarray(r.load_vertices))]
            out.load_vertices = np.asarray(stored.load_vertices)[at]
        if note:
            out.notes = [w.note()] + list(r.notes)
        return out

    res = onto_stored(result, True)
    if result.pseudo:
        res.pseudo = [onto_stored(s, False) for s in result.pseudo]
    return res
