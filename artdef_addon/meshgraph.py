"""The mesh's edge graph and which links may weigh on each vertex (the refined skin's candidates).

Graphs and geodesic reaches are remembered across a fit's many decompositions (:class:`_Remembered`).
"""
from __future__ import annotations


import numpy as np
from scipy.sparse import coo_matrix


def candidate_links(vertices: np.ndarray, faces: np.ndarray, incidence: np.ndarray, rings: int = 3,
                    radius: float | None = None) -> np.ndarray:
    """Which links may weigh on each vertex: (N, L) bool from the vertex–link ``incidence``.

    The links within ``rings`` edge rings, and with ``radius`` (a fraction of the bounding-box
    diagonal) also every link with a vertex within that geodesic distance along the mesh edges
    (Dijkstra from each link's vertices; links on another connected piece are never candidates),
    so a coarse mesh whose edges are longer than the radius still reaches its neighbours. A
    vertex's own links are always candidates. A vertex that reaches no link (in no triangle, which
    the scan format allows: docs/method_notes.md §2 segments triangles, so nothing ties it to a link) has every
    link as candidate: the data then choose its skin, by the single-link fit and the simplex solve,
    instead of a 0/0 weight row.
    """
    N, L = incidence.shape
    from .metric import digest
    mesh = digest(vertices, faces)
    A, E = _mesh_graph(mesh, vertices, faces)
    cand = incidence.astype(np.float64)
    for _ in range(max(rings - 1, 0)):
        cand = np.minimum(cand + A @ cand, 1.0)
    cand = cand > 0
    if radius is not None:
        from scipy.sparse.csgraph import dijkstra
        limit = radius * float(np.linalg.norm(np.ptp(vertices, axis=0)))
        for l in range(L):
            src = np.flatnonzero(incidence[:, l])
            if src.size == 0 or limit <= 0:
                continue
            key = (mesh, np.float64(limit).tobytes(), digest(src))
            reach = _REACH.get(key)
            if reach is None:
                reach = _REACH.put(key, np.flatnonzero(np.isfinite(
                    dijkstra(E, directed=False, indices=src, min_only=True, limit=limit))))
            cand[reach, l] = True
    cand[~cand.any(axis=1)] = True
    return cand


def _mesh_graph(key: bytes, vertices: np.ndarray, faces: np.ndarray):
    """The mesh's edge graph, remembered per mesh ``key`` (a fit asks for it in every decomposition):
    ``A`` (N, N) CSR, 1 where two vertices share an edge, and ``E`` the same edges weighted by their
    length (for :func:`scipy.sparse.csgraph.dijkstra`)."""
    hit = _GRAPHS.get(key)
    if hit is not None:
        return hit
    N = vertices.shape[0]
    f = faces
    a = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    A = coo_matrix((np.ones(len(a)), (a[:, 0], a[:, 1])), shape=(N, N)).tocsr()
    A = ((A + A.T) > 0).astype(np.float64)
    length = np.linalg.norm(vertices[a[:, 0]] - vertices[a[:, 1]], axis=1)
    E = coo_matrix((length + 1e-300, (a[:, 0], a[:, 1])), shape=(N, N)).tocsr()
    E = E.maximum(E.T)
    return _GRAPHS.put(key, (A, E))


class _Remembered:
    """Values by key, the oldest forgotten beyond ``size``."""

    def __init__(self, size: int):
        self.size = size
        self._d: dict = {}

    def get(self, key):
        return self._d.get(key)

    def put(self, key, value):
        self._d[key] = value
        while len(self._d) > self.size:
            self._d.pop(next(iter(self._d)))
        return value


#: meshes' edge graphs remembered by :func:`_mesh_graph` (a few: one scan's fits use one)
_GRAPHS = _Remembered(4)
#: links' geodesic reach remembered by :func:`candidate_links` (a fit's decompositions ask for the
#: same links again and again: a swap or a relabelling changes a few links' vertices at a time)
REACH_CACHE = 512
_REACH = _Remembered(REACH_CACHE)


def link_incidence(n_vertices: int, faces: np.ndarray, labels: np.ndarray, L: int, dense: bool = False):
    """Sparse (N, L) 0/1 matrix (CSC): vertex v touches a triangle of link l. Faces labelled −1
    count for no link. With ``dense`` an (N, L) bool array instead."""
    ok = labels >= 0
    rows = faces[ok].reshape(-1)
    if dense:
        inc = np.zeros((n_vertices, L), dtype=bool)
        inc[rows, np.repeat(labels[ok], 3)] = True
        return inc
    inc = coo_matrix((np.ones(rows.size), (rows, np.repeat(labels[ok], 3))), shape=(n_vertices, L)).tocsc()
    inc.sum_duplicates()
    inc.data[:] = 1.0
    return inc


def vertex_candidates(vertices, faces, labels, L, rings, radius, ground):
    """(N, L) candidate links of every vertex (see :func:`candidate_links`); L counts the ground."""
    N = vertices.shape[0]
    inc = link_incidence(N, faces, labels, L, dense=True)
    if ground is not None:
        inc[:, L - 1] = ground
    return candidate_links(vertices, faces, inc, rings=rings, radius=radius)
