"""Bad input never costs the user a file and always gets one clear line.

Here: out-of-range numbers and settings.

Every malformed file, unusable output path and out-of-range number ends with exit 2 and exactly one
stderr line naming the file or option; the input is never changed; a failed or interrupted write
leaves the earlier output byte-identical and no temporary behind; legal but unusual meshes fit.
"""

import numpy as np
import pytest

from artdef_addon import segmenter as SG
from artdef_addon import files, options, scan as S
from artdef_addon import result as RS

from badinput import _no_fit, rod, rod_file, run


@pytest.mark.parametrize("argv,says", [
    (["--links", "0"], "--links must be at least 1"),
    (["--links", "-3"], "--links must be at least 1"),
    (["--links", "2.5"], "--links must be a whole number"),
    (["--links", "many"], "or 'auto'"),
    (["--links", "585"], "at most 584 (the scan's 584 non-degenerate triangles)"),
    (["--links", "auto", "--max-links", "0"], "--max-links must be at least 1"),
    (["--links", "auto", "--max-links", "1000000"], "--max-links must be at most 100"),
    (["--links", "3", "--p-max", "1"], "--p-max must be above 1"),
    (["--links", "3", "--p-max", "nan"], "--p-max must be a finite number"),
    (["--links", "3", "--memory-budget", "0"], "--memory-budget must be above 0"),
    (["--links", "3", "--memory-budget", "inf"], "finite"),
    (["--links", "3", "--max-links", "x"], "--max-links: invalid int value"),
    (["--links", "3", "--mode", "nope"], "invalid choice"),
])
def test_fit_numbers_range_checked(rod_file, tmp_path, capsys, monkeypatch, argv, says):
    _no_fit(monkeypatch)
    code, _, err = run(capsys, "fit", rod_file, *argv, "-o", tmp_path / "o.npz")
    assert code == 2 and len(err) == 1 and says in err[0], err
    assert not (tmp_path / "o.npz").exists()


def test_max_links_is_bounded_by_the_triangles(tmp_path, capsys, monkeypatch):
    """A 4-triangle scan: --max-links 50 is refused at once (more counts than triangles)."""
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0], [2, 1, 0]], float)
    f = np.array([[0, 1, 2], [0, 2, 3], [1, 4, 5], [1, 5, 2]])
    p = tmp_path / "tiny.npz"
    files.write_scan(p, S.Scan(v, f, displacements=np.ones((2, 6, 3)) * [[[0.1]], [[0.2]]]))
    monkeypatch.setattr(SG, "Segmenter", lambda *a, **k: pytest.fail("fitted despite a bad --max-links"))
    code, _, err = run(capsys, "fit", p, "--links", "auto", "--max-links", "50")
    assert code == 2 and "--max-links must be at most 4 (the scan's 4 non-degenerate triangles)" in err[0]
    monkeypatch.undo()
    # the default (30) is clamped to the triangles, not refused
    code, out, err = run(capsys, "fit", p, "--links", "auto", "-o", tmp_path / "r.npz")
    assert code == 0 and err == [] and 1 <= RS.load_result(tmp_path / "r.npz").n_links <= 4


@pytest.mark.parametrize("argv,says", [
    (["rod", "--fields", "0"], "--fields must be at least 1"),
    (["rod", "--fields", "100000"], "--fields must be at most 1000"),
    (["branching", "--noise", "nan"], "--noise must be a finite number"),
    (["branching", "--noise", "-0.1"], "--noise must be at least 0"),
    (["rod", "--seed", "-1"], "--seed must be at least 0"),
    (["rod", "--noise", "0.1"], "apply to the branching sample only"),
    (["greens_rod", "--fields", "3"], "does not apply to greens_rod"),
    (["nosuch"], "unknown sample"),
])
def test_sample_numbers_range_checked(tmp_path, capsys, argv, says):
    code, _, err = run(capsys, "sample", *argv, "-o", tmp_path / "s.npz")
    assert code == 2 and len(err) == 1 and says in err[0], err
    assert not (tmp_path / "s.npz").exists()


def test_option_validators():
    r = options.IntRange(1, 30).within(10, " (triangles)")
    assert r.check("--k", "7") == 7 and r.check("--k", 10) == 10
    for bad, says in [(0, "at least 1"), (11, "at most 10 (triangles)"), (True, "whole number"),
                      ("1e400", "whole number"), (2.5, "whole number")]:
        with pytest.raises(options.OptionError, match=says.replace("(", r"\(").replace(")", r"\)")):
            r.check("--k", bad)
    assert options.IntRange(1, 30).within(100).hi == 30
    f = options.FloatRange(0.0, lo_open=True)
    assert f.check("--x", "0.5") == 0.5
    for bad in ("0", "-1", "nan", "inf", "abc", None):
        with pytest.raises(options.OptionError):
            f.check("--x", bad)


def test_settings_without_effect_are_said_not_dropped(rod_file, tmp_path, capsys):
    """--max-links with a fixed count and --p-max on a tracked scan are kept in the result (the one
    settings record the API and Blender share) and the command says they have no effect here."""
    code, out, err = run(capsys, "fit", rod_file, "--links", "3", "--max-links", "8", "--p-max", "4",
                         "-o", tmp_path / "o.npz")
    assert code == 0 and err == []
    assert "note: --max-links bounds the link-count search; it has no effect with a fixed --links" in out
    assert "note: --p-max (strain hardening under the probe loads) has no effect on a tracked scan" in out
    assert RS.load_result(tmp_path / "o.npz").p_max == 4.0
    code, out, err = run(capsys, "fit", rod_file, "--links", "3", "--p-max", "4", "-q", "-o", tmp_path / "q.npz")
    assert code == 0 and out == "" and err == []
