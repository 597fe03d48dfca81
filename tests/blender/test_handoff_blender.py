"""Animator and engine hand-off inside Blender: Export Rig, clip timing, Finalize, bone names an
animator can read, engine-friendly motion and the panel's plain words.

The acceptance case: a character built in Blender (a skinned tube, a 3-bone chain, rotations keyed
from frame 1 every 5 frames; :func:`handoffhelpers.build_character`). Files are read back with
Blender's importers and compared with the re-imported source at every keyed frame; glTF splits
vertices at seams, so vertices are matched by rest position.
"""
import importlib
import json
import os
import sys

import numpy as np
import pytest

from conftest import ADDON_MODULE, REPO_ROOT

bpy = pytest.importorskip("bpy")

from test_headless_gltf import _validate, accessor, read_glb  # noqa: E402  (GLB reader, validator)

from handoffhelpers import (BONES, KEY_STEP, _draw, _evaluated, _import, _menu_functions,
    build_character, glb_times)


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
    # residual shapes (if the skin leaves any to correct) are keyed at the same frames
    shapes = len(scan_obj.artdef.shape_keys)
    assert compat.keyed_frames(key_action) == ([1.0, 6.0, 11.0, 16.0, 21.0] if shapes else [])
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


# --------------------------------------------------------------------------
# 3. Finalize
# --------------------------------------------------------------------------


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
