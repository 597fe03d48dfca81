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
