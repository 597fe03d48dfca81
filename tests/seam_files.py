"""Meshes as files store them, made from welded ones: copies of vertices at seams (the tests of
seams.py and benchmarks/seams.py)."""
import numpy as np

from artdef_addon.scan import Scan


def split(vertices, faces, fields, islands):
    """The mesh as a file stores it: every island (a label per triangle) gets its own copies of its
    vertices, appended after the originals (a UV island, a hard edge, a soup when every triangle is
    one). ``fields`` (P, N, 3) tracked or None. Returns ``(vertices, faces, fields, source)``,
    ``source`` the original vertex of every stored one."""
    T = faces.shape[0]
    corner_island = np.repeat(islands, 3)
    corner_vertex = faces.ravel()
    # a vertex keeps its own index in the first island that uses it, a copy in every other one
    pair, inverse = np.unique(np.stack([corner_vertex, corner_island], 1), axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    first_island = np.full(vertices.shape[0], -1)
    first_island[pair[::-1, 0]] = pair[::-1, 1]
    is_copy = pair[:, 1] != first_island[pair[:, 0]]
    new_index = np.where(is_copy, vertices.shape[0] + np.cumsum(is_copy) - 1, pair[:, 0])
    source = np.concatenate([np.arange(vertices.shape[0]), pair[is_copy, 0]])
    faces2 = new_index[inverse].reshape(T, 3)
    return vertices[source], faces2, None if fields is None else fields[:, source], source


def welded(vertices, fields, source, stored_faces):
    """The stored mesh welded by hand: its distinct points in the order of their first stored copy
    (what merging the copies of a file keeps)."""
    _, first = np.unique(source, return_index=True)
    order = source[np.sort(first)]
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    return Scan(vertices[order], rank[source][stored_faces], displacements=fields[:, order]), rank[source]
