"""The panel's list of an animated file's meshes: Fields from File records every mesh of the file with
its vertex count and why it cannot be fitted; Resample Meshes samples the ticked ones into the scan
again, and refuses (one line, nothing changed) with a rig on the scan, no mesh ticked, a mesh that
cannot be fitted or a mesh no longer in the scene."""
import pytest

bpy = pytest.importorskip("bpy")

from ophelpers import draw_panel  # noqa: E402
from test_seams_files import two_meshes  # noqa: E402,F401  (the two-character file with a static prop)


def _load(path):
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    assert bpy.ops.artdef.fields_from_file(filepath=str(path), isolate=False) == {'FINISHED'}
    return bpy.context.view_layer.objects.active


def _scene():
    return sorted((o.name, len(o.data.vertices) if o.type == 'MESH' else 0) for o in bpy.data.objects)


def _refused(match):
    before = _scene()
    with pytest.raises(RuntimeError, match=match):
        bpy.ops.artdef.resample_meshes()
    assert _scene() == before


def test_the_list_shows_every_mesh_and_resampling_fits_the_ticked_ones(two_meshes):  # noqa: F811
    scan = _load(two_meshes)
    items = {it.name: it for it in scan.artdef.file_meshes}
    sizes = {n: len(bpy.data.objects[n].data.vertices) for n in ("Leg", "Other", "Prop")}
    assert items["Leg"].fit and items["Other"].fit and not items["Leg"].reason
    assert not items["Prop"].fit and items["Prop"].reason == "static"
    assert any(it.reason == "a bone's custom shape" for it in items.values())
    assert all(it.vertices == len(bpy.data.objects[n].data.vertices) for n, it in items.items())
    assert len(scan.data.vertices) == sizes["Leg"] + sizes["Other"]
    log = draw_panel()
    assert ("list", "ARTDEF_UL_file_meshes", "file_meshes") in log
    assert ("label", "Prop") in log and ("label", "static") in log and ("label", f"{sizes['Leg']:,}") in log
    assert ("operator", "artdef.resample_meshes", True) in log
    # the Prop cannot be ticked in the panel: its tickbox is drawn disabled
    assert ("set", "enabled", False) in log

    name = scan.name
    items["Leg"].fit = False
    assert bpy.ops.artdef.resample_meshes() == {'FINISHED'}
    scan = bpy.context.view_layer.objects.active
    assert scan.name == name and len(scan.data.vertices) == sizes["Other"]
    assert [(it.name, it.fit) for it in scan.artdef.file_meshes][:2] == [("Leg", False), ("Other", True)]
    assert "meshes fitted: Other; left out: " in scan.data["artdef_meshes"]
    assert sum(o.type == 'MESH' and o.name.startswith(name) for o in bpy.data.objects) == 1   # the old scan is gone
    assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}
    groups = {o.name for o in bpy.data.objects if o.type == 'MESH'
              and any(g.name.startswith("artdef_link_") for g in o.vertex_groups)}
    assert groups == {name}                         # the rig's groups land on the scan of Other only

    # refusals: nothing changes
    _refused("has a rig")
    assert bpy.ops.artdef.clear_rig() == {'FINISHED'}
    for it in scan.artdef.file_meshes:
        it.fit = False
    _refused("tick at least one mesh")
    prop = next(it for it in scan.artdef.file_meshes if it.name == "Prop")
    prop.fit = True
    _refused("mesh 'Prop' cannot be fitted: static")
    prop.fit = False
    next(it for it in scan.artdef.file_meshes if it.name == "Other").fit = True
    other = bpy.data.objects["Other"]
    other.name = "Renamed"
    _refused("mesh 'Other' is no longer in the scene")
    other.name = "Other"
    assert bpy.ops.artdef.resample_meshes() == {'FINISHED'}
    assert len(bpy.context.view_layer.objects.active.data.vertices) == sizes["Other"]
