"""Functions the worker-process tests call in a child (imported there from this folder)."""
import os
import subprocess
import sys

import numpy as np


def echo(arrays, params, report):
    """Doubles every array, reports three stages and a log line, returns its pid."""
    for k in range(3):
        report.progress(f"step {k}", k / 2)
    report.log(f"got {sorted(arrays)}")
    return ({"pid": os.getpid(), "params": params, "writable": bool(arrays["a"].flags.writeable)},
            {name: 2 * a for name, a in arrays.items()})


def fail(arrays, params, report):
    raise ValueError("the scan has no faces\nsecond line")


def abort(arrays, params, report):
    report.progress("before", 0.0)
    os.abort()


def leave(arrays, params, report):
    sys.exit(3)


def block(arrays, params, report):
    """Starts a grandchild (its pid in a log line), reports, then never returns."""
    child = subprocess.Popen([sys.executable, "-c", "import os; os.read(os.pipe()[0], 1)"])
    report.log(str(child.pid))
    report.progress("blocking", 0.5)
    os.read(os.pipe()[0], 1)


def allocate(arrays, params, report):
    """Fills an array of ``params['bytes']`` bytes (a MemoryError under a smaller limit)."""
    a = np.ones(int(params["bytes"]) // 8)
    return {"sum": float(a.sum())}


def row_sums(arrays, params, report):
    """The sums of rows s:e of a pool's shared array."""
    from artdef_addon import procs
    a = procs.shared(params["a"])
    s, e = params["rows"]
    if s < 0:
        raise ValueError("negative row")
    return {"pid": os.getpid()}, {"sums": a[s:e].sum(axis=1)}
