# SPDX-License-Identifier: GPL-3.0-or-later
"""The work of Fit and Preview Links, run off the main thread: no bpy access in a job.

A job calls the core (:func:`artdef_addon.fit` / :func:`artdef_addon.segment`) with a progress
callback that records the stage for the status bar and answers a cancel (Esc, or a hook of
:data:`.state.PROGRESS_HOOKS`).
"""

import threading
import time

from ..artdef_addon import api as _api
from ..artdef_addon.options import FitOptions
from . import fitquality, io
from .props import options_from
from .state import PROGRESS_HOOKS


#: Status-bar wording of the progress stages the core reports; ``True``: the
#: stage reports fractions (show a percentage), ``False``: one report at its start.
_STAGES = {
    "start": ("starting", False),
    "features": ("motions per triangle and field", True),
    "distances": ("pairwise distances", True),
    "cluster": ("clustering", True),
    "merge": ("merging pieces into links", True),
    "links": ("choosing the link count", True),
    "segment": ("segmenting into links", False),
    "motions": ("link motions", False),
    "relabel": ("relabelling faces by their skin", False),
    "skin": ("skin weights", False),
    "split": ("splitting links that hold two bones", False),
    "joints": ("joints and tree", False),
    "bones": ("bone frames", False),
    "pose": ("pose parameters", False),
    "residuals": ("residual and errors", False),
    "pseudo": ("one model per load point", True),
    "done": ("finishing", False),
}


def stage_text(stage, fraction):
    """A stage report as the status bar shows it: ``merge column 2`` -> readable words."""
    label, fractional = _STAGES.get(stage, (None, True))
    if label is None and stage.startswith("merge column "):
        label = f"merging pieces into links (load point {stage[len('merge column '):]})"
    if label is None:
        label = stage
    if not fractional:
        return label
    return f"{label} {100 * min(max(fraction, 0.0), 1.0):.0f}%"


class _FitJob:
    """One fit: the core's public :func:`artdef_addon.fit` runs here (possibly in a worker
    thread); no bpy access."""

    def __init__(self, scan, links, options=None, load_index=0):
        self.scan, self.links = scan, links            # links: int or "auto"
        self.options = options if options is not None else FitOptions()
        self.load_index = load_index
        self.link_reason = ""
        self.model = None            # the result whose rig is built (pseudo: one load point's)
        self.vertex_residual = None  # (N,) articulation residual of ``model``
        self.stage, self.fraction = "start", 0.0
        self.links_fraction = None   # while Auto Links tries link counts: how far it is
        self.cancel = threading.Event()
        self.result = None
        self.error = None
        self.seconds = 0.0
        self.thread = None

    def progress(self, stage, fraction):
        self.stage, self.fraction = stage, float(fraction)
        if stage == "links":
            # the search reports 1 when it has chosen; a fit of that count may follow
            self.links_fraction = float(fraction) if fraction < 1.0 else None
        if self.cancel.is_set():
            return True
        return any(hook(stage, fraction) for hook in list(PROGRESS_HOOKS))

    def run(self, on_progress=None):
        def callback(stage, fraction):
            stop = self.progress(stage, fraction)
            if on_progress is not None:
                on_progress(stage, fraction)
            return stop
        t0 = time.perf_counter()
        try:
            self.result = _api.fit(self.scan, self.links, self.options, callback)
            self.links_fraction = None
            self.links, self.link_reason = self.result.n_links, self.result.link_reason
            self.model, self.vertex_residual = model_of(self.result, self.scan, self.load_index)
        except BaseException as err:  # reported on the main thread
            self.error = err
        self.seconds = time.perf_counter() - t0

    @property
    def notes(self):
        """The core's notes on this fit (e.g. that and why the reduced method ran)."""
        return [str(n) for n in (getattr(self.result, "notes", None) or [])]

    @property
    def reduced(self):
        return bool(getattr(self.result, "reduced", False))

    def status_text(self):
        """What the status bar shows while the job runs."""
        text = stage_text(self.stage, self.fraction)
        if self.links_fraction is not None and self.stage != "links":
            # Auto Links segments every count up to Max Links: say where it is overall
            text = f"{stage_text('links', self.links_fraction)} ({text})"
        return text

    def start_thread(self):
        self.thread = threading.Thread(target=self.run, name="artdef-fit", daemon=True)
        self.thread.start()


def model_of(result, scan, load_index=0):
    """``(model, vertex residual (N,))``: the result whose rig is built — the result, or in pseudo
    mode load point ``load_index``'s model (None if there is none) — and its per-vertex
    articulation residual. Numpy only (runs in the fit's thread)."""
    model, fields = result, None
    if result.mode == "pseudo":
        pseudo = result.pseudo or []
        if load_index >= len(pseudo):
            return None, None
        model = pseudo[load_index]
        fields = result.groups[load_index] if result.groups else [3 * load_index + d for d in range(3)]
    return model, fitquality.vertex_residual(model, scan, fields)


class _PreviewJob:
    """Segment one scan for Preview Links (possibly in a worker thread); no bpy access.

    The core's :func:`artdef_addon.segment` keeps the segmentation, which the next preview or fit
    of the same scan and method settings reuses; the progress callback reports the stage and
    cancels on Esc, like the fit's.
    """

    def __init__(self, obj_name, stored, options, links):
        self.obj_name, self.stored, self.options = obj_name, stored, options
        self.links = links
        self.cached = _api.cached(stored.scan, options) is not None
        self.labels = None
        self.error = None
        self.stage, self.fraction = "start", 0.0
        self.cancel = threading.Event()
        self.thread = None

    def progress(self, stage, fraction):
        self.stage, self.fraction = stage, float(fraction)
        if self.cancel.is_set():
            return True
        return any(hook(stage, fraction) for hook in list(PROGRESS_HOOKS))

    def run(self):
        try:
            self.labels, _, _ = _api.segment(self.stored.scan, self.links, self.options, self.progress)
        except BaseException as err:  # reported on the main thread
            self.error = err

    def status_text(self):
        return stage_text(self.stage, self.fraction)

    def start_thread(self):
        self.thread = threading.Thread(target=self.run, name="artdef-preview", daemon=True)
        self.thread.start()


def _preview_job(obj, links):
    """A :class:`_PreviewJob` for ``obj``'s scan and its Reduced Method / Memory Budget settings."""
    return _PreviewJob(obj.name, io.read_scan(obj), options_from(obj.artdef), links)
