"""What reading an animated file in a child process first costs (``operators/isolated.py``).

*Fields from File* imports and samples an animated file in a child process before it imports it
into the scene, so that an importer crash on a damaged file cannot take Blender down. Prints, for a
generated morph-target .glb (default 10,048 vertices × 100 frames, Blender's glTF exporter), the
median seconds of: the import and sampling in this process without the child (``isolate=False``),
the child's read on its own (a Blender start plus the same import and sampling), and the whole
operator with the child; and writes the table to ``benchmarks/results/import_check.md``.

    .venv/bin/python benchmarks/bench_import_check.py
    .venv/bin/python benchmarks/bench_import_check.py --frames 30 --repeats 1
"""
from __future__ import annotations

import argparse
import importlib
import os
import statistics
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "benchmarks"))
sys.path.insert(0, os.path.join(ROOT, "tests", "blender"))
import report  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sides", type=int, default=64)
    ap.add_argument("--rings", type=int, default=157)
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=report.result_path("import_check.md"))
    a = ap.parse_args(argv)
    import bpy
    from morph_assets import wave_tube, write_morph_glb
    sys.path.insert(0, os.path.join(ROOT, "operators"))
    headless = importlib.import_module("headless")
    module = headless.ensure_registered()
    isolated = importlib.import_module(module + ".operators.isolated")
    folder = tempfile.mkdtemp(prefix="artdef-bench-import-")
    path = os.path.join(folder, "tube.glb")
    v, f, d = wave_tube(n_frames=a.frames, sides=a.sides, rings=a.rings)
    write_morph_glb(path, v, f, d)
    size = os.path.getsize(path)

    def timed(fn):
        out = []
        for _ in range(a.repeats):
            bpy.ops.wm.read_homefile(use_empty=True)
            t0 = time.perf_counter()
            fn()
            out.append(time.perf_counter() - t0)
        return statistics.median(out)

    in_process = timed(lambda: bpy.ops.artdef.fields_from_file(filepath=path, isolate=False))
    child = timed(lambda: isolated.read_in_child(path))
    both = timed(lambda: bpy.ops.artdef.fields_from_file(filepath=path, isolate=True))
    rows = [("import and sampling here, no child", in_process, 1.0),
            ("the child's read alone", child, child / in_process),
            ("Fields from File with the child first", both, both / in_process)]
    lines = [f"Generated morph-target .glb: {len(v):,} vertices × {a.frames} frames, {size / 2**20:.1f} MB; median of "
             f"{a.repeats} a line, one process (the machine is shared: compare the ratios).", "",
             "| step | seconds | / without the child |", "|---|---:|---:|"]
    lines += [f"| {name} | {t:.2f} | {r:.2f} |" for name, t, r in rows]
    print("\n".join(lines))
    report.write(a.out, "Reading an animated file in a child process first (`benchmarks/bench_import_check.py`)",
                 "\n".join(lines))
    import shutil
    shutil.rmtree(folder, ignore_errors=True)


if __name__ == "__main__":
    main()
    from artdef_addon.cli import exit_process
    exit_process(0)
