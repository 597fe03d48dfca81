"""Animated files as they are stored: a character whose mesh is split at seams (a UV seam down its
side, a hard ring) is fitted as one surface, and its exported rig keeps every seam closed.

The character of test_handoff with its edges on one meridian and one ring split (Blender's Edge
Split: each vertex there stored twice, the copies with the same skin), exported with Blender's glTF
exporter (which splits every vertex of the flat-shaded tube per face as well) and fitted by ``python -m artdef_addon fit source.glb --links 3 --glb out.glb``."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

bpy = pytest.importorskip("bpy")
bmesh = pytest.importorskip("bmesh")

from test_headless_gltf import read_glb  # noqa: E402
from handoffhelpers import KEYED, MAX_TOL, RMS_TOL, _import, _ok, _run, _skinned, build_character, compare, \
    world_positions  # noqa: E402  (the character and its read-back)


def _split_seams(obj):
    """Split ``obj``'s edges on the meridian at angle 0 and on the ring at height 1.5: the
    copies of those vertices keep their weights (bmesh carries the deform layer)."""
    bm = bmesh.new()
    bm.from_mesh(obj.data)
    seam = [e for e in bm.edges
            if all(abs(v.co.y) < 1e-6 and v.co.x > 0 for v in e.verts)
            or all(abs(v.co.z - 1.5) < 1e-6 for v in e.verts)]
    assert seam
    bmesh.ops.split_edges(bm, edges=seam)
    bm.to_mesh(obj.data)
    bm.free()


@pytest.fixture(scope="module")
def split_fit(installed_addon, tmp_path_factory):
    d = tmp_path_factory.mktemp("seams")
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    obj, _ = build_character()
    welded = len(obj.data.vertices)
    _split_seams(obj)
    stored = len(obj.data.vertices)
    source = d / "source.glb"
    assert bpy.ops.export_scene.gltf(filepath=str(source), export_format='GLB') == {'FINISHED'}
    gltf, _ = read_glb(source)     # the exporter splits more: the mesh is flat shaded (a hard edge everywhere)
    in_file = sum(gltf["accessors"][p["attributes"]["POSITION"]]["count"] for m in gltf["meshes"]
                  for p in m["primitives"])
    assert in_file >= stored > welded
    out = {"source": source, "glb": d / "out.glb", "welded": welded, "stored": in_file}
    out["proc"] = _ok(_run(["-m", "artdef_addon", "fit", str(source), "--links", "3", "--glb", str(out["glb"])],
                           cwd=d))
    return out


def test_split_file_is_fitted_on_its_distinct_points(split_fit):
    copies = split_fit["stored"] - split_fit["welded"]
    assert (f"{split_fit['stored']:,} vertices, {split_fit['welded']:,} distinct ({copies:,} copies at seams)"
            in split_fit["proc"].stdout), split_fit["proc"].stdout


def test_exported_rig_keeps_every_seam_closed(split_fit):
    ref, ref_rest = world_positions(_skinned(_import(split_fit["source"])), KEYED)
    moved, rest = world_positions(_skinned(_import(split_fit["glb"])), KEYED)
    worst, rms = compare(ref, ref_rest, moved, rest)
    assert worst < MAX_TOL and rms < RMS_TOL
    diag = float(np.linalg.norm(np.ptp(rest, axis=0)))
    pairs = cKDTree(rest).query_pairs(1e-7 * diag, output_type="ndarray")
    # the exporter stores the copies again (and more of its own); at every frame they are one point
    assert len(pairs) >= split_fit["stored"] - split_fit["welded"]
    gap = np.linalg.norm(moved[:, pairs[:, 0]] - moved[:, pairs[:, 1]], axis=-1)
    assert np.abs(moved - rest).max() > 0.05 * diag                 # the rig moves
    assert gap.max() <= 1e-6 * diag, gap.max() / diag


# --------------------------------------------------------------------------
# several animated meshes: every one fitted, as one rig
# --------------------------------------------------------------------------

@pytest.fixture(scope="module")
def two_meshes(installed_addon, tmp_path_factory):
    """A file with two characters, each its own armature and animation, and a static prop."""
    d = tmp_path_factory.mktemp("two")
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    build_character(name="Leg")
    _, arm2 = build_character(name="Other")
    arm2.location = (1.5, 0.0, 0.0)
    for f in KEYED:      # its own motion: about y, the other way
        for i, pb in enumerate(arm2.pose.bones):
            pb.rotation_euler = (0.0, -0.6 * np.sin(0.2 * f + i), 0.0)
            pb.keyframe_insert("rotation_euler", frame=f)
    bpy.ops.mesh.primitive_cube_add(size=0.3, location=(-1.5, 0.0, 0.0))
    bpy.context.active_object.name = "Prop"
    source = d / "two.glb"
    assert bpy.ops.export_scene.gltf(filepath=str(source), export_format='GLB') == {'FINISHED'}
    return source


@pytest.fixture(scope="module")
def two_fitted(two_meshes, tmp_path_factory):
    d = tmp_path_factory.mktemp("two_fit")
    out, blend = d / "out.glb", d / "out.blend"
    proc = _ok(_run(["-m", "artdef_addon", "fit", str(two_meshes), "--links", "6", "--glb", str(out),
                     "--blend", str(blend), "-o", str(d / "result.npz")], cwd=d))
    return proc, out, blend


def _sources(two_meshes):
    """The source file's two skinned meshes (Leg, Other), each playing its own animation."""
    imported = _import(two_meshes)
    for arm in (o for o in imported if o.type == 'ARMATURE' and o.animation_data.action is None):
        # Blender's importer plays one animation; the other character's waits in an NLA track
        arm.animation_data.action = arm.animation_data.nla_tracks[0].strips[0].action
        if hasattr(arm.animation_data, "action_slot") and arm.animation_data.action_slot is None:
            arm.animation_data.action_slot = arm.animation_data.action.slots[0]
    return sorted((o for o in imported if o.type == 'MESH' and o.find_armature() is not None), key=lambda o: o.name)


def test_each_source_mesh_has_its_own_rigged_object_in_the_blend(two_meshes, two_fitted):
    sources = _sources(two_meshes)
    refs = {o.name: world_positions(o, KEYED) for o in sources}
    counts = {o.name: len(o.data.vertices) for o in sources}
    assert bpy.ops.wm.open_mainfile(filepath=str(two_fitted[2])) == {'FINISHED'}
    rigged = sorted((o for o in bpy.data.objects if o.get("artdef_part_of") is not None), key=lambda o: o.name)
    assert [o.name for o in rigged] == ["Leg_rigged", "Other_rigged"]
    joined = rigged[0]["artdef_part_of"]
    arm = joined.artdef.rig
    assert arm is not None and arm.type == 'ARMATURE'
    assert all(o.parent == arm for o in rigged)                            # one armature over both
    for obj in rigged:
        name = obj["artdef_part_name"]
        mods = [m for m in obj.modifiers if m.type == 'ARMATURE']
        assert len(mods) == 1 and mods[0].object == arm
        assert sorted(vg.name for vg in obj.vertex_groups) == sorted(b.name for b in arm.data.bones)
        keys = obj.data.shape_keys
        ours = joined.data.shape_keys                                      # the fit's residual keys and replay
        assert keys is not None and [k.name for k in keys.key_blocks] == [k.name for k in ours.key_blocks]
        assert keys.animation_data.action == ours.animation_data.action
        assert len(obj.data.vertices) == counts[name]                      # the source's vertices, no other
        moved, rest = world_positions(obj, KEYED)                          # through the depsgraph
        worst, rms = compare(*refs[name], moved, rest)
        assert worst < MAX_TOL and rms < RMS_TOL, (name, worst, rms)
        assert np.abs(moved - rest).max() > 0.05 * float(np.linalg.norm(np.ptp(rest, axis=0)))
    # the panel's object for either is the joined scan, and Clear Rig removes all of the rig
    bpy.context.view_layer.objects.active = rigged[1]
    with bpy.context.temp_override(active_object=rigged[1], object=rigged[1]):
        assert bpy.ops.artdef.clear_rig() == {'FINISHED'}
    assert not [o for o in bpy.data.objects if o.get("artdef_part_of") is not None]
    assert not [o for o in bpy.data.objects if o.type == 'ARMATURE' and o.get("artdef_rig")]
    assert not joined.modifiers and not joined.hide_get()


def test_every_animated_mesh_is_fitted_as_one_rig(two_meshes, two_fitted):
    proc, out, _ = two_fitted
    note = next(ln for ln in proc.stdout.splitlines() if "meshes fitted:" in ln)
    assert "meshes fitted: Leg, Other; left out: " in note and "Prop (static)" in note, note
    assert "(a bone's custom shape)" in note      # the importer's bone shapes
    sources = _sources(two_meshes)
    assert sorted(o.name for o in sources) == ["Leg", "Other"]
    refs = [world_positions(o, KEYED) for o in sources]
    objects = _import(out)
    arms = [o for o in objects if o.type == 'ARMATURE']
    assert len(arms) == 1                                                  # one armature over both
    meshes = [o for o in objects if o.type == 'MESH' and o.find_armature() is not None]
    assert len(meshes) == 2                                                # each exported as its own mesh
    meshes.sort(key=lambda o: float(np.mean([v.co.x for v in o.data.vertices])))   # Leg at x 0, Other at 1.5
    assert all(o.find_armature() == arms[0] and len(o.vertex_groups) == 6 for o in meshes)
    for mesh, (ref, ref_rest) in zip(meshes, refs):      # each mesh replays its own animation
        moved, rest = world_positions(mesh, KEYED)
        assert len(rest) >= len(ref_rest)                                  # every vertex of it
        worst, rms = compare(ref, ref_rest, moved, rest)
        assert worst < MAX_TOL and rms < RMS_TOL, (mesh.name, worst, rms)


def test_mesh_option_fits_the_chosen_mesh_only(two_meshes, tmp_path):
    proc = _ok(_run(["-m", "artdef_addon", "fit", str(two_meshes), "--links", "3", "--mesh", "Other"], cwd=tmp_path))
    note = next(ln for ln in proc.stdout.splitlines() if "meshes fitted:" in ln)
    assert "meshes fitted: Other; left out: " in note and "Leg (not chosen)" in note and "Prop (static)" in note
    assert "tracked scan, 456 vertices" in proc.stdout, proc.stdout      # Other's own (half of both)
    bad = _run(["-m", "artdef_addon", "fit", str(two_meshes), "--links", "3", "--mesh", "Nope"], cwd=tmp_path)
    assert bad.returncode == 2 and "no mesh named 'Nope'" in bad.stderr, bad.stderr


def test_a_refit_replaces_its_own_rigged_objects_and_a_failed_one_keeps_them(two_fitted, monkeypatch):
    import importlib
    from artdef_addon.result import load_result
    from conftest import ADDON_MODULE
    apply = importlib.import_module(ADDON_MODULE + ".operators.apply")
    io = importlib.import_module(ADDON_MODULE + ".operators.io")
    parts = importlib.import_module(ADDON_MODULE + ".operators.parts")
    assert bpy.ops.wm.open_mainfile(filepath=str(two_fitted[2])) == {'FINISHED'}
    joined = next(o for o in bpy.data.objects if o.type == 'MESH' and len(o.data.get("artdef_parts", [])) == 2)
    result = load_result(two_fitted[1].parent / "result.npz")
    stored = io.read_scan(joined)
    before = {o.name for o in bpy.data.objects}
    apply.apply_result(bpy.context, joined, result, stored.scan, stored.tri_polygons)
    rigged = parts.parts_of(joined)
    assert [o.name for o in rigged] == ["Leg_rigged", "Other_rigged"]        # the new ones, named as before
    assert {o.name for o in bpy.data.objects} == before                         # nothing else added or left
    arm = joined.artdef.rig
    assert all(o.parent == arm and o.modifiers[0].object == arm for o in rigged)
    assert len([o for o in bpy.data.objects if o.type == 'ARMATURE' and o.get("artdef_rig")]) == 1
    names = {o.name: getattr(o.data, "name", None) for o in bpy.data.objects}

    def broken(context, obj):
        raise RuntimeError("write failed")
    monkeypatch.setattr(parts, "write_parts", broken)
    with pytest.raises(RuntimeError, match="write failed"):
        apply.apply_result(bpy.context, joined, result, stored.scan, stored.tri_polygons)
    assert parts.parts_of(joined) == rigged and joined.artdef.rig == arm        # the scene as it was
    assert {o.name: getattr(o.data, "name", None) for o in bpy.data.objects} == names and joined.hide_get()
    assert all(o.parent == arm and o.modifiers[0].object == arm for o in rigged)


def test_residual_keys_are_cut_per_rigged_object(two_meshes, tmp_path):
    """Each source mesh's rigged object holds the fit's residual keys on its own vertices: every key
    is the joined mesh's key on that part's vertex range, and with the armature off each object's
    key replay is the joined mesh's key replay of its part, at every keyed frame. Three links for
    two three-bone characters leave a residual: two keys hold it."""
    blend = tmp_path / "res.blend"
    _ok(_run(["-m", "artdef_addon", "fit", str(two_meshes), "--links", "3", "--residuals", "2",
              "--blend", str(blend)], cwd=tmp_path))
    assert bpy.ops.wm.open_mainfile(filepath=str(blend)) == {'FINISHED'}
    rigged = sorted((o for o in bpy.data.objects if o.get("artdef_part_of") is not None), key=lambda o: o.name)
    joined = rigged[0]["artdef_part_of"]
    parts = list(joined.data["artdef_parts"])
    ends = np.cumsum([int(s) for s in joined.data["artdef_part_sizes"]])
    starts = ends - np.diff(np.r_[0, ends])

    def key_co(block):
        co = np.empty(3 * len(block.data))
        block.data.foreach_get("co", co)
        return co.reshape(-1, 3)

    ours = joined.data.shape_keys.key_blocks
    assert len(ours) >= 3                          # Basis and the two residual keys (and the replay's own)
    moved_any = 0.0
    for obj in rigged:
        k = parts.index(obj["artdef_part_name"])
        blocks = obj.data.shape_keys.key_blocks
        assert len(obj.data.vertices) == ends[k] - starts[k]
        for mine, full in zip(blocks, ours):
            assert mine.name == full.name and len(mine.data) == len(obj.data.vertices)
            assert np.abs(key_co(mine) - key_co(full)[starts[k]:ends[k]]).max() < 1e-6
            moved_any = max(moved_any, float(np.abs(key_co(mine) - key_co(blocks[0])).max()))
    assert moved_any > 0.0                         # the residual keys are not empty
    for o in [joined, *rigged]:                    # the key replay alone, in the objects' own space
        for m in o.modifiers:
            m.show_viewport = False
    scene = bpy.context.scene
    for f in KEYED:
        scene.frame_set(f)
        dg = bpy.context.evaluated_depsgraph_get()
        full = np.array([v.co[:] for v in joined.evaluated_get(dg).to_mesh().vertices])
        joined.evaluated_get(dg).to_mesh_clear()
        for obj in rigged:
            k = parts.index(obj["artdef_part_name"])
            ev = obj.evaluated_get(dg)
            mine = np.array([v.co[:] for v in ev.to_mesh().vertices])
            ev.to_mesh_clear()
            assert np.abs(mine - full[starts[k]:ends[k]]).max() < 1e-6, (obj.name, f)
