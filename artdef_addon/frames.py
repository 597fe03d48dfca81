"""Per-triangle frames and relative rigid motions (paper §5.1, Eq. 4; docs/method_notes.md §2).

For a triangle (a0, a1, a2) the frame has x̂ along the first edge, ẑ along the normal
and ŷ = ẑ × x̂, with origin at the centroid. With E0 from the rest vertices and E1 from
the deformed ones, the triangle's finite spatial velocity is ν = E1 E0⁻¹, i.e.
R = R1 R0ᵀ and t = c1 − R c0. It is kept as (R, t), never as a twist.
"""
from __future__ import annotations

import numpy as np


def frames_from_offsets(d: np.ndarray):
    """Frames (T,3,3) and ``ok`` (T,) from each triangle's vertex offsets ``d`` (T,3,3).

    The frame depends on edge vectors only, so offsets from the centroid give the same frame as
    the positions (x̂ along the first edge, ẑ along the normal, ŷ = ẑ × x̂).
    """
    e1 = d[..., 1, :] - d[..., 0, :]
    n = np.cross(e1, d[..., 2, :] - d[..., 0, :])
    l1 = np.sqrt(np.einsum("...i,...i->...", e1, e1))
    ln = np.sqrt(np.einsum("...i,...i->...", n, n))
    scale = np.maximum(l1, 1e-300)
    ok = (l1 > 0) & (ln > 1e-12 * scale * scale)
    xh = e1 / np.where(ok, l1, 1.0)[..., None]
    zh = n / np.where(ok, ln, 1.0)[..., None]
    yh = np.cross(zh, xh)
    R = np.stack([xh, yh, zh], axis=-1)
    R[~ok] = np.eye(3)
    return R, ok


def triangle_frames(x: np.ndarray, faces: np.ndarray):
    """Frames of every triangle.

    ``x`` is (..., N, 3); returns ``(R, c, ok)`` with ``R`` (..., T, 3, 3) whose columns are
    x̂, ŷ, ẑ, ``c`` (..., T, 3) the centroids and ``ok`` (..., T) False where the triangle is
    degenerate (its frame is then the identity).
    """
    A = x[..., faces, :]                        # (..., T, 3, 3)
    c = A.mean(axis=-2)
    R, ok = frames_from_offsets(A - c[..., None, :])
    return R, c, ok


def relative_motions(x0: np.ndarray, x1: np.ndarray, faces: np.ndarray):
    """Rigid motion ν = E1 E0⁻¹ of every triangle from rest ``x0`` (N,3) to ``x1`` (..., N, 3).

    Returns ``(R, t)`` with shapes (..., T, 3, 3) and (..., T, 3): a rest-world point y
    goes to ``R @ y + t``. Degenerate triangles get the motion of their centroid only.
    """
    R0, c0, _ = triangle_frames(x0, faces)
    R1, c1, _ = triangle_frames(x1, faces)
    R = R1 @ np.swapaxes(R0, -1, -2)
    t = c1 - np.einsum("...ij,...j->...i", R, np.broadcast_to(c0, c1.shape))
    return R, t
