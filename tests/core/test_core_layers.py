"""The core's layering and public API.

* ``artdef_addon`` never imports Blender (bpy, bmesh, mathutils, addon_utils), not even inside a
  function, and its modules import each other without a cycle (lazy imports included): both read
  from every module's syntax tree, so a function that is never called still counts;
* ``artdef_addon.fit(artdef_addon.load_scan(path), links=...)`` works from plain Python, with one
  validated options object whose declaration the command line reads.
"""
import ast
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import artdef_addon
from artdef_addon import FitOptions, OptionsError, cli, files, options, samples, scan as S

CORE = Path(artdef_addon.__file__).resolve().parent
BLENDER = {"bpy", "bmesh", "mathutils", "addon_utils", "bpy_extras", "bl_math", "gpu"}


def _imports(path):
    """(module names imported absolutely, core modules imported relatively) of one file."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    absolute, core = set(), set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            absolute.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level == 0:
                absolute.add(node.module or "")
                if (node.module or "").split(".")[0] == "artdef_addon":
                    core.update(_core_targets(node.module.split(".")[1:], node.names))
            elif node.level == 1:
                core.update(_core_targets([node.module] if node.module else [], node.names))
            else:
                absolute.add("." * node.level + (node.module or ""))   # beyond the core package
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", "")) in (
                "import_module", "__import__") and node.args and isinstance(node.args[0], ast.Constant):
            absolute.add(str(node.args[0].value))
    return absolute, core


def _core_targets(parts, names):
    if parts and parts[0]:
        return {parts[0]}
    return {a.name for a in names if (CORE / f"{a.name}.py").is_file()}


def _graph():
    graph = {}
    for path in sorted(CORE.glob("*.py")):
        absolute, core = _imports(path)
        graph[path.stem] = (absolute, core - {path.stem})
    return graph


def test_core_never_names_blender():
    graph = _graph()
    assert len(graph) > 10
    for name, (absolute, _) in graph.items():
        roots = {m.split(".")[0] for m in absolute}
        assert not roots & BLENDER, f"artdef_addon/{name}.py imports {sorted(roots & BLENDER)}"
        assert not any(m.startswith("..") for m in absolute), \
            f"artdef_addon/{name}.py imports beyond the core: {sorted(m for m in absolute if m.startswith('..'))}"
        text = (CORE / f"{name}.py").read_text(encoding="utf-8")
        assert "import bpy" not in text and "importlib.import_module(\"bpy" not in text


def test_core_has_no_import_cycle():
    """Zero cycles among the core's modules, counting imports inside functions too."""
    graph = {k: {m for m in v[1] if m not in ("__init__", "__main__")} for k, v in _graph().items()
             if k not in ("__init__", "__main__")}
    state = {}

    def visit(node, stack):
        state[node] = "open"
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == "open":
                cycle = stack[stack.index(nxt):] + [nxt]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if nxt not in state:
                visit(nxt, stack + [nxt])
        state[node] = "done"

    for node in sorted(graph):
        if node not in state:
            visit(node, [node])


def test_the_layer_test_sees_lazy_and_relative_imports(tmp_path):
    """The checks above can fail: a lazy bpy import and a lazy relative import are both found."""
    p = tmp_path / "m.py"
    p.write_text("def f():\n    import bpy\n    from . import pipeline\n    from .scan import load_scan\n")
    absolute, core = _imports(p)
    assert "bpy" in absolute and {"pipeline", "scan"} <= core


def test_core_imports_without_blender():
    code = ("import sys; sys.modules['bpy'] = None; sys.modules['mathutils'] = None\n"
            "import artdef_addon, artdef_addon.cli, artdef_addon.api\n"
            "r = artdef_addon.fit(artdef_addon.samples.make('rod'), links=3)\n"
            "print(r.n_links)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=str(CORE.parent), timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "3"


def test_public_fit_from_a_file_auto_links_and_save_load(tmp_path):
    path = tmp_path / "rod.npz"
    files.write_scan(path, samples.make("rod"))
    result = artdef_addon.fit(artdef_addon.load_scan(path), links="auto",
                              options=FitOptions(max_links=6))
    assert result.n_links == 3 and result.link_reason.startswith("links auto: chose 3")
    assert result.options == FitOptions(max_links=6)
    # the search is its own stage in the timings, first, and the total counts it
    tm = result.timings
    stages = sum(v for k, v in tm.items() if k not in ("links", "total"))
    assert list(tm)[0] == "links" and tm["links"] > 0
    assert tm["total"] >= tm["links"] and tm["total"] >= stages
    result.save(tmp_path / "r.npz")
    back = artdef_addon.FitResult.load(tmp_path / "r.npz")
    np.testing.assert_array_equal(back.weights, result.weights)
    np.testing.assert_array_equal(back.face_labels, result.face_labels)
    assert back.link_reason == result.link_reason
    # the same fit given the count: same numbers
    ref = artdef_addon.fit(artdef_addon.load_scan(path), 3)
    assert "links" not in ref.timings
    np.testing.assert_array_equal(ref.face_labels, result.face_labels)
    np.testing.assert_allclose(ref.weights, result.weights, atol=1e-12)


def test_public_fit_keeps_the_segmentation_for_the_next_count():
    from artdef_addon import api
    api.clear_cache()
    scan = samples.make("branching")
    assert api.cached(scan) is None
    a = artdef_addon.fit(scan, 11)
    seg = api.cached(scan)
    assert seg is not None and seg.progress is None
    b = artdef_addon.fit(scan, 5, skin="seam")
    assert api.cached(scan) is seg and a.n_links == 11 and b.n_links == 5 and b.skin == "seam"
    labels, reduced, _ = artdef_addon.segment(scan, 11)
    assert api.cached(scan) is seg and not reduced
    np.testing.assert_array_equal(labels, a.face_labels)
    assert api.cached(scan, FitOptions(reduce="on")) is None      # another method: another entry


@pytest.mark.parametrize("bad, word", [
    (dict(mode="GLOBAL"), "mode"), (dict(p_max=1.0), "p_max"), (dict(p_max=float("nan")), "p_max"),
    (dict(max_links=0), "max_links"), (dict(max_links=2.5), "max_links"),
    (dict(memory_budget=0.0), "memory_budget"), (dict(skin="auto "), "skin"), (dict(reduce=True), "reduce"),
])
def test_options_are_checked_once_with_one_line(bad, word):
    with pytest.raises(OptionsError, match=word) as err:
        FitOptions(**bad)
    assert "\n" not in str(err.value)


def test_cli_checks_and_fitoptions_share_the_declared_bounds():
    """Each numeric setting's bounds are declared once: the command line's check
    (``Option.range``) and FitOptions accept and refuse the same values at and around them."""
    numeric = {n: o for n, (_, o) in FitOptions.declaration().items() if not o.choices}
    assert set(numeric) == {"p_max", "max_links", "memory_budget", "jobs", "residuals"}
    for name, opt in numeric.items():
        step = 1 if opt.type is int else 1e-9
        probes = [b + d for b in (opt.min, opt.max) if b is not None for d in (-step, 0, step)]
        for v in probes:
            try:
                opt.range.check("--" + name, v)
                cli_ok = True
            except options.OptionError:
                cli_ok = False
            try:
                FitOptions(**{name: v})
                core_ok = True
            except OptionsError:
                core_ok = False
            assert cli_ok == core_ok, (name, v, cli_ok, core_ok)
    assert numeric["max_links"].range.hi == options.MAX_AUTO_LINKS
    assert numeric["residuals"].range.hi == options.MAX_RESIDUAL_SHAPES and numeric["residuals"].auto
    # a refused bound: the flag's message (command line) and the setting's (FitOptions)
    with pytest.raises(options.OptionError, match="--memory-budget must be above 0"):
        numeric["memory_budget"].range.check("--memory-budget", 0)


def test_options_are_frozen_and_declare_everything():
    o = FitOptions()
    with pytest.raises(Exception):
        o.mode = "pseudo"
    decl = FitOptions.declaration()
    assert list(decl) == ["mode", "motion", "p_max", "max_links", "memory_budget", "jobs", "reduce", "strategy",
                          "skin", "residuals"]
    for name, (default, opt) in decl.items():
        assert opt.label and opt.description and getattr(o, name) == default
        assert not opt.choices or default in opt.values
    assert o.resolved("greens").strategy == "paper" and o.resolved("tracked").skin == "refined"


def test_cli_arguments_come_from_the_declaration(capsys):
    parser = cli._parser()
    fit = next(a for a in parser._actions if a.dest == "command").choices["fit"]
    by_dest = {a.dest: a for a in fit._actions}
    for name, (default, opt) in FitOptions.declaration().items():
        action = by_dest[name]
        # choices default to the declared value; numbers to None (not given: the declared default)
        assert action.default == (default if opt.choices else None)
        shown = "auto" if opt.auto else "off" if default is None else default
        assert opt.choices or f"(default: {shown})" in action.help
        assert tuple(action.choices or ()) == opt.values
        assert opt.description.split(",")[0].replace("%", "%%") in action.help


def test_cli_refuses_a_bad_option_in_one_line(tmp_path, capsys):
    path = tmp_path / "rod.npz"
    files.write_scan(path, samples.make("rod"))
    assert cli.main(["fit", str(path), "--links", "3", "--p-max", "0.5", "-o", str(tmp_path / "r.npz")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("artdef: error: --p-max must be above 1") and "\n" not in err
    assert not (tmp_path / "r.npz").exists()


def test_cancelled_fit_keeps_no_segmentation():
    from artdef_addon import api
    api.clear_cache()
    scan = samples.make("rod")
    with pytest.raises(artdef_addon.FitCancelled):
        artdef_addon.fit(scan, 3, progress=lambda stage, f: stage == "merge")
    assert api.cached(scan) is None
    assert artdef_addon.fit(scan, 3).n_links == 3 and api.cached(scan) is not None


def test_no_private_name_is_used_outside_its_core_module():
    """``from .m import _x`` or ``m._x`` between core modules: a private helper used elsewhere
    should be public (named, documented) or stay inside its module."""
    modules = {p.stem for p in CORE.glob("*.py")}
    found = []
    for path in sorted(CORE.glob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        aliases = {}
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.level == 1:
                for a in node.names:
                    if node.module is None and a.name in modules:
                        aliases[a.asname or a.name] = a.name
                    elif a.name.startswith("_") and not a.name.startswith("__"):
                        found.append(f"{path.stem} imports {node.module}.{a.name}")
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                    and node.value.id in aliases and node.attr.startswith("_") and not node.attr.startswith("__")):
                found.append(f"{path.stem} uses {aliases[node.value.id]}.{node.attr}")
    assert not found, found


def test_a_scan_is_checked_once_where_it_enters(tmp_path, monkeypatch):
    """Validation only where data enters: the file boundary checks a scan in full once; the public
    fit, the segmentation cache and the stages take the checked scan as it is (the command line
    too, from reading the file to writing the result)."""
    path = tmp_path / "rod.npz"
    files.write_scan(path, samples.make("rod"))
    calls = []
    real = S._check_scan
    monkeypatch.setattr(S, "_check_scan", lambda sc: calls.append(1) or real(sc))
    result = artdef_addon.fit(artdef_addon.load_scan(path), links=3)
    assert result.n_links == 3 and len(calls) == 1
    calls.clear()
    assert cli.main(["fit", str(path), "--links", "3", "-q", "-o", str(tmp_path / "r.npz")]) == 0
    assert len(calls) == 1
    calls.clear()
    artdef_addon.fit(samples.make("rod"), links=3)       # a scan made in Python enters at the fit
    assert len(calls) == 1
