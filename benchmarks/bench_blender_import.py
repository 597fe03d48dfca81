"""Blender side of large scans: importing a large scan and reading it back stays in seconds.

Prints, for a generated articulated scan (default about 1M triangles × 50 tracked fields):

- ``artdef.import_scan`` end to end, split into reading the ``.npz`` (the core's ``files.read_scan``:
  decompression and validation), building the mesh and storing the fields as attributes;
- ``operators.io.read_scan`` (what every fit and preview starts with: attributes → ``Scan``,
  fingerprint, validation);
- the first ``len(mesh.loop_triangles)`` (the panel's triangle count, computed lazily by Blender);
- the panel's cost estimate (from counts only);
- peak resident memory of each step (``VmHWM``, reset between steps) and the ``.npz`` size.

Each measurement runs in a fresh ``bpy`` process with the source tree loaded as an extension, so
the peaks are the import's own. The generated scan is cached (``--scan``); generation time is not
measured.

    .venv/bin/python benchmarks/bench_blender_import.py                  # 1M triangles × 50 fields
    .venv/bin/python benchmarks/bench_blender_import.py --triangles 100000 --fields 20
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "benchmarks"))
from peak import reset_peak as _reset_peak, status_kb as _status_kb  # noqa: E402


def make_scan(path: str, triangles: int, fields: int):
    sys.path.insert(0, ROOT)
    sys.path.insert(0, os.path.join(ROOT, "benchmarks"))
    from artdef_addon.files import write_scan as save_scan
    from generate import branching_scan
    t0 = time.perf_counter()
    scan, _ = branching_scan(triangles, fields)
    save_scan(path, scan)
    print(f"generated {scan.n_faces:,} triangles, {scan.n_vertices:,} vertices, {scan.n_fields} fields "
          f"-> {path} ({os.path.getsize(path) / 2 ** 20:.0f} MB, {time.perf_counter() - t0:.0f} s, "
          f"not measured)", flush=True)


# ---------------------------------------------------------------- child: one fresh bpy process
def child(path: str, steps: str):
    os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="artdef-bench-user-"))
    import importlib

    import bpy  # first: it puts Blender's scripts (addon_utils) on the path
    import addon_utils

    repo_dir = tempfile.mkdtemp(prefix="artdef-bench-repo-")
    os.symlink(ROOT, os.path.join(repo_dir, "artdef"))
    bpy.context.preferences.extensions.repos.new(name="artdef_bench", module="artdef_bench",
                                                 custom_directory=repo_dir, source='USER')
    addon_utils.extensions_refresh(ensure_wheels=True)
    mod = "bl_ext.artdef_bench.artdef"
    addon_utils.enable(mod, default_set=True)
    io = importlib.import_module(mod + ".operators.io")
    ops = importlib.import_module(mod + ".operators.ops")
    files_mod = importlib.import_module(mod + ".artdef_addon.files")
    bpy.ops.wm.read_homefile(use_empty=True)
    out = {"rss_start_mb": _status_kb("VmRSS") / 1024}

    # split the operator's time: wrap what import_scan_file calls
    parts = {}

    def timed(owner, name, key):
        fn = getattr(owner, name)

        def wrapper(*a, **kw):
            t = time.perf_counter()
            try:
                return fn(*a, **kw)
            finally:
                parts[key] = parts.get(key, 0.0) + time.perf_counter() - t
        setattr(owner, name, wrapper)

    timed(files_mod, "read_scan", "read_scan (core: read .npz + validate)")
    timed(io, "write_scan", "write_scan (field attributes)")
    timed(io, "new_mesh_from_scan", "new_mesh_from_scan (geometry + fields)")

    _reset_peak()
    t = time.perf_counter()
    assert bpy.ops.artdef.import_scan(filepath=path) == {'FINISHED'}
    out["import_s"] = time.perf_counter() - t
    out["import_peak_mb"] = _status_kb("VmHWM") / 1024
    out["import_parts"] = parts
    obj = bpy.context.view_layer.objects.active
    mesh = obj.data
    out["vertices"], out["polygons"] = len(mesh.vertices), len(mesh.polygons)

    t = time.perf_counter()
    ntri = len(mesh.loop_triangles)
    out["loop_triangles_s"] = time.perf_counter() - t
    out["triangles"] = ntri

    info = io.scan_info(mesh)
    t = time.perf_counter()
    est, _ = ops.method_plan(ntri, info["fields"], len(mesh.vertices), info["kind"])
    out["estimate_s"] = time.perf_counter() - t
    out["estimate"] = est.describe()

    if "read" in steps:
        _reset_peak()
        rss0 = _status_kb("VmRSS") / 1024
        t = time.perf_counter()
        stored = io.read_scan(obj)
        out["read_s"] = time.perf_counter() - t
        out["read_rss_before_mb"] = rss0
        out["read_peak_mb"] = _status_kb("VmHWM") / 1024
        out["read_fields"] = stored.scan.n_fields
        del stored
    print("RESULT " + json.dumps(out), flush=True)


# ---------------------------------------------------------------- parent
def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--triangles", type=int, default=1_000_000)
    ap.add_argument("--fields", type=int, default=50)
    ap.add_argument("--scan", help="scan .npz to use (generated there if missing)")
    ap.add_argument("--repeats", type=int, default=1, help="fresh processes per measurement")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--steps", default="read", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        child(a.child, a.steps)
        return
    path = a.scan or os.path.join(tempfile.gettempdir(), f"artdef_bench_{a.triangles}_{a.fields}.npz")
    if not os.path.exists(path):
        make_scan(path, a.triangles, a.fields)
    print(f"scan: {path} ({os.path.getsize(path) / 2 ** 20:.0f} MB on disk)")
    rows = []
    for _ in range(a.repeats):
        proc = subprocess.run([sys.executable, os.path.abspath(__file__), "--child", path],
                              capture_output=True, text=True)
        lines = [l for l in proc.stdout.splitlines() if l.startswith("RESULT ")]
        if proc.returncode != 0 or not lines:
            sys.exit(f"child failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
        rows.append(json.loads(lines[-1][len("RESULT "):]))
    r = min(rows, key=lambda r: r["import_s"])
    print(f"mesh: {r['vertices']:,} vertices, {r['triangles']:,} triangles, {r['read_fields']} fields")
    print(f"artdef.import_scan: {r['import_s']:.2f} s, peak RSS {r['import_peak_mb']:.0f} MB "
          f"(process at start {r['rss_start_mb']:.0f} MB)")
    for k, v in r["import_parts"].items():
        print(f"  {k}: {v:.2f} s")
    print(f"first len(mesh.loop_triangles): {r['loop_triangles_s']:.2f} s")
    print(f"panel estimate: {1e6 * r['estimate_s']:.0f} µs — {r['estimate']}")
    print(f"io.read_scan: {r['read_s']:.2f} s, peak RSS {r['read_peak_mb']:.0f} MB "
          f"(+{r['read_peak_mb'] - r['read_rss_before_mb']:.0f} MB over the {r['read_rss_before_mb']:.0f} MB before)")
    if len(rows) > 1:
        print("all runs (import s, read s): " + ", ".join(f"({x['import_s']:.2f}, {x['read_s']:.2f})" for x in rows))


if __name__ == "__main__":
    main()
