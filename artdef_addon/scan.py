"""Scan file format v1: a triangle mesh and its displacement fields.

A scan is either a measured discrete Green's function matrix Ξ (3N×3M, paper §3:
the displacement of every vertex under a unit load along x, y, z at each of M load
vertices) or a stack of tracked poses (paper §7.2, motion capture of a dense surface).
Both end up as P displacement fields (P, N, 3), which is all the segmentation needs.

This module is the data type and its checks only; files are read and written by the file
boundary, :func:`artdef_addon.files.read_scan` / :func:`artdef_addon.files.write_scan`
(``artdef_addon.load_scan`` is ``read_scan``), which imports this module and is never imported
by it.

File layout (``.npz``, read with ``allow_pickle=False``):

==================== ============ ==================================================
key                  shape        meaning
==================== ============ ==================================================
``vertices``         (N, 3) float rest positions
``faces``            (T, 3) int   triangles, 0-based vertex indices
``greens``           (3N, 3M)     column ``3k+e``: displacement (row ``3i+d``) for a
                                  unit load along axis e at load vertex k
``displacements``    (P, N, 3)    tracked fields (deformed − rest); exactly one of
                                  ``greens`` / ``displacements``
``load_vertices``    (M,) int     with ``greens``: the load vertex of block column k
``support_vertices`` (S,) int     optional: clamped vertices (the fixed ground link)
``probe_load``       ()  float    optional: traction used when measuring (default 1)
==================== ============ ==================================================
"""
from __future__ import annotations

import dataclasses

import numpy as np

FORMAT_VERSION = 1
_KNOWN_KEYS = {"vertices", "faces", "greens", "displacements", "load_vertices",
               "support_vertices", "probe_load", "format_version"}


#: largest coordinate or displacement magnitude accepted: the fit's moments multiply up to four
#: coordinates, which overflow float64 beyond about 1e77 (the rod scaled by 1e80 ended in "SVD did
#: not converge"; 1e75 fits), giving NaN instead of a result
MAX_MAGNITUDE = 1e60
#: smallest extent of a mesh accepted (its largest coordinate range): the mirror of MAX_MAGNITUDE, the fit's
#: moments multiply up to four coordinates, which underflow below about 1e-77 (a mesh 1e-100 across read as
#: "every triangle is degenerate", one 1e-170 across as fields "1e40 times the mesh's size (0)")
MIN_SIZE = 1e-60
#: largest displacement accepted, in units of the mesh's diagonal: no measurement moves an object
#: by 1e40 of its sizes, and from about 1e90 the fit's rest frames overflow (a Green's scan with
#: probe_load 1e90 ended in an internal error)
MAX_RELATIVE_FIELD = 1e40


class ScanError(ValueError):
    """Bad scan input; the message names the problem."""


@dataclasses.dataclass
class Scan:
    vertices: np.ndarray
    faces: np.ndarray
    greens: np.ndarray | None = None
    displacements: np.ndarray | None = None
    load_vertices: np.ndarray | None = None
    support_vertices: np.ndarray | None = None
    probe_load: float = 1.0
    # filled by validate_scan: indices of triangles with (near) zero area
    degenerate_faces: np.ndarray = dataclasses.field(
        default_factory=lambda: np.zeros(0, dtype=np.int64))
    # set by validate_scan: the (read-only) arrays and probe load it checked; a scan validated
    # once is not checked again while it holds exactly these (held here, so never recycled)
    _checked: tuple | None = dataclasses.field(default=None, repr=False, compare=False)
    # set by seams.weld_scan: (the _checked it welded, tolerance, scan of the distinct points, weld)
    _welded: tuple | None = dataclasses.field(default=None, repr=False, compare=False)

    def _inputs(self) -> tuple:
        return (self.vertices, self.faces, self.greens, self.displacements, self.load_vertices,
                self.support_vertices, self.degenerate_faces, self.probe_load)

    @property
    def kind(self) -> str:
        return "greens" if self.greens is not None else "tracked"

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def n_faces(self) -> int:
        return int(self.faces.shape[0])

    @property
    def n_loads(self) -> int:
        return 0 if self.greens is None else int(self.greens.shape[1] // 3)

    @property
    def n_fields(self) -> int:
        if self.greens is not None:
            return int(self.greens.shape[1])
        return int(self.displacements.shape[0])

    def field(self, c: int) -> np.ndarray:
        """Displacement field ``c`` as (N, 3). For a Green's scan this is Ξ e_c p̂ (docs/method_notes.md §1a)."""
        if self.greens is not None:
            return self.greens[:, c].reshape(-1, 3) * self.probe_load
        return self.displacements[c]

    def fields(self) -> np.ndarray:
        """All displacement fields, (P, N, 3)."""
        if self.greens is not None:
            n = self.n_vertices
            return (self.greens.reshape(n, 3, -1).transpose(2, 0, 1) * self.probe_load)
        return self.displacements


def _magnitude(a: np.ndarray) -> float:
    """max |a| (0 for an empty array) from the extremes, without the temporary of ``np.abs(a)``."""
    return max(abs(float(a.max())), abs(float(a.min()))) if a.size else 0.0


def _fields_magnitude(greens, displacements, probe_load: float) -> float:
    """max |field|: of ``greens`` × ``probe_load`` (a Green's scan) or of ``displacements``, from
    the arrays' extremes, without a copy of the fields."""
    return _magnitude(greens) * probe_load if greens is not None else _magnitude(displacements)


def reach(scan: Scan) -> float:
    """The largest coordinate magnitude a pose of ``scan`` can reach, max |vertex| + max |field|."""
    greens = None if scan.greens is None else np.asarray(scan.greens)
    return _magnitude(np.asarray(scan.vertices)) + _fields_magnitude(
        greens, np.asarray(scan.displacements), float(scan.probe_load))


def repeated_load_vertex(scan: Scan) -> str | None:
    """Why the Blender layer cannot hold ``scan``'s load points, or None: it marks one load point per
    vertex (the integer attribute ``artdef_load_index``), so a vertex listed twice in
    ``load_vertices`` is refused there before the fit (the core itself fits such a scan)."""
    if scan.load_vertices is None:
        return None
    lv = np.asarray(scan.load_vertices).ravel()
    values, counts = np.unique(lv, return_counts=True)
    if not np.any(counts > 1):
        return None
    vertex = int(values[counts > 1][0])
    points = np.nonzero(lv == vertex)[0]
    return (f"vertex {vertex} is listed {len(points)} times in load_vertices (load points "
            f"{', '.join(str(int(k)) for k in points)}); Blender holds one load point per vertex: "
            f"keep one of them and its three greens columns")


def _as_float(name, a, ndim):
    a = np.asarray(a)
    if a.dtype.kind not in "fiu":
        raise ScanError(f"{name} must be numeric, got dtype {a.dtype}")
    if a.ndim != ndim:
        raise ScanError(f"{name} must have {ndim} dimensions, got shape {a.shape}")
    a = a.astype(np.float64, copy=False)
    if not np.all(np.isfinite(a)):
        bad = int(np.count_nonzero(~np.isfinite(a)))
        raise ScanError(f"{name} contains {bad} NaN or infinite values")
    top = _magnitude(a)
    if top > MAX_MAGNITUDE:
        what = _WHAT_VALUES.get(name, f"{name} values")
        raise ScanError(f"{what} reach {top:.3g}, beyond {MAX_MAGNITUDE:.0e}, the largest magnitude the fit "
                        f"works with (its moments multiply up to four of them and would overflow): "
                        f"rescale the scan (other units)")
    return a


#: what :func:`_as_float`'s values are, for its messages
_WHAT_VALUES = {"vertices": "vertex coordinates", "displacements": "displacements",
                "greens": "Green's matrix entries (greens)"}


def _as_index(name, a, n, ndim=1):
    a = np.asarray(a)
    if a.dtype.kind not in "iu":
        if (a.dtype.kind == "f" and a.size and np.all(np.isfinite(a)) and np.all(a == np.round(a))
                and float(np.abs(a).max()) < 2 ** 53):
            a = a.astype(np.int64)
        elif a.size == 0:
            a = a.astype(np.int64)
        else:
            raise ScanError(f"{name} must be integer indices, got dtype {a.dtype}")
    if a.ndim != ndim:
        raise ScanError(f"{name} must have {ndim} dimension(s), got shape {a.shape}")
    if a.size:
        # the extremes in the array's own dtype, as exact Python integers: a uint64 index of 2**63 or
        # more would read as negative after the cast to int64
        lo, hi = int(a.min()), int(a.max())
        if lo < 0 or hi >= n:
            raise ScanError(f"{name} has indices out of range [0, {n}): min {lo}, max {hi}")
    return a.astype(np.int64)


def is_checked(scan: Scan) -> bool:
    """Whether ``scan`` came from :func:`validate_scan` and still holds exactly the arrays it
    checked: the fit's own modules take such a scan as it is (the scan is checked once, where it
    enters: a file read, a Blender mesh read, :func:`artdef_addon.fit`, a built-in sample)."""
    return scan._checked is not None and all(a is b for a, b in zip(scan._checked, scan._inputs()))


def validate_scan(scan: Scan) -> Scan:
    """Check shapes, dtypes, finiteness and index ranges; return a normalised copy.

    Degenerate triangles (zero area or repeated vertices) are not an error: they are
    recorded in ``degenerate_faces`` and the fit gives them their neighbours' link
    (docs/method_notes.md §2, notes).

    The copy holds read-only views of its arrays and remembers them, so validating it
    again (the Blender operators validate on reading the mesh, the fit on entry) returns
    it as is instead of re-reading every field; assigning a new array to it (or any
    scan not made here) is checked in full.
    """
    if is_checked(scan):
        return scan
    out = _check_scan(scan)
    for name in ("vertices", "faces", "greens", "displacements", "load_vertices",
                 "support_vertices", "degenerate_faces"):
        a = getattr(out, name)
        if a is not None:
            a = a.view()
            a.flags.writeable = False
            setattr(out, name, a)
    out._checked = out._inputs()
    return out


def _check_scan(scan: Scan) -> Scan:
    """The checks of :func:`validate_scan`, always run in full."""
    v = _as_float("vertices", scan.vertices, 2)
    if v.shape[1] != 3:
        raise ScanError(f"vertices must have shape (N, 3), got {v.shape}")
    n = v.shape[0]
    if n < 3:
        raise ScanError(f"the mesh needs at least 3 vertices, got {n}")
    f = np.asarray(scan.faces)
    if f.ndim != 2 or f.shape[1] != 3:
        raise ScanError(f"faces must be triangles with shape (T, 3), got {f.shape}"
                        " (non-triangle faces: triangulate the mesh first)")
    f = _as_index("faces", f, n, ndim=2)
    if f.shape[0] == 0:
        raise ScanError("the mesh has no faces")
    has_g = scan.greens is not None
    has_d = scan.displacements is not None
    if has_g == has_d:
        raise ScanError("a scan needs exactly one of 'greens' or 'displacements', got "
                        + ("both" if has_g else "neither"))
    g = d = lv = None
    if has_g:
        g = _as_float("greens", scan.greens, 2)
        if g.shape[0] != 3 * n or g.shape[1] % 3 != 0 or g.shape[1] == 0:
            raise ScanError(f"greens must have shape (3N, 3M) = (3*{n}, 3*M), got {g.shape}")
        if scan.load_vertices is None:
            raise ScanError("a Green's-matrix scan needs 'load_vertices' (M,)")
        lv = _as_index("load_vertices", scan.load_vertices, n)
        if lv.shape[0] != g.shape[1] // 3:
            raise ScanError(f"load_vertices has {lv.shape[0]} entries but greens has "
                            f"{g.shape[1] // 3} block columns")
    else:
        d = _as_float("displacements", scan.displacements, 3)
        if d.shape[1:] != (n, 3):
            raise ScanError(f"displacements must have shape (P, N, 3) = (P, {n}, 3), got {d.shape}")
        if d.shape[0] == 0:
            raise ScanError("too few fields: the scan has 0 displacement fields, at least 1 is needed")
        if scan.load_vertices is not None and np.asarray(scan.load_vertices).size:
            lv = _as_index("load_vertices", scan.load_vertices, n)
    sv = None
    if scan.support_vertices is not None and np.asarray(scan.support_vertices).size:
        sv = _as_index("support_vertices", scan.support_vertices, n)
    p = float(np.asarray(scan.probe_load))
    if not np.isfinite(p) or p <= 0:
        raise ScanError(f"probe_load must be a positive number, got {p}")
    extent = np.ptp(v, axis=0)
    across = float(extent.max())
    if across == 0:
        raise ScanError("every vertex is at one point: the mesh has no extent")
    if across < MIN_SIZE:
        # else every triangle read as degenerate (their areas underflow), or the fields as 1e40
        # times a mesh of size 0
        raise ScanError(f"the mesh is {across:.3g} across, below {MIN_SIZE:.0e}, the smallest the fit works "
                        f"with (its moments multiply up to four coordinates and would underflow): rescale "
                        f"the scan (other units)")
    size = across * float(np.linalg.norm(extent / across))     # the diagonal, without squares that underflow
    # the largest displacement (the fields are greens x probe_load), without a copy of the fields
    fields_top = _fields_magnitude(g, d, p)
    if has_g and (p > MAX_MAGNITUDE or not fields_top <= MAX_MAGNITUDE):
        # each factor within the bound, their product may not be
        raise ScanError(f"greens x probe_load reaches {fields_top:.3g} (probe_load {p:.3g}); the fields must stay "
                        f"below {MAX_MAGNITUDE:.0e} in magnitude")
    if fields_top > MAX_RELATIVE_FIELD * size:
        raise ScanError(f"the fields move vertices by up to {fields_top:.3g}, over {MAX_RELATIVE_FIELD:.0e} times the "
                        f"mesh's size ({size:.3g}): check their units" + (" and probe_load" if has_g else ""))
    out = Scan(v, f, g, d, lv, sv, p)
    # degenerate triangles: area relative to the mesh scale
    e1 = v[f[:, 1]] - v[f[:, 0]]
    e2 = v[f[:, 2]] - v[f[:, 0]]
    area2 = np.linalg.norm(np.cross(e1, e2), axis=1)
    scale = max(float(np.ptp(v, axis=0).max()), 1e-300)
    degenerate = area2 <= 1e-12 * scale * scale
    out.degenerate_faces = np.flatnonzero(degenerate)
    if out.degenerate_faces.size == f.shape[0]:
        raise ScanError("every triangle is degenerate (zero area)")
    fields = out.fields()
    if not np.any(fields):
        raise ScanError("too few fields: every displacement field is zero (nothing moves)")
    return out
