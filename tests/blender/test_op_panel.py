"""The ArtDef panel.

Run headless (bpy module) through the installed extension.

Everything goes through ``bpy.ops.artdef.*`` of the extension installed from the built zip
(fixtures ``installed_addon``, ``clean_scene``, ``pkg`` and ``sample_files`` in tests/conftest.py);
the core used for reference numbers is the installed copy too.
"""
import pytest

bpy = pytest.importorskip("bpy")

from ophelpers import draw_panel, import_scan


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


def test_panel_draws_with_an_unusable_memory_budget(clean_scene, sample_files):
    obj = import_scan(sample_files["rod"])
    obj.artdef.memory_budget = 0.0          # Blender keeps it at the declared minimum (above 0)
    assert obj.artdef.memory_budget > 0
    assert any(e[0] == "label" and str(e[1]).startswith("Estimate:") for e in draw_panel())
    obj.data["artdef_n_fields"] = "many"    # a damaged scan property: the panel still draws
    assert ("operator", "artdef.fit", True) in draw_panel()
    with pytest.raises(RuntimeError, match="field"):   # the fit reads the scan and says what is wrong
        bpy.ops.artdef.fit(links=3)
