r"""A compiled weight solve: what it would buy against Dem Bones. An experiment, not the product.

The extension's packages are bpy, numpy and scipy, so every skin decomposition round is numpy: about 6 µs a sample
row in the weight solve's batched active set (`skinning.simplex_least_squares`, a third to two fifths of a fit).
This script measures what the same algorithm compiled would change. The kernel below is that function row by row
(the same start, warm start, tolerances, support limit and choice between the two limited supports) compiled by
numba (`numba==0.68.1`, in `requirements-bench.txt`: it is not a dependency of the extension, and the fits below
only use it when this script installs it). Its LU solve is not LAPACK's, so the weights agree to round-off.

    .venv-4.5/bin/pip install -r requirements-bench.txt         # py-dem-bones and numba (Python 3.11)
    .venv-4.5/bin/python benchmarks/compiled_kernel.py --data ../shared/data
    .venv-4.5/bin/python benchmarks/compiled_kernel.py --compare --only CesiumMan,wolf,cheburashka,dembones_bone \
        --skip-rod --skip-auto-samples --repeats 3 --data ../shared/data --out /tmp/compare_compiled.md

Without ``--compare`` it fits each set with the numpy and the compiled weight solve in fresh processes, alternating
(``fit_ab.one``), and prints the median CPU and wall seconds, their ratio and both fits' answers (Karni–Gotsman
error, ARI, true joints, weight solves). With ``--compare`` it runs ``compare_dembones.py`` (the remaining arguments)
with the kernel installed: artdef and Dem Bones side by side. The first process compiles the kernel (about 12 s;
numba caches it under ``benchmarks/__pycache__``). Figures: ``benchmarks/results/compiled_kernel.md``.
"""
from __future__ import annotations

import argparse
import json
import os
import runpy
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)
sys.path.insert(0, HERE)

try:
    from numba import njit
except ImportError:          # main() says so in one line
    njit = None


def _jit(fn):
    return fn if njit is None else njit(cache=True, nogil=True)(fn)


@_jit
def _kkt(Q, q, P, m, K, rhs, z):
    """qp._kkt_solve for one row, by LU with partial pivoting into z (m+1,); False if singular."""
    n = m + 1
    for a in range(m):
        pa = 1.0 if P[a] else 0.0
        for b in range(m):
            pb = 1.0 if P[b] else 0.0
            K[a, b] = Q[a, b] * (2.0 * pa * pb)
        K[a, a] += 1.0 - pa
        K[a, m] = pa
        K[m, a] = pa
        rhs[a] = 2.0 * q[a] * pa
    K[m, m] = 0.0
    rhs[m] = 1.0
    # LU with partial pivoting
    for c in range(n):
        p = c
        big = abs(K[c, c])
        for r in range(c + 1, n):
            v = abs(K[r, c])
            if v > big:
                big = v
                p = r
        if big == 0.0:
            return False
        if p != c:
            for k in range(n):
                tmp = K[c, k]
                K[c, k] = K[p, k]
                K[p, k] = tmp
            tmp = rhs[c]
            rhs[c] = rhs[p]
            rhs[p] = tmp
        inv = 1.0 / K[c, c]
        for r in range(c + 1, n):
            f = K[r, c] * inv
            if f != 0.0:
                for k in range(c + 1, n):
                    K[r, k] -= f * K[c, k]
                rhs[r] -= f * rhs[c]
    for r in range(n - 1, -1, -1):
        s = rhs[r]
        for k in range(r + 1, n):
            s -= K[r, k] * z[k]
        z[r] = s / K[r, r]
    for a in range(m):
        if not P[a]:
            z[a] = 0.0
    return True


@_jit
def _settle(Q, q, P, w, m, K, rhs, z):
    """qp._active_set's settle for one row: the optimum on P, dropping weights that turn negative."""
    for _ in range(m):
        if not _kkt(Q, q, P, m, K, rhs, z):
            return          # singular (numpy takes the pseudo-inverse): the row keeps its iterate
        bad = False
        for a in range(m):
            if P[a] and z[a] <= 0.0:
                bad = True
        if not bad:
            for a in range(m):
                w[a] = z[a]
            return
        alpha = np.inf
        for a in range(m):
            if P[a] and z[a] <= 0.0:
                d = w[a] - z[a]
                if d < 1e-300:
                    d = 1e-300
                r = w[a] / d
                if r < alpha:
                    alpha = r
        if alpha < 0.0:
            alpha = 0.0
        if alpha > 1.0:
            alpha = 1.0
        for a in range(m):
            w[a] = w[a] + alpha * (z[a] - w[a])
            if P[a] and w[a] <= 1e-14:
                w[a] = 0.0
                P[a] = False


@_jit
def _active(Q, q, valid, max_rounds, w0, has_w0, w, P, m, K, rhs, z, g):
    """qp._active_set for one row (its start, warm start and tolerances): fills w, P; returns done."""
    scale_d = 0.0
    scale_q = 0.0
    for a in range(m):
        v = abs(Q[a, a])
        if v > scale_d:
            scale_d = v
        v = abs(q[a])
        if v > scale_q:
            scale_q = v
    scale = scale_d + scale_q + 1e-300
    j0 = 0
    best = np.inf
    for a in range(m):
        s = Q[a, a] - 2 * q[a] if valid[a] else np.inf
        if s < best:
            best = s
            j0 = a
    for a in range(m):
        w[a] = 0.0
        P[a] = False
    w[j0] = 1.0
    P[j0] = True
    if has_w0:
        tot = 0.0
        for a in range(m):
            v = w0[a] if valid[a] else 0.0
            if v < 0.0:
                v = 0.0
            g[a] = v
            tot += v
        if tot > 0:
            cnt = 0
            for a in range(m):
                w[a] = g[a] / tot
                P[a] = w[a] > 0
                if P[a]:
                    cnt += 1
            if cnt > 1:
                _settle(Q, q, P, w, m, K, rhs, z)
    for r in range(max_rounds):
        lam = 0.0
        for a in range(m):
            s = 0.0
            for b in range(m):
                s += Q[a, b] * w[b]
            g[a] = 2 * (s - q[a])
            lam += g[a] * w[a]
        j = 0
        vmin = np.inf
        for a in range(m):
            v = g[a] - lam if (valid[a] and not P[a]) else np.inf
            if v < vmin:
                vmin = v
                j = a
        if not (vmin < -1e-10 * scale):
            return True
        P[j] = True
        _settle(Q, q, P, w, m, K, rhs, z)
    return False


@_jit
def _top(score, valid, top, m, sub, used):
    """sub: the first ``top`` of a stable argsort of score, and valid."""
    for a in range(m):
        sub[a] = False
        used[a] = False
    for k in range(top):
        bi = -1
        bv = np.inf
        for a in range(m):
            if not used[a] and (bi == -1 or score[a] < bv):
                bv = score[a]
                bi = a
        used[bi] = True
        sub[bi] = valid[bi]


@_jit
def _obj(Q, q, w, m):
    """wᵀQw − 2qᵀw."""
    s = 0.0
    for a in range(m):
        t = 0.0
        for b in range(m):
            t += Q[a, b] * w[b]
        s += w[a] * t - 2 * q[a] * w[a]
    return s


@_jit
def _clip_normalise(x, m):
    """x (m,) clipped at 0 and divided by its sum, in place."""
    tot = 0.0
    for a in range(m):
        if x[a] < 0:
            x[a] = 0.0
        tot += x[a]
    for a in range(m):
        x[a] /= tot


@_jit
def _limited(Q, q, sub, w, top, ws, P, m, K, rhs, z, g):
    """The optimum on the links ``sub`` (at most ``top``) into ws, warm-started from the convex optimum w there,
    clipped at 0 and summing to 1 (``simplex_least_squares``' limited re-solve)."""
    st = np.empty(m)
    for a in range(m):
        st[a] = w[a] if sub[a] else 0.0
    _active(Q, q, sub, 3 * top, st, True, ws, P, m, K, rhs, z, g)
    _clip_normalise(ws, m)


@_jit
def _rows(Q, q, valid, max_support, w0, has_w0, out, wf):
    """skinning.simplex_least_squares row by row into out (N, m) and its convex optimum into wf (N, m)."""
    N, m = q.shape
    top = m if max_support < 1 else min(m, max_support)
    for i in range(N):
        K = np.empty((m + 1, m + 1))
        rhs = np.empty(m + 1)
        z = np.empty(m + 1)
        g = np.empty(m)
        w = np.empty(m)
        P = np.empty(m, dtype=np.bool_)
        nv = 0
        for a in range(m):
            if valid[i, a]:
                nv += 1
        if nv <= 1:
            for a in range(m):
                v = 1.0 if (nv == 1 and valid[i, a]) else 0.0
                out[i, a] = v
                wf[i, a] = v
            continue
        done = _active(Q[i], q[i], valid[i], 3 * m, w0[i], has_w0, w, P, m, K, rhs, z, g)
        cnt = 0
        for a in range(m):
            wf[i, a] = w[a]
            if w[a] > 0:
                cnt += 1
        if (not done) or cnt > top:
            score = np.empty(m)
            sub0 = np.empty(m, dtype=np.bool_)
            sub1 = np.empty(m, dtype=np.bool_)
            used = np.empty(m, dtype=np.bool_)
            for a in range(m):
                score[a] = -w[a]
            _top(score, valid[i], top, m, sub0, used)
            for a in range(m):
                score[a] = Q[i, a, a] - 2 * q[i, a] if valid[i, a] else np.inf
            _top(score, valid[i], top, m, sub1, used)
            same = True
            for a in range(m):
                if sub0[a] != sub1[a]:
                    same = False
            ws0 = np.empty(m)
            ws1 = np.empty(m)
            _limited(Q[i], q[i], sub0, w, top, ws0, P, m, K, rhs, z, g)
            best = ws0
            if not same:
                _limited(Q[i], q[i], sub1, w, top, ws1, P, m, K, rhs, z, g)
                if _obj(Q[i], q[i], ws1, m) < _obj(Q[i], q[i], ws0, m):
                    best = ws1
            for a in range(m):
                w[a] = best[a]
        _clip_normalise(w, m)
        for a in range(m):
            out[i, a] = w[a]




def simplex_least_squares(Q, q, valid, max_support=None, w0=None, convex=False):
    """``skinning.simplex_least_squares`` through the compiled kernel (the same arguments and returns)."""
    N, m = q.shape
    out, wf = np.empty((N, m)), np.empty((N, m))
    _rows(np.ascontiguousarray(Q, dtype=np.float64), np.ascontiguousarray(q, dtype=np.float64),
          np.ascontiguousarray(valid, dtype=np.bool_), -1 if max_support is None else int(max_support),
          np.zeros((N, m)) if w0 is None else np.ascontiguousarray(w0, dtype=np.float64), w0 is not None, out, wf)
    return (out, wf) if convex else out


def install() -> float:
    """Put the compiled weight solve in place of the numpy one; returns the seconds spent compiling (or loading
    the cache)."""
    from artdef_addon import skinning
    t0 = time.perf_counter()
    simplex_least_squares(np.eye(8)[None].repeat(2, 0), np.zeros((2, 8)), np.ones((2, 8), dtype=bool), 4, None, True)
    skinning.simplex_least_squares = simplex_least_squares
    return time.perf_counter() - t0


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if njit is None:
        print("compiled_kernel.py: needs numba (pip install -r requirements-bench.txt into the Python 3.11 venv)")
        return 2
    if argv and argv[0] == "--compare":
        secs = install()
        print(f"compiled weight solve installed ({secs:.1f} s to compile or load)", flush=True)
        sys.argv = [os.path.join(HERE, "compare_dembones.py")] + argv[1:]
        runpy.run_path(sys.argv[0], run_name="__main__")
        return 0
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", default="CesiumMan:19,wolf:21,cheburashka:11,dembones_bone:10")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--data", default=os.path.join(os.path.dirname(ROOT), "shared", "data"))
    ap.add_argument("--out", default=os.path.join(HERE, "results", "compiled_kernel.md"),
                    help="Markdown file (- for none)")
    ap.add_argument("--one", nargs=3, metavar=("HOW", "NAME", "LINKS"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.one:
        how, name, links = args.one
        if how == "compiled":
            install()
        from fit_ab import one
        print(json.dumps(one(ROOT, name, int(links), None, args.data)))
        return 0
    from fit_ab import alternating, answers, median
    rows = []
    for item in args.sets.split(","):
        name, _, links = item.partition(":")
        runs = alternating({how: [sys.executable, __file__, "--one", how, name, links, "--data", args.data]
                            for how in ("numpy", "compiled")}, args.reps)
        med, wall = median(runs, "cpu"), median(runs, "wall")
        a, b = answers(runs["numpy"][0]), answers(runs["compiled"][0])
        rows.append(f"| {name} | {links} | {med['numpy']:.2f} | {med['compiled']:.2f} | "
                    f"{med['compiled'] / med['numpy']:.2f} | {wall['numpy']:.2f} | {wall['compiled']:.2f} | {a} | "
                    f"{'same' if a == b else b} |")
        print(rows[-1], flush=True)
    table = ("| set | links | numpy CPU s | compiled CPU s | ratio | numpy wall s | compiled wall s | answers (numpy) "
             "| answers (compiled) |\n|---|---:|---:|---:|---:|---:|---:|---|---|\n" + "\n".join(rows))
    print(table)
    if args.out != "-":
        import report
        report.write(args.out, "A compiled weight solve against numpy (`benchmarks/compiled_kernel.py`)", table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
