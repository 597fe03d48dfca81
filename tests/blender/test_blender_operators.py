"""The operators of the installed extension, run headless (bpy module).

Everything goes through ``bpy.ops.artdef.*`` of the extension installed from
the built zip (fixtures ``installed_addon`` / ``clean_scene`` in conftest);
the core used for reference numbers is the installed copy too
(``bl_ext.user_default.artdef.artdef_addon``).
"""

import importlib

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

REL_TOL = 1e-4      # evaluated rig vs the core's model, relative to the displacement
HEAD_TOL = 1e-5     # bone heads vs the core's heads
FPF = 10            # default frames per field of the tracked replay


# --------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------

@pytest.fixture(scope="session")
def pkg(installed_addon):
    """Modules of the installed extension."""
    class P:
        scan = importlib.import_module(installed_addon + ".artdef_addon.scan")
        files = importlib.import_module(installed_addon + ".artdef_addon.files")
        samples = importlib.import_module(installed_addon + ".artdef_addon.samples")
        model = importlib.import_module(installed_addon + ".artdef_addon.model")
        ops = importlib.import_module(installed_addon + ".operators.ops")
        api = importlib.import_module(installed_addon + ".artdef_addon.api")
        cost = importlib.import_module(installed_addon + ".artdef_addon.cost")
        io = importlib.import_module(installed_addon + ".operators.io")
        rig = importlib.import_module(installed_addon + ".operators.rig")
    return P


@pytest.fixture(scope="session")
def sample_files(pkg, tmp_path_factory):
    d = tmp_path_factory.mktemp("scans")
    out = {}
    for name in ("rod", "branching", "greens_rod"):
        path = d / f"{name}.npz"
        pkg.files.write_scan(path, pkg.samples.make(name))
        out[name] = str(path)
    return out


def import_scan(path):
    assert bpy.ops.artdef.import_scan(filepath=path) == {'FINISHED'}
    obj = bpy.context.view_layer.objects.active
    assert obj is not None and obj.type == 'MESH'
    return obj


def rest_positions(obj):
    co = np.empty(3 * len(obj.data.vertices), dtype=np.float32)
    obj.data.vertices.foreach_get("co", co)
    return co.reshape(-1, 3).astype(np.float64)


def evaluated_positions(obj):
    dg = bpy.context.evaluated_depsgraph_get()
    dg.update()
    ev = obj.evaluated_get(dg)
    mesh = ev.to_mesh()
    try:
        co = np.empty(3 * len(mesh.vertices), dtype=np.float32)
        mesh.vertices.foreach_get("co", co)
    finally:
        ev.to_mesh_clear()
    return co.reshape(-1, 3).astype(np.float64)


def weight_matrix(obj, names):
    w = np.zeros((len(obj.data.vertices), len(names)))
    index = {obj.vertex_groups[n].index: j for j, n in enumerate(names)}
    for v in obj.data.vertices:
        for g in v.groups:
            j = index.get(g.group)
            if j is not None:
                w[v.index, j] = g.weight
    return w


def scene_snapshot():
    """Everything a fit could touch, as comparable plain data."""
    snap = {
        "objects": sorted((o.name, o.type, o.parent.name if o.parent else None,
                           tuple(round(x, 6) for row in o.matrix_world for x in row))
                          for o in bpy.data.objects),
        "armatures": sorted(a.name for a in bpy.data.armatures),
        "actions": sorted(a.name for a in bpy.data.actions),
        "meshes": {},
    }
    for o in bpy.data.objects:
        if o.type == 'MESH':
            keys = o.data.shape_keys
            snap["meshes"][o.name] = {
                "groups": [g.name for g in o.vertex_groups],
                "modifiers": [m.name for m in o.modifiers],
                "keys": [k.name for k in keys.key_blocks] if keys else [],
                "attributes": sorted(a.name for a in o.data.attributes),
                "rest": rest_positions(o).round(6).tobytes(),
                "has_fit": o.artdef.has_fit,
            }
    return snap


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
# fit: tracked scans
# --------------------------------------------------------------------------

def check_rig(pkg, obj, links, n_fields):
    st = obj.artdef
    arm = st.rig
    assert arm is not None and arm.type == 'ARMATURE'
    assert arm.name == f"{obj.name}_artdef_rig"
    result = pkg.ops.last_result(obj)
    assert result is not None and result.n_links == links
    names = [pkg.rig.GROUP_FMT.format(l) for l in range(links)]
    assert sorted(g.name for g in obj.vertex_groups if g.name.startswith("artdef_link_")) == names
    assert [b.name for b in arm.data.bones if b.use_deform] == names
    check_load_helpers(pkg, arm, names, greens=result.kappa is not None)
    keys = obj.data.shape_keys.key_blocks
    # a Green's rig: a first-order and a bump key per field (model.greens_keys)
    assert len(keys) == (2 if result.kappa is not None else 1) * n_fields + 1 and keys[0].name == "Basis"
    assert all(k.name.startswith("artdef_field_") for k in keys[1:])
    # bones: heads, tree, rotation mode; world = armature space (identity object transforms)
    for l, name in enumerate(names):
        bone = arm.data.bones[name]
        np.testing.assert_allclose(np.array(arm.matrix_world @ bone.head_local), result.heads[l],
                                   atol=HEAD_TOL)
        # Blender recomputes the frame from head, tail and roll in float32; bones
        # near -Y (a singular direction of its roll formula) differ by ~4e-5.
        np.testing.assert_allclose(np.array(bone.matrix_local.to_3x3()), result.frames[l], atol=1e-4)
        parent = result.parents[l]
        assert (bone.parent.name if bone.parent else None) == (names[parent] if parent >= 0 else None)
        assert not bone.use_connect and bone.use_deform
        assert arm.pose.bones[name].rotation_mode == 'XYZ'
    # weights
    w = weight_matrix(obj, names)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(w, result.weights, atol=1e-6)
    # parenting + modifier
    assert obj.parent == arm
    mod = obj.modifiers[0]
    assert mod.name == "ArtDef Armature" and mod.type == 'ARMATURE' and mod.object == arm
    assert obj.data.color_attributes.active_color.name == "artdef_links"
    return arm, result


def check_load_helpers(pkg, arm, names, greens):
    """Green's rigs: one hidden non-deforming helper bone per link bone (same rest
    frame and parent) that the link bone's Copy Transforms constraint puts before
    its own transform.  Tracked rigs: no helpers, no constraints."""
    helpers = [pkg.rig.HELPER_FMT.format(l) for l in range(len(names))]
    assert sorted(b.name for b in arm.data.bones if not b.use_deform) == (helpers if greens else [])
    for name, helper in zip(names, helpers):
        cons = arm.pose.bones[name].constraints
        if not greens:
            assert len(cons) == 0, name
            continue
        bone, hbone = arm.data.bones[name], arm.data.bones[helper]
        assert [c.name for c in hbone.collections] == [pkg.rig.HELPER_COLLECTION]
        assert not hbone.collections[0].is_visible
        assert hbone.parent == bone.parent
        np.testing.assert_allclose(np.array(hbone.matrix_local), np.array(bone.matrix_local), atol=1e-6)
        assert arm.pose.bones[helper].rotation_mode == 'XYZ'
        assert [c.type for c in cons] == ['COPY_TRANSFORMS']
        con = cons[0]
        assert (con.target, con.subtarget) == (arm, helper)
        assert (con.target_space, con.owner_space, con.mix_mode) == ('LOCAL', 'LOCAL', 'BEFORE_FULL')


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
        model = pkg.model.deform(result, rest, result.params[p], np.eye(ref.n_fields)[p])
        assert np.abs(x - model).max() <= REL_TOL * max(np.abs(model - rest).max(), scale)
        # ... which reproduces the input field within the fit's error
        rms = np.sqrt(np.mean(np.sum((x - rest - fields[p]) ** 2, axis=1)))
        assert rms <= result.rms_total + 1e-4 * scale, (p, rms, result.rms_total)


# --------------------------------------------------------------------------
# fit: Green's scans and load controls
# --------------------------------------------------------------------------

LOADS = np.array([[0.3, -0.2, 0.5], [0.0, 0.0, 0.0], [1.0, 0.5, -0.2], [0.1, 0.1, 2.1]])


def set_loads(obj, loads, names=None):
    names = range(len(loads)) if names is None else names
    for k, p in zip(names, loads):
        bpy.data.objects[f"artdef_load_{k}"].location = p


def assert_drivers_simple(obj):
    drivers = list(obj.artdef.rig.animation_data.drivers) + list(obj.data.shape_keys.animation_data.drivers)
    assert drivers
    for fc in drivers:
        d = fc.driver
        assert d.is_valid, fc.data_path
        # no (0,0),(1,1) keys: with them Blender snaps values near 0 or 1 to the key
        assert len(fc.keyframe_points) == 0, fc.data_path
        if d.type == 'SCRIPTED':
            assert d.is_simple_expression, (fc.data_path, d.expression)


@pytest.mark.parametrize("p_max,max_expr", [(0.0, None), (3.0, None), (0.0, 40)],
                         ids=["linear", "hardening", "split-expressions"])
def test_greens_loads_drive_rig_like_the_model(clean_scene, pkg, sample_files, monkeypatch,
                                               p_max, max_expr):
    assert not bpy.context.preferences.filepaths.use_scripts_auto_execute
    if max_expr is not None:  # force partial sums (long driver expressions)
        monkeypatch.setattr(pkg.rig, "MAX_EXPRESSION", max_expr)
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
    assert len(obj.data.shape_keys.key_blocks) == 1 + 2 * 3
    bpy.data.objects["artdef_load_2"].location = LOADS[2]
    x = evaluated_positions(obj)
    want = pkg.model.evaluate_loads(result, rest, LOADS[2:3])
    assert np.abs(x - want).max() / np.abs(want - rest).max() <= REL_TOL
    with pytest.raises(RuntimeError, match="Load Index"):
        bpy.ops.artdef.fit(links=3, mode='PSEUDO', load_index=len(ref.load_vertices))


def evaluated_pose(arm):
    """The armature's evaluated pose bones (drivers and constraints applied)."""
    dg = bpy.context.evaluated_depsgraph_get()
    dg.update()
    return arm.evaluated_get(dg).pose.bones


def fit_greens_rod(pkg, sample_files):
    """The Green's rod fitted with 3 links: (mesh object, armature, result, rest positions)."""
    obj = import_scan(sample_files["greens_rod"])
    rest = rest_positions(obj)
    assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}
    ref = pkg.files.read_scan(sample_files["greens_rod"])
    arm, result = check_rig(pkg, obj, 3, ref.n_fields)
    return obj, arm, result, rest


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
    driven_values = [(tuple(pose[h].rotation_euler), tuple(pose[h].location)) for h in helpers]
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
    assert len(keys) == 1 + 2 * ref.n_fields
    # Re-storing ignores the fit's own residual keys; clearing keeps the user's poses.
    assert bpy.ops.artdef.fields_from_shape_keys() == {'FINISHED'}
    assert pkg.io.read_scan(obj).scan.n_fields == ref.n_fields
    assert bpy.ops.artdef.clear_rig() == {'FINISHED'}
    assert [k.name for k in obj.data.shape_keys.key_blocks] == keys[:1 + ref.n_fields]


def test_preview_segments_in_a_worker_thread_and_cancels(clean_scene, pkg, sample_files):
    """The interactive Preview Links runs its first clustering off the main thread (issue 6):
    the worker gives the same links as the synchronous path, and Esc (a cancel) leaves no
    cached clustering and no colours behind."""
    obj = import_scan(sample_files["branching"])
    pkg.api.clear_cache()
    job = pkg.ops._preview_job(obj, 11)
    assert not job.cached
    job.start_thread()
    job.thread.join(timeout=600)
    assert job.error is None and job.labels is not None
    ref = pkg.ops._fit.Segmenter(pkg.io.read_scan(obj).scan).labels(11)
    assert len(np.unique(job.labels)) == 11 and np.array_equal(job.labels, ref)
    stages = []

    def hook(stage, fraction):
        stages.append(stage)
        return True  # cancel at the first report

    pkg.api.clear_cache()  # the first preview kept its clustering: cancel a fresh one
    pkg.ops.PROGRESS_HOOKS.append(hook)
    try:
        job = pkg.ops._preview_job(obj, 11)
        job.start_thread()
        job.thread.join(timeout=600)
    finally:
        pkg.ops.PROGRESS_HOOKS.remove(hook)
    assert stages and isinstance(job.error, pkg.ops._fit.FitCancelled)
    assert pkg.ops.cached_segmentation(obj) is None
    assert "artdef_links" not in obj.data.color_attributes


def test_preview_links_colours_faces_from_cached_clustering(clean_scene, pkg, sample_files):
    obj = import_scan(sample_files["branching"])
    pkg.api.clear_cache()
    assert bpy.ops.artdef.preview_links(links=11) == {'FINISHED'}
    seg = pkg.ops.cached_segmentation(obj)
    assert seg is not None
    attr = obj.data.color_attributes["artdef_links"]
    assert attr.domain == 'CORNER' and attr.data_type == 'BYTE_COLOR'
    assert obj.data.color_attributes.active_color.name == "artdef_links"

    def n_colours():
        c = np.empty(4 * len(attr.data), dtype=np.float32)
        obj.data.color_attributes["artdef_links"].data.foreach_get("color_srgb", c)
        return len(np.unique(c.reshape(-1, 4).round(3), axis=0))

    assert n_colours() == 11
    assert bpy.ops.artdef.preview_links(links=5) == {'FINISHED'}
    attr = obj.data.color_attributes["artdef_links"]
    assert n_colours() == 5
    assert pkg.ops.cached_segmentation(obj) is seg  # distances not recomputed
    # the fit reuses the cached clustering too, and colours by its links
    assert bpy.ops.artdef.fit(links=11) == {'FINISHED'}
    assert pkg.ops.cached_segmentation(obj) is seg
    attr = obj.data.color_attributes["artdef_links"]
    assert n_colours() == 11


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
    model = pkg.model.deform(result, rest, result.params[0], np.eye(result.residual.shape[0])[0])
    x = evaluated_positions(obj)  # mesh space = armature space
    assert np.abs(x - model).max() <= REL_TOL * np.abs(model - rest).max()
    assert bpy.ops.artdef.clear_rig() == {'FINISHED'}
    bpy.context.view_layer.update()
    assert obj.parent == holder and obj.parent_type == 'OBJECT'
    np.testing.assert_allclose(np.array(obj.matrix_world), np.array(world), atol=1e-6)
    assert obj.matrix_parent_inverse == Matrix.Identity(4)


def test_fit_job_runs_in_a_thread_and_cancels(pkg, sample_files):
    """The worker-thread job behind the interactive (modal, Esc) path."""
    fit_mod = importlib.import_module(pkg.scan.__name__.rsplit(".", 1)[0] + ".fit")
    scan = pkg.files.read_scan(sample_files["branching"])
    job = pkg.ops._FitJob(scan, 11)
    job.cancel.set()  # Esc before the first progress report
    job.start_thread()
    job.thread.join(60)
    assert not job.thread.is_alive()
    assert isinstance(job.error, fit_mod.FitCancelled) and job.result is None
    job = pkg.ops._FitJob(pkg.files.read_scan(sample_files["rod"]), 3)
    job.start_thread()
    job.thread.join(60)
    assert job.error is None and job.result.n_links == 3
    assert job.stage == "done" and job.fraction == 1.0
    seg = pkg.api.cached(job.scan)
    assert seg is not None and seg.progress is None  # the kept segmentation holds no callback


class _Layout:
    """Stand-in for UILayout that records what a panel draws and checks names."""

    def __init__(self, log):
        self.__dict__["log"] = log

    def _sub(self, *args, **kw):
        return _Layout(self.log)

    box = row = column = split = _sub

    def label(self, text="", **kw):
        self.log.append(("label", text))

    def separator(self, **kw):
        pass

    def prop(self, data, name, **kw):
        assert name in data.bl_rna.properties, name
        self.log.append(("prop", name))

    def operator(self, idname, **kw):
        mod, name = idname.split(".")
        op = getattr(getattr(bpy.ops, mod), name)
        props = op.get_rna_type().properties
        self.log.append(("operator", idname, op.poll()))

        class Props:
            def __setattr__(self, key, value):
                assert key in props, (idname, key)
        return Props()

    def __setattr__(self, key, value):
        assert key in ("scale_y", "use_property_split", "use_property_decorate", "enabled", "alert")
        self.log.append(("set", key, value))


def draw_panel():
    log = []
    panel = type("P", (), {"layout": _Layout(log)})()
    bpy.types.ARTDEF_PT_main.draw(panel, bpy.context)
    return log


def test_panel_draws_scan_settings_and_summary(clean_scene, sample_files):
    log = draw_panel()
    assert ("operator", "artdef.import_scan", True) in log
    bpy.ops.mesh.primitive_cube_add()
    assert ("label", "No scan on this mesh") in draw_panel()
    import_scan(sample_files["greens_rod"])
    log = draw_panel()
    labels = [e[1] for e in log if e[0] == "label"]
    assert f"Vertices: {len(bpy.context.active_object.data.vertices):,}" in labels
    assert "Fields: 12" in labels and any(l.startswith("Load points: 4") for l in labels)
    assert ("operator", "artdef.fit", True) in log
    assert {("prop", p) for p in ("links", "mode", "motion", "p_max")} <= set(log)
    assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}
    labels = [e[1] for e in draw_panel() if e[0] == "label"]
    assert any(l.startswith("Links: 3") for l in labels)
    assert any(l.startswith("RMS articulation") for l in labels)
    assert any(l.startswith("Time:") for l in labels)


# --------------------------------------------------------------------------
# fit quality you can see: residual attribute, per-link figures, replay range
# --------------------------------------------------------------------------

def test_fit_stores_residual_and_link_quality(clean_scene, pkg, sample_files, tmp_path):
    ref = pkg.files.read_scan(sample_files["rod"])
    obj = import_scan(sample_files["rod"])
    rest = rest_positions(obj)
    assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}
    result = pkg.ops.last_result(obj)
    mesh = obj.data
    attr = mesh.attributes["artdef_residual"]
    assert attr.domain == 'POINT' and attr.data_type == 'FLOAT'
    stored = np.empty(len(mesh.vertices), dtype=np.float32)
    attr.data.foreach_get("value", stored)
    # Independent of the core's model code: Blender's own evaluation of the
    # rig with the residual shape keys muted is the articulated motion alone.
    for kb in mesh.shape_keys.key_blocks[1:]:
        kb.mute = True
    fields = ref.fields()
    acc = np.zeros(len(rest))
    for p in range(ref.n_fields):
        bpy.context.scene.frame_set((p + 1) * FPF)
        acc += np.sum((evaluated_positions(obj) - rest - fields[p]) ** 2, axis=1)
    want = np.sqrt(acc / ref.n_fields)
    assert want.max() > 0
    np.testing.assert_allclose(stored, want, atol=1e-4 * np.abs(fields).max())
    # colours: blue at 0, red at the largest residual; the links stay the shown colours
    col = mesh.color_attributes["artdef_residual_color"]
    assert col.domain == 'POINT' and col.data_type == 'FLOAT_COLOR'
    rgba = np.empty(4 * len(col.data), dtype=np.float32)
    col.data.foreach_get("color_srgb", rgba)
    rgba = rgba.reshape(-1, 4)
    top, low = int(np.argmax(stored)), int(np.argmin(stored))
    assert rgba[top, 0] > 0.8 and rgba[top, 2] < 0.2          # red
    assert stored[low] < 0.1 * stored[top] and rgba[low, 2] > 0.8  # blue-ish
    assert mesh.color_attributes.active_color.name == "artdef_links"
    # per-link and overall figures, as stored properties
    st = obj.artdef
    assert st.fit_articulation_percent == pytest.approx(result.articulation_error_percent, rel=1e-6)
    assert st.fit_e_rms == pytest.approx(result.e_rms, rel=1e-5)            # issue 19's figures
    assert st.fit_rigid_percent == pytest.approx(result.rigid_error_percent, rel=1e-5)
    assert st.fit_articulated and result.articulated
    assert st.fit_residual_max == pytest.approx(float(stored.max()), rel=1e-5)
    assert len(st.fit_link_stats) == 3
    rigid = np.sqrt(np.mean(result.link_residuals ** 2, axis=0))
    for l, item in enumerate(st.fit_link_stats):
        assert item.name == f"artdef_link_{l:02d}" and item.link == l
        assert item.parent == result.parents[l]
        assert item.rigid_residual == pytest.approx(rigid[l], rel=1e-5, abs=1e-12)
        assert item.triangles == np.count_nonzero(result.face_labels == l)
        assert item.has_joint == bool(np.isfinite(result.joint_errors[l]))
        if item.has_joint:
            assert item.joint_error == pytest.approx(result.joint_errors[l], rel=1e-5, abs=1e-12)
    assert sum(i.has_joint for i in st.fit_link_stats) >= 2
    # the panel shows them
    st.show_link_stats = True
    labels = [e[1] for e in draw_panel() if e[0] == "label"]
    assert any(l.startswith("Articulation error (Karni–Gotsman):") and l.endswith("%") for l in labels)
    assert any(l.startswith("E_RMS: ") for l in labels) and any(l.startswith("One rigid motion: ") for l in labels)
    assert any(l.startswith("Vertex residual: mean") for l in labels)
    assert sum(l.startswith(("00 ", "01 ", "02 ")) for l in labels) == 3
    assert any(l.startswith("Replay: field p at frame (p+1)x10") for l in labels)
    assert bpy.ops.artdef.show_colours(which='RESIDUAL') == {'FINISHED'}
    assert mesh.color_attributes.active_color.name == "artdef_residual_color"
    log = draw_panel()
    assert ("operator", "artdef.show_colours", True) in log
    assert any(e[0] == "label" and e[1].startswith("Blue 0, red ") for e in log)
    assert bpy.ops.artdef.show_colours(which='LINKS') == {'FINISHED'}
    assert mesh.color_attributes.active_color.name == "artdef_links"
    # ... and survive save + reload
    path = str(tmp_path / "quality.blend")
    bpy.ops.wm.save_as_mainfile(filepath=path)
    bpy.ops.wm.open_mainfile(filepath=path)
    obj = bpy.data.objects["rod"]
    st = obj.artdef
    assert len(st.fit_link_stats) == 3 and st.fit_articulation_percent > 0
    assert st.fit_link_stats[1].rigid_residual == pytest.approx(rigid[1], rel=1e-5, abs=1e-12)
    assert "artdef_residual" in obj.data.attributes
    assert "artdef_residual_color" in obj.data.color_attributes


def test_replay_frame_range_is_set_and_restored(clean_scene, sample_files):
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 5, 50
    obj = import_scan(sample_files["rod"])
    n_fields = obj.data["artdef_n_fields"]
    assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}
    assert (scene.frame_start, scene.frame_end) == (0, FPF * n_fields)
    action = obj.artdef.rig.animation_data.action
    assert tuple(action.frame_range) == (0, FPF * n_fields)
    assert bpy.ops.artdef.fit(links=3, frames_per_field=4) == {'FINISHED'}
    assert (scene.frame_start, scene.frame_end) == (0, 4 * n_fields)
    assert obj.artdef.frames_per_field == 4
    assert bpy.ops.artdef.clear_rig() == {'FINISHED'}
    assert (scene.frame_start, scene.frame_end) == (5, 50)
    # a range the user changed after the fit is left alone
    assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}
    scene.frame_end = 77
    assert bpy.ops.artdef.clear_rig() == {'FINISHED'}
    assert (scene.frame_start, scene.frame_end) == (0, 77)


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
            # linear: the peak is the scan's own field (articulation + residual key)
            scene.frame_set(peak)
            field = probe * ref.greens[:, c].reshape(-1, 3)
            x = evaluated_positions(obj)
            assert np.abs(x - rest - field).max() <= REL_TOL * np.abs(field).max()


def test_pseudo_mode_sweeps_its_one_load_point(clean_scene, pkg, sample_files):
    obj = import_scan(sample_files["greens_rod"])
    assert bpy.ops.artdef.fit(links=3, mode='PSEUDO', load_index=2) == {'FINISHED'}
    scene = bpy.context.scene
    assert (scene.frame_start, scene.frame_end) == (0, 2 * 3 * FPF)
    emp = bpy.data.objects["artdef_load_2"]
    scene.frame_set(pkg.rig.sweep_frame(1, FPF))  # the empty's axis y
    np.testing.assert_allclose(np.array(emp.location), [0.0, float(obj.data["artdef_probe_load"]), 0.0],
                               atol=1e-6)


# --------------------------------------------------------------------------
# a jointed tube: numpy geometry, rigid chain poses
# --------------------------------------------------------------------------

SEGMENTS = 3
JOINTS = np.array([[0.0, 0.0, float(z)] for z in range(SEGMENTS)])  # heads of the chain's bones


def tube_geometry(rings_per_segment=6, sides=12, radius=0.15):
    """Quads along z in [0, SEGMENTS] with n-gon caps; the segment of every vertex."""
    n_rings = SEGMENTS * rings_per_segment + 1
    z = np.linspace(0.0, SEGMENTS, n_rings)
    a = 2 * np.pi * np.arange(sides) / sides
    verts = np.stack([np.tile(radius * np.cos(a), n_rings), np.tile(radius * np.sin(a), n_rings),
                      np.repeat(z, sides)], axis=1)
    polys = []
    for r in range(n_rings - 1):
        for s in range(sides):
            i, j = r * sides + s, r * sides + (s + 1) % sides
            polys.append([i, j, j + sides, i + sides])
    polys.append(list(range(sides))[::-1])
    polys.append(list(range((n_rings - 1) * sides, n_rings * sides)))
    segment = np.minimum((np.repeat(np.arange(n_rings), sides)) // rings_per_segment, SEGMENTS - 1)
    # the joint rings belong to the segment above them, except the top ring
    return verts, polys, segment


def random_rotations(rng, n_poses, max_angle=0.7):
    return rng.uniform(-max_angle, max_angle, size=(n_poses, SEGMENTS, 3))


def tube_weights(verts, blend=0.0):
    """(N, SEGMENTS) skin weights: hard by segment, or blended linearly over
    ``blend`` on either side of each joint (like a painted character)."""
    z = verts[:, 2]
    w = np.zeros((len(verts), SEGMENTS))
    lower = np.ones(len(verts))
    for b in range(1, SEGMENTS):
        zj = JOINTS[b, 2]
        t = (np.clip((z - zj + blend) / (2 * blend), 0.0, 1.0) if blend > 0
             else (z >= zj).astype(float))
        w[:, b - 1] = lower * (1 - t)
        lower = lower * t
    w[:, -1] = lower
    return w


def chain_pose(verts, weights, eulers, basis=np.eye(3)):
    """Linear blend skinning of a chain: bone b rotates by euler[b] (XYZ, in the
    bone frame ``basis``) about JOINTS[b], children follow."""
    from mathutils import Euler
    out = np.zeros_like(verts)
    R_acc, t_acc = np.eye(3), np.zeros(3)
    for b in range(SEGMENTS):
        R = basis @ np.array(Euler(eulers[b], 'XYZ').to_matrix()) @ basis.T
        # G_b = G_{b-1} o (rotate about joint b)
        t_local = JOINTS[b] - R @ JOINTS[b]
        R_acc, t_acc = R_acc @ R, R_acc @ t_local + t_acc
        out += weights[:, b:b + 1] * (verts @ R_acc.T + t_acc)
    return out


def check_joints(pkg, obj, tol_fraction=0.01):
    """The fitted rig's joints (heads of links with a parent) match JOINTS[1:]."""
    result = pkg.ops.last_result(obj)
    assert result.n_links == SEGMENTS
    arm = obj.artdef.rig
    heads = {b.name: np.array(b.head_local) for b in arm.data.bones}
    fitted = np.array([heads[pkg.rig.GROUP_FMT.format(l)] for l in range(SEGMENTS)
                       if result.parents[l] >= 0])
    assert len(fitted) == SEGMENTS - 1
    rest = rest_positions(obj)
    diag = np.linalg.norm(np.ptp(rest, axis=0))
    dist = np.linalg.norm(fitted[:, None] - JOINTS[None, 1:], axis=2)
    # every true joint has a fitted one nearby, one to one
    assert sorted(dist.argmin(axis=1).tolist()) == list(range(SEGMENTS - 1)), dist
    err = dist.min(axis=1).max() / diag
    assert err < tol_fraction, (err, fitted)
    return err


# --------------------------------------------------------------------------
# fields from animation
# --------------------------------------------------------------------------

def _edit_bones(arm, fn):
    view_layer = bpy.context.view_layer
    view_layer.objects.active = arm
    with bpy.context.temp_override(active_object=arm, object=arm, selected_objects=[arm],
                                   selected_editable_objects=[arm]):
        bpy.ops.object.mode_set(mode='EDIT')
        fn(arm.data.edit_bones)
        bpy.ops.object.mode_set(mode='OBJECT')


def build_animated_tube(rng, n_poses=8, blend=0.0):
    """The user's rig: a tube skinned to a 3-bone chain, keyed at frames 1..n."""
    verts, polys, segment = tube_geometry()
    weights = tube_weights(verts, blend)
    mesh = bpy.data.meshes.new("tube")
    mesh.from_pydata(verts.tolist(), [], polys)
    mesh.shade_smooth()
    tube = bpy.data.objects.new("tube", mesh)
    skel = bpy.data.objects.new("skel", bpy.data.armatures.new("skel"))
    for ob in (skel, tube):
        bpy.context.scene.collection.objects.link(ob)
    skel.location = (2.0, -1.0, 0.5)  # object space is what is sampled

    def bones(eb):
        parent = None
        for b in range(SEGMENTS):
            bone = eb.new(f"b{b}")
            bone.head, bone.tail = JOINTS[b], JOINTS[b] + (0, 0, 1)
            bone.parent, bone.use_connect = parent, parent is not None
            parent = bone
    _edit_bones(skel, bones)
    for b in range(SEGMENTS):
        vg = tube.vertex_groups.new(name=f"b{b}")
        for i in np.flatnonzero(weights[:, b] > 0):
            vg.add([int(i)], float(weights[i, b]), 'REPLACE')
    tube.parent = skel
    mod = tube.modifiers.new("Armature", 'ARMATURE')
    mod.object = skel
    tube.modifiers.new("Subdivision", 'SUBSURF')  # changes topology: off while sampling
    eulers = random_rotations(rng, n_poses)
    for f in range(n_poses):
        for b in range(SEGMENTS):
            pb = skel.pose.bones[f"b{b}"]
            pb.rotation_mode = 'XYZ'
            pb.rotation_euler = eulers[f, b]
            pb.keyframe_insert("rotation_euler", frame=f + 1)
    bpy.context.view_layer.objects.active = tube
    return tube, skel, verts, weights, eulers


@pytest.mark.parametrize("blend", [0.0, 0.3], ids=["hard-weights", "blended-weights"])
def test_armature_animation_fit_reproduces_its_joints(clean_scene, pkg, blend):
    """Issue 5: importing an armature-animated mesh and fitting it reproduces
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


def shape_key_blob():
    """A mesh whose shape keys are animated: frames 1-4 (3 and 4 equal)."""
    verts, polys, segment = tube_geometry(rings_per_segment=2, sides=6)
    mesh = bpy.data.meshes.new("blob")
    mesh.from_pydata(verts.tolist(), [], polys)
    obj = bpy.data.objects.new("blob", mesh)
    bpy.context.scene.collection.objects.link(obj)
    bpy.context.view_layer.objects.active = obj
    obj.shape_key_add(name="Basis")
    offsets = [np.outer(segment == s, [0.1 * (s + 1), 0.0, 0.05]) for s in range(2)]
    for s, off in enumerate(offsets):
        kb = obj.shape_key_add(name=f"k{s}")
        kb.data.foreach_set("co", (verts + off).astype(np.float32).ravel())
    values = {1: (1.0, 0.0), 2: (0.0, 1.0), 3: (0.5, 0.5), 4: (0.5, 0.5)}
    keys = mesh.shape_keys.key_blocks
    for f, vals in values.items():
        for s, v in enumerate(vals):
            keys[f"k{s}"].value = v
            keys[f"k{s}"].keyframe_insert("value", frame=f)
    return obj, verts, offsets, values


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


def _vertex_cutting_nodes():
    """Geometry nodes that delete the vertices with index < current frame."""
    ng = bpy.data.node_groups.new("cut", 'GeometryNodeTree')
    ng.interface.new_socket("Geometry", in_out='INPUT', socket_type='NodeSocketGeometry')
    ng.interface.new_socket("Geometry", in_out='OUTPUT', socket_type='NodeSocketGeometry')
    n = ng.nodes
    gin, gout = n.new('NodeGroupInput'), n.new('NodeGroupOutput')
    delete, index = n.new('GeometryNodeDeleteGeometry'), n.new('GeometryNodeInputIndex')
    time_, compare = n.new('GeometryNodeInputSceneTime'), n.new('FunctionNodeCompare')
    compare.data_type, compare.operation = 'FLOAT', 'LESS_THAN'
    ng.links.new(index.outputs[0], compare.inputs[0])
    ng.links.new(time_.outputs["Frame"], compare.inputs[1])
    ng.links.new(gin.outputs[0], delete.inputs["Geometry"])
    ng.links.new(compare.outputs[0], delete.inputs["Selection"])
    ng.links.new(delete.outputs[0], gout.inputs[0])
    return ng


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


# --------------------------------------------------------------------------
# mesh sequences (OBJ / PLY)
# --------------------------------------------------------------------------

def write_obj(path, verts, polys):
    with open(path, "w") as f:
        f.write("# ArtDef test\no tube\n")
        f.writelines(f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in verts)
        f.write("vn 0 0 1\n")
        f.writelines("f " + " ".join(f"{i + 1}//1" for i in poly) + "\n" for poly in polys)


def write_ply(path, verts, polys, fmt):
    head = (f"ply\nformat {fmt} 1.0\ncomment ArtDef test\nelement vertex {len(verts)}\n"
            "property float x\nproperty float y\nproperty float z\nproperty uchar flag\n"
            f"element face {len(polys)}\nproperty list uchar int vertex_indices\nend_header\n")
    with open(path, "wb") as f:
        f.write(head.encode())
        if fmt == "ascii":
            f.writelines(f"{x:.9g} {y:.9g} {z:.9g} 1\n".encode() for x, y, z in verts)
            f.writelines((f"{len(p)} " + " ".join(map(str, p)) + "\n").encode() for p in polys)
        else:
            vt = np.zeros(len(verts), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("f", "u1")])
            vt["x"], vt["y"], vt["z"] = np.asarray(verts).T
            f.write(vt.tobytes())
            for p in polys:
                f.write(bytes([len(p)]) + np.asarray(p, dtype="<i4").tobytes())


@pytest.fixture(scope="module")
def tube_poses():
    verts, polys, segment = tube_geometry()
    eulers = random_rotations(np.random.default_rng(11), 6)
    weights = tube_weights(verts)
    return verts, polys, [verts] + [chain_pose(verts, weights, e) for e in eulers]


def write_sequence(directory, poses, polys, name="pose_{:03d}.obj", fmt=None):
    directory.mkdir(exist_ok=True)
    paths = []
    for i, x in enumerate(poses):
        path = directory / name.format(i)
        write_obj(path, x, polys) if fmt is None else write_ply(path, x, polys, fmt)
        paths.append(str(path))
    return paths


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


# --------------------------------------------------------------------------
# core options: automatic link count, skin weights
# --------------------------------------------------------------------------

def test_fit_properties_are_the_cores_declaration(pkg):
    """The Fit operator's and the object's settings are made from FitOptions (one declaration):
    same defaults, choices (upper-cased ids), bounds and descriptions; the panel's Fit button
    copies every one of them."""
    options = importlib.import_module(pkg.scan.__name__.rsplit(".", 1)[0] + ".options")
    decl = options.FitOptions.declaration()
    for rna in (bpy.ops.artdef.fit.get_rna_type(), bpy.types.Object.bl_rna.properties["artdef"].fixed_type):
        props = rna.properties
        for name, (default, opt) in decl.items():
            p = props[name]
            assert p.name == opt.label and p.description.startswith(opt.description), name
            if opt.choices:
                assert [i.identifier for i in p.enum_items] == [v.upper() for v in opt.values]
                assert [i.description for i in p.enum_items] == [c.description for c in opt.choices]
                assert p.default == default.upper()
            else:
                assert p.default == pytest.approx(0 if default is None else default, rel=1e-6), name
                # an exclusive bound (memory budget > 0): Blender's minimum sits just above it
                want = 0 if opt.optional else opt.min + (1e-6 if opt.min_exclusive else 0)
                assert p.hard_min == pytest.approx(want, rel=1e-6, abs=1e-9), name
                if opt.min_exclusive and not opt.optional:
                    assert p.hard_min > opt.min, name
                if opt.max is not None:
                    assert p.hard_max == pytest.approx(opt.max, rel=1e-6), name
    st = bpy.types.Object.bl_rna.properties["artdef"].fixed_type.properties
    for name in pkg.ops.SETTING_NAMES:
        assert name in bpy.ops.artdef.fit.get_rna_type().properties and name in st
    # a value the declaration refuses is reported with the setting's label, nothing is made
    assert pkg.ops.options_from(type("S", (), dict(
        mode='GLOBAL', motion='LSQ', p_max=0.0, max_links=4, memory_budget=1.0, reduce='ON',
        strategy='PAPER', skin='SEAM'))()) == options.FitOptions(
        motion="lsq", max_links=4, memory_budget=1.0, reduce="on", strategy="paper", skin="seam")


def test_fit_skin_option(clean_scene, pkg, sample_files):
    ref = pkg.files.read_scan(sample_files["rod"])
    obj = import_scan(sample_files["rod"])
    props = bpy.ops.artdef.fit.get_rna_type().properties
    assert props["skin"].default == 'AUTO' and props["skin"].description
    assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}       # tracked: refined by default
    assert pkg.ops.last_result(obj).skin == "refined" and obj.artdef.fit_skin == "refined"
    _, result = check_rig(pkg, obj, 3, ref.n_fields)         # groups hold the refined weights
    assert np.count_nonzero(result.weights > 0, axis=1).max() <= 4
    assert bpy.ops.artdef.fit(links=3, skin='SEAM') == {'FINISHED'}
    assert pkg.ops.last_result(obj).skin == "seam" and obj.artdef.skin == 'SEAM'
    check_rig(pkg, obj, 3, ref.n_fields)
    obj = import_scan(sample_files["greens_rod"])
    assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}       # Green's: seam by default
    assert pkg.ops.last_result(obj).skin == "seam"


def test_fit_auto_links(clean_scene, pkg, sample_files):
    obj = import_scan(sample_files["rod"])
    assert bpy.ops.artdef.fit(auto_links=True, max_links=6) == {'FINISHED'}
    st = obj.artdef
    result = pkg.ops.last_result(obj)
    assert st.fit_link_reason.startswith(f"links auto: chose {result.n_links}")
    assert result.n_links == 3  # the rod sample's true link count
    assert st.links == st.fit_links == 3 and st.auto_links and st.max_links == 6
    assert len(st.rig.data.bones) == 3
    labels = [e[1] for e in draw_panel() if e[0] == "label"]
    # the panel says it in plain words (issue 17); the technical reason stays in fit_link_reason
    assert any(l.startswith("3 links leave") for l in labels)
    assert ("prop", "max_links") in draw_panel()
    # an explicit link count overrides the object's Auto Links setting
    assert bpy.ops.artdef.fit(links=2) == {'FINISHED'}
    assert pkg.ops.last_result(obj).n_links == 2 and not st.auto_links and st.fit_link_reason == ""
    # a tracked scan without support: the chooser's whole fits end at the chosen count, whose fit
    # the operator builds (not fitted twice)
    obj = import_scan(sample_files["branching"])
    assert bpy.ops.artdef.fit(auto_links=True, max_links=14) == {'FINISHED'}
    result = pkg.ops.last_result(obj)
    assert result.n_links == 11 and obj.artdef.fit_link_reason.startswith("links auto: chose 11")
    assert len(obj.artdef.rig.data.bones) == 11


# --------------------------------------------------------------------------
# scale (issue 6): memory budget, reduced method, cost estimate, progress words
# --------------------------------------------------------------------------

def test_memory_budget_switches_to_reduced_method_and_says_so(clean_scene, pkg, sample_files,
                                                              capfd):
    obj = import_scan(sample_files["branching"])
    st = obj.artdef
    props = bpy.ops.artdef.fit.get_rna_type().properties
    assert props["memory_budget"].default == 2.0 and props["memory_budget"].description
    assert props["reduce"].default == 'AUTO' and props["reduce"].description
    labels = [e[1] for e in draw_panel() if e[0] == "label"]
    assert {("prop", "reduce"), ("prop", "memory_budget")} <= set(draw_panel())
    assert any(l.startswith("Estimate: about ") for l in labels)
    assert "full method on 1,072 triangles" in labels
    # the default budget: the full method, no note
    assert bpy.ops.artdef.fit(links=11) == {'FINISHED'}
    assert pkg.ops.last_result(obj).notes == [] and st.fit_notes == "" and not st.fit_reduced
    full_seg = pkg.ops.cached_segmentation(obj)
    assert not full_seg.reduced
    capfd.readouterr()
    # a tiny budget: the fit switches to the reduced method, says why, still makes 11 bones
    assert bpy.ops.artdef.fit(links=11, memory_budget=0.001) == {'FINISHED'}
    result = pkg.ops.last_result(obj)
    assert result.n_links == 11 and len(st.rig.data.bones) == 11
    assert any("reduced method" in n for n in result.notes)
    assert "reduced method" in st.fit_notes and st.fit_reduced
    assert st.memory_budget == pytest.approx(0.001) and st.reduce == 'AUTO'
    out = capfd.readouterr()
    assert "reduced method" in out.out + out.err  # the operator's INFO reports
    seg = pkg.ops.cached_segmentation(obj)
    assert seg is not full_seg and seg.reduced  # the cache follows the settings
    labels = [e[1] for e in draw_panel() if e[0] == "label"]
    assert any("reduced method" in l for l in labels)                      # the fit's notes
    assert any(l.startswith("reduced method on about ") for l in labels)   # the estimate
    # Preview Links uses the object's settings: the cached reduced segmenter
    assert bpy.ops.artdef.preview_links(links=11) == {'FINISHED'}
    assert pkg.ops.cached_segmentation(obj) is seg
    # Reduced Method Off ignores the budget; back on the default budget: no note
    assert bpy.ops.artdef.fit(links=11, reduce='OFF') == {'FINISHED'}
    assert pkg.ops.last_result(obj).notes == [] and not pkg.ops.cached_segmentation(obj).reduced
    assert bpy.ops.artdef.fit(links=11, reduce='AUTO', memory_budget=2.0) == {'FINISHED'}
    assert pkg.ops.last_result(obj).notes == [] and st.fit_notes == "" and not st.fit_reduced
    assert not any("reduced method" in e[1] for e in draw_panel() if e[0] == "label")


def test_estimate_follows_the_settings(pkg):
    plan = pkg.ops.method_plan
    est, arg = plan(1_000_000, 50, 500_000, "tracked", 'AUTO', 2.0)
    # the reduced method: the patch stream's features over every triangle (the peak at this size,
    # above the 2 GB budget, which bounds the pairwise stage) and the scan's fields, under 4 GB
    stream = pkg.cost.stream_bytes(1_000_000, 50)
    assert est.reduced and arg is None and stream < est.memory_bytes < 4 * 2 ** 30
    est, arg = plan(1_000_000, 50, 500_000, "tracked", 'OFF', 2.0)
    assert not est.reduced and arg is False and est.memory_bytes > 1e12
    est, arg = plan(1000, 12, 500, "tracked", 'ON', 2.0)
    assert est.reduced and arg is True and est.units <= 1000
    est, arg = plan(1000, 12, 500, "greens", 'AUTO', 2.0)
    assert not est.reduced and arg is None
    # a tracked fit's skin decompositions grow with the link count; Auto Links prices the search
    few = plan(4672, 20, 2338, "tracked", 'AUTO', 2.0, links=5)[0].seconds
    many = plan(4672, 20, 2338, "tracked", 'AUTO', 2.0, links=40)[0].seconds
    auto = plan(4672, 20, 2338, "tracked", 'AUTO', 2.0, links=5, auto=True)[0].seconds
    assert few < many < auto
    # the search's curve segments every count up to Max Links
    assert plan(4672, 20, 2338, "tracked", 'AUTO', 2.0, auto=True, max_links=60)[0].seconds > auto


def test_fit_progress_reads_as_words(pkg):
    text = pkg.ops.stage_text
    for stage in ("features", "distances", "cluster", "merge", "links", "pseudo"):
        assert text(stage, 0.25).endswith(" 25%") and text(stage, 0.25) != f"{stage} 25%"
    assert text("merge column 3", 0.5) == "merging pieces into links (load point 3) 50%"
    for stage in ("segment", "motions", "relabel", "skin", "joints", "bones", "pose", "residuals"):
        assert text(stage, 0.0) != stage and not text(stage, 0.0).endswith("%")   # reported once: no 0%
    assert text("joints", 0.0) == "joints and tree"
    assert text("done", 1.0) == "finishing" and text("start", 0.0) == "starting"
    job = pkg.ops._FitJob(None, "auto")
    job.progress("links", 0.5)
    job.progress("merge", 0.2)
    assert job.status_text() == "choosing the link count 50% (merging pieces into links 20%)"
    # the search reports 1 when it has chosen: a fit of that count that follows shows its own stages
    job.progress("links", 1.0)
    job.progress("skin", 0.0)
    assert job.status_text() == "skin weights" and job.links_fraction is None


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


def test_import_scan_takes_blender_relative_paths(clean_scene, sample_files, tmp_path):
    import shutil
    shutil.copy(sample_files["rod"], tmp_path / "rod.npz")
    assert bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "s.blend")) == {'FINISHED'}
    assert bpy.ops.artdef.import_scan(filepath="//rod.npz") == {'FINISHED'}


def test_panel_draws_with_an_unusable_memory_budget(clean_scene, sample_files):
    obj = import_scan(sample_files["rod"])
    obj.artdef.memory_budget = 0.0          # Blender keeps it at the declared minimum (above 0)
    assert obj.artdef.memory_budget > 0
    assert any(e[0] == "label" and str(e[1]).startswith("Estimate:") for e in draw_panel())
    obj.data["artdef_n_fields"] = "many"    # a damaged scan property: the panel still draws
    assert ("operator", "artdef.fit", True) in draw_panel()
    with pytest.raises(RuntimeError, match="field"):   # the fit reads the scan and says what is wrong
        bpy.ops.artdef.fit(links=3)
