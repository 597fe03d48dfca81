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
from . import fit, samples, scan
from .api import load_scan, segment
from .fit import FitCancelled, FitResult
from .options import FitOptions, OptionsError
from .scan import Scan, ScanError

__all__ = ["fit", "load_scan", "segment", "FitOptions", "OptionsError", "FitResult", "FitCancelled",
           "Scan", "ScanError", "samples", "scan"]
