"""The Import Scan, Fields from Shape Keys and the scan stored on a mesh.

Run headless (bpy module) through the installed extension.

Everything goes through ``bpy.ops.artdef.*`` of the extension installed from the built zip
(fixtures ``installed_addon``, ``clean_scene``, ``pkg`` and ``sample_files`` in tests/conftest.py);
the core used for reference numbers is the installed copy too.
"""

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from ophelpers import import_scan


# --------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------


# --------------------------------------------------------------------------
# import and scan storage
# --------------------------------------------------------------------------

def test_registered_ui(installed_addon):
    for name in ("import_scan", "fields_from_shape_keys", "fit", "preview_links", "clear_rig",
                 "fields_from_animation", "import_mesh_sequence", "show_colours"):
        op = getattr(bpy.types, "ARTDEF_OT_" + name)
        assert {'REGISTER', 'UNDO'} <= set(op.bl_options), name
        assert op.__doc__ and len(op.__doc__) > 20, f"{name} has no tooltip"
    assert hasattr(bpy.types, "ARTDEF_PT_main")
    assert bpy.types.ARTDEF_PT_main.bl_category == "ArtDef"
    fit_props = bpy.ops.artdef.fit.get_rna_type().properties
    for prop in ("links", "mode", "motion", "p_max", "load_index", "frames_per_field"):
        assert fit_props[prop].description, prop
    assert fit_props["frames_per_field"].default == 10


def test_import_tracked_scan_round_trips(clean_scene, pkg, sample_files, tmp_path):
    ref = pkg.files.read_scan(sample_files["rod"])
    obj = import_scan(sample_files["rod"])
    mesh = obj.data
    assert len(mesh.vertices) == len(ref.vertices)
    assert len(mesh.polygons) == len(ref.faces)
    fields = [a for a in mesh.attributes if a.name.startswith("artdef_field_")]
    assert len(fields) == ref.n_fields
    assert all(a.domain == 'POINT' and a.data_type == 'FLOAT_VECTOR' for a in fields)
    assert mesh["artdef_kind"] == "tracked"
    # survives save + reload of the .blend
    path = str(tmp_path / "rod.blend")
    bpy.ops.wm.save_as_mainfile(filepath=path)
    bpy.ops.wm.open_mainfile(filepath=path)
    back = pkg.io.read_scan(bpy.data.objects["rod"]).scan
    assert back.kind == "tracked"
    np.testing.assert_allclose(back.vertices, ref.vertices, atol=1e-5)
    np.testing.assert_array_equal(back.faces, ref.faces)
    np.testing.assert_allclose(back.displacements, ref.displacements, rtol=1e-6, atol=1e-6)
    if ref.support_vertices is not None:
        np.testing.assert_array_equal(np.sort(back.support_vertices), np.sort(ref.support_vertices))


def test_import_greens_scan_round_trips(clean_scene, pkg, sample_files):
    ref = pkg.files.read_scan(sample_files["greens_rod"])
    obj = import_scan(sample_files["greens_rod"])
    back = pkg.io.read_scan(obj).scan
    assert back.kind == "greens"
    assert back.n_fields == ref.n_fields == 3 * len(ref.load_vertices)
    np.testing.assert_array_equal(back.load_vertices, ref.load_vertices)  # order kept
    np.testing.assert_allclose(back.greens, ref.greens, rtol=1e-6, atol=1e-6 * np.abs(ref.greens).max())
    assert back.probe_load == pytest.approx(ref.probe_load)
    index = obj.data.attributes["artdef_load_index"]
    assert index.data_type == 'INT' and index.domain == 'POINT'


@pytest.mark.parametrize("content", ["garbage", "no_faces", "missing"])
def test_bad_scan_file_reports_and_creates_nothing(clean_scene, tmp_path, content):
    path = tmp_path / "bad.npz"
    if content == "garbage":
        path.write_bytes(b"this is not a numpy archive")
    elif content == "no_faces":
        np.savez(path, vertices=np.zeros((4, 3)))
    before = (len(bpy.data.objects), len(bpy.data.meshes))
    with pytest.raises(RuntimeError) as err:  # ERROR reports raise in bpy.ops calls
        bpy.ops.artdef.import_scan(filepath=str(path))
    assert "bad.npz" in str(err.value) or "scan" in str(err.value).lower()
    assert (len(bpy.data.objects), len(bpy.data.meshes)) == before == (0, 0)


# --------------------------------------------------------------------------
# shape keys as a scan, preview
# --------------------------------------------------------------------------

def test_fields_from_shape_keys(clean_scene, pkg, sample_files):
    ref = pkg.files.read_scan(sample_files["rod"])
    mesh = bpy.data.meshes.new("mocap")
    mesh.from_pydata(ref.vertices.tolist(), [], ref.faces.tolist())
    obj = bpy.data.objects.new("mocap", mesh)
    bpy.context.scene.collection.objects.link(obj)
    bpy.context.view_layer.objects.active = obj
    obj.shape_key_add(name="Basis")
    for p, d in enumerate(ref.displacements):
        kb = obj.shape_key_add(name=f"pose{p}")
        kb.data.foreach_set("co", (ref.vertices + d).astype(np.float32).ravel())
    assert not bpy.ops.artdef.fit.poll()
    assert bpy.ops.artdef.fields_from_shape_keys() == {'FINISHED'}
    back = pkg.io.read_scan(obj).scan
    assert back.kind == "tracked" and back.n_fields == ref.n_fields
    np.testing.assert_allclose(back.displacements, ref.displacements, atol=1e-5)
    assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}
    keys = [k.name for k in obj.data.shape_keys.key_blocks]
    assert keys[:1 + ref.n_fields] == ["Basis"] + [f"pose{p}" for p in range(ref.n_fields)]
    basis = pkg.ops.last_result(obj).residual_basis
    assert len(keys) == 1 + ref.n_fields + (basis.keys if basis is not None else ref.n_fields)
    # Re-storing ignores the fit's own residual keys; clearing keeps the user's poses.
    assert bpy.ops.artdef.fields_from_shape_keys() == {'FINISHED'}
    assert pkg.io.read_scan(obj).scan.n_fields == ref.n_fields
    assert bpy.ops.artdef.clear_rig() == {'FINISHED'}
    assert [k.name for k in obj.data.shape_keys.key_blocks] == keys[:1 + ref.n_fields]


def test_fast_mesh_access_matches_blender_triangulation(clean_scene, pkg, sample_files):
    """read_scan's array access (attributes instead of per-item RNA) is Blender's own data."""
    import bmesh

    def rna(mesh):
        t = len(mesh.loop_triangles)
        faces = np.empty(3 * t, dtype=np.int32)
        mesh.loop_triangles.foreach_get("vertices", faces)
        polys = np.empty(t, dtype=np.int32)
        mesh.loop_triangles.foreach_get("polygon_index", polys)
        co = np.empty(3 * len(mesh.vertices), dtype=np.float32)
        mesh.vertices.foreach_get("co", co)
        return faces.reshape(-1, 3), polys, co.reshape(-1, 3)

    meshes = [import_scan(sample_files["branching"]).data]           # triangles only
    bpy.ops.mesh.primitive_monkey_add()                                # quads and triangles
    meshes.append(bpy.context.active_object.data)
    bpy.ops.mesh.primitive_cylinder_add(vertices=9)                    # n-gon caps
    meshes.append(bpy.context.active_object.data)
    bm = bmesh.new()                                                   # triangles, faces reordered
    bmesh.ops.create_icosphere(bm, subdivisions=2, radius=1.0)
    bmesh.ops.triangulate(bm, faces=bm.faces[:])
    bm.faces.sort(key=lambda f: -f.calc_center_median().z)
    bm.faces.index_update()
    ico = bpy.data.meshes.new("ico")
    bm.to_mesh(ico)
    bm.free()
    meshes.append(ico)
    for mesh in meshes:
        faces, polys, co = rna(mesh)
        fast_faces, fast_polys = pkg.io._triangles(mesh)
        np.testing.assert_array_equal(fast_faces, faces, err_msg=mesh.name)
        np.testing.assert_array_equal(fast_polys, polys, err_msg=mesh.name)
        np.testing.assert_array_equal(pkg.io._positions(mesh, len(mesh.vertices)), co)


def test_import_scan_takes_blender_relative_paths(clean_scene, sample_files, tmp_path):
    import shutil
    shutil.copy(sample_files["rod"], tmp_path / "rod.npz")
    assert bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "s.blend")) == {'FINISHED'}
    assert bpy.ops.artdef.import_scan(filepath="//rod.npz") == {'FINISHED'}
