"""The Fit operator on tracked scans (rig, replay, re-fit, failure, cancel, duplicates).

Run headless (bpy module) through the installed extension.

Everything goes through ``bpy.ops.artdef.*`` of the extension installed from the built zip
(fixtures ``installed_addon``, ``clean_scene``, ``pkg`` and ``sample_files`` in tests/conftest.py);
the core used for reference numbers is the installed copy too.
"""
import importlib
import os
import subprocess
import sys
import time

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from ophelpers import (FPF, REL_TOL, check_rig, evaluated_positions, field_model, import_scan,
    rest_positions, scene_snapshot)


# --------------------------------------------------------------------------
# fit: tracked scans
# --------------------------------------------------------------------------


@pytest.mark.parametrize("name,links", [("rod", 3), ("branching", 11)])
def test_fit_tracked_builds_rig_and_replays_fields(clean_scene, pkg, sample_files, name, links):
    ref = pkg.files.read_scan(sample_files[name])
    obj = import_scan(sample_files[name])
    rest = rest_positions(obj)
    assert bpy.ops.artdef.fit(links=links) == {'FINISHED'}
    arm, result = check_rig(pkg, obj, links, ref.n_fields)
    assert obj.artdef.has_fit and obj.artdef.fit_links == links
    assert arm.animation_data.action is not None
    fields = ref.fields()
    scale = np.abs(fields).max()
    scene = bpy.context.scene
    # the replay: rest at frame 0, field p at (p+1) * frames_per_field (default 10)
    assert (scene.frame_start, scene.frame_end) == (0, FPF * ref.n_fields)
    assert f"x{FPF}" in obj.artdef.fit_replay and "0-" in obj.artdef.fit_summary.splitlines()[-1]
    scene.frame_set(0)
    np.testing.assert_allclose(evaluated_positions(obj), rest, atol=1e-5 * np.abs(rest).max())
    for p in range(ref.n_fields):
        scene.frame_set((p + 1) * FPF)
        x = evaluated_positions(obj)
        # the rig is the core's model of field p ...
        model = field_model(pkg, result, rest, p)
        assert np.abs(x - model).max() <= REL_TOL * max(np.abs(model - rest).max(), scale)
        # ... which reproduces the input field within the fit's error: the articulated model's
        # with every field's own residual, else the low-rank basis's stated replay error
        err = np.linalg.norm(x - rest - fields[p], axis=1)
        basis = result.residual_basis
        if basis is None:
            assert np.sqrt(np.mean(err ** 2)) <= result.rms_total + 1e-4 * scale, (p, err, result.rms_total)
        else:
            diag = np.linalg.norm(np.ptp(rest, axis=0))
            assert err.max() <= basis.replay_error[0] / 100 * diag + 1e-4 * scale, (p, err.max(), basis)


# --------------------------------------------------------------------------
# undo, re-fit, failure, cancel, clear
# --------------------------------------------------------------------------

def test_undo_after_fit_restores_scene(clean_scene, sample_files):
    # undo=True (2nd positional argument) makes bpy.ops push the operator's
    # undo step as the UI does; headless calls don't push otherwise.
    bpy.ops.ed.undo_push(message="empty")
    assert bpy.ops.artdef.import_scan('EXEC_DEFAULT', True, filepath=sample_files["rod"]) == {'FINISHED'}
    before = scene_snapshot()
    assert bpy.ops.artdef.fit('EXEC_DEFAULT', True, links=3) == {'FINISHED'}
    assert scene_snapshot() != before
    assert bpy.ops.ed.undo() == {'FINISHED'}
    assert scene_snapshot() == before
    obj = bpy.data.objects["rod"]
    assert obj.artdef.rig is None and obj.data.shape_keys is None
    assert bpy.ops.ed.redo() == {'FINISHED'}
    assert bpy.data.objects["rod"].artdef.rig is not None


def test_refit_replaces_only_its_own_rig(clean_scene, pkg, sample_files):
    obj = import_scan(sample_files["rod"])
    n = len(obj.data.vertices)
    user_group = obj.vertex_groups.new(name="user_group")
    user_group.add(list(range(0, n, 2)), 0.25, 'REPLACE')
    user_obj = bpy.data.objects.new("user_thing", None)
    bpy.context.scene.collection.objects.link(user_obj)
    user_obj.location = (1, 2, 3)
    obj.modifiers.new("user_subsurf", 'SUBSURF')
    assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}
    first = obj.artdef.rig.name
    assert bpy.ops.artdef.fit(links=2) == {'FINISHED'}
    assert [a.name for a in bpy.data.armatures] == [f"{obj.name}_artdef_rig"]
    assert [o.name for o in bpy.data.objects if o.type == 'ARMATURE'] == [first]
    assert len(bpy.data.actions) == 2  # armature replay + shape-key replay, none left over
    assert sorted(g.name for g in obj.vertex_groups) == ["artdef_link_00", "artdef_link_01", "user_group"]
    assert user_group.weight(0) == pytest.approx(0.25)
    with pytest.raises(RuntimeError):
        user_group.weight(1)  # still not in the group
    assert [m.name for m in obj.modifiers] == ["ArtDef Armature", "user_subsurf"]
    assert tuple(bpy.data.objects["user_thing"].location) == (1, 2, 3)
    check_rig(pkg, obj, 2, pkg.files.read_scan(sample_files["rod"]).n_fields)
    # Clear Rig removes all of it and nothing else
    assert bpy.ops.artdef.clear_rig() == {'FINISHED'}
    assert sorted(o.name for o in bpy.data.objects) == ["rod", "user_thing"]
    assert [g.name for g in obj.vertex_groups] == ["user_group"]
    assert [m.name for m in obj.modifiers] == ["user_subsurf"]
    assert obj.data.shape_keys is None and obj.parent is None
    assert len(bpy.data.armatures) == 0 and len(bpy.data.actions) == 0
    assert "artdef_links" not in obj.data.color_attributes
    assert pkg.io.has_scan(obj.data)  # the scan stays


def test_failed_fit_changes_nothing(clean_scene, sample_files):
    obj = import_scan(sample_files["rod"])
    assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}
    before = scene_snapshot()
    with pytest.raises(RuntimeError, match="links"):
        bpy.ops.artdef.fit(links=100000)          # more links than triangles
    with pytest.raises(RuntimeError, match="Hardening"):
        bpy.ops.artdef.fit(links=3, p_max=0.5)    # p_max must be > 1
    with pytest.raises(RuntimeError, match="Green"):
        bpy.ops.artdef.fit(links=3, mode='PSEUDO')  # needs loads
    assert scene_snapshot() == before
    assert obj.artdef.fit_links == 3


def test_cancelled_fit_changes_nothing(clean_scene, pkg, sample_files):
    pkg.ops.worker.forget()    # the clustering runs (an earlier test's fit of this scan may be kept)
    import_scan(sample_files["branching"])
    before = scene_snapshot()
    seen = []

    def hook(stage, fraction):
        seen.append(stage)
        return stage == "cluster"  # cancel half-way through (distances done)

    pkg.ops.PROGRESS_HOOKS.append(hook)
    try:
        assert bpy.ops.artdef.fit(links=11) == {'CANCELLED'}
    finally:
        pkg.ops.PROGRESS_HOOKS.remove(hook)
    assert "cluster" in seen
    assert scene_snapshot() == before


def test_no_scan_no_fit(clean_scene):
    bpy.ops.mesh.primitive_cube_add()
    assert not bpy.ops.artdef.fit.poll()
    assert not bpy.ops.artdef.preview_links.poll()
    assert not bpy.ops.artdef.clear_rig.poll()


def test_rig_follows_mesh_transform_and_parent(clean_scene, pkg, sample_files):
    from mathutils import Matrix
    obj = import_scan(sample_files["rod"])
    rest = rest_positions(obj)
    holder = bpy.data.objects.new("user_parent", None)
    bpy.context.scene.collection.objects.link(holder)
    holder.location = (0.5, -1.0, 2.0)
    obj.parent = holder
    obj.location = (1.0, 2.0, 3.0)
    obj.rotation_euler = (0.3, 0.2, 0.1)
    obj.scale = (1.5, 1.5, 1.5)
    bpy.context.view_layer.update()
    world = obj.matrix_world.copy()
    assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}
    bpy.context.view_layer.update()
    arm = obj.artdef.rig
    assert arm.parent == holder
    np.testing.assert_allclose(np.array(arm.matrix_world), np.array(world), atol=1e-6)
    np.testing.assert_allclose(np.array(obj.matrix_world), np.array(world), atol=1e-6)
    result = pkg.ops.last_result(obj)
    bpy.context.scene.frame_set(FPF)
    model = field_model(pkg, result, rest, 0)
    x = evaluated_positions(obj)  # mesh space = armature space
    assert np.abs(x - model).max() <= REL_TOL * np.abs(model - rest).max()
    assert bpy.ops.artdef.clear_rig() == {'FINISHED'}
    bpy.context.view_layer.update()
    assert obj.parent == holder and obj.parent_type == 'OBJECT'
    np.testing.assert_allclose(np.array(obj.matrix_world), np.array(world), atol=1e-6)
    assert obj.matrix_parent_inverse == Matrix.Identity(4)


def test_fit_job_runs_in_the_worker_process_and_esc_ends_it(pkg, sample_files):
    """The job behind the interactive (modal, Esc) path: polled without blocking, it runs in the
    worker process; Esc (``cancel``) mid-fit ends that process within a second."""
    fit_mod = importlib.import_module(pkg.scan.__name__.rsplit(".", 1)[0] + ".result")
    job = pkg.ops._FitJob(pkg.files.read_scan(sample_files["rod"]), 3)
    job.start().wait()
    assert job.error is None and job.result.n_links == 3
    assert job.stage == "done" and job.fraction == 1.0
    assert job.pid != os.getpid() and pkg.ops.worker.cached(job.scan) is not None
    pkg.ops.worker.forget()                               # the clustering runs: stages to reach
    job = pkg.ops._FitJob(pkg.files.read_scan(sample_files["branching"]), 11).start()
    while not job.poll() and job.stage != "cluster":     # what the modal timer does
        try:
            pkg.ops.worker.SESSION.worker.process.wait(0.02)
        except subprocess.TimeoutExpired:
            pass
    proc = pkg.ops.worker.SESSION.worker.process
    t0 = time.monotonic()
    job.cancel()                                          # Esc
    assert proc.poll() is not None and time.monotonic() - t0 < 1.0
    assert job.poll() and isinstance(job.error, fit_mod.FitCancelled) and job.result is None
    assert pkg.ops.worker.SESSION.worker is None          # the next job starts a fresh worker


def test_the_fit_runs_in_a_worker_process(clean_scene, pkg, sample_files):
    """The panel's Fit computes in the add-on's worker, not in Blender's process."""
    obj = import_scan(sample_files["rod"])
    pkg.ops.worker.LAST_PID = None
    assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}
    assert pkg.ops.worker.LAST_PID not in (None, os.getpid())
    assert pkg.ops.worker.LAST_PID == pkg.ops.worker.SESSION.pid
    assert obj.artdef.fit_links == 3


def _fit_fails_cleanly(pkg, sample_files, match, hook=None, limit=None):
    """A fit whose worker fails (``hook`` at each progress report; ``limit``: the worker's memory
    limit for that fit) leaves the scene as it was, reports one error line, and Blender fits again
    afterwards."""
    session = pkg.ops.worker.SESSION
    obj = import_scan(sample_files["branching"])
    assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}      # a rig to keep
    before = scene_snapshot()
    if hook is not None:
        pkg.ops.PROGRESS_HOOKS.append(hook)
    session.memory_limit = limit
    try:
        with pytest.raises(RuntimeError, match=match) as info:
            bpy.ops.artdef.fit(links=11)
    finally:
        session.memory_limit = None
        if hook is not None:
            pkg.ops.PROGRESS_HOOKS.remove(hook)
    assert "\n" not in str(info.value).strip()
    assert scene_snapshot() == before and obj.artdef.fit_links == 3
    assert session.worker is None                            # the failed worker is gone
    assert bpy.ops.artdef.fit(links=11) == {'FINISHED'}      # Blender goes on
    assert obj.artdef.fit_links == 11


def test_a_worker_killed_mid_fit_leaves_the_scene_and_one_error_line(clean_scene, pkg, sample_files):
    import signal
    seen = []

    def kill(stage, fraction):
        if not seen:                  # at the first report the worker sends
            seen.append(pkg.ops.worker.SESSION.pid)
            os.kill(seen[0], signal.SIGKILL)
        return False

    _fit_fails_cleanly(pkg, sample_files, r"Fit failed: the worker process was killed \(SIGKILL", kill)
    assert seen and seen[0] != os.getpid()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="RLIMIT_AS is enforced on Linux")
def test_a_worker_over_its_memory_limit_leaves_the_scene_and_one_error_line(clean_scene, pkg, sample_files):
    _fit_fails_cleanly(pkg, sample_files, r"Fit failed: the worker process ran out of memory "
                                          r"\(its limit is 16 MB\)", limit=16 * 2**20)


def test_fit_validates_the_scan_once(clean_scene, pkg, sample_files, monkeypatch):
    """The operator validates the scan it reads from the mesh; the core's fit
    takes that validated scan as it is instead of checking every field again."""
    obj = import_scan(sample_files["rod"])
    calls = []
    check = pkg.scan._check_scan
    monkeypatch.setattr(pkg.scan, "_check_scan", lambda sc: calls.append(1) or check(sc))
    assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}
    assert obj.artdef.has_fit
    assert len(calls) == 1


def test_fitting_a_duplicate_keeps_the_originals_rig(clean_scene, sample_files):
    """A duplicated fitted mesh points at the original's armature: fitting or clearing the copy
    replaces only the copy's own rig."""
    obj = import_scan(sample_files["rod"])
    assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}
    arm = obj.artdef.rig
    assert bpy.ops.object.duplicate() == {'FINISHED'}
    copy = bpy.context.active_object
    assert copy != obj and copy.artdef.rig == arm
    assert bpy.ops.artdef.clear_rig() == {'FINISHED'}
    assert bpy.data.objects.get(arm.name) is not None and obj.parent == arm
    assert obj.modifiers["ArtDef Armature"].object == arm
    assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}
    assert obj.artdef.rig == arm and copy.artdef.rig not in (None, arm)


def test_a_linked_duplicate_leaves_the_originals_rig_alone(clean_scene, sample_files):
    """Objects sharing one mesh share its vertex groups and shape keys: fitting or clearing a
    linked duplicate of a fitted mesh would replace or remove the original's. Refused, one line,
    nothing changed; the original can still be re-fitted and cleared."""
    obj = import_scan(sample_files["rod"])
    before_fit = obj.copy()                     # linked duplicate made before the fit
    bpy.context.scene.collection.objects.link(before_fit)
    assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}
    assert bpy.ops.object.duplicate(linked=True) == {'FINISHED'}    # Alt+D after the fit
    after_fit = bpy.context.active_object
    assert after_fit.data == obj.data and after_fit.artdef.rig == obj.artdef.rig
    before = scene_snapshot()
    for copy in (before_fit, after_fit):
        with bpy.context.temp_override(active_object=copy, object=copy):
            with pytest.raises(RuntimeError, match=f"'{copy.name}' shares its mesh '{obj.data.name}' "
                                                   f"with '{obj.name}'"):
                bpy.ops.artdef.fit(links=2)
            if copy == after_fit:
                with pytest.raises(RuntimeError, match="Make Single User"):
                    bpy.ops.artdef.clear_rig()
    assert scene_snapshot() == before
    with bpy.context.temp_override(active_object=obj, object=obj):
        assert bpy.ops.artdef.fit(links=2) == {'FINISHED'}
        assert sorted(item.name for item in obj.artdef.groups) == ["artdef_link_00", "artdef_link_01"]
        assert bpy.ops.artdef.clear_rig() == {'FINISHED'}
    assert not obj.vertex_groups and obj.data.shape_keys is None


def test_name_bones_keeps_the_users_vertex_groups(clean_scene, sample_files):
    obj = import_scan(sample_files["rod"])
    obj.vertex_groups.new(name="user_vg")
    assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}
    with pytest.raises(RuntimeError, match="'user_vg' is a vertex group of the mesh that the fit did not make"):
        bpy.ops.artdef.name_bones(scheme='ONE', bone="artdef_link_00", new_name="user_vg")
    assert sorted(g.name for g in obj.vertex_groups) == ["artdef_link_00", "artdef_link_01", "artdef_link_02",
                                                         "user_vg"]
    # a long non-ASCII name: cut at Blender's 63 bytes, the record holds the name Blender keeps
    assert bpy.ops.artdef.name_bones(scheme='ONE', bone="artdef_link_01", new_name="é" * 40) == {'FINISHED'}
    kept = "é" * 31
    assert kept in obj.vertex_groups and kept in {item.name for item in obj.artdef.groups}
    assert bpy.ops.artdef.clear_rig() == {'FINISHED'}
    assert [g.name for g in obj.vertex_groups] == ["user_vg"]


def test_frames_per_field_past_blenders_last_frame_keeps_the_rig(clean_scene, sample_files):
    obj = import_scan(sample_files["rod"])
    assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}
    arm = obj.artdef.rig
    counts = {name: len(getattr(bpy.data, name)) for name in ("objects", "armatures", "actions")}
    with pytest.raises(RuntimeError, match="past Blender's last frame"):
        bpy.ops.artdef.fit(links=3, frames_per_field=10 ** 6)
    assert {name: len(getattr(bpy.data, name)) for name in counts} == counts
    assert obj.artdef.rig == arm and len(obj.vertex_groups) == 3
