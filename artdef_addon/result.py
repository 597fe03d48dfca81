"""The result of a fit (:class:`FitResult`), its ``.npz`` file, and a fit's cancellation.

:func:`report` is how every stage of a fit hands its progress to the caller's callback; a True
answer stops the fit with :class:`FitCancelled` (nothing produced).
"""
from __future__ import annotations

import dataclasses
import os

import numpy as np

from . import residuals as _residuals


class FitCancelled(Exception):
    """The progress callback asked to stop; nothing was produced."""


@dataclasses.dataclass
class FitResult:
    face_labels: np.ndarray
    parents: np.ndarray
    joints: np.ndarray
    joint_errors: np.ndarray
    heads: np.ndarray
    tails: np.ndarray
    frames: np.ndarray
    grounded: np.ndarray
    weights: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    angles: np.ndarray
    locations: np.ndarray
    residual: np.ndarray
    link_residuals: np.ndarray
    rms_articulation: float
    rms_total: float
    articulation_error_percent: float
    kappa: np.ndarray | None = None
    load_vertices: np.ndarray | None = None
    probe_load: float = 1.0
    p_max: float | None = None
    mode: str = "global"
    motion: str = "robust"
    skin: str = "seam"
    timings: dict = dataclasses.field(default_factory=dict)
    pseudo: list | None = None
    notes: list = dataclasses.field(default_factory=list)
    link_reason: str = ""            # why ``links="auto"`` chose this count (empty: count given)
    link_errors: list = dataclasses.field(default_factory=list)  # links auto: e(k) %, k = 1, 2, …
    options: object = None           # the FitOptions it was asked with ("auto" kept), when known
    reduced: bool = False            # the reduced method on patches ran
    estimate: object = None          # the cost.Estimate of the method that ran
    groups: list | None = None       # fields of each load point (Green's scans: pseudo models)
    # fidelity (docs/metrics.md): E_RMS in scene units, the per-vertex mean error in percent, and the
    # verdict's comparison (one rigid motion per frame, a linear model of about the rig's size); NaN: unknown
    e_rms: float = float("nan")
    vertex_mean_error_percent: float = float("nan")
    rigid_error_percent: float = float("nan")
    linear_error_percent: float = float("nan")
    linear_rank: int = 0
    articulated: bool = True
    residual_basis: object = None    # tracked scans: the rig's residual shapes (residuals.ResidualBasis)

    @property
    def n_links(self) -> int:
        return int(self.parents.shape[0])

    @property
    def params(self) -> np.ndarray:
        """Pose parameters per field, (P, L, 6): Euler XYZ then location."""
        return np.concatenate([self.angles, self.locations], axis=-1)

    def save(self, path) -> None:
        """Write this result as a ``.npz`` (see docs/formats.md)."""
        save_result(path, self)

    @classmethod
    def load(cls, path) -> "FitResult":
        """Read a result written by :meth:`save`."""
        return load_result(path)

    def error_percent_text(self) -> str:
        """The Karni–Gotsman distortion as text: "0.0274% Karni–Gotsman", or "n/a" where it is undefined
        (every frame's vertices at one point: nothing spreads about the frames' centroids). Defined for a
        single field too (docs/metrics.md), where the per-vertex-mean figure is not."""
        e = self.articulation_error_percent
        if np.isfinite(e):
            return f"{e:.3g}% Karni–Gotsman"
        return "n/a (the frames do not spread about their centroids)"

    def summary(self) -> str:
        lines = [f"links: {self.n_links}  mode: {self.mode}  motion: {self.motion}  skin: {self.skin}"]
        for l in range(self.n_links):
            j = self.joints[l]
            where = "free root" if np.isnan(j).any() else "joint (" + ", ".join(f"{v:.4f}" for v in j) + ")"
            par = "world" if self.parents[l] < 0 and self.grounded[l] else (
                "-" if self.parents[l] < 0 else f"link {self.parents[l]}")
            lines.append(f"  link {l:2d}: {np.count_nonzero(self.face_labels == l):6d} triangles, "
                         f"parent {par:>8s}, {where}, joint error {self.joint_errors[l]:.3g}")
        lines.append(f"rms error: articulation {self.rms_articulation:.4g} "
                     f"({self.error_percent_text()}, E_RMS {self.e_rms:.3g}), "
                     f"articulation + residual {self.rms_total:.3g}")
        if np.isfinite(self.rigid_error_percent):
            lines.append(f"reference models (Karni–Gotsman): one rigid motion per frame {self.rigid_error_percent:.3g}%, "
                         f"rank-{self.linear_rank} linear model {self.linear_error_percent:.3g}%"
                         + ("" if self.articulated else "; the data do not look articulated (see note)"))
        if self.residual_basis is not None:       # tracked: the rig's residual shapes and its replay error
            lines.append(self.residual_basis.describe())
        lines.append("time: " + ", ".join(f"{k} {v:.2f}s" for k, v in self.timings.items()))
        lines.extend(f"note: {n}" for n in self.notes)
        return "\n".join(lines)


def report(progress, stage, frac):
    """Tell ``progress(stage, fraction)`` where a fit is; a True answer cancels (:class:`FitCancelled`)."""
    if progress is not None and progress(stage, float(frac)):
        raise FitCancelled(f"cancelled during {stage}")


_ARRAYS = ("face_labels", "parents", "joints", "joint_errors", "heads", "tails", "frames", "grounded",
           "weights", "rotations", "translations", "angles", "locations", "residual", "link_residuals")


#: scalar fidelity figures (result files written without them read as NaN)
_FIDELITY = ("e_rms", "vertex_mean_error_percent", "rigid_error_percent", "linear_error_percent")


def save_result(path, result: FitResult) -> None:
    """Write a result ``.npz`` (see docs/formats.md, "Result file") atomically, with exactly the name ``path``."""
    from .files import write_npz
    write_npz(path, result_arrays(result), compress=True)


def result_arrays(result: FitResult) -> dict:
    """The arrays of a result file (what :func:`save_result` writes)."""
    out = {k: getattr(result, k) for k in _ARRAYS}
    out.update(rms_articulation=np.float64(result.rms_articulation), rms_total=np.float64(result.rms_total),
               articulation_error_percent=np.float64(result.articulation_error_percent),
               probe_load=np.float64(result.probe_load),
               p_max=np.float64(np.nan if result.p_max is None else result.p_max),
               mode=np.array(result.mode), motion=np.array(result.motion), skin=np.array(result.skin),
               notes=np.array([str(n) for n in result.notes], dtype=str),
               **{k: np.float64(getattr(result, k)) for k in _FIDELITY},
               linear_rank=np.int64(result.linear_rank), articulated=np.bool_(result.articulated),
               timing_names=np.array(list(result.timings.keys()), dtype=str),
               timing_seconds=np.array(list(result.timings.values()), dtype=np.float64),
               link_reason=np.array(result.link_reason), **_residuals.basis_arrays(result.residual_basis))
    if result.kappa is not None:
        out["kappa"] = result.kappa
        out["load_vertices"] = result.load_vertices
    if result.pseudo:
        out["pseudo_face_labels"] = np.stack([s.face_labels for s in result.pseudo])
        for k, sub in enumerate(result.pseudo):
            for name in _ARRAYS + ("kappa", "load_vertices"):
                out[f"pseudo{k}_{name}"] = getattr(sub, name)
    return out


def load_result(path) -> FitResult:
    """Read a result written by :func:`save_result` (never unpickles): :func:`files.read_result`
    checks every key, dtype and shape first; a bad file is one ``ScanError`` line."""
    from .files import BadFile, read_result_arrays
    d = read_result_arrays(path)
    try:
        return result_from_arrays(d)
    except (KeyError, ValueError, TypeError, IndexError) as exc:
        line = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise BadFile(f"{os.fspath(path)}: damaged result ({line})") from None


def result_from_arrays(d: dict) -> FitResult:
    """A :class:`FitResult` from the arrays of a checked result file."""

    def build(prefix=""):
        kw = {k: d[prefix + k] for k in _ARRAYS}
        r = FitResult(**kw, rms_articulation=float(d["rms_articulation"]), rms_total=float(d["rms_total"]),
                      articulation_error_percent=float(d["articulation_error_percent"]))
        r.probe_load = float(d["probe_load"])
        pm = float(d["p_max"])
        r.p_max = None if np.isnan(pm) else pm
        r.mode = str(d["mode"])
        r.motion = str(d["motion"])
        r.skin = str(d["skin"]) if "skin" in d else "seam"
        if not prefix:  # the fidelity keys; a file without them reads as NaN / defaults
            for k in _FIDELITY:
                if k in d:
                    setattr(r, k, float(d[k]))
            r.linear_rank = int(d["linear_rank"]) if "linear_rank" in d else 0
            r.articulated = bool(d["articulated"]) if "articulated" in d else True
            notes = d["notes"] if "notes" in d else np.array([], dtype=str)
            if notes.ndim != 1 or notes.dtype.kind not in "U":
                raise ValueError(f"notes must be a list of text, got {notes.dtype} of shape {notes.shape}")
            r.notes = notes.tolist()
        if prefix + "kappa" in d:
            r.kappa = d[prefix + "kappa"]
            r.load_vertices = d[prefix + "load_vertices"]
        return r
    res = build()
    res.timings = dict(zip(d["timing_names"].tolist(), d["timing_seconds"].tolist()))
    res.link_reason = str(d["link_reason"]) if "link_reason" in d else ""
    res.residual_basis = _residuals.basis_from_arrays(d)
    if "pseudo_face_labels" in d:
        res.pseudo = []
        k = 0
        while f"pseudo{k}_face_labels" in d:
            res.pseudo.append(build(f"pseudo{k}_"))
            k += 1
    return res

