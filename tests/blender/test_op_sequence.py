"""The Import Mesh Sequence operator (OBJ / PLY).

Run headless (bpy module) through the installed extension.

Everything goes through ``bpy.ops.artdef.*`` of the extension installed from the built zip
(fixtures ``installed_addon``, ``clean_scene``, ``pkg`` and ``sample_files`` in tests/conftest.py);
the core used for reference numbers is the installed copy too.
"""
import importlib

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from ophelpers import (SEGMENTS, chain_pose, check_joints, random_rotations, scene_snapshot,
    tube_geometry, tube_weights, write_obj, write_sequence)


# --------------------------------------------------------------------------
# mesh sequences (OBJ / PLY)
# --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tube_poses():
    verts, polys, segment = tube_geometry()
    eulers = random_rotations(np.random.default_rng(11), 6)
    weights = tube_weights(verts)
    return verts, polys, [verts] + [chain_pose(verts, weights, e) for e in eulers]


def test_mesh_sequence_import_and_fit(clean_scene, pkg, tube_poses, tmp_path):
    verts, polys, poses = tube_poses
    paths = write_sequence(tmp_path / "obj", poses, polys)
    assert bpy.ops.artdef.import_mesh_sequence(filepath=paths[0]) == {'FINISHED'}
    obj = bpy.context.active_object
    assert obj.name == "pose"
    assert len(obj.data.polygons) == len(polys)  # quads and caps kept as polygons
    scan = pkg.io.read_scan(obj).scan
    assert scan.kind == "tracked" and scan.n_fields == len(poses) - 1
    np.testing.assert_allclose(scan.vertices, verts, atol=1e-6)
    for p in range(1, len(poses)):
        np.testing.assert_allclose(scan.displacements[p - 1], poses[p] - verts, atol=1e-6)
    assert bpy.ops.artdef.fit(links=SEGMENTS) == {'FINISHED'}
    check_joints(pkg, obj)
    # PLY (ASCII and binary) sequences read the same; another rest pose on request
    for fmt in ("ascii", "binary_little_endian"):
        ply = write_sequence(tmp_path / fmt, poses, polys, name="scan{:d}.ply", fmt=fmt)
        assert bpy.ops.artdef.import_mesh_sequence(filepath=ply[3], rest_number=2) == {'FINISHED'}
        obj = bpy.context.active_object
        assert obj.name.startswith("scan") and obj.data["artdef_rest_file"] == "scan2.ply"
        scan = pkg.io.read_scan(obj).scan
        np.testing.assert_allclose(scan.vertices, poses[2], atol=1e-5)
        others = [x for i, x in enumerate(poses) if i != 2]
        np.testing.assert_allclose(scan.displacements, np.array(others) - poses[2], atol=1e-5)
    # a folder with one sequence works too
    assert bpy.ops.artdef.import_mesh_sequence(directory=str(tmp_path / "obj")) == {'FINISHED'}


@pytest.mark.parametrize("problem", ["faces", "vertices", "not_numbered", "unreadable", "single",
                                     "rest_number"])
def test_mesh_sequence_errors(clean_scene, tube_poses, tmp_path, problem):
    verts, polys, poses = tube_poses
    paths = write_sequence(tmp_path / "seq", poses[:5], polys)
    first = paths[0]
    if problem == "faces":
        write_obj(paths[4], poses[4], polys + [[0, 1, 13]])
        match = f"connectivity differs: pose_004.obj has {len(polys) + 1} faces, expected {len(polys)}"
    elif problem == "vertices":
        write_obj(paths[2], np.vstack([poses[2], [[9, 9, 9]]]), polys)
        match = f"connectivity differs: pose_002.obj has {len(verts) + 1} vertices, expected {len(verts)}"
    elif problem == "not_numbered":
        first = str(tmp_path / "seq" / "pose.obj")
        write_obj(first, verts, polys)
        match = "pose.obj is not numbered"
    elif problem == "unreadable":
        with open(paths[3], "wb") as f:
            f.write(b"\x00\x01garbage" * 10)
        match = "cannot read pose_003.obj"
    elif problem == "single":
        first = str(tmp_path / "one_0.obj")
        write_obj(first, verts, polys)
        match = "at least 2 numbered files"
    else:
        match = "no file numbered 9"
    before = (len(bpy.data.objects), len(bpy.data.meshes))
    with pytest.raises(RuntimeError, match=match):
        bpy.ops.artdef.import_mesh_sequence(filepath=first,
                                            rest_number=9 if problem == "rest_number" else -1)
    assert (len(bpy.data.objects), len(bpy.data.meshes)) == before


def test_sequence_reader_needs_no_bpy(installed_addon):
    """operators/sequence.py is plain Python + numpy (usable outside Blender)."""
    import subprocess
    import sys
    path = importlib.import_module(installed_addon + ".operators.sequence").__file__
    code = ("import sys, importlib.util\nsys.modules['bpy'] = None\n"
            f"spec = importlib.util.spec_from_file_location('seq', {path!r})\n"
            "m = importlib.util.module_from_spec(spec); spec.loader.exec_module(m)\n"
            "print(m.fan_triangles([4, 3], [0, 1, 2, 3, 3, 2, 4]).tolist())\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "[[0, 1, 2], [0, 2, 3], [3, 2, 4]]"


def test_ply_reader_skips_other_properties_and_elements(pkg, tmp_path):
    seq = importlib.import_module(pkg.io.__name__.rsplit(".", 1)[0] + ".sequence")
    verts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 2, 0]], dtype=np.float64)
    polys = [[0, 1, 2, 3], [3, 2, 4]]
    for fmt, e in (("binary_big_endian", ">"), ("binary_little_endian", "<"), ("ascii", None)):
        head = (f"ply\nformat {fmt} 1.0\nelement vertex 5\nproperty double z0\nproperty double x\n"
                "property double y\nproperty double z\nelement face 2\nproperty uchar flag\n"
                "property list ushort uint vertex_indices\nproperty list uchar float uvs\n"
                "element edge 1\nproperty int a\nproperty int b\nend_header\n")
        path = tmp_path / f"m_{fmt}.ply"
        with open(path, "wb") as f:
            f.write(head.encode())
            if e is None:
                f.writelines(f"9 {x} {y} {z}\n".encode() for x, y, z in verts)
                f.writelines(f"7 {len(p)} {' '.join(map(str, p))} 2 0.5 0.5\n".encode() for p in polys)
                f.write(b"0 1\n")
            else:
                f.write(np.column_stack([np.full(5, 9.0), verts]).astype(e + "f8").tobytes())
                for p in polys:
                    f.write(b"\x07" + np.array([len(p)], e + "u2").tobytes()
                            + np.array(p, e + "u4").tobytes() + b"\x02" + np.zeros(2, e + "f4").tobytes())
                f.write(np.array([0, 1], e + "i4").tobytes())
        m = seq.read_ply(str(path))
        np.testing.assert_array_equal(m.vertices, verts)
        assert m.sizes.tolist() == [4, 3] and m.indices.tolist() == [0, 1, 2, 3, 3, 2, 4]
        assert m.triangles.tolist() == [[0, 1, 2], [0, 2, 3], [3, 2, 4]]
    (tmp_path / "short.ply").write_bytes(head.replace("ascii", "binary_little_endian").encode() + b"\0" * 7)
    with pytest.raises(seq.SequenceError, match="ends inside"):
        seq.read_ply(str(tmp_path / "short.ply"))


def test_new_sources_undo(clean_scene, tube_poses, tmp_path):
    verts, polys, poses = tube_poses
    paths = write_sequence(tmp_path / "seq", poses[:3], polys)
    bpy.ops.ed.undo_push(message="empty")
    assert bpy.ops.artdef.import_mesh_sequence('EXEC_DEFAULT', True, filepath=paths[0]) == {'FINISHED'}
    assert [o.name for o in bpy.data.objects] == ["pose"]
    obj = bpy.data.objects["pose"]
    obj.shape_key_add(name="Basis")
    kb = obj.shape_key_add(name="bend")
    kb.data.foreach_set("co", poses[1].astype(np.float32).ravel())
    kb.value = 0.0
    kb.keyframe_insert("value", frame=1)
    kb.value = 1.0
    kb.keyframe_insert("value", frame=2)
    bpy.ops.ed.undo_push(message="keyed")
    before = scene_snapshot()
    assert bpy.ops.artdef.fields_from_animation('EXEC_DEFAULT', True, frame_start=1,
                                                frame_end=2) == {'FINISHED'}
    assert sorted(o.name for o in bpy.data.objects) == ["pose", "pose_scan"]
    assert bpy.ops.ed.undo() == {'FINISHED'}
    assert scene_snapshot() == before
    assert bpy.ops.ed.undo() == {'FINISHED'}
    assert bpy.ops.ed.undo() == {'FINISHED'}
    assert len(bpy.data.objects) == 0
