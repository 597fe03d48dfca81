"""The commutative distance ε between two triangles in one field (paper Eq. 5; METHOD §3).

The residual of motion ν_b applied to triangle a is r(b→a) = ‖ν_b(A0_a) − A1_a‖ over the
stacked 9-vector of a's three vertices. With the triangle's vertices written as centroid
plus offsets (a_i = c_a + d_i, Σ d_i = 0) the cross term vanishes and

    r²(b→a) = 3 ‖R_b c0_a + t_b − c1_a‖² + Σ_i ‖d_i‖² + ‖d'_i‖² − 2 ⟨R_b, Σ_i d'_i d_iᵀ⟩ ,

so every r(b→a) of a block of rows and columns is a few dense matrix products (METHOD §12),
and the large centroid coordinates never cancel against each other (precision stays at
round-off of the coordinates, not its square root).

The distance is ε(a,b) = |r(b→a) − r(a→a)| + |r(a→b) − r(b→b)| (choice A-2: absolute value).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .frames import relative_motions

#: default number of matrix entries per block (≈ 8 bytes × 4 arrays each)
BLOCK_ENTRIES = 2_000_000


@dataclasses.dataclass
class FieldFeatures:
    """Per-triangle quantities of one field that ε needs (all float64, T triangles)."""
    R: np.ndarray      # (T,3,3) motion rotation
    t: np.ndarray      # (T,3) motion translation
    c0: np.ndarray     # (T,3) rest centroid
    c1: np.ndarray     # (T,3) deformed centroid
    s: np.ndarray      # (T,) Σ ‖d‖² + ‖d'‖²
    K: np.ndarray      # (T,9) Σ d' dᵀ flattened
    r_self: np.ndarray  # (T,) r(a→a): the triangle's own non-rigidity
    disp: np.ndarray   # (T,) ‖A1 − A0‖ over the 9-vector

    @property
    def n(self) -> int:
        return self.t.shape[0]

    def take(self, idx) -> "FieldFeatures":
        return FieldFeatures(*(getattr(self, f.name)[idx] for f in dataclasses.fields(self)))

    def zero_distance(self) -> np.ndarray:
        """z(t) = |r(I→t) − r(ν_t→t)|: distance of each motion from the zero velocity (METHOD §5.3)."""
        return np.abs(self.disp - self.r_self)


def field_features(x0: np.ndarray, u: np.ndarray, faces: np.ndarray) -> FieldFeatures:
    """Features of one displacement field ``u`` (N,3) on rest positions ``x0`` (N,3)."""
    x1 = x0 + u
    R, t = relative_motions(x0, x1, faces)
    A0 = x0[faces]          # (T,3,3) vertex i, coord
    A1 = x1[faces]
    c0 = A0.mean(axis=1)
    c1 = A1.mean(axis=1)
    d0 = A0 - c0[:, None, :]
    d1 = A1 - c1[:, None, :]
    s = np.einsum("tij,tij->t", d0, d0) + np.einsum("tij,tij->t", d1, d1)
    K = np.einsum("tia,tib->tab", d1, d0).reshape(-1, 9)
    # own residual, straight from the definition (not the expanded form)
    moved = np.einsum("tab,tib->tia", R, A0) + t[:, None, :]
    r_self = np.sqrt(np.einsum("tij,tij->t", moved - A1, moved - A1))
    disp = np.sqrt(np.einsum("tij,tij->t", A1 - A0, A1 - A0))
    return FieldFeatures(R, t, c0, c1, s, K, r_self, disp)


def residuals(f: FieldFeatures, rows, cols) -> np.ndarray:
    """r(b→a) for b in ``rows`` (motions) and a in ``cols`` (triangles): (len(rows), len(cols))."""
    R = f.R[rows]
    e = (R.reshape(-1, 3) @ f.c0[cols].T).reshape(len(R), 3, -1)
    e += f.t[rows][:, :, None]
    e -= f.c1[cols].T[None]
    r2 = np.einsum("bka,bka->ba", e, e)
    r2 *= 3.0
    r2 += f.s[cols][None, :]
    r2 -= 2.0 * (R.reshape(-1, 9) @ f.K[cols].T)
    np.maximum(r2, 0.0, out=r2)
    return np.sqrt(r2, out=r2)


def distance_block(f: FieldFeatures, rows, cols) -> np.ndarray:
    """ε(i, j) for i in ``rows``, j in ``cols`` (Eq. 5, |·| variant)."""
    rows = np.asarray(rows)
    cols = np.asarray(cols)
    a = residuals(f, rows, cols)          # motion of row applied to col triangle
    a -= f.r_self[cols][None, :]
    np.abs(a, out=a)
    b = residuals(f, cols, rows).T        # motion of col applied to row triangle
    b -= f.r_self[rows][:, None]
    np.abs(b, out=b)
    a += b
    return a


def condensed_distance(f: FieldFeatures, block_entries: int = BLOCK_ENTRIES,
                       out: np.ndarray | None = None) -> np.ndarray:
    """The full ε matrix of one field as a condensed vector (the form ``linkage`` takes).

    Computed in row blocks, each written straight into its slice of the condensed vector
    (the upper triangle in row-major order), so peak memory is the vector plus one block.
    """
    n = f.n
    size = n * (n - 1) // 2
    if out is None:
        out = np.empty(size, dtype=np.float64)
    step = max(1, block_entries // max(n, 1))
    start = lambda i: i * n - i * (i + 1) // 2  # noqa: E731  condensed offset of row i
    for i0 in range(0, n - 1, step):
        i1 = min(n - 1, i0 + step)
        rows = np.arange(i0, i1)
        cols = np.arange(i0, n)
        blk = distance_block(f, rows, cols)
        mask = cols[None, :] > rows[:, None]
        out[start(i0):start(i1)] = blk[mask]
    return out


def distance_row_sums(f: FieldFeatures, rows, cols, block_entries: int = BLOCK_ENTRIES) -> np.ndarray:
    """Σ_{j∈cols} ε(i, j) for every i in ``rows`` without forming the whole block at once."""
    rows = np.asarray(rows)
    cols = np.asarray(cols)
    out = np.zeros(len(rows))
    step = max(1, block_entries // max(len(cols), 1))
    for i0 in range(0, len(rows), step):
        out[i0:i0 + step] = distance_block(f, rows[i0:i0 + step], cols).sum(axis=1)
    return out


def cross_sums(f: FieldFeatures, A, B, block_entries: int = BLOCK_ENTRIES):
    """Row and column sums of the ε block A×B: (Σ_{j∈B} ε(i,j) for i∈A, Σ_{i∈A} ε(i,j) for j∈B)."""
    A = np.asarray(A)
    B = np.asarray(B)
    sa = np.zeros(len(A))
    sb = np.zeros(len(B))
    step = max(1, block_entries // max(len(B), 1))
    for i0 in range(0, len(A), step):
        blk = distance_block(f, A[i0:i0 + step], B)
        sa[i0:i0 + step] = blk.sum(axis=1)
        sb += blk.sum(axis=0)
    return sa, sb
