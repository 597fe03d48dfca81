"""Damaged animated files and sequences never take the command or Blender down, and never become a rig.

Small valid files are made here (a skinned, keyed leg as .glb, .gltf + .bin, .fbx, .abc, .usdc and
.usda; a morph-target tube as .glb; a bending tube as OBJ/PLY sequences) and damaged by
``tests/damaged_files.py`` (cut short, flipped bits, empty, random bytes, another format, broken
JSON, accessors past the buffer, NaN in positions, morph targets, keyframe times and keyed values,
zero rotations, no animation, a .gltf without its .bin, sequences with a frame of another size,
NaN, a bad face index, garbage, a single frame, an empty folder). Each case, on the command line:
exit 2, exactly one ``artdef: error:`` line naming the file, no traceback, no output and no
temporary left, every input byte-identical, within a time limit. Through the operator that
imports (*Fields from File*): an ERROR report, the scene unchanged, Blender still running.
"""
import hashlib
import os
import subprocess
import sys
import time

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import damaged_files as D  # noqa: E402
from conftest import REPO_ROOT  # noqa: E402
from handoffhelpers import build_character  # noqa: E402
from morph_assets import wave_tube, write_morph_glb  # noqa: E402
from ophelpers import scene_snapshot  # noqa: E402

#: seconds one damaged case may take on the command line (Blender's start, the child's, the read)
CASE_SECONDS = 90


def _tube_sequence():
    sides, rings = 10, 13
    a = 2 * np.pi * np.arange(sides) / sides
    rest = np.stack([np.tile(0.2 * np.cos(a), rings), np.tile(0.2 * np.sin(a), rings),
                     np.repeat(np.linspace(0.0, 2.0, rings), sides)], axis=1)
    faces = np.array([[r * sides + s, r * sides + (s + 1) % sides, (r + 1) * sides + (s + 1) % sides,
                       (r + 1) * sides + s] for r in range(rings - 1) for s in range(sides)])
    poses = []
    for t in np.linspace(0.2, 0.8, 5):
        c, s = np.cos(t), np.sin(t)
        R = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
        p = rest.copy()
        up = rest[:, 2] > 1.0
        p[up] = (rest[up] - [0, 0, 1]) @ R.T + [0, 0, 1]
        poses.append(p)
    return rest, faces, poses


@pytest.fixture(scope="module")
def sources(installed_addon, tmp_path_factory):
    """The valid files, written by Blender's own exporters: ``{name: bytes}``."""
    d = tmp_path_factory.mktemp("valid")
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    obj, arm = build_character()
    for o in (obj, arm):
        o.select_set(True)
    bpy.ops.export_scene.gltf(filepath=str(d / "leg.glb"), export_format="GLB")
    bpy.ops.export_scene.gltf(filepath=str(d / "leg.gltf"), export_format="GLTF_SEPARATE")
    bpy.ops.export_scene.fbx(filepath=str(d / "leg.fbx"))
    bpy.ops.wm.alembic_export(filepath=str(d / "leg.abc"), start=1, end=bpy.context.scene.frame_end)
    bpy.ops.wm.usd_export(filepath=str(d / "leg.usdc"), export_animation=True)
    bpy.ops.wm.usd_export(filepath=str(d / "leg.usda"), export_animation=True)
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    write_morph_glb(str(d / "tube.glb"), *wave_tube(n_frames=12))
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    return {p.name: p.read_bytes() for p in d.iterdir()}


def _cases(src):
    groups = {}
    for ext, name, other in ((".glb", "leg.glb", "leg.fbx"), (".fbx", "leg.fbx", "leg.glb"),
                             (".abc", "leg.abc", "leg.usdc"), (".usdc", "leg.usdc", "leg.abc")):
        groups[ext[1:]] = D.generic(src[name], ext, 7, src[other])
    groups["glb_structure"] = {**D.glb_skinned(src["leg.glb"]), **D.glb_morph(src["tube.glb"])}
    groups["gltf"] = D.gltf_separate(src["leg.gltf"], src["leg.bin"], "leg.bin")
    groups["usda"] = D.usda_nan(src["leg.usda"])
    groups["sequence"] = D.sequences(*_tube_sequence())
    return groups


GROUPS = ("glb", "fbx", "abc", "usdc", "glb_structure", "gltf", "usda", "sequence")


def _lay_out(folder, entry, files):
    for rel, data in files.items():
        path = folder / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
    (folder / entry).mkdir(exist_ok=True) if entry == "seq" else None


def _digests(folder):
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in folder.rglob("*") if p.is_file()}


def _start(folder, entry):
    tmp = folder.parent / (folder.name + "-tmp")
    tmp.mkdir()
    env = dict(os.environ, PYTHONPATH=REPO_ROOT, TMPDIR=str(tmp), TEMP=str(tmp), TMP=str(tmp))
    proc = subprocess.Popen([sys.executable, "-m", "artdef_addon", "fit", entry, "--links", "2", "-o", "out.npz"],
                            cwd=folder, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    return proc, tmp, time.monotonic()


def test_every_case_is_counted(sources):
    """The suite holds at least 40 damaged cases, over every importer and both sequence readers."""
    groups = _cases(sources)
    names = [n for g in groups.values() for n in g]
    assert len(names) == len(set(names)) and len(names) >= 40, len(names)
    assert {n.split("_")[0] for n in names} >= {"glb", "gltf", "fbx", "abc", "usdc", "usda", "obj", "ply", "seq"}


@pytest.mark.parametrize("group", GROUPS)
def test_damaged_files_on_the_command_line(sources, group, tmp_path):
    """Every case of ``group``: exit 2, one ``artdef: error:`` line naming the file, no traceback,
    no output, no temporary, inputs unchanged, within :data:`CASE_SECONDS` (two cases at a time)."""
    cases = list(_cases(sources)[group].items())
    problems, running = [], []

    def finish(name, folder, proc, tmp, t0, before):
        try:
            out, err = proc.communicate(timeout=max(CASE_SECONDS - (time.monotonic() - t0), 1))
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
            problems.append(f"{name}: no answer within {CASE_SECONDS} s")
            return
        lines = [ln for ln in err.splitlines() if ln.strip()]
        errors = [ln for ln in lines if ln.startswith("artdef: error:")]
        entry = cases_by_name[name][0]
        shown = os.path.basename(entry) if entry != "seq" else "seq"
        if proc.returncode != 2 or len(errors) != 1 or "Traceback" in err + out:
            problems.append(f"{name}: exit {proc.returncode}, stderr {err.strip()[-300:]!r}")
        elif shown not in errors[0] and not (group == "sequence" and "sequence" in errors[0]):
            problems.append(f"{name}: the line does not name the file: {errors[0]}")
        if (folder / "out.npz").exists():
            problems.append(f"{name}: an output was written")
        if _digests(folder) != before:
            problems.append(f"{name}: an input changed or a file was left beside it")
        if list(tmp.iterdir()):
            problems.append(f"{name}: temporaries left: {[p.name for p in tmp.iterdir()]}")

    cases_by_name = dict(cases)
    for name, (entry, files) in cases:
        folder = tmp_path / name
        folder.mkdir()
        _lay_out(folder, entry, files)
        before = _digests(folder)
        running.append((name, folder, *_start(folder, entry), before))
        if len(running) == 2:
            finish(*running.pop(0))
    while running:
        finish(*running.pop(0))
    assert not problems, "\n".join(problems)


#: one case per importer and reader, through the operator in this very Blender
OPERATOR_CASES = ("abc_half", "abc_header_bits", "glb_nan_morph_targets", "glb_half", "fbx_tail_cut",
                  "usda_nan_keys", "usdc_random", "gltf_without_bin", "obj_nan", "ply_cut_short")


def test_damaged_files_through_the_import_operator(sources, clean_scene, tmp_path):
    """*Fields from File* on each case: an ERROR naming the file, nothing added to the scene (the
    crashing Alembic importer ran in a child process: this Blender goes on), the file unchanged."""
    cases = {n: c for g in _cases(sources).values() for n, c in g.items()}
    snapshot = scene_snapshot()
    frames = (bpy.context.scene.frame_start, bpy.context.scene.frame_end)
    for name in OPERATOR_CASES:
        entry, files = cases[name]
        folder = tmp_path / name
        folder.mkdir()
        _lay_out(folder, entry, files)
        before = _digests(folder)
        with pytest.raises(RuntimeError) as err:
            bpy.ops.artdef.fields_from_file(filepath=str(folder / entry))
        assert "Traceback" not in str(err.value), (name, str(err.value))
        assert scene_snapshot() == snapshot, name
        assert (bpy.context.scene.frame_start, bpy.context.scene.frame_end) == frames, name
        assert _digests(folder) == before, name
        assert len(bpy.data.meshes) == len(snapshot["meshes"]) and len(bpy.data.actions) == 0, name


@pytest.mark.parametrize("name", ["leg.glb", "leg.fbx", "leg.abc", "leg.usdc", "tube.glb"])
def test_a_valid_file_reads_as_before(sources, clean_scene, tmp_path, name, pkg):
    """A valid file: the child reads it cleanly, and the scan the operator makes with the child's
    check is the one it makes without (the same vertices, faces and fields, to the bit)."""
    path = tmp_path / name
    path.write_bytes(sources[name])
    isolated = __import__(pkg.ops.__package__ + ".isolated", fromlist=["read_in_child"])
    values = isolated.read_in_child(str(path))
    assert values["pid"] != os.getpid() and values["vertices"] > 0
    scans = []
    for isolate in (True, False):
        bpy.ops.wm.read_homefile(use_empty=True)
        assert 'FINISHED' in bpy.ops.artdef.fields_from_file(filepath=str(path), isolate=isolate)
        scans.append(pkg.io.read_scan(bpy.context.view_layer.objects.active).scan)
    a, b = scans
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)
    assert np.array_equal(a.displacements, b.displacements)
    assert len(a.vertices) == values["vertices"]


def test_a_read_past_its_time_limit_is_stopped(sources, clean_scene, tmp_path, pkg, monkeypatch):
    """A child that does not finish in time is ended: one line saying so, the scene unchanged."""
    path = tmp_path / "leg.usdc"
    path.write_bytes(sources["leg.usdc"])
    isolated = __import__(pkg.ops.__package__ + ".isolated", fromlist=["read_in_child"])
    monkeypatch.setattr(isolated, "BASE_SECONDS", 0.05)
    monkeypatch.setattr(isolated, "SECONDS_PER_MB", 0.0)
    snapshot = scene_snapshot()
    with pytest.raises(RuntimeError) as err:
        bpy.ops.artdef.fields_from_file(filepath=str(path))
    assert "did not finish reading leg.usdc within" in str(err.value), str(err.value)
    assert scene_snapshot() == snapshot
