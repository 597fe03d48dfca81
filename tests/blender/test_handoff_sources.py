"""Animator and engine hand-off from other inputs: FBX, Alembic, OBJ sequences, several clips in
one rig, and failed imports that leave nothing.

The acceptance case: a character built in Blender (a skinned tube, a 3-bone chain, rotations keyed
from frame 1 every 5 frames; :func:`handoffhelpers.build_character`). Files are read back with
Blender's importers and compared with the re-imported source at every keyed frame; glTF splits
vertices at seams, so vertices are matched by rest position.
"""
import importlib
import json

import numpy as np
import pytest

from conftest import ADDON_MODULE, REPO_ROOT

bpy = pytest.importorskip("bpy")

from test_headless_gltf import _validate, accessor, read_glb  # noqa: E402  (GLB reader, validator)

from handoffhelpers import (MAX_TOL, RMS_TOL, _import, _ok, _play_clip, _run, _skinned,
    _two_clip_character, _write_obj, build_character, compare, glb_times, world_positions)


# --------------------------------------------------------------------------
# 1b. other inputs: FBX, Alembic, an OBJ sequence
# --------------------------------------------------------------------------


def test_faces_a_blender_mesh_cannot_hold_are_said_to_be_left_out(clean_scene, tmp_path):
    """A sequence whose files repeat a face and have a face repeating a vertex: the import leaves both
    out (Mesh.validate) and says so, in Blender and on the command line."""
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [2, 0, 0], [2, 1, 0]], dtype=float)
    polys = [[0, 1, 2], [1, 3, 2], [1, 4, 3], [4, 5, 3], [0, 1, 2], [0, 0, 1]]
    for k in range(4):
        v = verts.copy()
        far = v[:, 0] > 1
        v[far, 0] = 1 + np.cos(0.2 * k) * (v[far, 0] - 1)
        v[far, 2] = np.sin(0.2 * k) * (verts[far, 0] - 1)
        _write_obj(tmp_path / f"pose_{k:03d}.obj", v, polys)
    assert bpy.ops.artdef.import_mesh_sequence(filepath=str(tmp_path / "pose_000.obj")) == {'FINISHED'}
    mesh = bpy.context.view_layer.objects.active.data
    assert len(mesh.polygons) == 4 and mesh["artdef_dropped_faces"] == 2
    proc = _run(["-m", "artdef_addon", "fit", str(tmp_path), "--links", "2", "-o", str(tmp_path / "r.npz")],
                cwd=tmp_path)
    _ok(proc)
    assert f"note: 2 faces of {tmp_path} were left out: they repeat a vertex or another face" in proc.stdout


@pytest.mark.parametrize("kind", ["fbx", "abc", "obj-sequence"])
def test_cli_fits_fbx_alembic_and_sequences(clean_scene, tmp_path, kind):
    obj, _arm = build_character(last_frame=21)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, 21
    if kind == "fbx":
        src = tmp_path / "source.fbx"
        assert bpy.ops.export_scene.fbx(filepath=str(src)) == {'FINISHED'}
        args = [str(src), "--frames", "1:40:5"]    # past the file's last key (21): up to it
        frames = [1, 6, 11, 16, 21]
    elif kind == "abc":
        src = tmp_path / "source.abc"
        assert bpy.ops.wm.alembic_export(filepath=str(src), start=1, end=21) == {'FINISHED'}
        args = [str(src), "--frames=-4:21:5"]   # from before the cache's first frame: its grid
        frames = [1, 6, 11, 16, 21]
    else:
        folder = tmp_path / "poses"
        folder.mkdir()
        polys = [tuple(p.vertices) for p in obj.data.polygons]
        _write_obj(folder / "pose_000.obj", [tuple(v.co) for v in obj.data.vertices], polys)
        for f in (5, 10, 15, 20):
            scene.frame_set(f)
            ev = obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
            _write_obj(folder / f"pose_{f:03d}.obj", [tuple(v.co) for v in ev.to_mesh().vertices],
                       polys)
            ev.to_mesh_clear()
        args = [str(folder)]
        frames = [0, 5, 10, 15, 20]        # a file's number is its frame; 000 is the rest
    out = tmp_path / "rig.glb"
    proc = _ok(_run(["-m", "artdef_addon", "fit", *args, "--links", "3", "--glb", str(out)],
                    cwd=tmp_path))
    assert "tracked scan" in proc.stdout
    gltf, binary = read_glb(out)
    assert len(gltf["meshes"]) == 1 and len(gltf["skins"]) == 1
    assert glb_times(gltf, binary) == pytest.approx([f / 24 for f in frames], abs=1e-4)
    if kind == "fbx":   # a range with no frame of the file: one line, nothing written
        empty = tmp_path / "empty.glb"
        proc = _run(["-m", "artdef_addon", "fit", str(src), "--frames", "30:40", "--links", "3",
                     "--glb", str(empty)], cwd=tmp_path)
        assert proc.returncode == 2 and proc.stderr.strip() == (
            "artdef: error: source.fbx: no frame within 30..40 (its frames are 1..21)"), proc.stderr
        assert not empty.exists()


def test_several_clips_fit_one_rig_with_one_action_each(clean_scene, tmp_path):
    """A character with two clips (Walk 1-21, Wave 1-11) in one glTF: one rig, one
    animation per clip at the clip's own frames, each reproducing its source clip."""
    _two_clip_character()
    src = tmp_path / "two.glb"
    assert bpy.ops.export_scene.gltf(filepath=str(src), export_format='GLB') == {'FINISHED'}
    out = tmp_path / "rig.glb"
    fbx = tmp_path / "rig.fbx"
    _ok(_run(["-m", "artdef_addon", "fit", str(src), "--links", "3", "--glb", str(out),
              "--fbx", str(fbx)], cwd=tmp_path))
    gltf, binary = read_glb(out)
    assert len(gltf["meshes"]) == 1 and len(gltf["skins"]) == 1
    anims = {a["name"]: a for a in gltf["animations"]}
    assert sorted(anims) == ["Walk", "Wave"]
    for name, last in (("Walk", 21), ("Wave", 11)):
        times = [float(t) for s in anims[name]["samplers"]
                 for t in accessor(gltf, binary, s["input"]).ravel()]
        assert min(times) == pytest.approx(1 / 24, abs=1e-4)
        assert max(times) == pytest.approx(last / 24, abs=1e-4)
        paths = {c["target"]["path"] for c in anims[name]["channels"]}
        # the residual shapes' weights (where the skin leaves anything to correct) in the same clip
        shapes = bool(gltf["meshes"][0]["primitives"][0].get("targets"))
        assert {"rotation"} | ({"weights"} if shapes else set()) <= paths
    refs = {}
    for name, frames in (("Walk", [1, 6, 11, 16, 21]), ("Wave", [1, 6, 11])):
        source = _skinned(_import(src))
        _play_clip(name)
        ref, ref_rest = world_positions(source, frames)
        refs[name] = ref[1]                 # frame 6
        rig_mesh = _skinned(_import(out))
        _play_clip(name)
        moved, rest = world_positions(rig_mesh, frames)
        worst, rms = compare(ref, ref_rest, moved, rest)
        print(f"clip {name}: max {100 * worst:.4f}%, rms {100 * rms:.4f}%")
        assert worst < MAX_TOL and rms < RMS_TOL
    # the two clips are different motions (the comparison switched clips)
    assert np.abs(refs["Walk"] - refs["Wave"]).max() > 0.05
    # FBX: one take per clip (armature + shape keys); Blender's FBX exporter writes an
    # NLA take from its strip's start, so the clip's frame 1 is the take's frame 0
    objects = _import(fbx)
    assert sorted(o.type for o in objects) == ['ARMATURE', 'MESH']
    takes = sorted({a.name.split("|")[-1] for a in bpy.data.actions})
    assert takes == ["Walk", "Wave"]
    for name, frames in (("Walk", [1, 6, 11, 16, 21]), ("Wave", [1, 6, 11])):
        objects = _import(fbx)
        rig_mesh = _skinned(objects)
        arm = rig_mesh.find_armature()
        # the shape keys' take only where the rig has residual shapes (the skin may be exact)
        for id_data in [i for i in (arm, rig_mesh.data.shape_keys) if i is not None]:
            owner = id_data.name
            action = next(a for a in bpy.data.actions
                          if a.name.endswith("|" + name) and a.name.startswith(owner))
            # 4.5 picks no slot by itself when the action is assigned
            importlib.import_module(ADDON_MODULE + ".operators.compat").assign_action(id_data, action)
        moved, rest = world_positions(rig_mesh, [f - 1 for f in frames])
        source = _skinned(_import(src))
        _play_clip(name)
        ref, ref_rest = world_positions(source, frames)
        worst, rms = compare(ref, ref_rest, moved, rest)
        print(f"FBX clip {name}: max {100 * worst:.4f}%, rms {100 * rms:.4f}%")
        assert worst < MAX_TOL and rms < RMS_TOL
    # last, as it skips without node: the Khronos validator, no error; no warning where the
    # exporter can leave the armature node out with one animation per clip (5.1 on), else
    # only that node's warning
    messages = json.loads(_validate(out).stdout)["issues"]["messages"]
    compat = importlib.import_module(ADDON_MODULE + ".operators.compat")
    allowed = set() if compat.gltf_tracks_drop_armature_node() else {"NODE_SKINNED_MESH_NON_ROOT"}
    assert {m["code"] for m in messages if m["severity"] == 1} <= allowed, messages


def test_refit_of_several_clips_in_blender(clean_scene, tmp_path, monkeypatch):
    """A two-clip file fitted in Blender, then fitted again: the re-fit replaces the clips' NLA
    tracks and actions under the same names; a re-fit whose rig build fails leaves the previous
    rig, its tracks and actions exactly as they were."""
    from test_blender_versions import _rig_state
    compat = importlib.import_module(ADDON_MODULE + ".operators.compat")
    replay = importlib.import_module(ADDON_MODULE + ".operators.replay")
    _two_clip_character()
    src = tmp_path / "two.glb"
    assert bpy.ops.export_scene.gltf(filepath=str(src), export_format='GLB') == {'FINISHED'}
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    assert bpy.ops.artdef.fields_from_file(filepath=str(src)) == {'FINISHED'}
    scan = bpy.context.view_layer.objects.active

    def names():
        return {n: sorted(d.name for d in getattr(bpy.data, n)) for n in ("objects", "armatures", "actions")}

    assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}
    first = names()
    assert bpy.ops.artdef.fit(links=2) == {'FINISHED'}
    assert names() == first
    tracks = sorted(t.name for t in scan.data.shape_keys.animation_data.nla_tracks)
    assert tracks == sorted(t.name for t in scan.artdef.rig.animation_data.nla_tracks) == ["Walk", "Wave"]
    before = _rig_state(scan, compat)
    real = replay._build_replay

    def fail_after(*args, **kwargs):
        real(*args, **kwargs)
        raise RuntimeError("forced failure")

    monkeypatch.setattr(replay, "_build_replay", fail_after)
    with pytest.raises(RuntimeError, match="forced failure"):
        bpy.ops.artdef.fit(links=3)
    monkeypatch.setattr(replay, "_build_replay", real)
    after = _rig_state(scan, compat)
    assert {k: v for k, v in after.items() if v != before[k]} == {}, \
        {k: before[k] for k, v in after.items() if v != before[k]}
    assert bpy.ops.artdef.clear_rig() == {'FINISHED'}
    assert names()["actions"] == ["Walk", "Wave"]       # the imported clips only


def test_several_sequences_fit_one_rig_with_one_clip_each(clean_scene, tmp_path):
    """``fit walk/ --clip wave/``: two OBJ sequences of one mesh (same rest file),
    one rig, one animation per sequence at the files' numbers."""
    obj, arm = build_character(last_frame=21)
    scene = bpy.context.scene
    polys = [tuple(p.vertices) for p in obj.data.polygons]
    rest = [tuple(v.co) for v in obj.data.vertices]
    numbers = {"walk": (5, 10, 15, 20), "wave": (3, 6, 9)}
    for name, frames in numbers.items():
        folder = tmp_path / name
        folder.mkdir()
        _write_obj(folder / "pose_000.obj", rest, polys)
        for f in frames:
            scene.frame_set(f if name == "walk" else 21 - f)
            ev = obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
            _write_obj(folder / f"pose_{f:03d}.obj", [tuple(v.co) for v in ev.to_mesh().vertices],
                       polys)
            ev.to_mesh_clear()
    out = tmp_path / "rig.glb"
    _ok(_run(["-m", "artdef_addon", "fit", str(tmp_path / "walk"), "--clip", str(tmp_path / "wave"),
              "--links", "3", "--glb", str(out)], cwd=tmp_path))
    gltf, binary = read_glb(out)
    assert len(gltf["meshes"]) == 1 and len(gltf["skins"]) == 1
    anims = {a["name"]: a for a in gltf["animations"]}
    assert sorted(anims) == ["walk", "wave"]
    for name, frames in numbers.items():
        times = sorted({round(float(t) * 24, 3) for s in anims[name]["samplers"]
                        for t in accessor(gltf, binary, s["input"]).ravel()})
        assert times[0] == 0 and times[-1] == frames[-1]
    # --frames applies to every input: the files numbered 6..15 of each (rest file kept)
    picked = tmp_path / "picked.glb"
    _ok(_run(["-m", "artdef_addon", "fit", str(tmp_path / "walk"), "--clip", str(tmp_path / "wave"),
              "--links", "3", "--frames", "6:15", "--glb", str(picked)], cwd=tmp_path))
    gltf, binary = read_glb(picked)
    for anim in gltf["animations"]:
        times = sorted({round(float(t) * 24, 3) for s in anim["samplers"]
                        for t in accessor(gltf, binary, s["input"]).ravel()})
        assert times[-1] == {"walk": 15, "wave": 9}[anim["name"]], (anim["name"], times)
    # a range with no file of one input: one line naming it, nothing written
    empty = tmp_path / "empty.glb"
    proc = _run(["-m", "artdef_addon", "fit", str(tmp_path / "walk"), "--clip", str(tmp_path / "wave"),
                 "--links", "3", "--frames", "10:12", "--glb", str(empty)], cwd=tmp_path)
    assert proc.returncode == 2 and "wave/pose_###.obj: no file is numbered within frames 10..12" \
        in proc.stderr, proc.stderr[-1500:]
    assert len(proc.stderr.strip().splitlines()) == 1 and not empty.exists()
    # a clip of another mesh: one line, nothing written
    other = tmp_path / "other"
    other.mkdir()
    _write_obj(other / "pose_000.obj", [(x, y, 2 * z) for x, y, z in rest], polys)
    _write_obj(other / "pose_001.obj", [(x + 0.1, y, 2 * z) for x, y, z in rest], polys)
    bad = tmp_path / "bad.glb"
    proc = _run(["-m", "artdef_addon", "fit", str(tmp_path / "walk"), "--clip", str(other),
                 "--links", "3", "--glb", str(bad)], cwd=tmp_path)
    assert proc.returncode == 2 and "another rest shape" in proc.stderr, proc.stderr[-1500:]
    assert not bad.exists()


def test_a_failed_import_of_an_animated_file_leaves_nothing(installed_addon, clean_scene, tmp_path):
    """A file whose mesh does not deform (only the object moves): one line naming the file, and
    every datablock the importer made (meshes, materials, actions) removed, the frames as they were."""
    bpy.ops.mesh.primitive_cube_add()
    cube = bpy.context.active_object
    for f, x in ((1, 0.0), (20, 3.0)):
        cube.location.x = x
        cube.keyframe_insert("location", frame=f)
    still = tmp_path / "still.glb"
    assert bpy.ops.export_scene.gltf(filepath=str(still), export_format='GLB') == {'FINISHED'}
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 5, 77
    counts = {name: len(getattr(bpy.data, name)) for name in ("objects", "meshes", "materials", "actions")}
    with pytest.raises(RuntimeError, match="still.glb"):
        bpy.ops.artdef.fields_from_file(filepath=str(still))
    assert {name: len(getattr(bpy.data, name)) for name in counts} == counts
    assert (scene.frame_start, scene.frame_end) == (5, 77)
