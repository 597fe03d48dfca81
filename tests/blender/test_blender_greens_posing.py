"""A Green's rig posed through Blender's depsgraph (load empties moved, the mesh evaluated) is G f to
first order on a solid it never saw (benchmarks/solids.py), with Python drivers off; a Green's rig
built by an earlier version is told to be refitted."""
import importlib

import numpy as np
import pytest

from benchmarks import solids as S

bpy = pytest.importorskip("bpy")


@pytest.fixture(scope="module")
def core(installed_addon):
    class P:
        files = importlib.import_module(installed_addon + ".artdef_addon.files")
        model = importlib.import_module(installed_addon + ".artdef_addon.model")
        ops = importlib.import_module(installed_addon + ".operators.ops")
        rig = importlib.import_module(installed_addon + ".operators.rig")
    return P


def _positions(obj, evaluated):
    if evaluated:
        dg = bpy.context.evaluated_depsgraph_get()
        dg.update()
        ev = obj.evaluated_get(dg)
        mesh = ev.to_mesh()
    else:
        mesh = obj.data
    co = np.empty(3 * len(mesh.vertices), dtype=np.float32)
    mesh.vertices.foreach_get("co", co)
    if evaluated:
        ev.to_mesh_clear()
    return co.reshape(-1, 3).astype(np.float64)


def _import(core, tmp_path, scan):
    path = str(tmp_path / "solid.npz")
    core.files.write_scan(path, scan)
    assert bpy.ops.artdef.import_scan(filepath=path) == {'FINISHED'}
    return bpy.context.view_layer.objects.active


@pytest.mark.parametrize("name,seed,mode,p_max", [("finger", 41, 'GLOBAL', 0.0), ("T", 42, 'GLOBAL', 3.0),
                                                  ("fork", 43, 'PSEUDO', 0.0)])
def test_small_loads_pose_G_f_through_the_depsgraph(clean_scene, core, tmp_path, name, seed, mode, p_max):
    assert not bpy.context.preferences.filepaths.use_scripts_auto_execute
    solid = S.make_solid(name, seed)
    scan = S.greens_scan(solid)
    obj = _import(core, tmp_path, scan)
    rest = _positions(obj, False)
    M, ph = scan.n_loads, scan.probe_load
    kw = dict(mode=mode, load_index=1) if mode == 'PSEUDO' else {}
    assert bpy.ops.artdef.fit(links=len(solid.joints) + 1, p_max=p_max, **kw) == {'FINISHED'}
    arm = obj.artdef.rig
    assert arm[core.rig.RIG_VERSION_PROP] == core.rig.RIG_VERSION and not core.rig.stale_greens_rig(obj)
    for fc in list(arm.animation_data.drivers) + list(obj.data.shape_keys.animation_data.drivers):
        assert fc.driver.is_valid and (fc.driver.type != 'SCRIPTED' or fc.driver.is_simple_expression)
    bpy.context.scene.frame_set(0)
    np.testing.assert_allclose(_positions(obj, True), rest, atol=1e-6 * np.abs(rest).max())
    rng = np.random.default_rng(seed)
    names = [1] if mode == 'PSEUDO' else range(M)
    for _ in range(3):
        f = np.zeros((M, 3))
        pts = [1] if mode == 'PSEUDO' else rng.choice(M, int(rng.integers(2, 4)), replace=False)
        d = rng.normal(size=(len(pts), 3))
        f[pts] = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0.05, 0.2, (len(pts), 1)) * ph
        for k in names:
            emp = bpy.data.objects[f"artdef_load_{k}"]
            emp.animation_data_clear()          # the load sweep's keys would set it back
            emp.location = f[k]
        u = _positions(obj, True) - rest
        gf = (scan.greens @ f.ravel()).reshape(-1, 3)
        assert np.linalg.norm(u - gf) <= 0.01 * np.linalg.norm(gf)
    # a rig built before the version mark keeps its drivers but is told to be refitted
    del arm[core.rig.RIG_VERSION_PROP]
    assert core.rig.stale_greens_rig(obj)
