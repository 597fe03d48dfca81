"""The fit settings (the core's options as properties, auto links, memory budget, progress).

Run headless (bpy module) through the installed extension.

Everything goes through ``bpy.ops.artdef.*`` of the extension installed from the built zip
(fixtures ``installed_addon``, ``clean_scene``, ``pkg`` and ``sample_files`` in tests/conftest.py);
the core used for reference numbers is the installed copy too.
"""
import importlib

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from ophelpers import check_rig, draw_panel, import_scan


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
        mode='GLOBAL', motion='LSQ', p_max=0.0, max_links=4, memory_budget=1.0, jobs=1, reduce='ON',
        strategy='PAPER', skin='SEAM', residuals=2, residuals_auto=False))()) == options.FitOptions(
        motion="lsq", max_links=4, memory_budget=1.0, jobs=1, reduce="on", strategy="paper", skin="seam",
        residuals=2)


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
    # the panel says it in plain words; the technical reason stays in fit_link_reason
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
# scale: memory budget, reduced method, cost estimate, progress words
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
    assert seg != full_seg and seg.reduced  # the cache follows the settings
    labels = [e[1] for e in draw_panel() if e[0] == "label"]
    assert any("reduced method" in l for l in labels)                      # the fit's notes
    assert any(l.startswith("reduced method on about ") for l in labels)   # the estimate
    # Preview Links uses the object's settings: the cached reduced segmenter
    assert bpy.ops.artdef.preview_links(links=11) == {'FINISHED'}
    assert pkg.ops.cached_segmentation(obj) == seg
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
