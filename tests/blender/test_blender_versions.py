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
    ("rig", "_build_replay", ("rod",)),
    ("rig", "_make_load_empties", ("greens_rod",)),
    ("rig", "_build_load_sweep", ("greens_rod",)),
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
    importlib.import_module(mods.ops.__name__.rsplit(".", 2)[0] + ".artdef_addon.api").clear_cache()  # no cached clustering: the fit runs every stage
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
