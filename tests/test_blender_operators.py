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


# --------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------

@pytest.fixture(scope="session")
def pkg(installed_addon):
    """Modules of the installed extension."""
    class P:
        scan = importlib.import_module(installed_addon + ".artdef_addon.scan")
        samples = importlib.import_module(installed_addon + ".artdef_addon.samples")
        model = importlib.import_module(installed_addon + ".artdef_addon.model")
        ops = importlib.import_module(installed_addon + ".operators.ops")
        io = importlib.import_module(installed_addon + ".operators.io")
        rig = importlib.import_module(installed_addon + ".operators.rig")
    return P


@pytest.fixture(scope="session")
def sample_files(pkg, tmp_path_factory):
    d = tmp_path_factory.mktemp("scans")
    out = {}
    for name in ("rod", "branching", "greens_rod"):
        path = d / f"{name}.npz"
        pkg.scan.save_scan(path, pkg.samples.make(name))
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
    for name in ("import_scan", "fields_from_shape_keys", "fit", "preview_links", "clear_rig"):
        op = getattr(bpy.types, "ARTDEF_OT_" + name)
        assert {'REGISTER', 'UNDO'} <= set(op.bl_options), name
        assert op.__doc__ and len(op.__doc__) > 20, f"{name} has no tooltip"
    assert hasattr(bpy.types, "ARTDEF_PT_main")
    assert bpy.types.ARTDEF_PT_main.bl_category == "ArtDef"
    fit_props = bpy.ops.artdef.fit.get_rna_type().properties
    for prop in ("links", "mode", "motion", "p_max", "load_index"):
        assert fit_props[prop].description, prop


def test_import_tracked_scan_round_trips(clean_scene, pkg, sample_files, tmp_path):
    ref = pkg.scan.load_scan(sample_files["rod"])
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
    ref = pkg.scan.load_scan(sample_files["greens_rod"])
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
    assert [b.name for b in arm.data.bones] == names
    keys = obj.data.shape_keys.key_blocks
    assert len(keys) == n_fields + 1 and keys[0].name == "Basis"
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


@pytest.mark.parametrize("name,links", [("rod", 3), ("branching", 11)])
def test_fit_tracked_builds_rig_and_replays_fields(clean_scene, pkg, sample_files, name, links):
    ref = pkg.scan.load_scan(sample_files[name])
    obj = import_scan(sample_files[name])
    rest = rest_positions(obj)
    assert bpy.ops.artdef.fit(links=links) == {'FINISHED'}
    arm, result = check_rig(pkg, obj, links, ref.n_fields)
    assert obj.artdef.has_fit and obj.artdef.fit_links == links
    assert arm.animation_data.action is not None
    fields = ref.fields()
    scale = np.abs(fields).max()
    scene = bpy.context.scene
    scene.frame_set(0)
    np.testing.assert_allclose(evaluated_positions(obj), rest, atol=1e-5 * np.abs(rest).max())
    for p in range(ref.n_fields):
        scene.frame_set(p + 1)
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
        if d.type == 'SCRIPTED':
            assert d.is_simple_expression, (fc.data_path, d.expression)


@pytest.mark.parametrize("p_max,max_expr", [(0.0, None), (3.0, None), (0.0, 40)],
                         ids=["linear", "hardening", "split-expressions"])
def test_greens_loads_drive_rig_like_the_model(clean_scene, pkg, sample_files, monkeypatch,
                                               p_max, max_expr):
    assert not bpy.context.preferences.filepaths.use_scripts_auto_execute
    if max_expr is not None:  # force partial sums (long driver expressions)
        monkeypatch.setattr(pkg.rig, "MAX_EXPRESSION", max_expr)
    ref = pkg.scan.load_scan(sample_files["greens_rod"])
    obj = import_scan(sample_files["greens_rod"])
    rest = rest_positions(obj)
    assert bpy.ops.artdef.fit(links=3, p_max=p_max) == {'FINISHED'}
    arm, result = check_rig(pkg, obj, 3, ref.n_fields)
    assert (result.p_max is None) == (p_max == 0.0)
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
    ref = pkg.scan.load_scan(sample_files["greens_rod"])
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
    check_rig(pkg, obj, 2, pkg.scan.load_scan(sample_files["rod"]).n_fields)
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
        return stage == "merge"  # cancel half-way through

    pkg.ops.PROGRESS_HOOKS.append(hook)
    try:
        assert bpy.ops.artdef.fit(links=11) == {'CANCELLED'}
    finally:
        pkg.ops.PROGRESS_HOOKS.remove(hook)
    assert "merge" in seen
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
    ref = pkg.scan.load_scan(sample_files["rod"])
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


def test_preview_links_colours_faces_from_cached_clustering(clean_scene, pkg, sample_files):
    obj = import_scan(sample_files["branching"])
    pkg.ops._SEGMENTERS.clear()
    assert bpy.ops.artdef.preview_links(links=11) == {'FINISHED'}
    seg = pkg.ops._SEGMENTERS[obj.name][1]
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
    assert pkg.ops._SEGMENTERS[obj.name][1] is seg  # distances not recomputed
    # the fit reuses the cached clustering too, and colours by its links
    assert bpy.ops.artdef.fit(links=11) == {'FINISHED'}
    assert pkg.ops._SEGMENTERS[obj.name][1] is seg
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
    bpy.context.scene.frame_set(1)
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
    scan = pkg.scan.load_scan(sample_files["branching"])
    job = pkg.ops._FitJob(scan, 11, "global", "robust", None)
    job.cancel.set()  # Esc before the first progress report
    job.start_thread()
    job.thread.join(60)
    assert not job.thread.is_alive()
    assert isinstance(job.error, fit_mod.FitCancelled) and job.result is None
    job = pkg.ops._FitJob(pkg.scan.load_scan(sample_files["rod"]), 3, "global", "robust", None)
    job.start_thread()
    job.thread.join(60)
    assert job.error is None and job.result.n_links == 3
    assert job.stage == "done" and job.fraction == 1.0
    assert job.segmenter is not None and job.segmenter.progress is None


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
