"""Articulated test scans of a chosen size, with known links, joints and tree.

The built-in branching object (``samples.branching``: a hub box with five two-segment square
arms, 11 links, ~1.07k triangles) is refined by splitting every edge into ``n`` equal parts
(each triangle becomes n² triangles, shared edge points are shared vertices, so the mesh stays
one connected surface). Positions and the true skin weights of the new vertices are the
barycentric interpolation of the coarse ones: the coarse weights are piecewise linear along
each arm with kinks on coarse rings, so the refined mesh carries exactly the same blends.
Poses are linear blend skinning of random rotations about the true joints
(``samples.random_poses``), so the scan is articulated with seams blended over 1–2 units.

``branching_scan(target_triangles, n_fields)`` picks ``n`` so that 1072·n² is nearest the
target: 1k → n=1 (1 072), 5k → 2 (4 288), 20k → 4 (17 152), 100k → 10 (107 200),
1M → 31 (1 030 192).
"""
from __future__ import annotations

import os
import sys

import numpy as np
import scipy.sparse as sp

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from artdef_addon import samples  # noqa: E402
from artdef_addon.scan import Scan, validate_scan  # noqa: E402

BASE_TRIANGLES = 1072  # triangles of samples.branching's mesh


def subdivide(vertices: np.ndarray, faces: np.ndarray, n: int):
    """Split every edge into ``n`` parts: returns (S, faces_new) with ``S`` a sparse (N', N)
    interpolation matrix (new vertex = S @ old vertex attributes) and the refined faces (n²·T, 3),
    oriented like their parent triangle."""
    N = len(vertices)
    T = len(faces)
    if n <= 1:
        return sp.identity(N, format="csr"), faces.copy()
    # unique undirected edges, stored low→high
    sides = np.stack([faces[:, [1, 2]], faces[:, [2, 0]], faces[:, [0, 1]]], axis=1)  # side k opposite vertex k
    lo = np.minimum(sides[..., 0], sides[..., 1])
    hi = np.maximum(sides[..., 0], sides[..., 1])
    key = lo.astype(np.int64) * N + hi
    uniq, edge_id = np.unique(key.reshape(-1), return_inverse=True)
    edge_id = edge_id.reshape(T, 3)
    E = len(uniq)
    e_lo = uniq // N
    e_hi = uniq % N
    inner = (n - 1) * (n - 2) // 2
    n_new = N + E * (n - 1) + T * inner
    # interpolation rows: originals, edge points, interior points
    rows, cols, vals = [np.arange(N)], [np.arange(N)], [np.ones(N)]
    k = np.arange(1, n)
    er = N + np.arange(E)[:, None] * (n - 1) + (k - 1)[None, :]          # (E, n-1)
    rows += [er.ravel(), er.ravel()]
    cols += [np.repeat(e_lo, n - 1), np.repeat(e_hi, n - 1)]
    vals += [np.tile(1 - k / n, E), np.tile(k / n, E)]
    # lattice point (i, j) of a triangle (v0, v1, v2): barycentric (n-i-j, i, j)/n
    ids = {}
    local = 0
    tri = np.arange(T)
    for i in range(n + 1):
        for j in range(n + 1 - i):
            a, b, c = n - i - j, i, j
            zeros = (a == 0) + (b == 0) + (c == 0)
            if zeros == 2:
                v = 0 if a == n else (1 if b == n else 2)
                ids[i, j] = faces[:, v]
            elif zeros == 1:
                side = 0 if a == 0 else (1 if b == 0 else 2)          # the zero weight is opposite this vertex
                q = [2, 0, 1][side]                                   # side (v1,v2), (v2,v0), (v0,v1)
                wq = (a, b, c)[q]                                    # weight of the side's second vertex
                step = np.where(faces[:, q] == e_hi[edge_id[:, side]], wq, n - wq)  # steps from the low end
                ids[i, j] = N + edge_id[:, side] * (n - 1) + (step - 1)
            else:
                gid = N + E * (n - 1) + tri * inner + local
                local += 1
                ids[i, j] = gid
                rows += [gid, gid, gid]
                cols += [faces[:, 0], faces[:, 1], faces[:, 2]]
                vals += [np.full(T, a / n), np.full(T, b / n), np.full(T, c / n)]
    S = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n_new, N))
    out = []
    for i in range(n):
        for j in range(n - i):
            out.append(np.stack([ids[i, j], ids[i + 1, j], ids[i, j + 1]], axis=1))
            if i + j <= n - 2:
                out.append(np.stack([ids[i + 1, j], ids[i + 1, j + 1], ids[i, j + 1]], axis=1))
    return S, np.concatenate(out).astype(np.int64)


def split_for(target_triangles: int) -> int:
    """The edge split ``n`` whose refined branching object is nearest ``target_triangles``."""
    n = max(1, int(round(np.sqrt(target_triangles / BASE_TRIANGLES))))
    return n


def branching_scan(target_triangles: int = 1000, n_fields: int = 10, seed: int = 0, max_deg: float = 40.0,
                   n: int | None = None):
    """(Scan, truth) of the branching object refined to about ``target_triangles`` triangles.

    truth: ``face_labels`` (T,), ``joints`` (11,3) (NaN for the free hub root), ``parents`` (11,),
    ``weights`` (N,11), ``n_links`` = 11, ``split`` = n.
    """
    coarse, truth = samples.branching(n_fields=1)
    n = split_for(target_triangles) if n is None else int(n)
    S, faces = subdivide(coarse.vertices, coarse.faces, n)
    x0 = np.asarray(S @ coarse.vertices)
    w = np.asarray(S @ truth["weights"])
    joints = truth["joints"].copy()
    pose_joints = joints.copy()
    pose_joints[0] = 0.0  # the hub rotates about its centre
    u = samples.random_poses(x0, w, pose_joints, truth["parents"], n_fields=n_fields, max_deg=max_deg, seed=seed)
    labels = (w[faces].sum(axis=1)).argmax(axis=1)
    out = dict(face_labels=labels, joints=joints, parents=truth["parents"].copy(), weights=w,
               n_links=int(len(np.unique(labels))), split=n)
    return validate_scan(Scan(x0, faces, displacements=u)), out


if __name__ == "__main__":
    import argparse
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("triangles", type=int, nargs="?", default=1000)
    ap.add_argument("--fields", type=int, default=10)
    ap.add_argument("-o", "--output", help="write the scan (+ gt_* truth) as .npz")
    a = ap.parse_args()
    scan, truth = branching_scan(a.triangles, a.fields)
    print(f"split n={truth['split']}: {scan.n_vertices} vertices, {scan.n_faces} triangles, "
          f"{scan.n_fields} fields, {truth['n_links']} links")
    if a.output:
        np.savez_compressed(a.output, vertices=scan.vertices, faces=scan.faces, displacements=scan.displacements,
                            gt_joints=truth["joints"], gt_parents=truth["parents"], gt_weights=truth["weights"],
                            gt_face_labels=truth["face_labels"])
