"""The fit's independent work spread over the processes of its pool (:func:`procs.current`).

Each function here has a serial path (no pool, or ``jobs`` 1) and a pooled one that gives the same
numbers: the pool's workers run the same numpy code on their share of the work, reading the
large arrays from files written once per fit (:meth:`procs.Pool.share`), and the replies come back
in task order. The child's halves are the ``*_task`` functions.
"""
from __future__ import annotations

import numpy as np

from . import procs
from .metric import RestGeometry

CORE = procs.CORE

#: the per-field neighbour distances go to the pool from this many triangles: a pool worker's
#: start-up (importing numpy, scipy and the core) costs about 0.6 s of CPU, about what one field's
#: distances cost at 100k triangles, so smaller scans stay on the serial path
POOL_TRIANGLES = 100_000


# ------------------------------------------------------ per-field neighbour distances (§5.3)

def neighbour_stream(x0, fields, faces, rest: RestGeometry, pairs, which, progress=None):
    """``(d (E,), z)`` of :func:`patches.neighbour_distances` for each field ``p`` in ``which``,
    yielded in that order (the reduced method's per-field pairwise stage); ``progress(i)`` is
    called before field ``which[i]`` is yielded. Pooled: one field a task, a few in flight."""
    from .patches import neighbour_distances
    pool = procs.current()
    if pool is None or len(which) < 2 or len(faces) < POOL_TRIANGLES:
        for i, p in enumerate(which):
            if progress is not None:
                progress(i)
            yield neighbour_distances(x0, fields[p], faces, rest, pairs)
        return
    paths = {name: pool.share(a) for name, a in
             (("x0", x0), ("fields", fields), ("faces", faces), ("pairs", pairs), ("m0", rest.m0),
              ("R0", rest.R0), ("c0", rest.c0), ("d0", rest.d0), ("s0", rest.s0))}
    tasks = [{"p": int(p), **paths} for p in which]
    for i, (values, arrays) in enumerate(pool.imap(f"{CORE}.parallel:neighbour_task", tasks)):
        if progress is not None:
            progress(i)
        yield arrays["d"], values["z"]


def neighbour_task(arrays, params, report):
    from .patches import neighbour_distances
    sh = procs.shared
    rest = RestGeometry(sh(params["m0"]), sh(params["R0"]), sh(params["c0"]), sh(params["d0"]),
                        sh(params["s0"]))
    d, z = neighbour_distances(sh(params["x0"]), np.asarray(sh(params["fields"])[params["p"]]),
                               sh(params["faces"]), rest, sh(params["pairs"]))
    return {"z": float(z)}, {"d": d}


# ------------------------------------------------------------ the refined skin's weight solve

def weight_blocks(xh, G, cols, q, valid, w0, xx, max_influences, convex, parts):
    """:func:`skinning.solve_rows` of each vertex block ``(s, e)`` of ``parts`` on the fit's pool
    (the child's half: :func:`skinning.weight_task`):
    a list of ``(weights, convex optimum or None, errors)`` in block order, or None without a pool
    (the caller solves the blocks itself: the same rows, the same numbers)."""
    pool = procs.current()
    if pool is None or len(parts) < 2:
        return None
    named = {"xh": xh, "G": G, "cols": cols, "q": q, "valid": valid, "xx": xx}
    if w0 is not None:
        named["w0"] = w0
    paths = {k: pool.share(a) for k, a in named.items()}
    tasks = [{"rows": [int(s), int(e)], "max_influences": int(max_influences), "convex": bool(convex),
              **paths} for s, e in parts]
    out = []
    for _, arrays in pool.imap(f"{CORE}.skinning:weight_task", tasks):
        out.append((arrays["w"], arrays.get("free"), arrays["err"]))
    return out
