"""Animator and engine hand-off: fit the animated file you have from the command line,
export what you fitted the way engines expect (``python -m artdef_addon fit source.glb --links auto
--glb out.glb --fbx out.fbx``), and read it back.

The acceptance case: a character built in Blender (a skinned tube, a 3-bone chain, rotations keyed
from frame 1 every 5 frames; :func:`handoffhelpers.build_character`). Files are read back with
Blender's importers and compared with the re-imported source at every keyed frame; glTF splits
vertices at seams, so vertices are matched by rest position.
"""
import os

import pytest

from conftest import ADDON_MODULE, REPO_ROOT

bpy = pytest.importorskip("bpy")

from test_headless_gltf import _validate, accessor, read_glb  # noqa: E402  (GLB reader, validator)

from handoffhelpers import (BONES, KEYED, LAST_FRAME, MAX_TOL, RMS_TOL, _import, _ok, _run,
    _skinned, build_character, compare, glb_times, world_positions)


# --------------------------------------------------------------------------
# the character
# --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def source_glb(installed_addon, tmp_path_factory):
    d = tmp_path_factory.mktemp("source")
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    build_character()
    path = d / "source.glb"
    assert bpy.ops.export_scene.gltf(filepath=str(path), export_format='GLB') == {'FINISHED'}
    return path


@pytest.fixture(scope="module")
def cli_fit(source_glb, tmp_path_factory):
    """The issue's command (plus --fbx and -o): one run shared by the tests below."""
    d = tmp_path_factory.mktemp("fit")
    out = {"glb": d / "out.glb", "fbx": d / "out.fbx", "npz": d / "out.npz"}
    proc = _ok(_run(["-m", "artdef_addon", "fit", str(source_glb), "--links", "auto",
                     "--glb", str(out["glb"]), "--fbx", str(out["fbx"]), "-o", str(out["npz"])],
                    cwd=d))
    out["proc"] = proc
    return out


# --------------------------------------------------------------------------
# reading back
# --------------------------------------------------------------------------


# --------------------------------------------------------------------------
# 1. fit the file you have (the "What it must show")
# --------------------------------------------------------------------------

def test_fit_animated_glb_exports_one_clean_rig(cli_fit, source_glb):
    gltf, binary = read_glb(cli_fit["glb"])
    src, src_bin = read_glb(source_glb)
    assert len(gltf["meshes"]) == 1 and len(gltf.get("skins", [])) == 1
    prims = gltf["meshes"][0]["primitives"]
    attrs = {a for p in prims for a in p["attributes"]}
    assert not any(a.startswith("COLOR_") for a in attrs), attrs
    assert not any(a.startswith("_") for a in attrs), attrs
    for p in prims:  # at most 4 influences: one JOINTS/WEIGHTS set
        assert "WEIGHTS_0" in p["attributes"] and "WEIGHTS_1" not in p["attributes"]
    # only the rig: its mesh and its joints (no node of the source character, no
    # armature object); the joints are named after the source's bones
    names = {n.get("name") for n in gltf["nodes"]}
    assert len(gltf["nodes"]) == 1 + len(gltf["skins"][0]["joints"]), names
    assert "Leg" not in names and "LegRig" not in names
    assert set(BONES) <= names, names
    # one animation, keyed at the source's times (no rest key at 0, same length)
    assert len(gltf["animations"]) == 1
    assert glb_times(gltf, binary) == glb_times(src, src_bin)
    assert _validate(cli_fit["glb"]).returncode == 0      # Khronos validator: no error, no warning
    assert min(glb_times(src, src_bin)) == pytest.approx(1 / 24, abs=1e-4)


def test_fit_animated_glb_reproduces_the_source(cli_fit, source_glb):
    source = _skinned(_import(source_glb))
    ref, ref_rest = world_positions(source, KEYED)
    objects = _import(cli_fit["glb"])
    assert len([o for o in objects if o.type == 'ARMATURE']) == 1
    moved, rest = world_positions(_skinned(objects), KEYED)
    worst, rms = compare(ref, ref_rest, moved, rest)
    print(f"glTF round trip: max {100 * worst:.4f}%, rms {100 * rms:.4f}% of the diagonal")
    assert worst < MAX_TOL and rms < RMS_TOL
    # and between the keys (the exporter's sampling, the importer's interpolation)
    between = [f + 2 for f in KEYED[:-1]]
    ref_b, _ = world_positions(_skinned(_import(source_glb)), between)
    moved_b, rest_b = world_positions(_skinned(_import(cli_fit["glb"])), between)
    assert compare(ref_b, ref_rest, moved_b, rest_b)[0] < MAX_TOL


def test_fbx_round_trip_reproduces_the_source(cli_fit, source_glb):
    source = _skinned(_import(source_glb))
    ref, ref_rest = world_positions(source, KEYED)
    objects = _import(cli_fit["fbx"])
    assert sorted(o.type for o in objects) == ['ARMATURE', 'MESH'], [o.name for o in objects]
    mesh = _skinned(objects)
    assert not len(mesh.data.color_attributes)
    assert mesh.data.shape_keys is None or all(
        kb.name.startswith("artdef_field_") or kb == mesh.data.shape_keys.reference_key
        for kb in mesh.data.shape_keys.key_blocks)
    moved, rest = world_positions(mesh, KEYED)
    worst, rms = compare(ref, ref_rest, moved, rest)
    print(f"FBX round trip: max {100 * worst:.4f}%, rms {100 * rms:.4f}% of the diagonal")
    assert worst < MAX_TOL and rms < RMS_TOL
    arm = next(o for o in objects if o.type == 'ARMATURE')
    start, end = arm.animation_data.action.frame_range
    assert (round(start), round(end)) == (1, LAST_FRAME)


def test_cli_reports_fit_of_animated_file(cli_fit):
    out = cli_fit["proc"].stdout
    assert "source.glb: tracked scan" in out and "links auto: chose" in out
    assert cli_fit["npz"].is_file()


def test_blender_script_fits_an_animated_file(source_glb, tmp_path):
    """``blender -b -P scripts/artdef_fit.py -- fit ...``, run as plain Python with bpy,
    with --frames choosing every 10th frame."""
    out = tmp_path / "rig.glb"
    proc = _ok(_run([str(REPO_ROOT / "scripts" / "artdef_fit.py"), "--", "fit", str(source_glb),
                     "--links", "3", "--frames", "1:41:10", "--glb", str(out),
                     "--rotation-only"], cwd=tmp_path))
    line = [l for l in proc.stdout.splitlines() if l.startswith("rotation-only joints")]
    assert len(line) == 1 and "added error max" in line[0], proc.stdout[-2000:]
    gltf, binary = read_glb(out)
    assert len(gltf["meshes"]) == 1 and len(gltf["skins"]) == 1
    assert glb_times(gltf, binary)[0] == pytest.approx(1 / 24, abs=1e-4)
    assert glb_times(gltf, binary)[-1] == pytest.approx(41 / 24, abs=1e-4)


@pytest.mark.parametrize("argv, words", [
    (["nothing.glb"], "no such file"),
    (["notes.txt"], "not a scan"),
    (["SRC", "--frames", "9:1"], "--frames"),
    (["SRC", "--glb", "SRC"], "overwrite the input"),
])
def test_cli_bad_animated_input_is_one_line(source_glb, tmp_path, argv, words):
    argv = [str(source_glb) if a == "SRC" else a for a in argv]
    proc = _run(["-m", "artdef_addon", "fit", *argv, "--links", "2"], cwd=tmp_path, timeout=300)
    assert proc.returncode == 2, proc.stderr
    err = [line for line in proc.stderr.splitlines() if line.startswith("artdef: error:")]
    assert len(err) == 1 and words in err[0], proc.stderr[-2000:]
    assert source_glb.stat().st_size > 0


def test_export_rig_never_replaces_the_file_the_scan_came_from(installed_addon, source_glb, clean_scene, tmp_path):
    """Export Rig to the animated file the scan was sampled from: one line, the file unchanged;
    a folder or a path through a file: one line, nothing written."""
    import shutil
    src = tmp_path / "walk.glb"
    shutil.copy(source_glb, src)
    before = src.read_bytes()
    assert bpy.ops.artdef.fields_from_file(filepath=str(src)) == {'FINISHED'}
    assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}
    with pytest.raises(RuntimeError, match="walk.glb is the file the scan was imported from"):
        bpy.ops.artdef.export_rig(filepath=str(src))
    assert src.read_bytes() == before
    arm = bpy.context.active_object.artdef.rig        # Export Rig from the armature: the same
    with bpy.context.temp_override(active_object=arm, object=arm):
        with pytest.raises(RuntimeError, match="walk.glb is the file the scan was imported from"):
            bpy.ops.artdef.export_rig(filepath=str(src))
    assert src.read_bytes() == before
    with pytest.raises(RuntimeError, match="give a file name, not a folder"):
        bpy.ops.artdef.export_rig(filepath=str(tmp_path) + os.sep)
    with pytest.raises(RuntimeError, match="is a file, not a folder"):
        bpy.ops.artdef.export_rig(filepath=str(src / "out.glb"))
    assert sorted(os.listdir(tmp_path)) == ["walk.glb"]
