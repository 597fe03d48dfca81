"""The fit and the segmentation in a worker process (:mod:`procs`), as the Blender operators run them.

Two halves, both bpy-free:

- what the child runs (``jobs:fit``, ``jobs:segment``, ``jobs:cached``): the scan arrives as arrays,
  the options as JSON; the result goes back as the arrays of a result file
  (:func:`fit.result_arrays`), never as a pickle;
- :class:`Session`, the parent's side: one worker process kept from call to call, so the
  segmentation the child's :mod:`api` keeps (its O(T²) distances and trees) serves the next
  preview or fit of the same scan, as it did in one process. Cancelling, a crash or a memory
  failure ends that process; the next call starts a fresh one.

The worker's memory limit is :data:`LIMIT_FACTOR` times the fit's memory budget (plus
:data:`LIMIT_SLACK`): the budget is what the fit plans to use, the limit what stops a runaway
fit before it takes the machine's memory (and the user's session with it).
"""
from __future__ import annotations

import dataclasses
import os

from . import procs
from .options import FitOptions
from .scan import Scan

#: the worker's memory limit over the fit's planned budget, and the bytes added to it (imports,
#: the scan's own arrays)
LIMIT_FACTOR = 2.0
LIMIT_SLACK = 0.5 * 2**30
_SCAN_ARRAYS = ("vertices", "faces", "greens", "displacements", "load_vertices", "support_vertices")
CORE = procs.CORE


def scan_message(scan: Scan):
    """``(arrays, values)``: ``scan`` as a worker call's arrays and JSON values."""
    arrays = {k: getattr(scan, k) for k in _SCAN_ARRAYS if getattr(scan, k) is not None}
    return arrays, {"probe_load": float(scan.probe_load)}


def _scan(arrays, params) -> Scan:
    return Scan(**{k: arrays[k] for k in _SCAN_ARRAYS if k in arrays},
                probe_load=float(params["probe_load"]))


def _options(params) -> FitOptions:
    return FitOptions(**params["options"])


def _links(params):
    return params["links"] if params["links"] == "auto" else int(params["links"])


# ----------------------------------------------------------------------- in the worker process

def fit(arrays, params, report):
    """The child's half of :meth:`Session.fit`: :func:`api.fit`; the result's arrays."""
    from . import api, result as _result
    result = api.fit(_scan(arrays, params), _links(params), _options(params), report.progress)
    extra = {"pid": os.getpid(), "link_errors": [float(e) for e in result.link_errors],
             "reduced": bool(result.reduced),
             "groups": result.groups,
             "estimate": None if result.estimate is None else dataclasses.asdict(result.estimate)}
    return extra, _result.result_arrays(result)


def segment(arrays, params, report):
    """The child's half of :meth:`Session.segment`: :func:`api.segment`'s labels."""
    from . import api
    labels, reduced, notes = api.segment(_scan(arrays, params), _links(params), _options(params),
                                         report.progress)
    return ({"pid": os.getpid(), "reduced": bool(reduced), "notes": [str(n) for n in notes]},
            {"labels": labels})


def cached(arrays, params, report):
    """The child's half of :meth:`Session.cached`: which kept segmentation would serve."""
    from . import api
    seg = api.cached(_scan(arrays, params), _options(params))
    if seg is None:
        return {"token": None, "reduced": False}
    if getattr(seg, "kept_token", None) is None:
        _TOKENS.append(None)
        seg.kept_token = f"{os.getpid()}-{len(_TOKENS)}"     # unique across workers and their lives
    return {"token": seg.kept_token, "reduced": bool(seg.reduced)}


_TOKENS = []


# ---------------------------------------------------------------------------- the parent's side

@dataclasses.dataclass(frozen=True)
class Kept:
    """A segmentation the worker keeps: ``token`` names it (equal while the same one serves),
    ``reduced``: whether it is the reduced method's."""
    token: str
    reduced: bool


def result_from(values: dict, arrays: dict, options: FitOptions):
    """The :class:`fit.FitResult` of a ``fit`` call's reply (``options``: as the call was asked)."""
    from . import cost, result as _result
    result = _result.result_from_arrays(arrays)
    result.options = options                  # as asked, as :func:`api.fit` keeps it
    result.link_errors, result.reduced = values["link_errors"], values["reduced"]
    result.groups = values["groups"]
    result.estimate = None if values["estimate"] is None else cost.Estimate(**values["estimate"])
    return result


class Session:
    """One worker process for the fits of a front end (Blender): started on the first call,
    kept while calls succeed (with the segmentations its :mod:`api` keeps), ended by
    :meth:`close`, :meth:`kill`, or any call that fails other than by raising in the fit."""

    def __init__(self, memory_limit: float | None = None):
        self.memory_limit = memory_limit      # bytes; None: from each call's memory budget
        self.worker = None
        self.call = None           # the running call, if any

    @property
    def pid(self):
        return None if self.worker is None else self.worker.pid

    def _worker(self, options: FitOptions) -> procs.Worker:
        limit = self.memory_limit or LIMIT_FACTOR * options.budget_bytes + LIMIT_SLACK
        w = self.worker
        if w is not None and (not w.alive() or w.memory_limit != limit):
            self.close()
        if self.worker is None:
            self.worker = procs.Worker(memory_limit=limit, preload=[f"{CORE}.api"],
                                       name="artdef-fit").start()
        return self.worker

    def submit(self, function: str, scan: Scan, links, options: FitOptions | None) -> procs.Call:
        """Start ``function`` (``fit``, ``segment``, ``cached``) on ``scan`` in the worker."""
        options = options or FitOptions()
        arrays, values = scan_message(scan)
        values.update(options=options.as_dict(), links=links)
        self.call = self._worker(options).submit(f"{CORE}.jobs:{function}", arrays, values)
        return self.call

    def outcome(self, call: procs.Call):
        """``(values, arrays)`` of a finished call; a failure other than the fit's own exception
        ends the worker (its state is not trusted), then raises :class:`procs.WorkerError`."""
        try:
            return call.result()
        except procs.WorkerError as err:
            if err.kind != "error":
                self.close()
            raise
        finally:
            if self.call is call:
                self.call = None

    def kill(self) -> None:
        """End the worker now (Esc): within a second, whatever it was doing."""
        if self.worker is not None:
            self.worker.kill()
        self.close()

    def close(self) -> None:
        if self.worker is not None:
            self.worker.close()
            self.worker = None

    # -- blocking conveniences (scripts, the background path)
    def fit(self, scan: Scan, links, options=None, progress=None):
        """:func:`api.fit` in the worker: a :class:`fit.FitResult`. ``progress(stage, fraction)``
        is called here, in the caller's process, for each stage the worker reports; returning
        True kills the worker and raises :class:`fit.FitCancelled`."""
        options = options or FitOptions()
        values, arrays = self._wait(self.submit("fit", scan, links, options), progress)
        return result_from(values, arrays, options)

    def segment(self, scan: Scan, links: int, options=None, progress=None):
        """:func:`api.segment` in the worker: ``(labels (T,), reduced, notes)``."""
        values, arrays = self._wait(self.submit("segment", scan, links, options), progress)
        return arrays["labels"], values["reduced"], values["notes"]

    def cached(self, scan: Scan, options=None):
        """The worker's kept segmentation for ``scan`` and ``options`` (:class:`Kept`), or None:
        nothing kept, or no worker running."""
        if self.worker is None or not self.worker.alive():
            return None
        values, _ = self._wait(self.submit("cached", scan, 0, options), None)
        return None if values["token"] is None else Kept(values["token"], values["reduced"])

    def _wait(self, call, progress):
        def each(message):
            if "progress" in message and progress is not None:
                return bool(progress(*message["progress"]))
            return False
        try:
            call.wait(each)
        except procs.WorkerError:
            pass
        return self.outcome_or_cancelled(call)

    def outcome_or_cancelled(self, call):
        """:meth:`outcome`, with a cancelled call raised as :class:`fit.FitCancelled`."""
        from .result import FitCancelled
        try:
            return self.outcome(call)
        except procs.WorkerError as err:
            if err.kind == "cancelled":
                raise FitCancelled("cancelled") from None
            raise
