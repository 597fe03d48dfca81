"""The hand-off table: a rig fitted to a morph-target animation against the file it replaces, beside
Dem Bones' skin at the same bone count.

Each source is a morph-target animated .glb made with Blender (``tests/blender/morph_assets.py``:
one shape key a frame, played by its weights, as three.js' Horse): a looping cycle of a shared
rig's true skeleton (``rig_cycle``, written without normals as the Horse), Dem Bones' own sample
animation (every 8th of its 400 frames) and the generated flexing tube (``wave_tube``: UV seams,
hard edges, normals; part of its motion no bone explains). Per source the command the hand-off
asks for runs as a user would, ``python -m artdef_addon fit X.glb --links auto --glb out.glb``
(default settings), and the table gives:

* the source's and the rig's vertices and file size;
* the bones and the residual shapes (rank) the rig has, as the fit chose them;
* the replay error, max (worst vertex of any keyed frame) and RMS in % of the bounding-box
  diagonal, of the rig read back by Blender's glTF importer against the source read back, at the
  source's keyed frames, and of the skin alone (the fit's own figure, no residual shape);
* Dem Bones (SSDR, ``py-dem-bones``, at most 4 influences) on the same animation with as many bones
  as the rig: its skin's error the same way (its own bone matrices per frame, no residual).

Run with the Python that has both Blender and Dem Bones (cp311)::

    .venv-4.5/bin/python benchmarks/handoff.py [--quick] [--data ../shared/data]

``--quick``: the three smallest sources. Writes ``benchmarks/results/handoff.md`` (``--out``).
"""
from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "tests", "blender"))

import report  # noqa: E402
from artdef_addon import gltfinfo  # noqa: E402
import morph_assets  # noqa: E402

#: shared rigs whose true skeleton is posed into a cycle (smallest first)
RIGS = ("gltf_RiggedFigure", "gltf_Fox", "threejs_RobotExpressive", "gltf_CesiumMan")
FRAMES = 30
DEMBONES_ITERS = 30


def sources(data: str, quick: bool):
    """(name, vertices, faces, displacements, normals) of every source animation."""
    out = []
    for name in RIGS:
        path = os.path.join(data, name + ".npz")
        if not os.path.isfile(path):
            continue
        z = np.load(path)
        d = morph_assets.rig_cycle(z["vertices"], z["gt_joints"], z["gt_parents"], z["gt_weights"], n_frames=FRAMES)
        out.append((f"{name} cycle", z["vertices"], z["faces"], d, False))
    bone = os.path.join(data, "dembones_bone.npz")
    if os.path.isfile(bone):
        z = np.load(bone)
        out.append(("dembones_bone (every 8th frame)", z["vertices"], z["faces"], z["displacements"][::8], True))
    out.append(("flexing tube (generated)", *morph_assets.wave_tube(n_frames=FRAMES), True))
    if quick:
        out = sorted(out, key=lambda s: len(s[1]))[:3]
    return out


def run_fit(source: str, out: str) -> tuple:
    """The hand-off command on ``source``: (its printed output, wall seconds)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([ROOT, os.environ.get("PYTHONPATH", "")]))
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "artdef_addon", "fit", source, "--links", "auto", "--glb", out],
                          capture_output=True, text=True, env=env, cwd=os.path.dirname(out))
    if proc.returncode != 0:
        raise RuntimeError(f"fit {source} failed: {proc.stderr.strip().splitlines()[-1:]}")
    return proc.stdout, time.perf_counter() - t0


def dembones(x0, faces, X, bones: int) -> tuple:
    """Dem Bones' skin of positions ``X (P, N, 3)`` with ``bones`` bones: (max, RMS) error in % of the
    diagonal, seconds; None when py-dem-bones is not installed."""
    try:
        from py_dem_bones.portable import _prepare_solver, _read_skinning_result
    except ImportError:
        return None
    t0 = time.perf_counter()
    solver = _prepare_solver(x0, X, bones, faces=faces, max_influences=4, iterations=DEMBONES_ITERS)
    solver.compute()
    out = _read_skinning_result(solver)
    W, M = out.weights, out.transforms
    Xhat = np.einsum("bn,pbij,nj->pni", W, M[:, :, :3, :3], x0) + np.einsum("bn,pbi->pni", W, M[:, :, :3, 3])
    diag = float(np.linalg.norm(np.ptp(x0, axis=0)))
    err = np.linalg.norm(X - Xhat, axis=-1)
    return 100 * err.max() / diag, 100 * np.sqrt(np.mean(err ** 2)) / diag, time.perf_counter() - t0


def measure(name, v, f, d, normals, tmp) -> dict:
    src = os.path.join(tmp, "source.glb")
    out = os.path.join(tmp, "rig.glb")
    _, frames = morph_assets.write_morph_glb(src, v, f, d, normals=normals)
    log, secs = run_fit(src, out)
    shapes = re.search(r"residual shapes: (\d+) of", log)
    skin = re.search(r"skin alone max ([\d.e+-]+)% RMS ([\d.e+-]+)%", log)
    worst, rms = morph_assets.replay_error(src, out, frames)
    s_counts, r_counts = morph_assets.glb_mesh_counts(src), morph_assets.glb_mesh_counts(out)
    bones = gltfinfo.contents(out)["bones"]
    x0 = np.asarray(v, dtype=np.float64)
    row = dict(name=name, frames=len(d), src_vertices=s_counts[2], vertices=r_counts[2], meshes=r_counts[0],
               skins=r_counts[1], src_bytes=os.path.getsize(src), bytes=os.path.getsize(out), bones=bones,
               rank=int(shapes.group(1)) if shapes else -1, max=100 * worst, rms=100 * rms,
               skin=(float(skin.group(1)), float(skin.group(2))) if skin else (float("nan"),) * 2, seconds=secs,
               dembones=dembones(x0, np.asarray(f), x0[None] + np.asarray(d), bones))
    print(row, flush=True)
    return row


def table(rows) -> str:
    lines = ["| source | frames | vertices source → rig | file source → rig (ratio) | bones | residual shapes "
             "| replay max / RMS % | skin alone max / RMS % | Dem Bones skin max / RMS % | fit s / Dem Bones s |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        db = r["dembones"]
        lines.append(
            f"| {r['name']} | {r['frames']} | {r['src_vertices']:,} → {r['vertices']:,} "
            f"| {r['src_bytes'] / 1e3:,.0f} kB → {r['bytes'] / 1e3:,.0f} kB ({r['bytes'] / r['src_bytes']:.2f}) "
            f"| {r['bones']} | {r['rank']} | {r['max']:.3f} / {r['rms']:.4f} | {r['skin'][0]:.3f} / {r['skin'][1]:.4f} "
            f"| {f'{db[0]:.3f} / {db[1]:.4f}' if db else 'not installed'} "
            f"| {r['seconds']:.0f} / {f'{db[2]:.0f}' if db else '-'} |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=os.path.join(os.path.dirname(ROOT), "shared", "data"))
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", default=report.result_path("handoff.md"))
    a = ap.parse_args(argv)
    import bpy
    rows = []
    for name, v, f, d, normals in sources(a.data, a.quick):
        with tempfile.TemporaryDirectory() as tmp:
            rows.append(measure(name, v, f, d, normals, tmp))
    body = (f"Blender {bpy.app.version_string}; `fit X.glb --links auto --glb rig.glb`, default settings; Dem Bones "
            f"{DEMBONES_ITERS} iterations, at most 4 influences, as many bones as the rig. Errors in % of the "
            f"bounding-box diagonal at the source's keyed frames (replay: both files read back by Blender's glTF "
            f"importer). The bars: one mesh, one skin, no more vertices and no more bytes than the source, replay "
            f"within 1.5 % max and 0.3 % RMS.\n\n" + table(rows))
    report.write(a.out, "Hand-off: rig against the morph-target animation it replaces", body)


if __name__ == "__main__":
    main()
