"""artdef core: articulated deformation from displacement fields (Lang, Pai & Seidel, GI 2003).

Plain numpy/scipy, no ``bpy``. The public API (the command line, the Blender operators and
scripts all use it):

>>> import artdef_addon
>>> scan = artdef_addon.samples.make("rod")            # or artdef_addon.load_scan("scan.npz")
>>> result = artdef_addon.fit(scan, links=3)           # or links="auto"
>>> result.n_links
3

``artdef_addon.fit(scan, links, options=None, progress=None)`` takes a :class:`FitOptions`
(every fit setting, declared once in :mod:`artdef_addon.options`) and returns a
:class:`FitResult` with ``save(path)`` / ``FitResult.load(path)``.
"""
import sys as _sys

if _sys.argv[:1] == ["-m"]:
    # ``python -m artdef_addon`` (the command line): a Ctrl-C while numpy and scipy load gives the
    # command line's one line, not a traceback; nothing has been read or written yet.
    # ``__main__`` puts Python's own handler back before the command runs.
    import signal as _signal

    def _interrupted_while_loading(signum, frame):
        what = "terminated" if signum == _signal.SIGTERM else "interrupted"
        _sys.stderr.write(f"artdef: error: {what}; no file was written or changed\n")
        _sys.stderr.flush()
        import os as _os
        _os._exit(128 + signum)

    try:
        _signal.signal(_signal.SIGINT, _interrupted_while_loading)
        _signal.signal(_signal.SIGTERM, _interrupted_while_loading)
    except ValueError:      # not the main thread
        pass

from . import samples, scan
from .api import fit, load_scan, segment
from .result import FitCancelled, FitResult
from .options import FitOptions, OptionsError
from .scan import Scan, ScanError

__all__ = ["fit", "load_scan", "segment", "FitOptions", "OptionsError", "FitResult", "FitCancelled",
           "Scan", "ScanError", "samples", "scan"]
