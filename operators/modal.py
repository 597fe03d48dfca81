# SPDX-License-Identifier: GPL-3.0-or-later
"""The interactive path shared by Fit and Preview Links: the worker process runs the job, a modal
timer polls its progress, Esc ends it."""

import traceback

from ..artdef_addon import procs as _procs
from ..artdef_addon import result as _result
from ..artdef_addon import scan as _scan

#: exceptions of the core that mean bad input (reported as their one line, no traceback)
_BAD_INPUT = {"ScanError", "OptionsError", "BadFile", "ValueError"}


class _WorkerModal:
    """The interactive path shared by Fit and Preview Links: the job runs in the worker process,
    a modal timer polls its stage and progress, Esc ends it, the view can still be navigated.

    The operator sets ``_what`` (status-bar word) and implements ``_finish(context, job)``.
    """
    _what = "job"
    _job = None
    _timer = None

    def _start_modal(self, context, job):
        self._job = job
        wm = context.window_manager
        wm.progress_begin(0, 1000)
        self._timer = wm.event_timer_add(0.1, window=context.window)
        wm.modal_handler_add(self)
        job.start()
        self._status(context, job.status_text())
        return {'RUNNING_MODAL'}

    def _status(self, context, text):
        if context.workspace is not None:
            context.workspace.status_text_set(
                None if text is None else f"ArtDef {self._what}: {text} — Esc to cancel")

    def _end(self, context):
        wm = context.window_manager
        if self._timer is not None:
            wm.event_timer_remove(self._timer)
            self._timer = None
        wm.progress_end()
        self._status(context, None)

    def modal(self, context, event):
        job = self._job
        if event.type == 'ESC':
            job.cancel()            # the worker is killed: ended within a second
            self._end(context)
            self.report({'WARNING'}, f"{self._what.capitalize()} cancelled; the scene is unchanged")
            return {'CANCELLED'}
        if event.type == 'TIMER':
            finished = job.poll()   # never blocks
            context.window_manager.progress_update(int(1000 * min(max(job.fraction, 0.0), 1.0)))
            self._status(context, job.status_text())
            if finished:
                self._end(context)
                return self._finish(context, job)
            return {'RUNNING_MODAL'}
        if event.type in {'MIDDLEMOUSE', 'WHEELUPMOUSE', 'WHEELDOWNMOUSE', 'TRACKPADPAN',
                          'TRACKPADZOOM', 'MOUSEMOVE', 'INBETWEEN_MOUSEMOVE'}:
            return {'PASS_THROUGH'}  # let the user navigate the view while it runs
        return {'RUNNING_MODAL'}  # block editing: the job works on a snapshot

    def _failed(self, job):
        """Report a cancelled or failed job (True), or nothing (False).  Main thread only."""
        err = job.error
        what = self._what.capitalize()
        if err is None:
            return False
        if isinstance(err, _result.FitCancelled):
            self.report({'WARNING'}, f"{what} cancelled; the scene is unchanged")
        elif isinstance(err, _procs.WorkerError):
            bug = err.kind == "error" and err.type_name not in _BAD_INPUT
            if bug and err.details:
                print(err.details)          # a bug in the worker: its traceback to the console
            tag = f" ({err.type_name})" if bug else ""
            self.report({'ERROR'}, f"{what} failed{tag}: {err}"
                        + ("" if err.kind == "error" else "; the scene is unchanged"))
        elif isinstance(err, (_scan.ScanError, ValueError)):
            self.report({'ERROR'}, f"{what} failed: {err}")
        else:
            traceback.print_exception(type(err), err, err.__traceback__)
            self.report({'ERROR'}, f"{what} failed ({type(err).__name__}): {err}")
        return True

    def cancel(self, context):  # window closed / file loaded while running
        if self._job is not None:
            self._job.cancel()
        self._end(context)
