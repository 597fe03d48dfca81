"""Which Blender versions the built extension zip really works in: version x step.

For each given Python that has a ``bpy`` module (one Blender version each), in a
fresh process whose ``sys.path`` has **no scipy** (a shadow of its site-packages
without scipy, as Blender itself ships none), with a private user directory:

1. install   ``bpy.ops.extensions.package_install_files`` of the zip; the
             bundled scipy wheel for this Python lands in the extension site-packages
2. enable    the add-on is enabled, ``bpy.ops.artdef.*`` registered, and
             ``import scipy`` resolves to the bundled copy
3. import    ``bpy.ops.artdef.import_scan`` of a tracked and a Green's sample scan
4. fit tracked  ``bpy.ops.artdef.fit`` on the tracked rod: armature, replay action
5. fit Green's  ``bpy.ops.artdef.fit`` on the Green's rod: drivers on the rig
6. glTF + validator  Export Rig (``bpy.ops.artdef.export_rig``, Blender's glTF exporter)
             for both rigs; the Khronos validator (``scripts/validate_gltf.js``) must
             report 0 errors
7. failed fit   a fit whose rig build raises half-way (monkeypatched) and a fit
             cancelled half-way leave every ``bpy.data`` collection's count unchanged

Usage::

    python benchmarks/blender_matrix.py --zip dist/artdef-0.1.0-linux_x64.zip \\
        4.5=/work/venvs/py311/bin/python 5.2=.venv/bin/python ...

Writes ``benchmarks/results/blender_matrix.md`` (``--out``) and prints it.
"""

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
VALIDATE_JS = ROOT / "scripts" / "validate_gltf.js"
STEPS = ("install", "enable", "import", "fit tracked", "fit Green's", "glTF + validator",
         "failed fit")

# Runs inside the target Python.  argv: zip, out_dir.  Prints one JSON line.
PROBE = r'''
import json, os, sys, tempfile, time, traceback
site = next(p for p in sys.path if p.endswith("site-packages"))
shadow = tempfile.mkdtemp()
for name in os.listdir(site):
    if not name.startswith("scipy"):
        os.symlink(os.path.join(site, name), os.path.join(shadow, name))
sys.path[sys.path.index(site)] = shadow
os.environ["BLENDER_USER_RESOURCES"] = tempfile.mkdtemp()
zip_path, out_dir = sys.argv[1], sys.argv[2]
res = {"steps": {}}
def step(name, fn):
    t0 = time.perf_counter()
    try:
        detail = fn()
        res["steps"][name] = {"ok": True, "detail": detail or "", "s": time.perf_counter() - t0}
        return True
    except BaseException as ex:
        traceback.print_exc()
        res["steps"][name] = {"ok": False, "detail": f"{type(ex).__name__}: {ex}"[:300],
                              "s": time.perf_counter() - t0}
        return False
def done():
    print("MATRIX " + json.dumps(res), flush=True)
    os._exit(0)  # bpy 4.5 may hang at exit after a glTF export
try:
    import scipy
    res["error"] = "scipy importable without the extension: " + scipy.__file__
    done()
except ImportError:
    pass
import bpy, addon_utils, importlib, numpy
res["blender"] = bpy.app.version_string
res["python"] = "%d.%d.%d" % sys.version_info[:3]
res["numpy"] = numpy.__version__
MOD = "bl_ext.user_default.artdef"
S = {}
def install():
    r = bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default",
                                                 enable_on_install=True)
    assert r == {"FINISHED"}, r
    sp = os.path.join(os.environ["BLENDER_USER_RESOURCES"], "extensions", ".local", "lib",
                      "python%d.%d" % sys.version_info[:2], "site-packages")
    dists = [d for d in os.listdir(sp) if d.startswith("scipy-")]
    assert dists, "no scipy wheel installed under " + sp
    assert not os.path.exists(os.path.join(sp, "numpy")), "numpy was installed"
    return dists[0].replace(".dist-info", "")
def enable():
    if not addon_utils.check(MOD)[1]:
        addon_utils.enable(MOD, default_set=True)
    assert addon_utils.check(MOD)[1], "not enabled"
    assert "fit" in dir(bpy.ops.artdef), dir(bpy.ops.artdef)
    import scipy, scipy.sparse.linalg
    assert os.environ["BLENDER_USER_RESOURCES"] in os.path.realpath(scipy.__file__), scipy.__file__
    res["scipy"] = scipy.__version__
    return "bundled scipy " + scipy.__version__
def pkg(name):
    return importlib.import_module(MOD + "." + name)
def imp():
    files, samples = pkg("artdef_addon.files"), pkg("artdef_addon.samples")
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    for name in ("rod", "greens_rod"):
        path = os.path.join(out_dir, name + ".npz")
        files.write_scan(path, samples.make(name))
        assert bpy.ops.artdef.import_scan(filepath=path) == {"FINISHED"}
        S[name] = bpy.context.view_layer.objects.active.name
    return "rod (tracked), greens_rod (Green's)"
def fit(name):
    obj = bpy.data.objects[S[name]]
    for o in bpy.data.objects:
        o.select_set(o == obj)
    bpy.context.view_layer.objects.active = obj
    with bpy.context.temp_override(active_object=obj, object=obj, selected_objects=[obj]):
        assert bpy.ops.artdef.fit(links=3) == {"FINISHED"}
    arm = obj.artdef.rig
    assert arm is not None and len(arm.data.bones) >= 3
    return obj, arm
def fit_tracked():
    obj, arm = fit("rod")
    assert arm.animation_data.action is not None, "no replay action"
    return "%d bones, rms %.3g" % (len(arm.data.bones), obj.artdef.fit_rms_articulation)
def fit_greens():
    obj, arm = fit("greens_rod")
    bone_drivers = len(arm.animation_data.drivers)
    key_drivers = len(obj.data.shape_keys.animation_data.drivers)
    assert bone_drivers > 0 and key_drivers > 0, (bone_drivers, key_drivers)
    return "%d bone + %d shape-key drivers" % (bone_drivers, key_drivers)
def gltf():
    out = []
    for name in ("rod", "greens_rod"):
        obj = bpy.data.objects[S[name]]
        for o in bpy.data.objects:
            o.select_set(o == obj)
        bpy.context.view_layer.objects.active = obj
        path = os.path.join(out_dir, name + ".glb")
        with bpy.context.temp_override(active_object=obj, object=obj, selected_objects=[obj]):
            assert bpy.ops.artdef.export_rig(filepath=path, export_format="GLB") == {"FINISHED"}
        assert os.path.getsize(path) > 0, path
        out.append(path)
    res["glb"] = out
def counts():
    return {n: len(getattr(bpy.data, n)) for n in pkg("operators.rig").id_collections()}
def failed():
    rig, ops = pkg("operators.rig"), pkg("operators.ops")
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    obj_names = []
    for name in ("rod", "greens_rod"):
        assert bpy.ops.artdef.import_scan(filepath=os.path.join(out_dir, name + ".npz")) == {"FINISHED"}
        obj_names.append(bpy.context.view_layer.objects.active.name)
    before = counts()
    compat = pkg("operators.compat")
    # (module, function, scans whose fit calls it): each raises right after the
    # real function ran, so what that stage made exists when the fit fails
    stages = [(compat, "new_action", obj_names), (rig, "_build_replay", obj_names[:1]),
              (rig, "_build_load_sweep", obj_names[1:]), (rig, "_set_frame_range", obj_names)]
    tried = 0
    for mod, f, names in stages:
        real = getattr(mod, f)
        def boom(*a, _real=real, **k):
            _real(*a, **k)
            raise RuntimeError("forced failure")
        setattr(mod, f, boom)
        try:
            for n in names:
                obj = bpy.data.objects[n]
                bpy.context.view_layer.objects.active = obj
                with bpy.context.temp_override(active_object=obj, object=obj):
                    try:
                        r = bpy.ops.artdef.fit(links=3)
                    except RuntimeError as ex:  # the operator's ERROR report, in background mode
                        assert "forced failure" in str(ex), ex
                        r = {"CANCELLED"}
                assert r == {"CANCELLED"}, (f, n, r)
                tried += 1
        finally:
            setattr(mod, f, real)
    pkg("artdef_addon.api").clear_cache()  # the failed fits cached their clustering: cluster again
    hook = lambda stage, fraction: stage == "cluster"
    ops.PROGRESS_HOOKS.append(hook)
    try:
        for n in obj_names:
            obj = bpy.data.objects[n]
            with bpy.context.temp_override(active_object=obj, object=obj):
                assert bpy.ops.artdef.fit(links=3) == {"CANCELLED"}
            tried += 1
    finally:
        ops.PROGRESS_HOOKS.remove(hook)
    after = counts()
    diff = {k: (before[k], after[k]) for k in before if before[k] != after[k]}
    assert not diff, "counts changed: %s" % diff
    return "%d failed/cancelled fits, %d collections unchanged" % (tried, len(before))
ok = step("install", install) and step("enable", enable) and step("import", imp)
if ok:
    step("fit tracked", fit_tracked)
    step("fit Green's", fit_greens)
    if res["steps"]["fit tracked"]["ok"] and res["steps"]["fit Green's"]["ok"]:
        step("glTF + validator", gltf)
    step("failed fit", failed)
done()
'''


def validate(glb):
    proc = subprocess.run(["node", str(VALIDATE_JS), glb, "--json"], capture_output=True,
                          text=True, timeout=300)
    if proc.returncode not in (0, 1):
        return None, proc.stderr.strip()[-200:]
    issues = json.loads(proc.stdout)["issues"]
    return issues["numErrors"], f"{issues['numErrors']} errors, {issues['numWarnings']} warnings"


def run_one(label, python, zip_path):
    work = tempfile.mkdtemp(prefix=f"artdef-matrix-{label}-")
    t0 = time.perf_counter()
    try:
        # its temporary files (Blender's own blender_* folder, which the probe's os._exit leaves) go
        # under ``work``, removed below
        proc = subprocess.run([python, "-c", PROBE, str(zip_path), work], capture_output=True,
                              text=True, timeout=1800, cwd=work, env=dict(os.environ, TMPDIR=work))
        lines = [l for l in proc.stdout.splitlines() if l.startswith("MATRIX ")]
        if not lines:
            return {"label": label, "error": (proc.stderr or proc.stdout)[-500:], "steps": {}}
        res = json.loads(lines[-1][len("MATRIX "):])
        if "glTF + validator" in res["steps"] and res["steps"]["glTF + validator"]["ok"]:
            details = []
            for glb in res.get("glb", []):
                errors, text = validate(glb)
                details.append(f"{Path(glb).stem}: {text}")
                if errors != 0:
                    res["steps"]["glTF + validator"]["ok"] = False
            res["steps"]["glTF + validator"]["detail"] = "; ".join(details)
        res["label"] = label
        res["seconds"] = time.perf_counter() - t0
        return res
    finally:
        shutil.rmtree(work, ignore_errors=True)


def table(results, zip_path):
    head = ["Blender", "Python", "numpy", "scipy (bundled)"] + list(STEPS) + ["time"]
    zdir = Path(zip_path).resolve().parent.parent
    commit = subprocess.run(["git", "-C", str(zdir), "rev-parse", "--short", "HEAD"],
                            capture_output=True, text=True).stdout.strip() or "?"
    lines = [f"Zip: `{Path(zip_path).name}` ({Path(zip_path).stat().st_size / 1e6:.0f} MB, built "
             f"by `make extension` in a checkout at {commit}); each Blender in a fresh process "
             "with no scipy of its own (`python benchmarks/blender_matrix.py`).", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    notes = []
    for r in results:
        row = [r.get("blender", r["label"]), r.get("python", "?"), r.get("numpy", "?"),
               r.get("scipy", "?")]
        for s in STEPS:
            st = r["steps"].get(s)
            row.append("–" if st is None else ("pass" if st["ok"] else "**FAIL**"))
            if st is not None and (st["detail"] or not st["ok"]):
                notes.append(f"- {r.get('blender', r['label'])}, {s}: {st['detail']}")
        if "error" in r:
            notes.append(f"- {r['label']}: {r['error']}")
        row.append(f"{r.get('seconds', 0):.0f} s")
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines + ["", "Details:", ""] + notes) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--zip", required=True, help="the linux-x64 extension zip")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "blender_matrix.md"))
    ap.add_argument("pythons", nargs="+", help="LABEL=/path/to/python (one bpy version each)")
    a = ap.parse_args()
    results = []
    for item in a.pythons:
        label, python = item.split("=", 1)
        python = os.path.abspath(python)   # the probe runs in its own directory (not resolved: a venv's link)
        print(f"blender_matrix: {label} ({python}) ...", flush=True)
        results.append(run_one(label, python, Path(a.zip).resolve()))
    text = table(results, a.zip)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text("# Blender version x step (the built zip)\n\n" + text)
    print(text)
    failed = [r for r in results if "error" in r or not all(
        r["steps"].get(s, {}).get("ok") for s in STEPS)]
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
