"""The commutative distance ε between two triangles in one field (paper Eq. 5; docs/method_notes.md §3).

The residual of motion ν_b = (R_b, t_b) applied to triangle a is r(b→a) = ‖ν_b(A0_a) − A1_a‖ over
the stacked 9-vector of a's three vertices. Writing a's vertices as centroid plus offsets
(a_i = c_a + d_i, Σ d_i = 0) the cross term vanishes, and expanding the square gives an inner
product of a 17-vector of the motion b with a 17-vector of the triangle a (docs/method_notes_model.md §12):

    r²(b→a) = 3‖R_b c0_a + t_b − c1_a‖² + Σ_i ‖d_i‖² + ‖d'_i‖² − 2⟨R_b, Σ_i d'_i d_iᵀ⟩
            = g(b) · f(a),
    g(b) = [1, ‖t_b‖², R_bᵀ t_b, vec R_b, t_b]
    f(a) = [3‖c0_a‖² + 3‖c1_a‖² + s_a, 3, 6 c0_a, −vec(6 c1_a c0_aᵀ + 2 K_a), −6 c1_a]

so all residuals of a block of rows and columns are ONE dense matrix product, then a square
root. Coordinates are centred (rest and deformed separately; residuals are invariant under
that) to keep the cancellation in the expanded square at round-off of the object's size.

The distance is ε(a,b) = |r(b→a) − r(a→a)| + |r(a→b) − r(b→b)| (choice A-2: absolute value).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .frames import frames_from_offsets, triangle_frames

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
    g: np.ndarray      # (T,17) motion features (rows of the residual product)
    f: np.ndarray      # (T,17) triangle features (columns of the residual product)

    @property
    def n(self) -> int:
        return self.t.shape[0]

    def take(self, idx) -> "FieldFeatures":
        return FieldFeatures(*(getattr(self, f.name)[idx] for f in dataclasses.fields(self)))

    def zero_distance(self) -> np.ndarray:
        """z(t) = |r(I→t) − r(ν_t→t)|: distance of each motion from the zero velocity
        (docs/method_notes.md §5.3)."""
        return np.abs(self.disp - self.r_self)


@dataclasses.dataclass
class RestGeometry:
    """What every field's features share: the rest frames, centroids and vertex offsets."""
    m0: np.ndarray     # (3,) mean rest vertex
    R0: np.ndarray     # (T,3,3) rest frames
    c0: np.ndarray     # (T,3) rest centroids
    d0: np.ndarray     # (T,3,3) rest vertex offsets from the centroid
    s0: np.ndarray     # (T,) Σ ‖d0‖²


def rest_geometry(x0: np.ndarray, faces: np.ndarray) -> RestGeometry:
    """Rest-shape quantities of :func:`field_features`, computed once per mesh."""
    R0, c0, _ = triangle_frames(x0, faces)
    d0 = x0[faces] - c0[:, None, :]
    return RestGeometry(x0.mean(axis=0), R0, c0, d0, np.einsum("tij,tij->t", d0, d0))


def field_features(x0: np.ndarray, u: np.ndarray, faces: np.ndarray,
                   rest: RestGeometry | None = None, u_mean: np.ndarray | None = None) -> FieldFeatures:
    """Features of one displacement field ``u`` (N,3) on rest positions ``x0`` (N,3).

    Pass ``rest`` (:func:`rest_geometry`) when computing many fields of one mesh: the rest frames
    and offsets are then not recomputed. Everything is formed from the displacements of each
    triangle's vertices and the rest offsets, so no deformed position is gathered twice.
    ``u_mean``: ``u.mean(axis=0)`` when the caller already has it (one field's features taken a
    block of faces at a time, :func:`patches.neighbour_distances`).
    """
    if rest is None:
        rest = rest_geometry(x0, faces)
    U = u[faces]                                  # (T,3,3) vertex displacements
    disp = np.sqrt(np.einsum("tij,tij->t", U, U))
    um = U.mean(axis=1)
    c0 = rest.c0
    c1 = c0 + um
    d0 = rest.d0
    d1 = d0 + (U - um[:, None, :])
    R1, _ = frames_from_offsets(d1)
    R = np.matmul(R1, np.swapaxes(rest.R0, -1, -2))           # ν = E1 E0⁻¹ (Eq. 4)
    t = c1 - np.einsum("tij,tj->ti", R, c0)
    s = rest.s0 + np.einsum("tij,tij->t", d1, d1)
    K = np.einsum("tia,tib->tab", d1, d0).reshape(-1, 9)
    # own residual straight from the definition (not the expanded form): R d0 − d1
    diff = np.matmul(d0, np.swapaxes(R, -1, -2))
    diff -= d1
    r_self = np.sqrt(np.einsum("tij,tij->t", diff, diff))
    del diff
    # centred copies for the product form
    m0 = rest.m0
    m1 = m0 + (u.mean(axis=0) if u_mean is None else u_mean)
    cc0 = c0 - m0
    cc1 = c1 - m1
    tc = t + R @ m0 - m1
    T = len(t)
    g = np.empty((T, 17))
    g[:, 0] = 1.0
    g[:, 1] = np.einsum("ti,ti->t", tc, tc)
    g[:, 2:5] = np.einsum("tji,tj->ti", R, tc)
    g[:, 5:14] = R.reshape(T, 9)
    g[:, 14:17] = tc
    fa = np.empty((T, 17))
    fa[:, 0] = 3 * np.einsum("ti,ti->t", cc0, cc0) + 3 * np.einsum("ti,ti->t", cc1, cc1) + s
    fa[:, 1] = 3.0
    fa[:, 2:5] = 6 * cc0
    fa[:, 5:14] = -(6 * np.einsum("ta,tb->tab", cc1, cc0).reshape(T, 9) + 2 * K)
    fa[:, 14:17] = -6 * cc1
    return FieldFeatures(R, t, c0, c1, s, K, r_self, disp, g, fa)


def triangle_motions(U: np.ndarray, rest: RestGeometry):
    """The motions ν = (R, t) of :func:`field_features` alone, for the displacements ``U`` (..., T, 3, 3)
    of each triangle's vertices in any number of fields: R (..., T, 3, 3), t (..., T, 3) (Eq. 4)."""
    um = U.mean(axis=-2)
    c1 = rest.c0 + um
    d1 = rest.d0 + (U - um[..., None, :])
    R1, _ = frames_from_offsets(d1)
    R = np.matmul(R1, np.swapaxes(rest.R0, -1, -2))
    t = c1 - np.einsum("...ij,...j->...i", R, np.broadcast_to(rest.c0, c1.shape))
    return R, t


def residuals(f: FieldFeatures, rows, cols) -> np.ndarray:
    """r(b→a) for b in ``rows`` (motions) and a in ``cols`` (triangles): (len(rows), len(cols))."""
    r2 = f.g[rows] @ f.f[cols].T
    np.maximum(r2, 0.0, out=r2)
    return np.sqrt(r2, out=r2)


def distance_block(f: FieldFeatures, rows, cols) -> np.ndarray:
    """ε(i, j) for i in ``rows``, j in ``cols`` (Eq. 5, |·| variant)."""
    rows = np.asarray(rows)
    cols = np.asarray(cols)
    a = residuals(f, rows, cols)          # motion of row applied to col triangle
    a -= f.r_self[cols][None, :]
    np.abs(a, out=a)
    if rows.shape == cols.shape and np.array_equal(rows, cols):
        # one set against itself (a small link's medoids, the merge's medoid pairs): the reverse
        # residuals are this product's transpose, the same numbers as a second product gives
        a += a.T
        return a
    b = residuals(f, cols, rows).T        # motion of col applied to row triangle
    b -= f.r_self[rows][:, None]
    np.abs(b, out=b)
    a += b
    return a


def distances_to_one(g: np.ndarray, f: np.ndarray, r_self: np.ndarray, a: int) -> np.ndarray:
    """ε(a, j) for every unit j in each of several fields, from their features stacked fields first:
    ``g``, ``f`` (F, n, 17), ``r_self`` (F, n) → (F, n). Each field's row equals
    :func:`distance_block` of that field's features for rows [a] and all columns, to the bit (the
    products' slices have that function's shapes and strides; the rest is elementwise): the merge
    of §5.2 takes its new row of medoid distances over all fields at once."""
    fwd = np.matmul(g[:, a:a + 1], np.swapaxes(f, 1, 2))[:, 0]      # r(a→j)²
    rev = np.matmul(g, np.swapaxes(f[:, a:a + 1], 1, 2))[:, :, 0]   # r(j→a)²
    for r2 in (fwd, rev):
        np.maximum(r2, 0.0, out=r2)
        np.sqrt(r2, out=r2)
    fwd -= r_self
    np.abs(fwd, out=fwd)
    rev -= r_self[:, a:a + 1]
    np.abs(rev, out=rev)
    fwd += rev
    return fwd


def row_medians(a: np.ndarray) -> np.ndarray:
    """``np.median(a, axis=1)`` of a finite (n, r) block, to the bit, about 5x faster: one
    partition at the upper middle, whose lower part's maximum is the lower middle (np.median
    partitions at both and checks for NaN)."""
    r = a.shape[1]
    h = r // 2
    part = np.partition(a, h, axis=1)
    if r % 2:
        return part[:, h].copy()
    return (part[:, :h].max(axis=1) + part[:, h]) / 2


def digest(*arrays) -> bytes:
    """A 16-byte digest of arrays — their dtypes, shapes and contents, in order: the key of a value
    cached from them (:mod:`merge`'s clusters' sums, :mod:`skinning`'s links' geodesic reach)."""
    import hashlib
    h = hashlib.blake2b(digest_size=16)
    for x in arrays:
        x = np.ascontiguousarray(x)
        h.update(f"{x.dtype.str}{x.shape}".encode())     # not repr(dtype): a fifth of a small merge's time
        h.update(x.view(np.uint8).reshape(-1) if x.size else b"")
    return h.digest()


def worker_count() -> int:
    """The CPUs this process may use, 1 to 4 (the fields whose features are in flight)."""
    import os
    try:
        return max(1, min(4, len(os.sched_getaffinity(0))))
    except AttributeError:  # not on Linux
        return max(1, min(4, os.cpu_count() or 1))


def condensed_distance(f: FieldFeatures, block_entries: int = BLOCK_ENTRIES,
                       out: np.ndarray | None = None, accumulate: float | None = None) -> np.ndarray:
    """The full ε matrix of one field as a condensed vector (the form ``linkage`` takes).

    Computed in row blocks, each written straight into its slice of the condensed vector (the
    upper triangle in row-major order), so peak memory is the vector plus one block.
    With ``accumulate=w`` the block is added as ``out += w·ε`` instead (streaming a weighted sum
    over fields without a second T² buffer).
    """
    n = f.n
    size = n * (n - 1) // 2
    if out is None:
        out = np.zeros(size, dtype=np.float64) if accumulate is not None else np.empty(size, dtype=np.float64)
    step = max(1, block_entries // max(n, 1))
    start = lambda i: i * n - i * (i + 1) // 2  # noqa: E731  condensed offset of row i

    def work(i0):
        i1 = min(n - 1, i0 + step)
        rows = np.arange(i0, i1)
        cols = np.arange(i0, n)
        blk = distance_block(f, rows, cols)
        mask = cols[None, :] > rows[:, None]
        if accumulate is None:
            out[start(i0):start(i1)] = blk[mask]
        else:
            out[start(i0):start(i1)] += accumulate * blk[mask]

    for i0 in range(0, n - 1, step):
        work(i0)
    return out


def subsample(idx: np.ndarray, cap: int | None) -> np.ndarray:
    """At most ``cap`` evenly spaced members of ``idx`` (all of them when ``cap`` is None)."""
    if cap is None or len(idx) <= cap:
        return idx
    return idx[np.linspace(0, len(idx) - 1, cap).astype(np.int64)]


def distance_row_sums(f: FieldFeatures, rows, cols, block_entries: int = BLOCK_ENTRIES,
                      sample: int | None = None, col_weights=None) -> np.ndarray:
    """Σ_{j∈cols} c_j ε(i, j) for every i in ``rows`` without forming the whole block at once.

    ``col_weights`` c (len(cols),) defaults to 1. With ``sample`` the sum over a large ``cols``
    is estimated from ``sample`` evenly spaced members, scaled to the full weight (a CLARA-style
    medoid estimate for big clusters).
    """
    rows = np.asarray(rows)
    cols = np.asarray(cols)
    pick = subsample(np.arange(len(cols)), sample)
    sub = cols[pick]
    if col_weights is None:
        w = None
        scale = len(cols) / max(len(sub), 1)
    else:
        col_weights = np.asarray(col_weights, dtype=np.float64)
        w = col_weights[pick]
        scale = col_weights.sum() / max(w.sum(), 1e-300)
    out = np.zeros(len(rows))
    step = max(1, block_entries // max(len(sub), 1))
    for i0 in range(0, len(rows), step):
        blk = distance_block(f, rows[i0:i0 + step], sub)
        out[i0:i0 + step] = blk.sum(axis=1) if w is None else blk @ w
    return out * scale


def cross_sums(f: FieldFeatures, A, B, block_entries: int = BLOCK_ENTRIES, sample: int | None = None,
               wA=None, wB=None):
    """Row and column sums of the ε block A×B: (Σ_{j∈B} w_j ε(i,j) for i∈A, Σ_{i∈A} w_i ε(i,j) for j∈B).

    ``wA``/``wB`` weigh the members (default 1). Exact unless both sides exceed ``sample``; then
    each sum is estimated from a subsample of the other side.
    """
    A = np.asarray(A)
    B = np.asarray(B)
    if sample is not None and len(A) > sample and len(B) > sample:
        return (distance_row_sums(f, A, B, block_entries, sample, wB),
                distance_row_sums(f, B, A, block_entries, sample, wA))
    sa = np.zeros(len(A))
    sb = np.zeros(len(B))
    step = max(1, block_entries // max(len(B), 1))
    for i0 in range(0, len(A), step):
        blk = distance_block(f, A[i0:i0 + step], B)
        sa[i0:i0 + step] = blk.sum(axis=1) if wB is None else blk @ wB
        sb += blk.sum(axis=0) if wA is None else wA[i0:i0 + step] @ blk
    return sa, sb
