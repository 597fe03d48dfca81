# SPDX-License-Identifier: GPL-3.0-or-later
"""The fit and Preview Links' segmentation as jobs in the add-on's worker process (no bpy here).

Blender does not support Python threads beside its main loop, and a fit that runs out of memory
must not take the user's session down, so the core runs in one worker process
(:class:`artdef_addon.jobs.Session`, :data:`SESSION`): the operator reads the mesh on the main
thread and starts a job (:meth:`FitJob.start`), a modal timer calls :meth:`poll` for the stage and
progress, Esc calls :meth:`cancel` (the worker ends within a second), and when the job is done the
operator builds the rig from :attr:`FitJob.result` on the main thread. A worker that crashes, is
killed or runs out of memory is one line in :attr:`error`; Blender and its scene are untouched.
The worker outlives a job, so the segmentation it keeps serves the next preview or fit.
"""

import time

from ..artdef_addon import jobs as _jobs
from ..artdef_addon import procs as _procs
from ..artdef_addon.options import FitOptions
from ..artdef_addon.result import FitCancelled
from .state import PROGRESS_HOOKS

#: the add-on's one worker process (started by the first job, ended on unregister)
SESSION = _jobs.Session()

#: the process id that computed the last job's result (scripts, tests: not Blender's own)
LAST_PID = None


class _Job:
    """One call into :data:`SESSION`: :meth:`start`, then :meth:`poll` until it returns True
    (or :meth:`wait`); :attr:`error` holds why it gave no result (:class:`FitCancelled` when
    cancelled, a :class:`procs.WorkerError` otherwise)."""

    _function = ""

    def __init__(self, scan, links, options=None):
        self.scan, self.links = scan, links
        self.options = options if options is not None else FitOptions()
        self.stage, self.fraction = "start", 0.0
        self.error = None
        self.seconds = 0.0
        self.call = None
        self.finished = False
        self._t0 = None

    @property
    def pid(self):
        """The worker's process id (None before :meth:`start`)."""
        return SESSION.pid

    def start(self):
        self._t0 = time.perf_counter()
        try:
            self.call = SESSION.submit(self._function, self.scan, self.links, self.options)
        except (_procs.WorkerError, OSError) as err:
            self._end(err if isinstance(err, _procs.WorkerError)
                      else _procs.WorkerError("crashed", f"the worker process could not start: {err}"))
        return self

    def progress(self, stage, fraction) -> bool:
        """A report of the worker's: recorded for the status bar; True (cancel) if a hook of
        :data:`.state.PROGRESS_HOOKS` asks."""
        self.stage, self.fraction = stage, float(fraction)
        return any(hook(stage, fraction) for hook in list(PROGRESS_HOOKS))

    def poll(self) -> bool:
        """Read the worker's reports (never blocks); True once the job has ended."""
        if self.finished:
            return True
        for message in self.call.poll():
            if "progress" in message and self.progress(*message["progress"]):
                self.cancel()
                return True
        if not self.call.done:
            return False
        global LAST_PID
        try:
            values, arrays = SESSION.outcome_or_cancelled(self.call)
            LAST_PID = values.get("pid")
            self._done(values, arrays)
        except (FitCancelled, _procs.WorkerError) as err:
            self._end(err)
            return True
        self._end(None)
        return True

    def wait(self, on_poll=None):
        """Block until the job ends (scripts, background mode); ``on_poll()`` after each poll."""
        while not self.poll():
            if on_poll is not None:
                on_poll()
            try:
                SESSION.worker.process.wait(0.05)
            except Exception:       # TimeoutExpired, or the worker already gone
                pass
        return self

    def cancel(self):
        """End the job now (Esc): the worker is killed within a second; nothing was produced."""
        if not self.finished:
            SESSION.kill()
            self._end(FitCancelled("cancelled"))

    def _end(self, error):
        self.error = error
        self.finished = True
        self.seconds = time.perf_counter() - (self._t0 or time.perf_counter())

    def _done(self, values, arrays):
        raise NotImplementedError


class FitJob(_Job):
    """One fit (:func:`artdef_addon.fit`) in the worker; ``model_of(result, scan, load_index)``
    (the operators' choice of the model whose rig is built) runs here when the result is back."""

    _function = "fit"

    def __init__(self, scan, links, options=None, load_index=0, model_of=None):
        super().__init__(scan, links, options)
        self.load_index = load_index
        self.model_of = model_of
        self.link_reason = ""
        self.links_fraction = None   # while Auto Links tries link counts: how far it is
        self.result = None
        self.model = None            # the result whose rig is built (pseudo: one load point's)
        self.vertex_residual = None  # (N,) articulation residual of ``model``

    def progress(self, stage, fraction):
        if stage == "links":
            # the search reports 1 when it has chosen; a fit of that count may follow
            self.links_fraction = float(fraction) if fraction < 1.0 else None
        return super().progress(stage, fraction)

    def _done(self, values, arrays):
        self.result = _jobs.result_from(values, arrays, self.options)
        self.links_fraction = None
        self.links, self.link_reason = self.result.n_links, self.result.link_reason
        if self.model_of is not None:
            self.model, self.vertex_residual = self.model_of(self.result, self.scan, self.load_index)

    @property
    def notes(self):
        """The core's notes on this fit (e.g. that and why the reduced method ran)."""
        return [str(n) for n in (getattr(self.result, "notes", None) or [])]

    @property
    def reduced(self):
        return bool(getattr(self.result, "reduced", False))


class PreviewJob(_Job):
    """Preview Links' segmentation (:func:`artdef_addon.segment`) in the worker: :attr:`labels`."""

    _function = "segment"

    def __init__(self, scan, links, options=None):
        super().__init__(scan, links, options)
        self.labels = None

    def _done(self, values, arrays):
        self.labels = arrays["labels"]


def cached(scan, options=None):
    """The worker's kept segmentation for ``scan`` and ``options`` (``jobs.Kept``), or None."""
    try:
        return SESSION.cached(scan, options)
    except (_procs.WorkerError, FitCancelled):
        return None


def forget():
    """End the worker and the segmentations it keeps."""
    SESSION.close()
