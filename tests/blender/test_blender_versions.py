"""What differs between the supported Blender versions (operators/compat.py),
and that a failed or cancelled fit leaves no datablock of any kind behind.

Runs in every Blender the test command covers (bpy 5.2 LTS in .venv, bpy 4.5
LTS in .venv-4.5), on the extension installed from the built zip."""

import importlib

import pytest

bpy = pytest.importorskip("bpy")


@pytest.fixture(scope="module")
def mods(installed_addon):
    class M:
        compat = importlib.import_module(installed_addon + ".operators.compat")
        rig = importlib.import_module(installed_addon + ".operators.rig")
        loads = importlib.import_module(installed_addon + ".operators.loads")
        replay = importlib.import_module(installed_addon + ".operators.replay")
        ops = importlib.import_module(installed_addon + ".operators.ops")
        files = importlib.import_module(installed_addon + ".artdef_addon.files")
        samples = importlib.import_module(installed_addon + ".artdef_addon.samples")
    return M


@pytest.fixture(scope="module")
def scan_files(mods, tmp_path_factory):
    d = tmp_path_factory.mktemp("scans")
    out = {}
    for name in ("rod", "greens_rod"):
        out[name] = str(d / f"{name}.npz")
        mods.files.write_scan(out[name], mods.samples.make(name))
    return out


def _import(path):
    assert bpy.ops.artdef.import_scan(filepath=path) == {'FINISHED'}
    return bpy.context.view_layer.objects.active


def counts(mods):
    """Number of datablocks in every ``bpy.data`` collection (objects, meshes,
    armatures, actions, images, texts, shape_keys, ...)."""
    return {name: len(getattr(bpy.data, name)) for name in mods.rig.id_collections()}


def test_every_datablock_collection_is_counted(mods):
    names = set(mods.rig.id_collections())
    assert {"objects", "meshes", "armatures", "actions", "images", "texts", "shape_keys",
            "collections", "materials", "node_groups"} <= names, sorted(names)


def test_new_action_keys_grouped_fcurves(clean_scene, mods):
    """compat.new_action: an action in its own slot with grouped F-Curves that animate."""
    ob = bpy.data.objects.new("keyed", None)
    bpy.context.scene.collection.objects.link(ob)
    action, new_fcurve = mods.compat.new_action(ob, "keyed_action")
    assert ob.animation_data.action == action
    assert ob.animation_data.action_slot is not None
    curves = [new_fcurve("location", i, "Moves") for i in range(3)]
    new_fcurve("rotation_euler", 2, "Turns")
    for i, fc in enumerate(curves):
        fc.keyframe_points.insert(0.0, 0.0)
        fc.keyframe_points.insert(10.0, float(i + 1))
    assert [fc.group.name for fc in curves] == ["Moves"] * 3
    assert curves[0].group == curves[2].group           # one group per name
    bpy.context.scene.frame_set(10)
    assert tuple(round(v, 6) for v in ob.location) == (1.0, 2.0, 3.0)


# (module attribute, function, scans whose fit reaches it): the function runs, then
# raises, so whatever that stage of the rig build made exists when the fit fails.
_STAGES = [
    ("rig", "_fill_vertex_group", ("rod", "greens_rod")),
    ("rig", "_make_armature", ("rod", "greens_rod")),
    ("compat", "new_action", ("rod", "greens_rod")),
    ("replay", "_build_replay", ("rod",)),
    ("loads", "_make_load_empties", ("greens_rod",)),
    ("loads", "_build_load_sweep", ("greens_rod",)),
    ("rig", "write_residual", ("rod", "greens_rod")),
]


@pytest.mark.parametrize("module,function,scans", _STAGES, ids=[s[1] for s in _STAGES])
def test_failed_rig_build_leaves_every_datablock_count_unchanged(
        clean_scene, mods, scan_files, monkeypatch, module, function, scans):
    owner = getattr(mods, module)
    real = getattr(owner, function)
    made = []

    def fail_after(*args, **kwargs):
        real(*args, **kwargs)
        made.append(sum(counts(mods).values()))
        raise RuntimeError("forced failure")

    monkeypatch.setattr(owner, function, fail_after)
    for name in scans:
        obj = _import(scan_files[name])
        before = counts(mods)
        names_before = {n: sorted(db.name for db in getattr(bpy.data, n)) for n in before}
        with pytest.raises(RuntimeError, match="forced failure"):
            bpy.ops.artdef.fit(links=3)
        assert made, f"{function} was never reached"
        if function != "_fill_vertex_group":  # vertex groups are not datablocks
            assert made[-1] > sum(before.values()), "the stage made nothing: test proves nothing"
        assert counts(mods) == before
        assert {n: sorted(db.name for db in getattr(bpy.data, n)) for n in before} == names_before
        assert obj.artdef.rig is None and not obj.artdef.has_fit
        assert not obj.vertex_groups and obj.parent is None and not obj.modifiers


@pytest.mark.parametrize("stage", ["features", "cluster", "merge", "joints"])
@pytest.mark.parametrize("name", ["rod", "greens_rod"])
def test_cancelled_fit_leaves_every_datablock_count_unchanged(clean_scene, mods, scan_files,
                                                              stage, name):
    _import(scan_files[name])
    mods.ops.worker.forget()  # no kept clustering: the fit runs every stage
    before = counts(mods)
    seen = []

    def hook(s, fraction):
        seen.append(s)
        return s == stage

    mods.ops.PROGRESS_HOOKS.append(hook)
    try:
        assert bpy.ops.artdef.fit(links=3) == {'CANCELLED'}
    finally:
        mods.ops.PROGRESS_HOOKS.remove(hook)
    assert stage in seen
    assert counts(mods) == before


def _rig_state(obj, compat):
    """Everything of ``obj``'s rig and colours a re-fit could touch, as comparable plain data
    (``compat``: the extension's operators/compat, to read actions on every Blender)."""
    import numpy as np

    def drivers(id_data):
        ad = id_data.animation_data if id_data is not None else None
        if ad is None:
            return []
        return sorted((fc.data_path, fc.array_index, fc.driver.expression,
                       tuple(sorted((v.name, v.targets[0].id.name if v.targets[0].id else None,
                                     v.targets[0].data_path) for v in fc.driver.variables)))
                      for fc in ad.drivers)

    def action(id_data):
        ad = id_data.animation_data if id_data is not None else None
        if ad is None:
            return None
        return (ad.action.name if ad.action else None,
                sorted((t.name, tuple(s.action.name for s in t.strips if s.action)) for t in ad.nla_tracks))

    def attr(mesh, name):
        a = mesh.attributes.get(name)
        if a is None:
            return None
        key = "color" if a.data_type in ('FLOAT_COLOR', 'BYTE_COLOR') else "value"
        width = 4 if key == "color" else 1
        v = np.empty(width * len(a.data), dtype=np.float32)
        a.data.foreach_get(key, v)
        return (a.domain, a.data_type, v.round(5).tobytes())

    mesh, st, arm = obj.data, obj.artdef, obj.artdef.rig
    keys = mesh.shape_keys
    n = len(mesh.vertices)
    weights = {}
    for vg in obj.vertex_groups:
        weights[vg.name] = tuple(round(g.weight, 6) for v in mesh.vertices for g in v.groups
                                 if g.group == vg.index)
    key_co = {}
    if keys is not None:
        for kb in keys.key_blocks:
            co = np.empty(3 * n, dtype=np.float32)
            kb.data.foreach_get("co", co)
            key_co[kb.name] = (co.round(5).tobytes(), kb.relative_key.name, kb.slider_min, kb.slider_max)
    colours = mesh.color_attributes
    scene = bpy.context.scene
    dg = bpy.context.evaluated_depsgraph_get()
    dg.update()
    ev = obj.evaluated_get(dg)
    posed = ev.to_mesh()
    try:
        pose_co = np.empty(3 * len(posed.vertices), dtype=np.float32)
        posed.vertices.foreach_get("co", pose_co)
    finally:
        ev.to_mesh_clear()
    return {
        "evaluated": pose_co.round(4).tobytes(),
        "fcurves": {a.name: sorted((fc.data_path, fc.array_index, len(fc.keyframe_points))
                                   for fc in compat.action_fcurves(a)) for a in bpy.data.actions},
        "data": {c: sorted(db.name for db in getattr(bpy.data, c)) for c in ("objects", "meshes",
                 "armatures", "actions", "shape_keys", "collections")},
        "groups": [vg.name for vg in obj.vertex_groups], "weights": weights,
        "keys": [kb.name for kb in keys.key_blocks] if keys else [], "key_co": key_co,
        "key_drivers": drivers(keys), "key_action": action(keys),
        "arm": None if arm is None else (arm.name, arm.data.name, sorted(b.name for b in arm.data.bones),
                                         [tuple(round(x, 6) for x in b.head_local) for b in arm.data.bones],
                                         sorted(c.name for c in arm.children), drivers(arm),
                                         action(arm), sorted(k for k in arm.keys())),
        "empties": sorted((o.name, o.parent.name if o.parent else None, action(o), drivers(o))
                          for o in bpy.data.objects if o.get("artdef_load") is not None),
        "parent": (obj.parent.name if obj.parent else None, obj.parent_type,
                   tuple(round(x, 6) for row in obj.matrix_parent_inverse for x in row),
                   tuple(round(x, 6) for row in obj.matrix_world for x in row)),
        "modifiers": [(m.name, m.type, getattr(getattr(m, "object", None), "name", None)) for m in obj.modifiers],
        "colours": sorted(a.name for a in colours),
        "active_colour": colours.active_color.name if colours.active_color else None,
        "render_colour": colours.render_color_index,
        "attrs": {name: attr(mesh, name) for name in ("artdef_links", "artdef_residual",
                                                     "artdef_residual_color")},
        "record": (st.has_fit, st.made_basis, [g.name for g in st.groups], [k.name for k in st.shape_keys],
                   st.key_action.name if st.key_action else None,
                   st.key_action_previous.name if st.key_action_previous else None,
                   st.old_parent.name if st.old_parent else None, st.set_frame_range,
                   tuple(st.replay_frame_range), tuple(st.old_frame_range), st.fit_links),
        "frames": (scene.frame_start, scene.frame_end),
    }


def _failing_after(real):
    """``real`` run, then a RuntimeError("forced failure"): a rig build failing just after a stage."""
    def fail_after(*args, **kwargs):
        real(*args, **kwargs)
        raise RuntimeError("forced failure")
    return fail_after


@pytest.mark.parametrize("module,function,scans", _STAGES, ids=[s[1] for s in _STAGES])
def test_failed_refit_keeps_the_previous_rig(clean_scene, mods, scan_files, monkeypatch,
                                             module, function, scans):
    """A re-fit whose rig build fails leaves the previous rig exactly as it was: armature, load
    empties, vertex groups, shape keys, drivers, actions, colours, parent, frame range."""
    owner = getattr(mods, module)
    real = getattr(owner, function)
    fail_after = _failing_after(real)

    for name in scans:
        obj = _import(scan_files[name])
        assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}
        bpy.context.scene.frame_set(7)
        bpy.context.view_layer.update()
        before, counted = _rig_state(obj, mods.compat), counts(mods)
        monkeypatch.setattr(owner, function, fail_after)
        with pytest.raises(RuntimeError, match="forced failure"):
            bpy.ops.artdef.fit(links=2)
        monkeypatch.setattr(owner, function, real)
        assert counts(mods) == counted
        after = _rig_state(obj, mods.compat)
        assert {k: v for k, v in after.items() if v != before[k]} == {}, \
            {k: before[k] for k, v in after.items() if v != before[k]}
        # and the kept rig still works: Clear Rig removes it, a re-fit replaces it
        assert bpy.ops.artdef.fit(links=2) == {'FINISHED'}
        assert obj.artdef.fit_links == 2 and len(obj.artdef.rig.data.bones) in (2, 4)


@pytest.mark.parametrize("module,function,scans", _STAGES, ids=[s[1] for s in _STAGES])
def test_failed_first_fit_keeps_the_preview_colours(clean_scene, mods, scan_files, monkeypatch,
                                                    module, function, scans):
    """Preview Links' face colours, made before a first fit whose rig build fails, stay."""
    owner = getattr(mods, module)
    real = getattr(owner, function)
    fail_after = _failing_after(real)

    for name in scans:
        obj = _import(scan_files[name])
        assert bpy.ops.artdef.preview_links(links=2) == {'FINISHED'}
        before = _rig_state(obj, mods.compat)
        assert before["attrs"]["artdef_links"] is not None
        monkeypatch.setattr(owner, function, fail_after)
        with pytest.raises(RuntimeError, match="forced failure"):
            bpy.ops.artdef.fit(links=3)
        monkeypatch.setattr(owner, function, real)
        after = _rig_state(obj, mods.compat)
        assert {k: v for k, v in after.items() if v != before[k]} == {}, \
            {k: before[k] for k, v in after.items() if v != before[k]}
