# SPDX-License-Identifier: GPL-3.0-or-later
"""The work of Fit and Preview Links, run in the add-on's worker process (:mod:`.worker`): no
bpy access in a job. The worker's progress reports give the stage for the status bar; a cancel
(Esc, or a hook of :data:`.state.PROGRESS_HOOKS`) ends the worker.
"""

from . import fitquality, io
from .props import options_from
from .worker import FitJob, PreviewJob, cached


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


class _FitJob(FitJob):
    """One fit in the add-on's worker process (:mod:`.worker`); no bpy access."""

    def __init__(self, scan, links, options=None, load_index=0):
        super().__init__(scan, links, options, load_index, model_of=model_of)

    def status_text(self):
        """What the status bar shows while the job runs."""
        text = stage_text(self.stage, self.fraction)
        if self.links_fraction is not None and self.stage != "links":
            # Auto Links segments every count up to Max Links: say where it is overall
            text = f"{stage_text('links', self.links_fraction)} ({text})"
        return text


def model_of(result, scan, load_index=0):
    """``(model, vertex residual (N,))``: the result whose rig is built — the result, or in pseudo
    mode load point ``load_index``'s model (None if there is none) — and its per-vertex
    articulation residual. Numpy only."""
    model, fields = result, None
    if result.mode == "pseudo":
        pseudo = result.pseudo or []
        if load_index >= len(pseudo):
            return None, None
        model = pseudo[load_index]
        fields = result.groups[load_index] if result.groups else [3 * load_index + d for d in range(3)]
    return model, fitquality.vertex_residual(model, scan, fields)


class _PreviewJob(PreviewJob):
    """Segment one scan for Preview Links in the worker process; no bpy access.

    The worker keeps the segmentation, which the next preview or fit of the same scan and method
    settings reuses; Esc ends the worker like the fit's.
    """

    def __init__(self, obj_name, stored, options, links):
        super().__init__(stored.scan, links, options)
        self.obj_name, self.stored = obj_name, stored
        self.cached = cached(stored.scan, options) is not None

    def status_text(self):
        return stage_text(self.stage, self.fraction)


def _preview_job(obj, links):
    """A :class:`_PreviewJob` for ``obj``'s scan and its Reduced Method / Memory Budget settings."""
    return _PreviewJob(obj.name, io.read_scan(obj), options_from(obj.artdef), links)
