"""One fit per command: the CPU time of ``fit -o R --blend B`` against ``fit -o R``.

Runs ``python -m artdef_addon fit SCAN --links L -o R`` and the same with ``--blend B`` as
subprocesses of the Python given by ``--python`` (one with the bpy module), ``--repeat`` times each,
alternating, and measures each run's CPU time (user + system) with
``resource.getrusage(RUSAGE_CHILDREN)`` — a loaded machine stretches wall time, not CPU time.
Then it opens the .blend and checks that its vertex groups hold the .npz result's skin weights.
Prints a Markdown table and writes it to ``benchmarks/results/one_fit_per_command.md`` (``--out`` elsewhere,
``-`` nowhere).

    /work/venvs/py311-50/bin/python benchmarks/one_fit_per_command.py \\
        --scan ../shared/data/gltf_CesiumMan.npz --links 19
"""
from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile

import numpy as np

import report

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

_GROUPS = """
import sys, bpy, numpy as np
bpy.ops.wm.open_mainfile(filepath=sys.argv[1])
mesh = [o for o in bpy.data.objects if o.type == 'MESH'][0]
names = [g.name for g in mesh.vertex_groups]
w = np.zeros((len(mesh.data.vertices), len(names)))
for v in mesh.data.vertices:
    for g in v.groups:
        w[v.index, g.group] = g.weight
np.savez(sys.argv[2], weights=w, names=np.array(names))
"""


def _cpu(python, args, cwd):
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    proc = subprocess.run([python, *args], cwd=cwd, capture_output=True, text=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(args)} failed:\n{proc.stderr[-3000:]}")
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scan", default=os.path.join(ROOT, "..", "shared", "data", "gltf_CesiumMan.npz"))
    ap.add_argument("--links", default="19")
    ap.add_argument("--python", default=sys.executable)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--out", default=report.result_path("one_fit_per_command.md"), help="Markdown file (- for none)")
    a = ap.parse_args(argv)
    scan = os.path.abspath(a.scan)
    with tempfile.TemporaryDirectory(prefix="artdef-onefit-") as d:
        r, b = os.path.join(d, "r.npz"), os.path.join(d, "b.blend")
        base = ["-m", "artdef_addon", "fit", scan, "--links", str(a.links), "-q"]
        plain, blend = [], []
        for _ in range(a.repeat):
            plain.append(_cpu(a.python, base + ["-o", r], ROOT))
            blend.append(_cpu(a.python, base + ["-o", r, "--blend", b], ROOT))
        subprocess.run([a.python, "-c", _GROUPS, b, os.path.join(d, "w.npz")], check=True,
                       capture_output=True)
        with np.load(r) as res, np.load(os.path.join(d, "w.npz")) as g:
            w, groups = res["weights"], g["weights"]
        # bones and groups are renamed root-first by the command line: match each link's column
        match = np.abs(w[:, :, None] - groups[:, None, :]).max(axis=0).argmin(axis=1)
        diff = float(np.abs(groups[:, match] - w).max()) if len(set(match.tolist())) == w.shape[1] else float("inf")
    p, q = min(plain), min(blend)
    table = "\n".join([
        "| scan | links | `fit -o R` CPU s | `fit -o R --blend B` CPU s | ratio | max abs(.blend − .npz weights) |",
        "|---|---|---|---|---|---|",
        f"| {os.path.basename(scan)} | {w.shape[1]} | {p:.1f} (runs: {', '.join(f'{x:.1f}' for x in plain)}) "
        f"| {q:.1f} (runs: {', '.join(f'{x:.1f}' for x in blend)}) | {q / p:.2f} | {diff:.2g} |"])
    print(table)
    if a.out != "-":
        report.write(a.out, "One fit per command (`benchmarks/one_fit_per_command.py`)", table)
    return 0 if q <= 1.5 * p and diff <= 1e-6 else 1


if __name__ == "__main__":
    sys.exit(main())
