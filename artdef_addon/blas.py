"""One BLAS thread for stretches of many small matrix products.

The link-count search's tree curve (:func:`linkcount.articulation_error_curve`) segments the scan
for every count: thousands of distance blocks, each a (rows × 17) @ (17 × cols) product
(:func:`metric.residuals`). OpenBLAS runs products of that size on all its threads, and on a busy
machine its threads spend more time waiting for each other than multiplying: on this project's
2-core reference machine under load, CesiumMan's curve took 21-29 s with numpy's default threads
and 9.6 s with one, the same errors to the bit (``docs/speed.md``, "The link-count search").

:func:`single_threaded` sets OpenBLAS (the BLAS of numpy's wheels and Blender's numpy) to one
thread for a ``with`` block and restores the count after. Where numpy uses another BLAS, or the
library cannot be found, it does nothing. The setting is process-wide.
"""
from __future__ import annotations

import contextlib
import ctypes
import glob
import os

_SETTERS = ("scipy_openblas_set_num_threads64_", "scipy_openblas_set_num_threads",
            "openblas_set_num_threads64_", "openblas_set_num_threads")
_found = None
_depth = 0
_saved = None


def _openblas():
    """(set_num_threads, get_num_threads) of the OpenBLAS numpy loaded, or None."""
    global _found
    if _found is None:
        _found = ()
        try:
            import numpy
            root = os.path.dirname(os.path.dirname(os.path.abspath(numpy.__file__)))
            paths = []
            for pattern in ("numpy.libs/*openblas*", "numpy/.dylibs/*openblas*", "numpy/_core/*openblas*"):
                paths += glob.glob(os.path.join(root, pattern))
            for path in sorted(paths):
                try:
                    lib = ctypes.CDLL(path)
                except OSError:
                    continue
                for name in _SETTERS:
                    set_ = getattr(lib, name, None)
                    get_ = getattr(lib, name.replace("_set_", "_get_"), None)
                    if set_ is not None and get_ is not None:
                        set_.argtypes, set_.restype = [ctypes.c_int], None
                        get_.argtypes, get_.restype = [], ctypes.c_int
                        _found = (set_, get_)
                        break
                if _found:
                    break
        except Exception:   # never let a missing or unusual BLAS stop a fit
            _found = ()
    return _found or None


@contextlib.contextmanager
def single_threaded():
    """Run the ``with`` block with one OpenBLAS thread (nested blocks: the count is restored
    when the outermost one ends)."""
    global _depth, _saved
    fns = _openblas()
    if fns is None:
        yield
        return
    set_, get_ = fns
    if _depth == 0:
        _saved = int(get_())
        set_(1)
    _depth += 1
    try:
        yield
    finally:
        _depth -= 1
        if _depth == 0 and _saved is not None:
            set_(_saved)
