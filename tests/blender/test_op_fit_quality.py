"""The fit's quality as the scene shows it (residual attribute, per-link figures, replay range).

Run headless (bpy module) through the installed extension.

Everything goes through ``bpy.ops.artdef.*`` of the extension installed from the built zip
(fixtures ``installed_addon``, ``clean_scene``, ``pkg`` and ``sample_files`` in tests/conftest.py);
the core used for reference numbers is the installed copy too.
"""

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from ophelpers import FPF, draw_panel, evaluated_positions, import_scan, rest_positions


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
    assert st.fit_e_rms == pytest.approx(result.e_rms, rel=1e-5)            # the fidelity figures
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
