"""The Fit operator on Green's scans (load controls, helper bones, load sweep).

Run headless (bpy module) through the installed extension.

Everything goes through ``bpy.ops.artdef.*`` of the extension installed from the built zip
(fixtures ``installed_addon``, ``clean_scene``, ``pkg`` and ``sample_files`` in tests/conftest.py);
the core used for reference numbers is the installed copy too.
"""

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from ophelpers import (FPF, LOADS, REL_TOL, assert_drivers_simple, check_rig, evaluated_pose,
    evaluated_positions, fit_greens_rod, import_scan, rest_positions, set_loads)


# --------------------------------------------------------------------------
# fit: Green's scans and load controls
# --------------------------------------------------------------------------


@pytest.mark.parametrize("p_max,max_expr", [(0.0, None), (3.0, None), (0.0, 40)],
                         ids=["linear", "hardening", "split-expressions"])
def test_greens_loads_drive_rig_like_the_model(clean_scene, pkg, sample_files, monkeypatch,
                                               p_max, max_expr):
    assert not bpy.context.preferences.filepaths.use_scripts_auto_execute
    if max_expr is not None:  # force partial sums (long driver expressions)
        monkeypatch.setattr(pkg.drivers, "MAX_EXPRESSION", max_expr)
    ref = pkg.files.read_scan(sample_files["greens_rod"])
    obj = import_scan(sample_files["greens_rod"])
    rest = rest_positions(obj)
    assert bpy.ops.artdef.fit(links=3, p_max=p_max) == {'FINISHED'}
    arm, result = check_rig(pkg, obj, 3, ref.n_fields)
    assert (result.p_max is None) == (p_max == 0.0)
    bpy.context.scene.frame_set(0)  # the load sweep's rest frame: every load 0
    m = len(ref.load_vertices)
    for k in range(m):
        emp = bpy.data.objects[f"artdef_load_{k}"]
        assert emp.parent == arm
        np.testing.assert_allclose(np.array(emp.matrix_world.translation), rest[ref.load_vertices[k]],
                                   atol=1e-5)
    assert_drivers_simple(obj)
    if max_expr is not None:
        assert any(fc.driver.type == 'SUM' for fc in arm.animation_data.drivers)
    np.testing.assert_allclose(evaluated_positions(obj), rest, atol=1e-6 * np.abs(rest).max())
    for loads in (LOADS[:m], -0.5 * LOADS[:m], 3.0 * LOADS[:m]):
        set_loads(obj, loads)
        x = evaluated_positions(obj)
        want = pkg.model.evaluate_loads(result, rest, loads)
        err = np.abs(x - want).max() / np.abs(want - rest).max()
        assert err <= REL_TOL, err


def test_pseudo_mode_builds_one_load_points_rig(clean_scene, pkg, sample_files):
    ref = pkg.files.read_scan(sample_files["greens_rod"])
    obj = import_scan(sample_files["greens_rod"])
    rest = rest_positions(obj)
    assert bpy.ops.artdef.fit(links=3, mode='PSEUDO', load_index=2) == {'FINISHED'}
    result = pkg.ops.last_result(obj)
    assert result.kappa.shape[2] == 3
    loads_objs = [o.name for o in bpy.data.objects if o.name.startswith("artdef_load_")]
    assert loads_objs == ["artdef_load_2"]
    assert len(obj.data.shape_keys.key_blocks) == 1 + 3
    bpy.data.objects["artdef_load_2"].location = LOADS[2]
    x = evaluated_positions(obj)
    want = pkg.model.evaluate_loads(result, rest, LOADS[2:3])
    assert np.abs(x - want).max() / np.abs(want - rest).max() <= REL_TOL
    with pytest.raises(RuntimeError, match="Load Index"):
        bpy.ops.artdef.fit(links=3, mode='PSEUDO', load_index=len(ref.load_vertices))


def test_greens_loads_drive_helper_bones_that_link_bones_follow(clean_scene, pkg, sample_files):
    """The drivers sit on the helper bones only; with no keys of their own the
    link bones take the helpers' pose, and the mesh is exactly what link bones
    driven directly (the former rig) give."""
    obj, arm, result, rest = fit_greens_rod(pkg, sample_files)
    names = [pkg.rig.GROUP_FMT.format(l) for l in range(3)]
    helpers = [pkg.rig.HELPER_FMT.format(l) for l in range(3)]
    driven = {fc.data_path.split('"')[1] for fc in arm.animation_data.drivers
              if fc.data_path.startswith("pose.bones[")}
    assert driven and driven <= set(helpers), driven
    bpy.context.scene.frame_set(0)
    set_loads(obj, LOADS[:len(result.load_vertices)])
    x = evaluated_positions(obj)
    size = np.abs(rest).max()
    assert np.abs(x - rest).max() > 1e-3 * size  # the loads move the mesh
    pose = evaluated_pose(arm)
    for name, helper in zip(names, helpers):
        np.testing.assert_allclose(np.array(pose[name].matrix), np.array(pose[helper].matrix),
                                   atol=1e-5 * size)
    # the former rig: the helpers' driven values on the link bones, no constraint
    driven_values = [(tuple(pose[h].rotation_quaternion.to_euler('XYZ')), tuple(pose[h].location)) for h in helpers]
    for name, (rotation, location) in zip(names, driven_values):
        pb = arm.pose.bones[name]
        pb.constraints[pkg.rig.LOAD_CONSTRAINT].mute = True
        pb.rotation_euler, pb.location = rotation, location
    np.testing.assert_allclose(evaluated_positions(obj), x, atol=1e-5 * size)


def test_greens_link_bones_take_animator_keys_on_top_of_loads(clean_scene, pkg, sample_files):
    """A rotation keyed on a link bone adds to the load-driven motion (a driver on
    the link bone itself would override the key)."""
    from mathutils import Euler

    obj, arm, result, rest = fit_greens_rod(pkg, sample_files)
    scene = bpy.context.scene
    children = {int(p) for p in result.parents if p >= 0}
    k = next(l for l in range(3) if result.parents[l] >= 0 and l not in children)  # a leaf link
    name, helper = pkg.rig.GROUP_FMT.format(k), pkg.rig.HELPER_FMT.format(k)
    # the sweep's peak of the load case (field c) that turns link k the most
    c = int(np.argmax(np.abs(np.asarray(result.kappa)[k, :3]).max(axis=0)))
    peak = pkg.rig.sweep_frame(c, FPF)
    scene.frame_set(peak)
    x_loaded = evaluated_positions(obj)
    loaded = np.array(evaluated_pose(arm)[name].matrix)
    key = (0.3, -0.2, 0.25)
    pb = arm.pose.bones[name]
    pb.rotation_euler = key
    assert pb.keyframe_insert("rotation_euler", frame=peak)
    scene.frame_set(0)
    scene.frame_set(peak)
    np.testing.assert_allclose(tuple(pb.rotation_euler), key, atol=1e-6)
    pose = evaluated_pose(arm)
    size = np.abs(rest).max()
    assert not np.allclose(np.array(pose[helper].matrix_basis), np.eye(4), atol=1e-6)  # loaded
    want = pose[helper].matrix @ Euler(key, 'XYZ').to_matrix().to_4x4()
    np.testing.assert_allclose(np.array(pose[name].matrix), np.array(want), atol=1e-5 * size)
    # the mesh follows: vertices of link k alone turn with it, the others stay
    keyed = np.array(pose[name].matrix)
    x = evaluated_positions(obj)
    w = np.asarray(result.weights)
    own, other = w[:, k] > 1.0 - 1e-6, w[:, k] == 0.0
    assert own.any() and other.any()
    moved = np.c_[x_loaded[own], np.ones(own.sum())] @ (keyed @ np.linalg.inv(loaded)).T
    np.testing.assert_allclose(x[own], moved[:, :3], atol=1e-5 * size)
    np.testing.assert_allclose(x[other], x_loaded[other], atol=1e-5 * size)
    assert np.abs(x[own] - x_loaded[own]).max() > 1e-2 * size


def test_greens_clear_rig_removes_helpers_and_refit_rebuilds(clean_scene, pkg, sample_files):
    obj, arm, result, rest = fit_greens_rod(pkg, sample_files)
    assert bpy.ops.artdef.clear_rig() == {'FINISHED'}
    assert [o.name for o in bpy.data.objects] == [obj.name]
    assert len(bpy.data.armatures) == 0 and len(bpy.data.actions) == 0
    assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}
    assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}  # a re-fit replaces its own rig
    assert [a.name for a in bpy.data.armatures] == [f"{obj.name}_artdef_rig"]
    arm, result = check_rig(pkg, obj, 3, pkg.files.read_scan(sample_files["greens_rod"]).n_fields)
    assert len(arm.data.bones) == 6
    set_loads(obj, LOADS[:len(result.load_vertices)])
    want = pkg.model.evaluate_loads(result, rest, LOADS[:len(result.load_vertices)])
    x = evaluated_positions(obj)
    assert np.abs(x - want).max() / np.abs(want - rest).max() <= REL_TOL


def test_greens_load_sweep_sets_and_restores_frame_range(clean_scene, sample_files):
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 3, 40
    obj = import_scan(sample_files["greens_rod"])
    m = obj.data["artdef_n_loads"]
    assert bpy.ops.artdef.fit(links=3, frames_per_field=4) == {'FINISHED'}
    # load k along axis d (field c = 3k+d): 0 at 2c*F, probe load at (2c+1)*F, 0 at (2c+2)*F
    assert (scene.frame_start, scene.frame_end) == (0, 2 * 3 * m * 4)
    assert obj.artdef.fit_replay.startswith("load sweep")
    assert "artdef_residual" in obj.data.attributes
    actions = [bpy.data.objects[f"artdef_load_{k}"].animation_data.action for k in range(m)]
    assert all(a is not None and a.get("artdef_made") for a in actions)
    assert bpy.ops.artdef.clear_rig() == {'FINISHED'}
    assert (scene.frame_start, scene.frame_end) == (3, 40)
    assert not any(a.name.endswith("_sweep") for a in bpy.data.actions)


@pytest.mark.parametrize("p_max", [0.0, 3.0], ids=["linear", "hardening"])
def test_greens_load_sweep_shows_each_load_case(clean_scene, pkg, sample_files, p_max):
    """At the sweep's peak frame of load k along axis d the rig is the model under
    that probe load alone; half-way up, under half of it."""
    ref = pkg.files.read_scan(sample_files["greens_rod"])
    obj = import_scan(sample_files["greens_rod"])
    rest = rest_positions(obj)
    assert bpy.ops.artdef.fit(links=3, p_max=p_max) == {'FINISHED'}
    result = pkg.ops.last_result(obj)
    scene = bpy.context.scene
    m, probe = len(ref.load_vertices), float(ref.probe_load)
    for c in range(3 * m):
        k, d = divmod(c, 3)
        peak = pkg.rig.sweep_frame(c, FPF)
        full = np.zeros((m, 3))
        full[k, d] = probe
        scale = np.abs(pkg.model.evaluate_loads(result, rest, full) - rest).max()
        for frame, amount in ((peak, 1.0), (peak - FPF // 2, 0.5), (peak + FPF, 0.0)):
            scene.frame_set(frame)
            loads = amount * full
            got = np.array([bpy.data.objects[f"artdef_load_{j}"].location for j in range(m)])
            np.testing.assert_allclose(got, loads, atol=1e-6 * probe)
            x = evaluated_positions(obj)
            want = pkg.model.evaluate_loads(result, rest, loads)
            err = np.abs(x - want).max() / scale
            assert err <= REL_TOL, (c, frame, err)
        if p_max == 0.0:
            # linear: on the way up the rig is the scan's own field scaled, to first order: a tenth of
            # the probe load within 5 % of a tenth of the field, and half that load half as far off
            field = probe * ref.greens[:, c].reshape(-1, 3)
            off = []
            for frame, sub, amount in ((peak - FPF + 1, 0.0, 0.1), (peak - FPF, 0.5, 0.05)):
                scene.frame_set(frame, subframe=sub)
                x = evaluated_positions(obj)
                off.append(np.abs(x - rest - amount * field).max() / np.abs(amount * field).max())
            assert off[0] <= 0.05 and off[1] <= 0.6 * off[0], (c, off)


def test_pseudo_mode_sweeps_its_one_load_point(clean_scene, pkg, sample_files):
    obj = import_scan(sample_files["greens_rod"])
    assert bpy.ops.artdef.fit(links=3, mode='PSEUDO', load_index=2) == {'FINISHED'}
    scene = bpy.context.scene
    assert (scene.frame_start, scene.frame_end) == (0, 2 * 3 * FPF)
    emp = bpy.data.objects["artdef_load_2"]
    scene.frame_set(pkg.rig.sweep_frame(1, FPF))  # the empty's axis y
    np.testing.assert_allclose(np.array(emp.location), [0.0, float(obj.data["artdef_probe_load"]), 0.0],
                               atol=1e-6)
