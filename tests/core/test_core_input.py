"""Bad input gets a clear error naming the problem; files are never unpickled."""
import subprocess
import sys

import numpy as np
import pytest

import artdef_addon
from artdef_addon import files, samples, scan as S
from artdef_addon import result as RS


@pytest.fixture
def rod():
    return samples.make("rod")


def _scan(rod, **kw):
    d = dict(vertices=rod.vertices, faces=rod.faces, displacements=rod.displacements)
    d.update(kw)
    return S.Scan(**d)


@pytest.mark.parametrize("kw,match", [
    (dict(displacements=np.zeros((3, 5, 3))), r"displacements must have shape \(P, N, 3\)"),
    (dict(faces=np.array([[0, 1, 2, 3]])), "non-triangle faces"),
    (dict(faces=np.array([[0, 1, 999]])), "out of range"),
    (dict(displacements=None), "neither"),
    (dict(greens=np.zeros((3, 3))), "both"),
    (dict(displacements=np.zeros((0, 297, 3))), "too few fields"),
    (dict(displacements=np.zeros((2, 297, 3))), "too few fields"),
    (dict(probe_load=-1.0), "probe_load must be a positive"),
    (dict(vertices=np.zeros((297, 2))), r"vertices must have shape \(N, 3\)"),
    (dict(faces=np.array([[0.5, 1, 2]])), "integer indices"),
])
def test_bad_scan_messages(rod, kw, match):
    with pytest.raises(S.ScanError, match=match):
        S.validate_scan(_scan(rod, **kw))


def test_nan_is_named(rod):
    d = rod.displacements.copy()
    d[1, 5, 2] = np.nan
    with pytest.raises(S.ScanError, match="displacements contains 1 NaN"):
        S.validate_scan(_scan(rod, displacements=d))


def test_greens_shape_and_loads(rod):
    n = rod.n_vertices
    with pytest.raises(S.ScanError, match=r"greens must have shape \(3N, 3M\)"):
        S.validate_scan(S.Scan(rod.vertices, rod.faces, greens=np.zeros((3 * n, 4)), load_vertices=[0]))
    with pytest.raises(S.ScanError, match="needs 'load_vertices'"):
        S.validate_scan(S.Scan(rod.vertices, rod.faces, greens=np.ones((3 * n, 3))))
    with pytest.raises(S.ScanError, match="load_vertices has 2 entries"):
        S.validate_scan(S.Scan(rod.vertices, rod.faces, greens=np.ones((3 * n, 3)), load_vertices=[0, 1]))


def test_degenerate_triangles_reported_and_handled(rod):
    faces = np.vstack([rod.faces, [[10, 10, 11]], [[20, 21, 21]]])
    sc = S.validate_scan(_scan(rod, faces=faces))
    assert sc.degenerate_faces.tolist() == [len(rod.faces), len(rod.faces) + 1]
    r = artdef_addon.fit(sc, 3)
    assert r.face_labels.shape == (len(faces),) and r.face_labels.min() >= 0
    # the degenerate faces take their neighbours' link
    assert r.face_labels[-2] == r.face_labels[np.flatnonzero((rod.faces == 10).any(1))[0]]


def test_more_links_than_triangles(rod):
    v = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    tiny = S.Scan(v, np.array([[0, 1, 2], [0, 2, 3]]), displacements=np.ones((2, 4, 3)) * [[[0], [0.1], [0.2], [0]]])
    with pytest.raises(S.ScanError, match=r"more links requested \(3\) than triangles \(2\)"):
        artdef_addon.fit(tiny, 3)


def test_bad_options(rod):
    """Settings are checked where they enter, the public fit (FitOptions), before any work."""
    with pytest.raises(artdef_addon.OptionsError, match="pseudo-articulation needs a Green's-matrix scan"):
        artdef_addon.fit(rod, 3, mode="pseudo")
    with pytest.raises(artdef_addon.OptionsError, match="p_max must be a number greater than 1"):
        artdef_addon.fit(rod, 3, p_max=0.5)
    with pytest.raises(artdef_addon.OptionsError, match="mode must be one of"):
        artdef_addon.fit(rod, 3, mode="nope")
    assert not issubclass(artdef_addon.OptionsError, S.ScanError)     # the scan is not at fault


def test_load_refuses_pickles_and_garbage(tmp_path):
    obj = tmp_path / "obj.npz"
    np.savez(obj, vertices=np.array([{"a": 1}], dtype=object), faces=np.zeros((1, 3), int))
    with pytest.raises(S.ScanError, match="obj.npz: member 'vertices' holds Python objects"):
        files.read_scan(obj)
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip at all")
    with pytest.raises(S.ScanError, match="junk.npz: a text file, not a .npz archive"):
        files.read_scan(junk)
    with pytest.raises(S.ScanError, match="missing.npz: no such file"):
        files.read_scan(tmp_path / "missing.npz")
    missing = tmp_path / "nofaces.npz"
    np.savez(missing, vertices=np.zeros((3, 3)))
    with pytest.raises(S.ScanError, match="nofaces.npz: no 'faces' array"):
        files.read_scan(missing)


def test_scan_roundtrip(tmp_path):
    sc = samples.make("greens_rod", probe_load=2.5)
    files.write_scan(tmp_path / "g.npz", sc)
    back = files.read_scan(tmp_path / "g.npz")
    assert back.kind == "greens" and back.probe_load == 2.5
    assert np.array_equal(back.greens, sc.greens) and np.array_equal(back.load_vertices, sc.load_vertices)
    assert np.allclose(back.fields(), sc.fields())


def test_cli_bad_input_exit_code_and_no_output(tmp_path):
    bad = tmp_path / "bad.npz"
    np.savez(bad, vertices=np.zeros((5, 3)), faces=np.array([[0, 1, 2]]), displacements=np.zeros((2, 4, 3)))
    out = tmp_path / "out.npz"
    p = subprocess.run([sys.executable, "-m", "artdef_addon", "fit", str(bad), "--links", "3", "-o", str(out)],
                       capture_output=True, text=True)
    assert p.returncode == 2
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and "displacements must have shape" in lines[0]
    assert not out.exists()


def test_cli_sample_and_fit(tmp_path):
    scan = tmp_path / "rod.npz"
    res = tmp_path / "res.npz"
    run = lambda *a: subprocess.run([sys.executable, "-m", "artdef_addon", *a], capture_output=True, text=True)  # noqa: E731
    assert run("sample", "rod", "-o", str(scan)).returncode == 0
    p = run("fit", str(scan), "--links", "3", "-o", str(res))
    assert p.returncode == 0, p.stderr
    assert "joint (12.0000" in p.stdout and "time:" in p.stdout
    r = RS.load_result(res)
    assert r.n_links == 3


def test_validated_scan_is_checked_once(rod, monkeypatch):
    """A validated scan passes through validate_scan (and the fit) without a second full
    check; its arrays are read-only, and a new array put into it is checked again."""
    calls = []
    check = S._check_scan
    monkeypatch.setattr(S, "_check_scan", lambda sc: calls.append(1) or check(sc))
    sc = S.validate_scan(_scan(rod))
    assert len(calls) == 1
    assert S.validate_scan(sc) is sc and len(calls) == 1
    artdef_addon.fit(sc, 3)
    assert len(calls) == 1
    with pytest.raises(ValueError, match="read-only"):
        sc.displacements[0, 0, 0] = np.nan
    bad = rod.displacements.copy()
    bad[0, 0, 0] = np.nan
    sc.displacements = bad
    with pytest.raises(S.ScanError, match="NaN"):
        S.validate_scan(sc)
    assert len(calls) == 2
