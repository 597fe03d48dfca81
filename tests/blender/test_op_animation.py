"""The Fields from Animation operator (armature, shape-key, Alembic and glTF sources).

Run headless (bpy module) through the installed extension.

Everything goes through ``bpy.ops.artdef.*`` of the extension installed from the built zip
(fixtures ``installed_addon``, ``clean_scene``, ``pkg`` and ``sample_files`` in tests/conftest.py);
the core used for reference numbers is the installed copy too.
"""

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from ophelpers import (SEGMENTS, _vertex_cutting_nodes, build_animated_tube, chain_pose,
    check_joints, rest_positions, scene_snapshot, shape_key_blob)


# --------------------------------------------------------------------------
# a jointed tube: numpy geometry, rigid chain poses
# --------------------------------------------------------------------------


# --------------------------------------------------------------------------
# fields from animation
# --------------------------------------------------------------------------


@pytest.mark.parametrize("blend", [0.0, 0.3], ids=["hard-weights", "blended-weights"])
def test_armature_animation_fit_reproduces_its_joints(clean_scene, pkg, blend):
    """Importing an armature-animated mesh and fitting it reproduces
    that armature's joint positions."""
    import time
    rng = np.random.default_rng(5)
    tube, skel, verts, weights, eulers = build_animated_tube(rng, n_poses=8, blend=blend)
    scene = bpy.context.scene
    scene.frame_set(4)
    source_before = scene_snapshot()["meshes"]["tube"]
    t0 = time.perf_counter()
    assert bpy.ops.artdef.fields_from_animation(frame_start=1, frame_end=8) == {'FINISHED'}
    sample_seconds = time.perf_counter() - t0
    obj = bpy.context.active_object
    assert obj.name == "tube_scan" and obj != tube
    # the source is as it was, the frame is back
    assert scene.frame_current == 4
    assert scene_snapshot()["meshes"]["tube"] == source_before
    assert all(m.show_viewport for m in tube.modifiers)
    # the copy: no armature, parent, shape keys or animation; the subdivision stays
    assert [m.type for m in obj.modifiers] == ['SUBSURF']
    assert obj.parent is None and obj.data.shape_keys is None and obj.animation_data is None
    np.testing.assert_allclose(np.array(obj.matrix_world), np.array(tube.matrix_world), atol=1e-6)
    np.testing.assert_allclose(rest_positions(obj), verts, atol=1e-6)
    # the fields are the rig's poses (object space), independent of Blender's evaluation
    scan = pkg.io.read_scan(obj).scan
    assert scan.kind == "tracked" and scan.n_fields == 8
    assert list(obj.data["artdef_frames"]) == list(range(1, 9))
    basis = np.array(skel.data.bones["b0"].matrix_local.to_3x3())  # bone y = world z
    for f in range(8):
        np.testing.assert_allclose(verts + scan.displacements[f],
                                   chain_pose(verts, weights, eulers[f], basis), atol=1e-5)
    # fit: the rig's joints are the armature's
    assert bpy.ops.artdef.fit(links=SEGMENTS) == {'FINISHED'}
    err = check_joints(pkg, obj)
    print(f"armature tube (blend {blend}): {len(verts)} vertices, sampling {sample_seconds:.3f} s, "
          f"joint error {100 * err:.3f}% of the diagonal")
    # the fit's armature deforms the copy only (nothing stacks on the user's rig)
    assert obj.modifiers[0].object == obj.artdef.rig and len(tube.modifiers) == 2


def test_fields_from_shape_key_animation_with_rest_frame(clean_scene, pkg):
    obj, verts, offsets, values = shape_key_blob()
    assert bpy.ops.artdef.fields_from_animation(frame_start=1, frame_end=4, rest_frame=3) == {'FINISHED'}
    new = bpy.context.active_object
    assert new.name == "blob_scan" and new.data.shape_keys is None
    assert [k.name for k in obj.data.shape_keys.key_blocks] == ["Basis", "k0", "k1"]  # source intact
    assert obj.data.shape_keys.animation_data.action is not None
    assert new.data["artdef_rest_frame"] == 3
    mix = {f: verts + sum(v * o for v, o in zip(vals, offsets)) for f, vals in values.items()}
    np.testing.assert_allclose(rest_positions(new), mix[3], atol=1e-6)
    scan = pkg.io.read_scan(new).scan
    # frames 3 and 4 equal the rest: skipped
    assert list(new.data["artdef_frames"]) == [1, 2] and scan.n_fields == 2
    for i, f in enumerate((1, 2)):
        np.testing.assert_allclose(scan.displacements[i], mix[f] - mix[3], atol=1e-6)
    # default rest: the base mesh; the scene's frame range by default
    bpy.context.view_layer.objects.active = obj
    bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, 2
    assert bpy.ops.artdef.fields_from_animation() == {'FINISHED'}
    scan = pkg.io.read_scan(bpy.context.active_object).scan
    np.testing.assert_allclose(scan.vertices, verts, atol=1e-6)
    np.testing.assert_allclose(scan.displacements[0], offsets[0], atol=1e-6)


def test_fields_from_alembic_cache(clean_scene, pkg, tmp_path):
    """A Mesh Sequence Cache (Alembic) samples like the animation it was made from."""
    obj, verts, offsets, values = shape_key_blob()
    abc = str(tmp_path / "blob.abc")
    assert bpy.ops.wm.alembic_export(filepath=abc, start=1, end=4, as_background_job=False) == {'FINISHED'}
    assert bpy.ops.artdef.fields_from_animation(frame_start=1, frame_end=4, rest_frame=3) == {'FINISHED'}
    want = pkg.io.read_scan(bpy.context.active_object).scan
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    assert bpy.ops.wm.alembic_import(filepath=abc, as_background_job=False) == {'FINISHED'}
    cached = [o for o in bpy.data.objects if o.type == 'MESH']
    assert len(cached) == 1 and [m.type for m in cached[0].modifiers] == ['MESH_SEQUENCE_CACHE']
    bpy.context.view_layer.objects.active = cached[0]
    assert bpy.ops.artdef.fields_from_animation(frame_start=1, frame_end=4, rest_frame=3) == {'FINISHED'}
    new = bpy.context.active_object
    assert new != cached[0] and len(new.modifiers) == 0  # the cache reader stays on the source
    got = pkg.io.read_scan(new).scan
    R = np.array(new.matrix_world.to_3x3())  # object space of the import may be rotated (Y-up)
    np.testing.assert_allclose(got.vertices @ R.T, want.vertices, atol=1e-5)
    np.testing.assert_allclose(got.displacements @ R.T, want.displacements, atol=1e-5)


def test_fields_from_animation_reports_changing_connectivity(clean_scene):
    bpy.ops.mesh.primitive_uv_sphere_add(segments=8, ring_count=6)
    obj = bpy.context.active_object
    n = len(obj.data.vertices)
    mod = obj.modifiers.new("Cut", 'NODES')
    mod.node_group = _vertex_cutting_nodes()
    before = scene_snapshot()
    frame = bpy.context.scene.frame_current
    with pytest.raises(RuntimeError, match=f"connectivity differs at frame 1: {n - 1} vertices, "
                                           f"expected {n}"):
        bpy.ops.artdef.fields_from_animation(frame_start=0, frame_end=3)
    assert scene_snapshot() == before and bpy.context.scene.frame_current == frame
    with pytest.raises(RuntimeError, match="empty"):
        bpy.ops.artdef.fields_from_animation(frame_start=5, frame_end=3)
    mod.show_viewport = False  # nothing moves now
    with pytest.raises(RuntimeError, match="does not move"):
        bpy.ops.artdef.fields_from_animation(frame_start=0, frame_end=3)
    assert len(bpy.data.objects) == 1


# --------------------------------------------------------------------------
# glTF morph targets arrive as shape keys
# --------------------------------------------------------------------------

def test_gltf_morph_targets_become_fields(clean_scene, pkg, sample_files, tmp_path):
    ref = pkg.files.read_scan(sample_files["rod"])
    mesh = bpy.data.meshes.new("morphs")
    mesh.from_pydata(ref.vertices.tolist(), [], ref.faces.tolist())
    mesh.shade_smooth()
    obj = bpy.data.objects.new("morphs", mesh)
    bpy.context.scene.collection.objects.link(obj)
    obj.shape_key_add(name="Basis")
    for p, d in enumerate(ref.displacements):
        obj.shape_key_add(name=f"pose{p}").data.foreach_set(
            "co", (ref.vertices + d).astype(np.float32).ravel())
    glb = str(tmp_path / "morphs.glb")
    assert bpy.ops.export_scene.gltf(  # the scene holds only this mesh
        filepath=glb, export_format='GLB', export_yup=True,
        export_morph=True, export_morph_normal=False, export_normals=False,
        export_texcoords=False, export_animations=False, export_materials='NONE') == {'FINISHED'}
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    assert bpy.ops.import_scene.gltf(filepath=glb) == {'FINISHED'}
    imported = [o for o in bpy.data.objects if o.type == 'MESH']
    assert len(imported) == 1
    obj = imported[0]
    bpy.context.view_layer.objects.active = obj
    names = [k.name for k in obj.data.shape_keys.key_blocks]
    assert names[1:] == [f"pose{p}" for p in range(ref.n_fields)]
    assert bpy.ops.artdef.fields_from_shape_keys() == {'FINISHED'}
    scan = pkg.io.read_scan(obj).scan
    # same vertices (maybe reordered): match them by rest position
    assert len(scan.vertices) == len(ref.vertices)
    d = np.linalg.norm(scan.vertices[:, None] - ref.vertices[None], axis=2)
    order = d.argmin(axis=1)
    assert d.min(axis=1).max() < 1e-5 and len(np.unique(order)) == len(order)
    np.testing.assert_allclose(scan.displacements, ref.displacements[:, order], atol=1e-5)
    assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}
    assert len(obj.artdef.rig.data.bones) == 3
    assert pkg.ops.last_result(obj).n_links == 3
