"""Animator and engine hand-off (issue 17): fit the animated file you have,
export what you fitted the way engines expect, and read it back.

The acceptance case: a character built in Blender (a skinned tube, a 3-bone
chain, rotations keyed from frame 1 every 5 frames) exported with Blender's
own glTF exporter, fitted by ``python -m artdef_addon fit source.glb --links
auto --glb out.glb --fbx out.fbx``; the files are read back with Blender's
importers and compared with the re-imported source at every keyed frame.
glTF splits vertices at seams, so vertices are matched by rest position.
"""

import importlib
import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from conftest import ADDON_MODULE, REPO_ROOT

bpy = pytest.importorskip("bpy")

from test_headless_gltf import _validate, accessor, read_glb  # noqa: E402  (GLB reader, validator)

KEY_STEP = 5
LAST_FRAME = 41                 # keys at 1, 6, ..., 41
KEYED = list(range(1, LAST_FRAME + 1, KEY_STEP))
MAX_TOL = 0.01                  # of the bounding-box diagonal, at the worst vertex
RMS_TOL = 0.002


def _run(args, cwd, timeout=900):
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        [str(REPO_ROOT)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    proc = subprocess.run([sys.executable, *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=timeout)
    return proc


def _ok(proc):
    assert proc.returncode == 0, (
        f"exit {proc.returncode}\n--- stdout\n{proc.stdout[-4000:]}\n--- stderr\n{proc.stderr[-4000:]}")
    return proc


# --------------------------------------------------------------------------
# the character
# --------------------------------------------------------------------------

def _edit_bones(arm, fn):
    view_layer = bpy.context.view_layer
    view_layer.objects.active = arm
    with bpy.context.temp_override(active_object=arm, object=arm, selected_objects=[arm],
                                   selected_editable_objects=[arm]):
        bpy.ops.object.mode_set(mode='EDIT')
        fn(arm.data.edit_bones)
        bpy.ops.object.mode_set(mode='OBJECT')


BONES = ("hip", "knee", "ankle")


def build_character(last_frame=LAST_FRAME, step=KEY_STEP, name="Leg"):
    """A tube (12 sides, 19 rings, 3 units tall) skinned with blended weights to
    a chain hip > knee > ankle, rotations keyed at 1, 1+step, ..., last_frame."""
    sides, rings, height = 12, 19, 3.0
    z = np.linspace(0.0, height, rings)
    ang = np.arange(sides) * 2 * math.pi / sides
    verts = np.array([(0.2 * math.cos(a), 0.2 * math.sin(a), zz) for zz in z for a in ang])
    polys = [(r * sides + s, r * sides + (s + 1) % sides, (r + 1) * sides + (s + 1) % sides,
              (r + 1) * sides + s) for r in range(rings - 1) for s in range(sides)]
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(verts.tolist(), [], polys)
    obj = bpy.data.objects.new(name, mesh)
    arm = bpy.data.objects.new(f"{name}Rig", bpy.data.armatures.new(f"{name}Rig"))
    for o in (arm, obj):
        bpy.context.scene.collection.objects.link(o)

    def bones(eb):
        parent = None
        for i, n in enumerate(BONES):
            b = eb.new(n)
            b.head, b.tail = (0, 0, float(i)), (0, 0, float(i + 1))
            b.parent, b.use_connect = parent, parent is not None
            parent = b
    _edit_bones(arm, bones)
    for i, n in enumerate(BONES):
        w = np.clip(1.0 - np.abs(verts[:, 2] - (i + 0.5)), 0.0, 1.0)
        if i == 0:
            w[verts[:, 2] < 0.5] = 1.0
        if i == len(BONES) - 1:
            w[verts[:, 2] > 2.5] = 1.0
        vg = obj.vertex_groups.new(name=n)
        for v in np.flatnonzero(w > 0):
            vg.add([int(v)], float(w[v]), 'REPLACE')
    obj.parent = arm
    obj.modifiers.new("Armature", 'ARMATURE').object = arm
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, last_frame
    for f in range(1, last_frame + 1, step):
        t = (f - 1) / max(last_frame - 1, 1)
        for i, n in enumerate(BONES):
            pb = arm.pose.bones[n]
            pb.rotation_mode = 'XYZ'
            pb.rotation_euler = (0.7 * math.sin(2 * math.pi * t + i),
                                 0.4 * math.sin(4 * math.pi * t) * (i > 0), 0.0)
            pb.keyframe_insert("rotation_euler", frame=f)
    bpy.context.view_layer.objects.active = obj
    return obj, arm


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

def _import(path):
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    if str(path).endswith(".fbx"):
        # Blender's FBX importer shifts animation by +1 frame by default
        # (anim_offset=1): the file's times are the source's, read them as such.
        assert bpy.ops.import_scene.fbx(filepath=str(path), anim_offset=0.0) == {'FINISHED'}
    else:
        assert bpy.ops.import_scene.gltf(filepath=str(path)) == {'FINISHED'}
    return [o for o in bpy.data.objects]


def _skinned(objects):
    meshes = [o for o in objects if o.type == 'MESH' and o.find_armature() is not None]
    assert len(meshes) == 1, [(o.name, o.type) for o in objects]
    return meshes[0]


def world_positions(obj, frames):
    """(F, N, 3) evaluated world positions of ``obj`` at ``frames`` and (N, 3) at rest."""
    scene = bpy.context.scene
    out = []
    for f in frames:
        scene.frame_set(f)
        dg = bpy.context.evaluated_depsgraph_get()
        ev = obj.evaluated_get(dg)
        me = ev.to_mesh()
        co = np.empty(3 * len(me.vertices), dtype=np.float32)
        me.vertices.foreach_get("co", co)
        mw = np.array(ev.matrix_world)
        ev.to_mesh_clear()
        co = co.reshape(-1, 3).astype(np.float64)
        out.append(co @ mw[:3, :3].T + mw[:3, 3])
    rest = np.empty(3 * len(obj.data.vertices), dtype=np.float32)
    obj.data.vertices.foreach_get("co", rest)
    mw = np.array(obj.matrix_world)
    return np.array(out), rest.reshape(-1, 3) @ mw[:3, :3].T + mw[:3, 3]


def compare(reference, ref_rest, moved, rest):
    """(max, rms) distance between ``moved`` and ``reference`` as fractions of the
    diagonal, vertices matched by nearest rest position."""
    from scipy.spatial import cKDTree
    dist, index = cKDTree(ref_rest).query(rest)
    diag = float(np.linalg.norm(np.ptp(ref_rest, axis=0)))
    assert dist.max() < 1e-4 * diag, "the output's rest mesh is not the source's"
    err = np.linalg.norm(moved - reference[:, index], axis=-1)
    return err.max() / diag, math.sqrt(float(np.mean(err ** 2))) / diag


def glb_times(gltf, binary):
    return sorted({round(float(t), 5) for a in gltf.get("animations", [])
                   for s in a["samplers"] for t in accessor(gltf, binary, s["input"]).ravel()})


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


# --------------------------------------------------------------------------
# 2. Export Rig operator (UI path), clip timing
# --------------------------------------------------------------------------

@pytest.fixture
def fitted_character(clean_scene, installed_addon):
    """The character fitted in the scene through Fields from Animation + Fit."""
    obj, arm = build_character(last_frame=21)
    scene = clean_scene
    scene.frame_start, scene.frame_end = 1, 100  # the user's range: must stay
    assert bpy.ops.artdef.fields_from_animation(frame_start=1, frame_end=21,
                                                frame_step=KEY_STEP) == {'FINISHED'}
    scan_obj = bpy.context.active_object
    assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}
    return scan_obj, obj, arm


def test_replay_keeps_the_source_frames(fitted_character, installed_addon):
    scan_obj, source, _arm = fitted_character
    compat = importlib.import_module(installed_addon + ".operators.compat")
    rig_action = scan_obj.artdef.rig.animation_data.action
    assert compat.keyed_frames(rig_action) == [1.0, 6.0, 11.0, 16.0, 21.0]
    key_action = scan_obj.data.shape_keys.animation_data.action
    assert compat.keyed_frames(key_action) == [1.0, 6.0, 11.0, 16.0, 21.0]
    scene = bpy.context.scene
    assert (scene.frame_start, scene.frame_end) == (1, 100)
    # the replay matches the source at its keys
    for f in (6, 16):
        scene.frame_set(f)
        dg = bpy.context.evaluated_depsgraph_get()
        a = np.array([v.co for v in scan_obj.evaluated_get(dg).to_mesh().vertices])
        b = np.array([v.co for v in source.evaluated_get(dg).to_mesh().vertices])
        diag = np.linalg.norm(np.ptp(b, axis=0))
        assert np.abs(a - b).max() < 1e-3 * diag


def test_export_rig_operator_writes_only_the_rig(fitted_character, tmp_path):
    scan_obj, source, arm = fitted_character
    assert "menu_export" in _menu_functions(bpy.types.TOPBAR_MT_file_export)
    drawn = _draw()
    for idname in ("artdef.export_rig", "artdef.finalize", "artdef.name_bones",
                   "artdef.rotation_only"):
        assert ("operator", idname, True) in drawn, idname       # panel buttons, enabled
    groups_before = [g.name for g in scan_obj.vertex_groups]
    selected_before = sorted(o.name for o in bpy.context.selected_objects)
    path = tmp_path / "rig.glb"
    assert bpy.ops.artdef.export_rig(filepath=str(path)) == {'FINISHED'}
    gltf, binary = read_glb(path)
    assert len(gltf["meshes"]) == 1 and len(gltf["skins"]) == 1
    names = {n.get("name") for n in gltf["nodes"]}
    assert scan_obj.name in names and source.name not in names and not names & set(BONES)
    attrs = {a for p in gltf["meshes"][0]["primitives"] for a in p["attributes"]}
    assert not any(a.startswith("COLOR_") for a in attrs)
    assert glb_times(gltf, binary) == pytest.approx([f / 24 for f in (1, 6, 11, 16, 21)], abs=1e-4)
    # the scene is as it was: the mesh keeps its groups (the source's too), selection, name
    assert [g.name for g in scan_obj.vertex_groups] == groups_before
    assert sorted(o.name for o in bpy.context.selected_objects) == selected_before
    assert bpy.data.objects.get(scan_obj.name) == scan_obj
    assert len([o for o in bpy.data.objects if o.type == 'MESH']) == 2
    # debug colours only when asked
    dbg = tmp_path / "debug.glb"
    assert bpy.ops.artdef.export_rig(filepath=str(dbg), debug_attributes=True) == {'FINISHED'}
    attrs = {a for p in read_glb(dbg)[0]["meshes"][0]["primitives"] for a in p["attributes"]}
    assert "COLOR_0" in attrs


def test_file_operators_take_paths_next_to_the_blend_without_warnings(fitted_character, tmp_path):
    """'//' paths (next to the saved .blend) export the rig there and import it back as a scan,
    and Blender does not warn that the file path properties cannot take them (5.3 does for
    ImportHelper's/ExportHelper's own ``filepath``)."""
    import warnings
    scan_obj = fitted_character[0]
    assert bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "s.blend")) == {'FINISHED'}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert bpy.ops.artdef.export_rig(filepath="//rig.glb") == {'FINISHED'}
        assert (tmp_path / "rig.glb").is_file() and not (tmp_path / "//rig.glb").exists()
        meshes = {o.name for o in bpy.data.objects if o.type == 'MESH'}
        assert bpy.ops.artdef.fields_from_file(filepath="//rig.glb") == {'FINISHED'}
    new = bpy.context.view_layer.objects.active
    assert new.name not in meshes and new.type == 'MESH'
    assert new.data["artdef_source_path"] == str(tmp_path / "rig.glb")
    triangles = sum(len(p.vertices) - 2 for p in scan_obj.data.polygons)   # glTF triangulates
    assert len(new.data.polygons) == triangles
    relative = [w for w in caught if "relative" in str(w.message)]
    assert not relative, relative[0].message


def test_export_rig_from_the_armature_and_as_fbx(fitted_character, tmp_path):
    scan_obj, _source, _arm = fitted_character
    rig_obj = scan_obj.artdef.rig
    bpy.context.view_layer.objects.active = rig_obj
    path = tmp_path / "rig.fbx"
    assert bpy.ops.artdef.export_rig(filepath=str(path), export_format='FBX') == {'FINISHED'}
    objects = _import(path)
    assert sorted(o.type for o in objects) == ['ARMATURE', 'MESH']


def test_export_rig_writes_all_or_nothing(fitted_character, tmp_path, monkeypatch):
    """Export Rig writes through a hidden folder and renames into place: an exporter that fails
    half-way leaves the user's previous export byte-identical and no temporary behind; glTF
    Separate puts the .gltf and its .bin side by side."""
    export = importlib.import_module(ADDON_MODULE + ".operators.export")
    path = tmp_path / "rig.glb"
    path.write_bytes(b"the previous export")
    real = export._gltf

    def half_written(target, *args, **kwargs):
        with open(target, "wb") as f:
            f.write(b"glTF half")
        raise RuntimeError("disk full")

    monkeypatch.setattr(export, "_gltf", half_written)
    with pytest.raises(RuntimeError, match="Export failed: disk full"):
        bpy.ops.artdef.export_rig(filepath=str(path))
    assert path.read_bytes() == b"the previous export"
    assert sorted(os.listdir(tmp_path)) == ["rig.glb"]
    monkeypatch.setattr(export, "_gltf", real)
    assert bpy.ops.artdef.export_rig(filepath=str(path)) == {'FINISHED'}
    assert read_glb(path)[0]["skins"]
    sep = tmp_path / "sep" / "rig.gltf"
    assert bpy.ops.artdef.export_rig(filepath=str(sep), export_format='GLTF_SEPARATE') == {'FINISHED'}
    assert sorted(os.listdir(sep.parent)) == ["rig.bin", "rig.gltf"]
    doc = json.loads(sep.read_text())
    assert [b["uri"] for b in doc["buffers"]] == ["rig.bin"]
    assert os.path.getsize(sep.parent / "rig.bin") == doc["buffers"][0]["byteLength"]


def test_export_rig_needs_a_rig(clean_scene):
    obj, _arm = build_character(last_frame=6)
    bpy.context.view_layer.objects.active = obj
    assert not bpy.ops.artdef.export_rig.poll()


def test_greens_rig_exports_baked_without_helpers(clean_scene, installed_addon, tmp_path):
    scan_mod = importlib.import_module(installed_addon + ".artdef_addon.files")
    samples = importlib.import_module(installed_addon + ".artdef_addon.samples")
    npz = tmp_path / "greens.npz"
    scan_mod.write_scan(npz, samples.make("greens_rod"))
    assert bpy.ops.artdef.import_scan(filepath=str(npz)) == {'FINISHED'}
    obj = bpy.context.active_object
    assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}
    path = tmp_path / "greens.glb"
    assert bpy.ops.artdef.export_rig(filepath=str(path)) == {'FINISHED'}
    gltf, binary = read_glb(path)
    names = {n.get("name") for n in gltf["nodes"]}
    assert not any(n.startswith("artdef_load") for n in names), names  # no empties, no helpers
    assert len(gltf["animations"]) == 1
    paths = {c["target"]["path"] for c in gltf["animations"][0]["channels"]}
    assert "weights" in paths and "rotation" in paths
    # the live rig is unchanged: drivers, no baked action left behind
    arm = obj.artdef.rig
    assert arm.animation_data.action is None and len(arm.animation_data.drivers) > 0


def _menu_functions(menu):
    """Names of the functions appended to a menu (File > Export ...)."""
    return [f.__name__ for f in menu._dyn_ui_initialize()
            if f.__module__.endswith(".operators.export")]


# --------------------------------------------------------------------------
# 3. Finalize
# --------------------------------------------------------------------------

def _evaluated(obj, frames):
    return world_positions(obj, frames)[0]


def test_finalize_leaves_a_plain_armature_and_mesh(fitted_character, installed_addon):
    scan_obj, source, _ = fitted_character
    rig_mod = importlib.import_module(installed_addon + ".operators.rig")
    io_mod = importlib.import_module(installed_addon + ".operators.io")
    arm = scan_obj.artdef.rig
    # input data on the mesh: a shape key the fit did not make
    scan_obj.shape_key_add(name="source_smile", from_mix=False)
    before = _evaluated(scan_obj, [1, 6, 13, 21])
    assert bpy.ops.artdef.finalize() == {'FINISHED'}
    assert not rig_mod.has_rig(scan_obj) and not io_mod.has_scan(scan_obj.data)
    assert not len(scan_obj.data.color_attributes)
    assert rig_mod.RESIDUAL_ATTR not in scan_obj.data.attributes
    compat = importlib.import_module(installed_addon + ".operators.compat")
    for id_data in (scan_obj, scan_obj.data, arm, arm.data):
        # 4.5 lists the registered Object.artdef group among keys(): not a custom property
        assert not [k for k in compat.custom_keys(id_data) if k.startswith("artdef")], id_data
    keys = [kb.name for kb in scan_obj.data.shape_keys.key_blocks]
    assert "source_smile" not in keys
    assert sorted(g.name for g in scan_obj.vertex_groups) == \
        sorted(b.name for b in arm.data.bones if b.use_deform)
    assert source.hide_get()                       # the source no longer sits under the rig
    np.testing.assert_allclose(_evaluated(scan_obj, [1, 6, 13, 21]), before, atol=1e-6)
    assert not bpy.ops.artdef.clear_rig.poll()      # ArtDef no longer manages it


def test_finalize_bakes_a_greens_rig(clean_scene, installed_addon, tmp_path):
    scan_mod = importlib.import_module(installed_addon + ".artdef_addon.files")
    samples = importlib.import_module(installed_addon + ".artdef_addon.samples")
    npz = tmp_path / "greens.npz"
    scan_mod.write_scan(npz, samples.make("greens_rod"))
    assert bpy.ops.artdef.import_scan(filepath=str(npz)) == {'FINISHED'}
    obj = bpy.context.active_object
    assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}
    arm = obj.artdef.rig
    scene = bpy.context.scene
    frames = [scene.frame_start + 10, scene.frame_start + 37, scene.frame_end - 10]
    before = _evaluated(obj, frames)
    assert bpy.ops.artdef.finalize() == {'FINISHED'}
    assert not [o for o in bpy.data.objects if o.type == 'EMPTY']
    assert all(b.use_deform for b in arm.data.bones)
    assert not arm.animation_data.drivers and not obj.data.shape_keys.animation_data.drivers
    assert not any(pb.constraints for pb in arm.pose.bones)
    diag = np.linalg.norm(np.ptp(before[0], axis=0))
    assert np.abs(_evaluated(obj, frames) - before).max() < 1e-4 * diag


# --------------------------------------------------------------------------
# 4. bones an animator can read
# --------------------------------------------------------------------------

def test_fields_from_animation_leaves_the_source_skin_out(fitted_character):
    scan_obj, _source, _ = fitted_character
    arm = scan_obj.artdef.rig
    assert {g.name for g in scan_obj.vertex_groups} == {b.name for b in arm.data.bones}


def test_bones_take_the_source_joint_names(fitted_character):
    scan_obj, source, _ = fitted_character
    arm = scan_obj.artdef.rig
    before = _evaluated(scan_obj, [6, 16])
    assert bpy.ops.artdef.name_bones(scheme='AUTO') == {'FINISHED'}
    names = [b.name for b in arm.data.bones]
    assert sorted(names) == sorted(BONES)
    # each fitted bone sits on the source bone it is named after
    src = source.find_armature().data.bones
    for b in arm.data.bones:
        mid = 0.5 * (np.array(b.head_local) + np.array(b.tail_local))
        s = src[b.name]
        assert s.head_local.z - 0.01 <= mid[2] <= s.tail_local.z + 0.01, (b.name, mid)
    # vertex groups and the fit's records follow; the motion is unchanged
    assert {g.name for g in scan_obj.vertex_groups} == set(names)
    assert {item.name for item in scan_obj.artdef.groups} == set(names)
    np.testing.assert_allclose(_evaluated(scan_obj, [6, 16]), before, atol=1e-6)


def test_bones_numbered_root_first_and_renamed_one_by_one(fitted_character):
    scan_obj, _source, _ = fitted_character
    arm = scan_obj.artdef.rig
    before = _evaluated(scan_obj, [11])
    assert bpy.ops.artdef.name_bones(scheme='TREE') == {'FINISHED'}
    number = {b.name: int(b.name.split("_")[1]) for b in arm.data.bones}
    assert arm.data.bones["bone_00"].parent is None
    for b in arm.data.bones:
        assert b.parent is None or number[b.parent.name] < number[b.name]
    assert bpy.ops.artdef.name_bones(scheme='ONE', bone="bone_01", new_name="thigh") == {'FINISHED'}
    assert "thigh" in arm.data.bones and "thigh" in scan_obj.vertex_groups
    assert "bone_01" not in scan_obj.vertex_groups
    np.testing.assert_allclose(_evaluated(scan_obj, [11]), before, atol=1e-6)
    # a name in use is refused, nothing changes
    with pytest.raises(RuntimeError):
        bpy.ops.artdef.name_bones(scheme='ONE', bone="thigh", new_name="bone_00")
    assert "thigh" in arm.data.bones


def test_tree_order_is_root_first():
    from importlib import import_module
    naming = import_module([m for m in sys.modules if m.endswith("operators.naming")][0])
    # 0 <- 2 <- 1, 2 <- 3 <- 4 (link 2 the root, its branch 3-4 bigger than 0-1? equal: index)
    order = naming.tree_order([2, 0, -1, 2, 3])
    assert order[0] == 2
    pos = {l: i for i, l in enumerate(order)}
    assert pos[0] < pos[1] and pos[3] < pos[4]


# --------------------------------------------------------------------------
# 5. engine-friendly motion
# --------------------------------------------------------------------------

def test_rotation_only_joints_keep_bone_lengths_and_report_the_error(fitted_character,
                                                                     installed_addon):
    scan_obj, source, _ = fitted_character
    compat = importlib.import_module(installed_addon + ".operators.compat")
    arm = scan_obj.artdef.rig
    # make the fitted joints imperfect: a child bone translates a little at frame 11
    child = next(b for b in arm.data.bones if b.parent is not None)
    pb = arm.pose.bones[child.name]
    for f, x in ((1, 0.0), (11, 0.03), (21, 0.0)):
        pb.location = (x, 0.0, 0.0)
        pb.keyframe_insert("location", frame=f)
    assert bpy.ops.artdef.rotation_only() == {'FINISHED'}
    paths = {(fc.data_path.split('"')[1], fc.data_path.rsplit(".", 1)[1])
             for fc in compat.action_fcurves(arm.animation_data.action)}
    children = {b.name for b in arm.data.bones if b.parent is not None}
    assert not {(b, p) for b, p in paths if b in children and p in ("location", "scale")}
    worst, rms = scan_obj.data["artdef_rotation_only_error"]
    # the 0.03 translation removed at frame 11 is what it reports (diagonal ~3.03)
    diag = np.linalg.norm(np.ptp(np.array([v.co for v in scan_obj.data.vertices]), axis=0))
    assert worst == pytest.approx(100 * 0.03 / diag, rel=0.05)
    assert 0 < rms < worst
    # bone lengths fixed: every child bone's head stays at its parent's joint
    bpy.context.scene.frame_set(11)
    for b in arm.pose.bones:
        if b.parent is not None:
            rest_offset = (b.bone.parent.matrix_local.inverted() @ b.bone.matrix_local).translation
            posed_offset = (b.parent.matrix.inverted() @ b.matrix).translation
            assert (posed_offset - rest_offset).length < 1e-5


# --------------------------------------------------------------------------
# 6. plain words in the panel
# --------------------------------------------------------------------------

def _draw(closed=True):
    from test_blender_operators import _Layout

    class Layout(_Layout):
        def _sub(self, *args, **kw):
            return Layout(self.log)
        box = row = column = split = _sub

        def panel(self, idname, default_closed=True):
            self.log.append(("panel", idname))
            return Layout(self.log), (None if closed else Layout(self.log))

    log = []
    bpy.types.ARTDEF_PT_main.draw(type("P", (), {"layout": Layout(log)})(), bpy.context)
    return log


def test_panel_shows_greens_settings_only_for_greens_and_the_rest_under_advanced(
        clean_scene, installed_addon, tmp_path):
    obj, _arm = build_character(last_frame=11)
    assert bpy.ops.artdef.fields_from_animation(frame_start=1, frame_end=11,
                                                frame_step=KEY_STEP) == {'FINISHED'}
    log = _draw(closed=True)
    props = {e[1] for e in log if e[0] == "prop"}
    assert not props & {"mode", "p_max", "load_index"}          # tracked scan
    assert not props & {"motion", "skin", "reduce", "memory_budget"}  # Advanced is closed
    assert ("panel", "ARTDEF_fit_advanced") in log
    props = {e[1] for e in _draw(closed=False) if e[0] == "prop"}
    assert {"motion", "reduce", "memory_budget"} <= props
    scan_mod = importlib.import_module(installed_addon + ".artdef_addon.files")
    samples = importlib.import_module(installed_addon + ".artdef_addon.samples")
    npz = tmp_path / "greens.npz"
    scan_mod.write_scan(npz, samples.make("greens_rod"))
    assert bpy.ops.artdef.import_scan(filepath=str(npz)) == {'FINISHED'}
    props = {e[1] for e in _draw() if e[0] == "prop"}
    assert {"mode", "p_max"} <= props


def test_auto_links_reason_in_one_plain_sentence(clean_scene, installed_addon):
    wording = importlib.import_module(installed_addon + ".artdef_addon.wording")
    obj, _arm = build_character(last_frame=21)
    assert bpy.ops.artdef.fields_from_animation(frame_start=1, frame_end=21,
                                                frame_step=KEY_STEP) == {'FINISHED'}
    scan_obj = bpy.context.active_object
    assert bpy.ops.artdef.fit(auto_links=True, max_links=6) == {'FINISHED'}
    errors = list(scan_obj["artdef_link_errors"])
    links = scan_obj.artdef.fit_links
    assert len(errors) >= links and errors[0] > errors[links - 1]
    sentence = wording.plain_link_reason(links, errors)
    assert sentence.endswith(".") and ". " not in sentence      # one sentence
    assert "tau" not in sentence and "k^" not in sentence and "log scale" not in sentence
    assert sentence.startswith(f"{links} links leave ")
    labels = [e[1] for e in _draw(closed=True) if e[0] == "label"]
    assert "unexplained" in " ".join(labels)
    # the sentence says the fit's own error, the one the panel reports below it (not the quick curve's)
    fitted = scan_obj.artdef.fit_articulation_percent
    assert f"{links} links leave {wording._percent(fitted)} of the motion unexplained" in " ".join(labels)
    assert ("panel", "ARTDEF_link_curve") in _draw(closed=True)
    curve = [e[1] for e in _draw(closed=False) if e[0] == "label" and "links  " in e[1]]
    assert len(curve) == len(errors) and curve[links - 1].endswith("<")


# --------------------------------------------------------------------------
# 1b. other inputs: FBX, Alembic, an OBJ sequence
# --------------------------------------------------------------------------

def _write_obj(path, verts, polys):
    with open(path, "w") as f:
        f.write("".join(f"v {x:.7f} {y:.7f} {z:.7f}\n" for x, y, z in verts))
        f.write("".join("f " + " ".join(str(i + 1) for i in p) + "\n" for p in polys))


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


def _play_clip(clip):
    """Make clip ``clip`` (an NLA track name, as Blender's glTF importer stores a
    file's animations) the active action of every object and shape-key set."""
    for o in bpy.data.objects:
        for id_data in (o, getattr(o.data, "shape_keys", None)):
            ad = getattr(id_data, "animation_data", None) if id_data is not None else None
            if ad is None:
                continue
            strips = [s for t in ad.nla_tracks if t.name == clip for s in t.strips]
            if strips:
                ad.use_nla = False
                ad.action = strips[0].action
                if hasattr(ad, "action_slot") and ad.action_slot is None and ad.action.slots:
                    ad.action_slot = ad.action.slots[0]


def _two_clip_character():
    """The test character with two clips: Walk (its action, frames 1-21) and Wave (keys at 1, 6, 11,
    on an NLA track named Wave). Returns (mesh, armature, walk, wave)."""
    obj, arm = build_character(last_frame=21)
    walk = arm.animation_data.action
    walk.name = "Walk"
    wave = bpy.data.actions.new("Wave")
    arm.animation_data.action = wave
    for f in (1, 6, 11):
        for i, n in enumerate(BONES):
            arm.pose.bones[n].rotation_euler = (0.0, 0.0, 0.5 * math.sin(f / 3 + i))
            arm.pose.bones[n].keyframe_insert("rotation_euler", frame=f)
    arm.animation_data.action = walk
    track = arm.animation_data.nla_tracks.new()
    track.name = "Wave"
    track.strips.new("Wave", 1, wave)
    return obj, arm, walk, wave


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
        assert {"rotation", "weights"} <= paths
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
        for id_data in (arm, rig_mesh.data.shape_keys):
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
    rig = importlib.import_module(ADDON_MODULE + ".operators.rig")
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
    real = rig._build_replay

    def fail_after(*args, **kwargs):
        real(*args, **kwargs)
        raise RuntimeError("forced failure")

    monkeypatch.setattr(rig, "_build_replay", fail_after)
    with pytest.raises(RuntimeError, match="forced failure"):
        bpy.ops.artdef.fit(links=3)
    monkeypatch.setattr(rig, "_build_replay", real)
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
