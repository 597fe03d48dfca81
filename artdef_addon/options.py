"""Fit options: every setting of a fit, declared once.

:class:`FitOptions` is a frozen dataclass. Each field's ``metadata`` (an :class:`Option`) carries
what every front end needs — label, description, type, default, the allowed values with their own
descriptions, unit, bounds, and whether the setting only matters for Green's scans or is an
advanced one. The command line (:mod:`artdef_addon.cli`) builds its ``argparse`` arguments from
it, the Blender layer (``operators/props.py``) its ``bpy.props`` properties, the panel its rows:
no front end repeats a default, a choice or a description.

Spelling: one canonical, lower-case value per choice (``"global"``, ``"refined"`` …); Blender's
enum identifiers are those values upper-cased (a mechanical rule of the Blender layer, not a
second spelling). ``p_max`` is ``None`` when hardening is off (the Blender property shows that as
0). ``memory_budget`` is in GB (2³⁰ bytes); :attr:`FitOptions.budget_bytes` gives bytes.

Values are checked once, when the options are made (``OptionsError``: one line naming the setting).
The bounds are declared here only: ``FitOptions`` checks them, :attr:`Option.range` turns them
into the command line's flag checks (:class:`IntRange` / :class:`FloatRange`, whose
:class:`OptionError` names the flag), and the Blender layer reads them as property min/max.
The "auto" rules (strategy, skin) live here too, in :meth:`FitOptions.resolved`.
"""
from __future__ import annotations

import dataclasses
import math
import re

import numpy as np


GB = 2 ** 30

#: the most link counts ``links="auto"`` may try: each count is a segmentation plus a skin solve,
#: so the search grows with it (``benchmarks/results/links_auto.md``)
MAX_AUTO_LINKS = 100


class OptionsError(ValueError):
    """A fit setting out of range or not one of its choices (not a :class:`ScanError`: the scan may
    be fine). Bad input all the same: every front end reports it in one line; the message names the
    setting, ``option`` is the field's name (a front end may show its label instead)."""

    def __init__(self, message: str, option: str | None = None):
        super().__init__(message)
        self.option = option


class OptionError(ValueError):
    """A command-line value out of its range; one line naming the flag and the range."""


@dataclasses.dataclass(frozen=True)
class IntRange:
    """Whole number in [lo, hi] (``hi`` None: unbounded). ``check`` returns it as ``int``."""
    lo: int | None = None
    hi: int | None = None
    why_hi: str = ""

    def check(self, name: str, value) -> int:
        if isinstance(value, (bool, np.bool_)):
            raise OptionError(f"{name} must be a whole number, got {value!r}")
        if isinstance(value, str):
            # text (the command line): decimal digits only, read exactly ("1e0", "3_0" and other
            # scripts' digits are not counts; a huge count is repeated as written)
            text = value.strip()
            if not re.fullmatch(r"[+-]?[0-9]+", text):
                raise OptionError(f"{name} must be a whole number, got {value!r}")
            v = int(text)
        else:
            try:
                f = float(value)
                ok = math.isfinite(f) and f == int(f)
            except (TypeError, ValueError, OverflowError):
                ok = False
            if not ok:
                raise OptionError(f"{name} must be a whole number, got {value!r}")
            v = int(f) if not isinstance(value, (int, np.integer)) else int(value)
        if self.lo is not None and v < self.lo:
            raise OptionError(f"{name} must be at least {self.lo}, got {v}")
        if self.hi is not None and v > self.hi:
            raise OptionError(f"{name} must be at most {self.hi}{self.why_hi}, got {v}")
        return v

    def within(self, hi: int, why: str = "") -> "IntRange":
        """The same range with its upper bound lowered to ``hi`` (e.g. a scan's triangle count)."""
        return IntRange(self.lo, hi if self.hi is None else min(self.hi, hi),
                        why if self.hi is None or hi < self.hi else self.why_hi)


@dataclasses.dataclass(frozen=True)
class FloatRange:
    """Finite number in [lo, hi] (or (lo, hi] with ``lo_open``); ``hi`` None: unbounded."""
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False

    def check(self, name: str, value) -> float:
        try:
            v = float(value)
        except (TypeError, ValueError, OverflowError):
            raise OptionError(f"{name} must be a number, got {value!r}") from None
        if not math.isfinite(v):
            raise OptionError(f"{name} must be a finite number, got {value!r}")
        if self.lo is not None and (v <= self.lo if self.lo_open else v < self.lo):
            raise OptionError(f"{name} must be {'above' if self.lo_open else 'at least'} {self.lo:g}, got {v:g}")
        if self.hi is not None and v > self.hi:
            raise OptionError(f"{name} must be at most {self.hi:g}, got {v:g}")
        return v


#: the most residual shapes a tracked rig may have (``residuals``): each is a morph target of the
#: whole mesh in an export, so a rig with more would rival the vertex animation it replaces
MAX_RESIDUAL_SHAPES = 64
#: ``residuals="auto"``: the replay error the rank reaches, % of the bounding-box diagonal (the worst
#: vertex of any frame, and the RMS over vertices and frames), with the fewest shapes
RESIDUAL_TARGET_MAX = 1.0
RESIDUAL_TARGET_RMS = 0.2
#: ``residuals="auto"``: at most this share of the frames (each shape stands for that many frames)
RESIDUAL_FRAME_SHARE = 0.25

#: the link count's range (not a :class:`FitOptions` field: ``fit``'s own argument); the scan's
#: usable triangles lower its upper bound (``within``)
LINKS = IntRange(1)


@dataclasses.dataclass(frozen=True)
class Choice:
    value: str
    label: str
    description: str


@dataclasses.dataclass(frozen=True)
class Option:
    """What a front end needs to show and check one fit setting."""
    label: str
    description: str
    type: type
    choices: tuple = ()              # of Choice; empty for numbers
    unit: str = ""
    min: float | None = None         # inclusive bound
    min_exclusive: bool = False      # the bound itself is not allowed (p_max > 1)
    soft_min: float | None = None    # where the Blender slider starts
    soft_max: float | None = None
    max: float | None = None
    why_max: str = ""                # said after the upper bound when it is exceeded
    optional: bool = False           # None allowed ("off")
    auto: bool = False               # None allowed: "auto", chosen from the data
    tracked_only: bool = False       # only matters for tracked scans
    greens_only: bool = False        # only matters for Green's-matrix scans
    advanced: bool = False           # for experts and comparisons; the defaults are the product

    @property
    def values(self) -> tuple:
        return tuple(c.value for c in self.choices)

    @property
    def range(self) -> "IntRange | FloatRange":
        """The bounds above as a validator (numbers only): the command line checks its flags with
        it, naming the flag in the message."""
        if self.type is int:
            return IntRange(None if self.min is None else int(self.min),
                            None if self.max is None else int(self.max), self.why_max)
        return FloatRange(self.min, self.max, lo_open=self.min_exclusive)


def _field(default, **meta):
    return dataclasses.field(default=default, metadata={"option": Option(**meta)})


@dataclasses.dataclass(frozen=True)
class FitOptions:
    """Every setting of a fit except the link count (paper §5–§7; docs/method_notes.md §2–§5,
    docs/method_notes_model.md §6–§10)."""
    mode: str = _field(
        "global", label="Mode", type=str,
        description="One articulated model for all fields, or one per load point of a Green's scan",
        choices=(Choice("global", "Global", "One articulated model for all fields (the main path)"),
                 Choice("pseudo", "Pseudo", "Fit each load point separately (pseudo-articulation, "
                                            "paper §7.2); the rig is built from one load point's "
                                            "model")),
        greens_only=True)
    motion: str = _field(
        "robust", label="Motion", type=str,
        description="How each link's rigid motion is estimated",
        choices=(Choice("robust", "Robust", "Each link moves with its motion centroid: the member "
                                            "triangle whose motion agrees exactly with at least "
                                            "half of the link (paper §6; stays correct with up to "
                                            "50% outlying triangles)"),
                 Choice("lsq", "Least Squares", "Least-squares rigid motion fitted to all the "
                                                "link's triangles (for comparison)")),
        advanced=True)
    p_max: float | None = _field(
        None, label="Max Hardening", type=float, unit="probe loads", min=1.0, min_exclusive=True,
        soft_max=20.0, optional=True, greens_only=True,
        description="Strain hardening limit p_max in units of the probe load (> 1, paper §7.1); "
                    "off by default (linear response)")
    max_links: int = _field(
        30, label="Max Links", type=int, min=1, max=MAX_AUTO_LINKS, soft_max=64,
        why_max=" (the error curve segments the counts up to it)",
        description="Links auto: the largest link count tried")
    memory_budget: float = _field(
        2.0, label="Memory Budget", type=float, unit="GB", min=0.0, min_exclusive=True, max=1e6,
        soft_min=0.1, soft_max=64.0,
        advanced=True,
        description="Most memory the fit may use, in GB (2^30 bytes). With Reduced Method 'auto' a "
                    "scan whose full method would need more switches to the reduced method on "
                    "patches instead of running out of memory; it also sets how many patches the "
                    "reduced method uses")
    jobs: int = _field(
        0, label="Jobs", type=int, min=0, max=256, soft_max=64, advanced=True,
        description="Processes the fit's independent work is spread over (0: one per core of "
                    "the machine; 1: the serial path, the same rig)")
    reduce: str = _field(
        "auto", label="Reduced Method", type=str,
        description="Segment small patches of triangles instead of every triangle (large scans)",
        choices=(Choice("auto", "Auto", "Use the reduced method on patches only when the full "
                                        "method would need more memory than the Memory Budget "
                                        "(the fit then says so)"),
                 Choice("on", "On", "Always use the reduced method: the method on small patches of "
                                    "triangles whose motions agree, seams refined per triangle "
                                    "(fast, bounded memory)"),
                 Choice("off", "Off", "Always use the paper's full method over all triangle pairs "
                                      "(memory grows with the square of the triangle count)")),
        advanced=True)
    strategy: str = _field(
        "auto", label="Strategy", type=str,
        description="How the fields are combined into links",
        choices=(Choice("auto", "Auto", "Paper for Green's scans, summed for tracked scans"),
                 Choice("summed", "Summed", "One clustering tree over the fields' summed distances "
                                            "(bounded memory; better on smoothly skinned "
                                            "characters)"),
                 Choice("paper", "Paper", "The paper's per-field trees with split and merge "
                                          "(§5.2; two levels for Green's scans)")),
        advanced=True)
    skin: str = _field(
        "auto", label="Skin", type=str,
        description="How the skin weights are made",
        choices=(Choice("auto", "Auto", "Refined for tracked scans, seam-blended for Green's scans"),
                 Choice("seam", "Seam", "Weights blended across the seams between links (paper)"),
                 Choice("refined", "Refined", "Per-vertex convex weights (at most 4 nearby links) "
                                              "solved by least squares over all fields: reproduces "
                                              "the capture closely with few bones")),
        advanced=True)

    residuals: int | None = _field(
        None, label="Residual Shapes", type=int, min=0, max=MAX_RESIDUAL_SHAPES, soft_max=16, auto=True,
        tracked_only=True,
        description="Tracked scans: how many principal shapes of what the skin leaves (residual shape "
                    "keys, one weight per frame). Auto: the fewest whose replay error reaches "
                    f"max {RESIDUAL_TARGET_MAX:g}%, RMS {RESIDUAL_TARGET_RMS:g}% of the bounding-box "
                    f"diagonal, at most {RESIDUAL_FRAME_SHARE:.0%} of the frames; 0: skin only, no shape keys")

    def __post_init__(self):
        for f in dataclasses.fields(self):
            opt = f.metadata["option"]
            v = getattr(self, f.name)
            if v is None and (opt.optional or opt.auto):
                continue
            if opt.choices:
                if not isinstance(v, str) or v not in opt.values:
                    raise OptionsError(f"{f.name} must be one of {', '.join(opt.values)}; got {v!r}", f.name)
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise OptionsError(f"{f.name} must be a number; got {v!r}", f.name)
            if opt.type is int and int(v) != v:
                raise OptionsError(f"{f.name} must be a whole number; got {v!r}", f.name)
            if not math.isfinite(v):
                raise OptionsError(f"{f.name} must be finite; got {v!r}", f.name)
            low_ok = opt.min is None or (v > opt.min if opt.min_exclusive else v >= opt.min)
            if not low_ok:
                rel = "a number greater than" if opt.min_exclusive else "at least"
                raise OptionsError(f"{f.name} must be {rel} {opt.min:g}"
                                   + (" (or off)" if opt.optional else "") + f"; got {v!r}", f.name)
            if opt.max is not None and v > opt.max:
                raise OptionsError(f"{f.name} must be at most {opt.max:g}; got {v!r}", f.name)
            object.__setattr__(self, f.name, opt.type(v))

    # ------------------------------------------------------------------ reading
    @classmethod
    def declaration(cls) -> dict:
        """``{name: (default, Option)}`` in declaration order, for the front ends."""
        return {f.name: (f.default, f.metadata["option"]) for f in dataclasses.fields(cls)}

    @property
    def budget_bytes(self) -> float:
        return float(self.memory_budget) * GB

    @property
    def processes(self) -> int:
        """The processes :attr:`jobs` asks for (0: the CPUs this process may use)."""
        if self.jobs:
            return int(self.jobs)
        from .procs import cores
        return cores()

    @property
    def reduce_arg(self) -> bool | None:
        """The segmenter's switch: None (decide by the budget), True, False."""
        return {"auto": None, "on": True, "off": False}[self.reduce]

    def replace(self, **changes) -> "FitOptions":
        return dataclasses.replace(self, **changes)

    def resolved(self, kind: str) -> "FitOptions":
        """The "auto" rules for a scan of ``kind`` (``"greens"`` or ``"tracked"``): strategy paper
        for Green's scans, summed for tracked ones; skin seam for Green's scans, refined for
        tracked ones. ``reduce`` stays: it depends on the scan's size, not only its kind."""
        greens = kind == "greens"
        return self.replace(
            strategy=("paper" if greens else "summed") if self.strategy == "auto" else self.strategy,
            skin=("seam" if greens else "refined") if self.skin == "auto" else self.skin)

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def describe(name: str) -> str:
    """The one-line description of option ``name`` (with its unit), for help texts."""
    opt = FitOptions.declaration()[name][1]
    return opt.description
