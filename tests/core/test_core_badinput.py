"""Bad input never costs the user a file and always gets one clear line (issue 15).

Every malformed file, unusable output path and out-of-range number ends with exit 2 and exactly one
stderr line naming the file or option; the input is never changed; a failed or interrupted write
leaves the earlier output byte-identical and no temporary behind; legal but unusual meshes fit.
"""
import errno
import gzip
import hashlib
import importlib.util
import io
import os
import resource
import subprocess
import sys
import zipfile

import numpy as np
import pytest

import artdef_addon
from artdef_addon import cli, files, fit as F, options, samples, scan as S

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def digest(path):
    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


def run(capsys, *argv):
    """cli.main in-process: (exit code, stdout, stderr lines)."""
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, [line for line in err.splitlines() if line.strip()]


def leftovers(directory):
    return [n for n in os.listdir(directory) if n.startswith(".artdef-tmp")]


def npy(arr):
    f = io.BytesIO()
    np.save(f, arr)
    return f.getvalue()


def raw_npz(path, members):
    with zipfile.ZipFile(path, "w") as z:
        for key, data in members.items():
            z.writestr(key, data)
    return path


@pytest.fixture(scope="module")
def rod():
    return samples.make("rod")


@pytest.fixture
def rod_file(rod, tmp_path):
    p = tmp_path / "rod.npz"
    files.write_scan(p, rod)
    return p


def _members(rod, **over):
    m = {"vertices.npy": npy(rod.vertices), "faces.npy": npy(rod.faces),
         "displacements.npy": npy(rod.displacements)}
    m.update(over)
    return {k: v for k, v in m.items() if v is not None}


def _huge_header(rod):
    data = npy(rod.vertices)
    return data.replace(repr(rod.vertices.shape).encode(), b"(9999999999, 3)", 1)


def bad_scans(rod, d):
    """name → (path, what the line must say)."""
    good = d / "good.npz"
    files.write_scan(good, rod)
    raw = good.read_bytes()
    cases = {}
    (d / "truncated.npz").write_bytes(raw[: len(raw) // 2])
    cases["truncated"] = (d / "truncated.npz", "damaged or truncated")
    np.save(d / "plain.npy", rod.vertices)
    os.replace(d / "plain.npy", d / "npy.npz")
    cases["npy under npz name"] = (d / "npy.npz", "single .npy array")
    (d / "text.npz").write_text("vertices 1 2 3\n")
    cases["text file"] = (d / "text.npz", "a text file, not a .npz archive")
    (d / "gz.npz").write_bytes(gzip.compress(raw))
    cases["gzip under npz name"] = (d / "gz.npz", "a gzip-compressed file, not a .npz archive")
    (d / "empty.npz").write_bytes(b"")
    cases["empty"] = (d / "empty.npz", "empty")
    cases["enormous header"] = (raw_npz(d / "huge.npz", _members(rod, **{"vertices.npy": _huge_header(rod)})),
                                "declares shape (9999999999, 3)")
    cases["string probe_load"] = (raw_npz(d / "sprobe.npz", _members(rod, **{"probe_load.npy": npy(np.array("abc"))})),
                                  "'probe_load' must be a single number")
    cases["string vertices"] = (raw_npz(d / "sverts.npz", _members(
        rod, **{"vertices.npy": npy(rod.vertices.astype(str))})), "vertices must be numeric")
    cases["pickled member"] = (raw_npz(d / "pickle.npz", _members(
        rod, **{"faces.npy": npy(np.array([{"a": 1}], dtype=object))})), "Python objects")
    cases["wrong member names"] = (raw_npz(d / "names.npz", _members(
        rod, **{"vertices.npy": None, "verts.npy": npy(rod.vertices)})), "no 'vertices' array")
    cases["not an npy member"] = (raw_npz(d / "member.npz", _members(rod, **{"notes.txt": b"hi"})),
                                  "member 'notes.txt' is not a .npy array")
    cases["truncated member"] = (raw_npz(d / "tmember.npz", _members(
        rod, **{"vertices.npy": npy(rod.vertices)[:-40]})), "truncated")
    cases["NaN"] = (raw_npz(d / "nan.npz", _members(
        rod, **{"displacements.npy": npy(np.where(np.arange(3)[:, None, None] == 1, np.nan,
                                                  rod.displacements))})), "NaN")
    cases["index out of range"] = (raw_npz(d / "index.npz", _members(
        rod, **{"faces.npy": npy(rod.faces + 1000)})), "out of range")
    os.mkdir(d / "dir.npz")
    cases["directory"] = (d / "dir.npz", "is a directory")
    cases["missing"] = (d / "missing.npz", "no such file")
    return cases


CASES = ["truncated", "npy under npz name", "text file", "gzip under npz name", "empty", "enormous header", "string probe_load",
         "string vertices", "pickled member", "wrong member names", "not an npy member", "truncated member",
         "NaN", "index out of range", "directory", "missing"]


# (fit reads a directory as an OBJ/PLY sequence folder, in Blender: not this boundary's case)
@pytest.mark.parametrize("case,command", [(c, m) for c in CASES for m in ("fit", "info")
                                          if (c, m) != ("directory", "fit")])
def test_bad_scan_file_one_line_exit_2_nothing_written(rod, tmp_path, capsys, case, command):
    path, says = bad_scans(rod, tmp_path)[case]
    before = digest(path) if os.path.isfile(path) else None
    out = tmp_path / "out.npz"
    argv = ["fit", path, "--links", "3", "-o", out] if command == "fit" else ["info", path]
    code, _, err = run(capsys, *argv)
    assert code == 2
    assert len(err) == 1, err
    assert err[0].startswith("artdef: error: ") and os.path.basename(path) in err[0] and says in err[0], err
    assert "Traceback" not in err[0] and "pickled data" not in err[0] or case == "pickled member"
    assert not out.exists() and leftovers(tmp_path) == []
    if before is not None:
        assert digest(path) == before


def test_load_scan_is_the_boundary_blender_uses(rod, tmp_path):
    """``artdef_addon.load_scan`` is ``files.read_scan`` (what the Blender import operator calls):
    the same one-line BadFile."""
    assert artdef_addon.load_scan is files.read_scan
    for case, (path, says) in bad_scans(rod, tmp_path).items():
        with pytest.raises(files.BadFile) as exc:
            files.read_scan(path)
        msg = str(exc.value)
        assert "\n" not in msg and says in msg and os.path.basename(path) in msg, (case, msg)


def test_enormous_header_is_refused_before_allocating(rod, tmp_path, monkeypatch):
    path = raw_npz(tmp_path / "huge.npz", _members(rod, **{"vertices.npy": _huge_header(rod)}))
    calls = []
    real = np.frombuffer
    monkeypatch.setattr(files.np, "frombuffer", lambda *a, **k: calls.append(1) or real(*a, **k))
    with pytest.raises(files.BadFile, match=r"239,999,999,976 bytes\) but holds"):
        files.read_npz(path)
    assert calls == []      # refused from the header alone


@pytest.fixture(scope="module")
def result_file(rod, tmp_path_factory):
    p = tmp_path_factory.mktemp("res") / "res.npz"
    F.save_result(p, F.fit(rod, 3))
    return p


@pytest.mark.parametrize("damage,says", [
    (lambda d: d.pop("joints"), "'joints', which is missing"),
    (lambda d: d.update(rms_total=np.array("x")), "'rms_total' must be a single number"),
    (lambda d: d.update(parents=np.array([0.5, 1.0, 2.0])), "'parents' must be a 1-D integer array"),
    (lambda d: d.update(face_labels=d["face_labels"] + 7), "refer to links that do not exist"),
    (lambda d: d.pop("mode"), "text value 'mode'"),
])
def test_bad_result_file(result_file, tmp_path, capsys, damage, says):
    d = dict(np.load(result_file))
    damage(d)
    p = tmp_path / "bad_result.npz"
    np.savez(p, **d)
    before = digest(p)
    code, _, err = run(capsys, "info", p)
    assert code == 2 and len(err) == 1 and says in err[0] and "bad_result.npz" in err[0], err
    with pytest.raises(files.BadFile, match=says.replace("(", r"\(").replace(")", r"\)")):
        F.load_result(p)
    assert digest(p) == before


def test_result_round_trip_and_info(result_file, capsys):
    code, out, err = run(capsys, "info", result_file)
    assert code == 0 and err == [] and "fit result" in out and "links: 3" in out


# ---------------------------------------------------------------- output paths
def _no_fit(monkeypatch):
    def boom(*a, **k):
        raise AssertionError("the fit ran before the output paths were checked")
    monkeypatch.setattr(F, "Segmenter", boom)


def test_output_is_the_input_refused_before_work(rod_file, tmp_path, capsys, monkeypatch):
    _no_fit(monkeypatch)
    before = digest(rod_file)
    os.link(rod_file, tmp_path / "hard.npz")
    os.symlink(rod_file, tmp_path / "soft.npz")
    for argv, says in [
        (["-o", rod_file], "would overwrite the input"),
        (["-o", tmp_path / "sub" / ".." / "rod.npz"], "does not exist"),
        (["-o", tmp_path / "hard.npz"], "would overwrite the input"),
        (["-o", tmp_path / "soft.npz"], "would overwrite the input"),
        (["--blend", rod_file], "must end in .blend"),
        (["--glb", tmp_path / "x.gltf"], "must end in .glb"),
        (["--png", tmp_path / "x.jpg"], "must end in .png"),
        (["-o", tmp_path / "nodir" / "r.npz"], "does not exist"),
        (["-o", tmp_path], "is a directory"),
        (["-o", tmp_path / "a.blend", "--blend", tmp_path / "a.blend"], "name the same file"),
    ]:
        code, _, err = run(capsys, "fit", rod_file, "--links", "3", *argv)
        assert code == 2 and len(err) == 1 and says in err[0], (argv, err)
    assert digest(rod_file) == before
    assert sorted(os.listdir(tmp_path)) == ["hard.npz", "rod.npz", "soft.npz"]


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write into a read-only directory")
def test_read_only_directory_refused_before_work(rod_file, tmp_path, capsys, monkeypatch):
    _no_fit(monkeypatch)
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        code, _, err = run(capsys, "fit", rod_file, "--links", "3", "-o", ro / "r.npz")
    finally:
        ro.chmod(0o700)
    assert code == 2 and len(err) == 1 and "is not writable" in err[0]


def test_output_written_with_exactly_the_name_given(rod_file, tmp_path, capsys):
    out = tmp_path / "result.dat"
    code, stdout, err = run(capsys, "fit", rod_file, "--links", "3", "-o", out, "-q")
    assert code == 0 and err == []
    assert sorted(os.listdir(tmp_path)) == ["result.dat", "rod.npz"]
    assert F.load_result(out).n_links == 3
    code, stdout, err = run(capsys, "sample", "rod", "-o", tmp_path / "scan.bin")
    assert code == 0 and "wrote" in stdout and (tmp_path / "scan.bin").is_file()
    assert files.read_scan(tmp_path / "scan.bin").n_vertices == 297


# ---------------------------------------------------------------- failed or interrupted writes
@pytest.mark.parametrize("failure,code,says", [
    (OSError(errno.ENOSPC, "No space left on device"), 1, "No space left on device"),
    (KeyboardInterrupt(), 130, "interrupted"),
])
def test_failed_overwrite_keeps_the_earlier_result(rod_file, tmp_path, capsys, monkeypatch, failure, code, says):
    out = tmp_path / "out.npz"
    assert run(capsys, "fit", rod_file, "--links", "3", "-o", out, "-q")[0] == 0
    before = digest(out)
    real = files._savez

    def half_then_fail(f, arrays, compress):
        real(f, arrays, compress)
        f.truncate(f.tell() // 2)       # a partial file, as a full disk leaves
        raise failure
    monkeypatch.setattr(files, "_savez", half_then_fail)
    got, _, err = run(capsys, "fit", rod_file, "--links", "2", "-o", out, "-q")
    assert got == code and len(err) == 1 and says in err[0], err
    assert digest(out) == before and F.load_result(out).n_links == 3
    assert leftovers(tmp_path) == []


def test_file_size_limit_keeps_the_earlier_result(rod_file, tmp_path):
    """A real failing write: RLIMIT_FSIZE below the result's size (write → EFBIG)."""
    out = tmp_path / "out.npz"
    env = dict(os.environ, PYTHONPATH=ROOT)
    cmd = [sys.executable, "-m", "artdef_addon", "fit", str(rod_file), "--links", "3", "-q", "-o", str(out)]
    assert subprocess.run(cmd, env=env, capture_output=True, timeout=300).returncode == 0
    before = digest(out)
    cmd[cmd.index("3")] = "2"

    def limit():
        resource.setrlimit(resource.RLIMIT_FSIZE, (4096, resource.RLIM_INFINITY))
    p = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300, preexec_fn=limit)
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 1 and len(lines) == 1 and "File too large" in lines[0], p.stderr
    assert digest(out) == before and leftovers(tmp_path) == []


def test_ctrl_c_during_the_fit(tmp_path, interrupt_at):
    scan = tmp_path / "br.npz"
    files.write_scan(scan, samples.make("branching"))
    out = tmp_path / "out.npz"
    out.write_bytes(b"earlier result")
    code, err = interrupt_at([sys.executable, "-m", "artdef_addon", "fit", str(scan), "--links", "auto",
                              "-o", str(out)], "estimate:", tmp_path)
    lines = err.strip().splitlines()
    assert code == 130 and lines == ["artdef: error: interrupted; no file was written or changed"], err
    assert out.read_bytes() == b"earlier result" and leftovers(tmp_path) == []


# ---------------------------------------------------------------- numeric options
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
    monkeypatch.setattr(F, "Segmenter", lambda *a, **k: pytest.fail("fitted despite a bad --max-links"))
    code, _, err = run(capsys, "fit", p, "--links", "auto", "--max-links", "50")
    assert code == 2 and "--max-links must be at most 4 (the scan's 4 non-degenerate triangles)" in err[0]
    monkeypatch.undo()
    # the default (30) is clamped to the triangles, not refused
    code, out, err = run(capsys, "fit", p, "--links", "auto", "-o", tmp_path / "r.npz")
    assert code == 0 and err == [] and 1 <= F.load_result(tmp_path / "r.npz").n_links <= 4


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


# ---------------------------------------------------------------- legal but unusual meshes
def test_unreferenced_vertices_fit_with_sensible_weights(rod):
    """Vertices in no triangle (legal in the format) used to give 'SVD did not converge' (a 0/0
    skin row). Copies of mesh vertices, moving with them but in no triangle, now get weights whose
    skin reproduces them as well as the originals."""
    src = np.array([5, 150, 290])
    v = np.vstack([rod.vertices, rod.vertices[src]])
    d = np.concatenate([rod.displacements, rod.displacements[:, src]], axis=1)
    for skin in ("refined", "seam"):
        r = F.fit(S.Scan(v, rod.faces, displacements=d), 3, skin=skin)
        assert np.all(np.isfinite(r.weights)) and np.allclose(r.weights.sum(axis=1), 1.0)
        assert np.all(np.isfinite(r.residual))
        err = np.linalg.norm(r.residual, axis=2)               # (P, N) rest-space residual
        extent = np.ptp(rod.vertices, axis=0).max()
        if skin == "refined":   # the data choose their links: as good as the originals
            assert np.all(err[:, -3:] <= err[:, src] + 1e-3 * extent)


def test_unusual_meshes_fit_on_the_command_line(rod, tmp_path, capsys):
    faces = np.vstack([rod.faces, [[10, 10, 11]], [[20, 21, 21]], [[0, 1, 1]]])
    cases = {
        "degenerate": S.Scan(rod.vertices, faces, displacements=rod.displacements),
        "pieces": samples.make("branching", disconnected=True),
        "unreferenced": S.Scan(np.vstack([rod.vertices, [[50.0, 50, 50]]]), rod.faces,
                               displacements=np.concatenate([rod.displacements, np.zeros((3, 1, 3))], 1)),
    }
    for name, sc in cases.items():
        p = tmp_path / f"{name}.npz"
        files.write_scan(p, sc)
        code, out, err = run(capsys, "fit", p, "--links", "3", "-o", tmp_path / f"{name}_r.npz")
        assert code == 0 and err == [], (name, err)
        r = F.load_result(tmp_path / f"{name}_r.npz")
        assert r.face_labels.shape == (sc.n_faces,) and np.isfinite(r.rms_articulation), name


def test_single_field_error_is_not_available_not_zero(rod, tmp_path, capsys):
    """One field: the Karni–Gotsman distortion (about each frame's centroid, issue 19) is defined and
    reported; the old per-vertex-mean figure divides by zero and is NaN, never 0."""
    p = tmp_path / "one.npz"
    files.write_scan(p, S.Scan(rod.vertices, rod.faces, displacements=rod.displacements[1:2]))
    code, out, err = run(capsys, "fit", p, "--links", "3", "-o", tmp_path / "r.npz")
    assert code == 0 and err == []
    r = F.load_result(tmp_path / "r.npz")
    assert np.isfinite(r.articulation_error_percent) and f"{r.articulation_error_percent:.3g}% Karni" in out
    assert np.isnan(r.vertex_mean_error_percent)
    # a two-field fit reports both
    r2 = F.fit(S.Scan(rod.vertices, rod.faces, displacements=rod.displacements[:2]), 3)
    assert np.isfinite(r2.articulation_error_percent) and f"{r2.articulation_error_percent:.3g}%" in r2.summary()
    assert np.isfinite(r2.vertex_mean_error_percent)
    # --links auto on one field stays bounded (the undefined error counts as nothing to explain)
    code, out, err = run(capsys, "fit", p, "--links", "auto", "--max-links", "8", "-q")
    assert code == 0 and err == []


# ---------------------------------------------------------------- mesh sequences
def _sequence_module():
    spec = importlib.util.spec_from_file_location("artdef_seq", os.path.join(ROOT, "operators", "sequence.py"))
    m = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(m)
    return m


def test_mixed_obj_ply_sequence_is_refused(tmp_path):
    seq = _sequence_module()
    obj = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"
    ply = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
           "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    (tmp_path / "pose_000.obj").write_text(obj)
    (tmp_path / "pose_001.obj").write_text(obj)
    (tmp_path / "pose_002.ply").write_text(ply)
    with pytest.raises(seq.SequenceError, match=r"pose_### mixes .obj and .ply files \(pose_002.ply"):
        seq.find_sequence(str(tmp_path / "pose_000.obj"))
    with pytest.raises(seq.SequenceError, match=r"mixes .obj and .ply files; a sequence is one format"):
        seq.find_sequence(str(tmp_path))
    (tmp_path / "pose_002.ply").unlink()
    assert len(seq.find_sequence(str(tmp_path / "pose_000.obj"))) == 2


def test_sequence_frames_pick_files_by_number_and_keep_the_rest(tmp_path):
    """--frames on a sequence: a file's number is its frame; the rest file stays (first here,
    or the one chosen), the others are those numbered START, START+STEP, ... up to END; a range
    with no file names the sequence and its numbers."""
    seq = _sequence_module()
    paths = [str(tmp_path / "walk" / f"pose_{n:03d}.obj") for n in (0, 5, 10, 15, 20)]
    assert seq.select_frames(paths, 0, 5, 15, 10) == ([paths[0], paths[1], paths[3]], 0)
    assert seq.select_frames(paths, 0, 10, None, None) == ([paths[0], paths[2], paths[3], paths[4]], 0)
    assert seq.select_frames(paths, 2, None, 6, None) == ([paths[0], paths[1], paths[2]], 2)
    with pytest.raises(seq.SequenceError, match=r"walk/pose_###.obj: no file is numbered within "
                                                r"frames 6..9 \(its files are numbered 0..20\)"):
        seq.select_frames(paths, 0, 6, 9, None)
    with pytest.raises(seq.SequenceError,
                       match=r"within frames 10..10 but the rest pose \(pose_010.obj\), which is not a field"):
        seq.select_frames(paths, 2, 10, 10, 1)   # only the rest file itself


def test_setup_on_a_full_disk_says_so_before_creating_anything(tmp_path):
    """scripts/env.sh (the README's commands' set-up) checks the free space before it creates or
    fills a virtual environment: one line naming the disk and the space, exit 1, nothing created
    (pip would otherwise stop half-way with 'No space left on device')."""
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    (tmp_path / "scripts").mkdir()
    for name in ("requirements.txt", "requirements-dev.txt", "requirements-4.5.txt"):
        (tmp_path / name).write_bytes(open(os.path.join(root, name), "rb").read())
    (tmp_path / "scripts" / "env.sh").write_bytes(open(os.path.join(root, "scripts", "env.sh"), "rb").read())
    before = sorted(os.listdir(tmp_path))
    env = dict(os.environ, ARTDEF_ENV_NEED_MB=str(2 ** 40))
    for what in ("dev", "4.5"):
        run = subprocess.run(["bash", str(tmp_path / "scripts" / "env.sh"), what], env=env,
                             capture_output=True, text=True, timeout=60)
        assert run.returncode == 1
        lines = run.stderr.strip().splitlines()
        assert len(lines) == 1 and "MB free on the disk of" in lines[0] and "free some space" in lines[0]
        assert sorted(os.listdir(tmp_path)) == before


# ---------------------------------------------------------------- files a run reads, files it replaces
def test_output_may_not_replace_a_file_of_an_input_sequence_or_gltf(rod_file, tmp_path, capsys, monkeypatch):
    """The "not an input" check covers every file a run reads: each OBJ/PLY of a sequence's folder
    (given as the folder, a pattern or one numbered file) and a .gltf's external buffers and images.
    Refused with one line before any work; the files stay byte-identical."""
    _no_fit(monkeypatch)
    seq = tmp_path / "seq"
    seq.mkdir()
    for n in range(4):
        (seq / f"pose_{n:03d}.obj").write_text(f"v {n} 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    gl = tmp_path / "gl"
    gl.mkdir()
    (gl / "data.bin").write_bytes(b"\0" * 64)
    (gl / "tex a.png").write_bytes(b"png")
    (gl / "model.gltf").write_text('{"asset": {"version": "2.0"}, "buffers": [{"uri": "data.bin", "byteLength": 64}],'
                                   ' "images": [{"uri": "tex%20a.png"}, {"uri": "data:image/png;base64,AA=="}]}')
    before = {p: digest(p) for p in list(seq.iterdir()) + list(gl.iterdir())}
    for scan, out in [(seq, seq / "pose_002.obj"), (seq / "pose_000.obj", seq / "pose_003.obj"),
                      (str(seq / "pose_*.obj"), seq / "pose_001.obj"), (gl / "model.gltf", gl / "data.bin"),
                      (gl / "model.gltf", gl / "tex a.png")]:
        code, _, err = run(capsys, "fit", scan, "--links", "3", "-o", out)
        assert code == 2 and len(err) == 1 and "would overwrite the input file" in err[0], (scan, out, err)
    code, _, err = run(capsys, "fit", rod_file, "--links", "3", "--clip", seq, "-o", seq / "pose_001.obj")
    assert code == 2 and len(err) == 1 and "would overwrite the input file" in err[0], err
    assert {p: digest(p) for p in before} == before
    assert sorted(os.listdir(gl)) == ["data.bin", "model.gltf", "tex a.png"]


def test_outputs_are_replaced_all_or_nothing(tmp_path):
    """files.Outputs.commit: when a later rename fails, the files already replaced are put back,
    the error names the user's file (not a temporary), and nothing temporary is left."""
    first, second = tmp_path / "a.npz", tmp_path / "b.npz"
    first.write_bytes(b"earlier a")
    second.mkdir()                        # a rename onto a non-empty directory fails
    (second / "keep").write_text("x")
    out = files.Outputs()
    with out:
        files._savez(open(out.path(first), "wb"), {"x": np.arange(3)}, False)
        with open(out.path(second), "wb") as f:
            f.write(b"new b")
        with pytest.raises(OSError) as info:
            out.commit()
    assert info.value.filename == str(second)
    assert first.read_bytes() == b"earlier a" and out.committed == []
    assert leftovers(tmp_path) == []
    # a file that did not exist before is removed again
    third = tmp_path / "c.npz"
    out = files.Outputs()
    with out:
        with open(out.path(third), "wb") as f:
            f.write(b"new c")
        with open(out.path(second), "wb") as f:
            f.write(b"new b")
        with pytest.raises(OSError):
            out.commit()
    assert not third.exists() and leftovers(tmp_path) == []


def test_replaced_outputs_keep_their_permissions_and_links(rod_file, tmp_path, capsys):
    """An output replaced keeps its permission bits (a private result stays private); an output
    path that is a symbolic link is written through: the link stays, its target is replaced."""
    private = tmp_path / "private.npz"
    private.write_bytes(b"old")
    private.chmod(0o600)
    target = tmp_path / "target.npz"
    target.write_bytes(b"old")
    link = tmp_path / "link.npz"
    os.symlink(target, link)
    for out in (private, link):
        code, _, err = run(capsys, "fit", rod_file, "--links", "3", "-o", out, "-q")
        assert code == 0 and err == [], err
    assert (private.stat().st_mode & 0o777) == 0o600 and F.load_result(private).n_links == 3
    assert os.path.islink(link) and os.readlink(link) == str(target) and F.load_result(target).n_links == 3
    code, _, err = run(capsys, "fit", rod_file, "--links", "3", "-o", "/dev/stdout")
    assert code == 2 and len(err) == 1 and "not a regular file" in err[0], err
    assert leftovers(tmp_path) == []


def test_sigterm_during_the_fit(tmp_path, interrupt_at):
    """``kill`` / ``timeout`` / a cancelled job (SIGTERM): one line, exit 143, the earlier output
    byte-identical and no temporary left, as for Ctrl-C."""
    import signal
    scan = tmp_path / "br.npz"
    files.write_scan(scan, samples.make("branching"))
    out = tmp_path / "out.npz"
    out.write_bytes(b"earlier result")
    code, err = interrupt_at([sys.executable, "-m", "artdef_addon", "fit", str(scan), "--links", "auto",
                              "-o", str(out)], "estimate:", tmp_path, sig=signal.SIGTERM)
    lines = err.strip().splitlines()
    assert code == 143 and lines == ["artdef: error: terminated; no file was written or changed"], err
    assert out.read_bytes() == b"earlier result" and leftovers(tmp_path) == []


def test_extreme_but_accepted_scans_fit_quietly(rod, tmp_path):
    """Fields that are one rigid translation (every residual zero) and coordinates near the
    accepted bound: exit 0 and nothing on stderr with -q (numpy's overflow notes used to leak)."""
    flat = S.Scan(rod.vertices, rod.faces, displacements=np.broadcast_to(
        np.array([1.0, 2.0, 0.5]), rod.displacements.shape).copy())
    big = S.Scan(rod.vertices * 1e55, rod.faces, displacements=rod.displacements * 1e55)
    for name, sc, links in (("flat", flat, "auto"), ("big", big, "3")):
        files.write_scan(tmp_path / f"{name}.npz", sc)
        p = subprocess.run([sys.executable, "-m", "artdef_addon", "fit", str(tmp_path / f"{name}.npz"),
                            "--links", links, "-q", "-o", str(tmp_path / f"{name}_out.npz")],
                           env=dict(os.environ, PYTHONPATH=ROOT), capture_output=True, text=True, timeout=300)
        assert p.returncode == 0 and p.stderr == "", (name, p.stderr)


def test_fields_far_beyond_the_mesh_are_refused(tmp_path, capsys):
    """greens x probe_load is the field: each factor within bounds, the product may not be; and no
    measurement moves an object by 1e40 of its sizes (the fit's frames overflowed at 1e90)."""
    g = samples.make("greens_rod")
    for name, sc, says in [
        ("probe", S.Scan(g.vertices, g.faces, greens=g.greens, load_vertices=g.load_vertices, probe_load=1e250),
         "greens x probe_load reaches"),
        ("far", S.Scan(g.vertices, g.faces, greens=g.greens, load_vertices=g.load_vertices, probe_load=1e45),
         "times the mesh's size"),
    ]:
        path = tmp_path / f"{name}.npz"
        files.write_npz(path, {**files.scan_arrays(S.Scan(g.vertices, g.faces, greens=g.greens,
                                                          load_vertices=g.load_vertices)),
                               "probe_load": np.float64(sc.probe_load)})
        code, _, err = run(capsys, "fit", path, "--links", "3", "-q")
        assert code == 2 and len(err) == 1 and says in err[0] and str(path) in err[0], err


def test_result_notes_must_be_text(result_file, tmp_path, capsys):
    d = dict(np.load(result_file, allow_pickle=False))
    d["notes"] = np.array(5)
    bad = tmp_path / "bad.npz"
    np.savez(bad, **d)
    code, _, err = run(capsys, "info", bad)
    assert code == 2 and len(err) == 1 and "notes must be a list of text" in err[0], err


@pytest.mark.parametrize("argv,says", [
    (["--frames", "0:3000000000"], "(Blender's frame numbers are 32-bit)"),
    (["--frames=-3000000000:5"], "(Blender's frame numbers are 32-bit)"),
    (["--frames", "-5:3"], "--frames applies to animated files and sequences"),   # read as a range
])
def test_frames_values_checked(rod_file, tmp_path, capsys, monkeypatch, argv, says):
    _no_fit(monkeypatch)
    code, _, err = run(capsys, "fit", rod_file, "--links", "3", *argv, "-o", tmp_path / "o.npz")
    assert code == 2 and len(err) == 1 and says in err[0], err


def test_special_files_in_a_sequence_are_refused(tmp_path):
    """A FIFO would block the read for ever (and Ctrl-C with it); a link to a device could be endless."""
    seq = _sequence_module()
    (tmp_path / "pose_000.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n")
    os.mkfifo(tmp_path / "pose_001.obj")
    os.symlink("/dev/zero", tmp_path / "pose_002.obj")
    for n in (1, 2):
        with pytest.raises(seq.SequenceError, match=rf"cannot read pose_00{n}.obj: not a regular file"):
            seq.read_mesh(str(tmp_path / f"pose_00{n}.obj"))
    # the vertex number an OBJ face names is repeated as written (OBJ counts from 1)
    with pytest.raises(seq.SequenceError, match=r"a face refers to vertex 9, but the file has 3 vertices"):
        seq.read_mesh(str(tmp_path / "pose_000.obj"))
    # a number beyond 64 bits is not named as 2**63 - 1 (numpy's reader saturates it)
    for big in ("99999999999999999999", "-99999999999999999999"):
        (tmp_path / "big.obj").write_text(f"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 {big}\n")
        with pytest.raises(seq.SequenceError, match=r"big.obj: a face refers to a vertex number beyond "
                                                    r"9223372036854775807 \(the file has 3 vertices\)"):
            seq.read_mesh(str(tmp_path / "big.obj"))


def test_malformed_binary_ply_is_one_line(tmp_path):
    """A negative list length or a face count the file cannot hold: one line naming the file (they
    escaped as numpy's 'invalid shape' / 'Unable to allocate 7.28 TiB')."""
    seq = _sequence_module()
    head = ("ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
            "property float z\nelement face {faces}\nproperty list {ctype} int vertex_indices\nend_header\n")
    xyz = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype="<f4").tobytes()
    cases = {
        "neg_char": (head.format(faces=1, ctype="char").encode() + xyz + np.int8(-1).tobytes(), "negative length"),
        "neg_int": (head.format(faces=2, ctype="int").encode() + xyz + np.array([3, 0, 1, 2], "<i4").tobytes()
                    + np.int32(-2).tobytes(), "negative length"),
        "huge": (head.format(faces=10 ** 12, ctype="uchar").encode() + xyz + bytes([3]) + np.arange(3, dtype="<i4")
                 .tobytes(), "the file ends inside the PLY 'face' element"),
        "two": (head.format(faces=1, ctype="uchar").encode() + xyz + bytes([2]) + np.arange(2, dtype="<i4").tobytes(),
                "a face has 2 vertices"),
    }
    for key, (data, says) in cases.items():
        path = tmp_path / f"{key}_000.ply"
        path.write_bytes(data)
        with pytest.raises(seq.SequenceError, match=rf"^{key}_000.ply: .*{says}"):
            seq.read_mesh(str(path))


def test_a_killed_runs_temporaries_are_removed_by_the_next(rod_file, tmp_path, capsys):
    """SIGKILL (or the out-of-memory killer) leaves an output's hidden temporary folder: the next
    command writing there removes those of processes that no longer run, and no other."""
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = tmp_path / f".artdef-tmp-{dead.pid}-x1"
    stale.mkdir()
    (stale / "out.npz").write_bytes(b"partial")
    alive = tmp_path / f".artdef-tmp-{os.getppid()}-x2"       # a running process's
    alive.mkdir()
    legacy = tmp_path / ".artdef-tmp-abcdef"                    # no process number: left alone
    legacy.mkdir()
    code, _, err = run(capsys, "fit", rod_file, "--links", "3", "-o", tmp_path / "out.npz", "-q")
    assert code == 0 and err == []
    assert not stale.exists() and alive.is_dir() and legacy.is_dir()
    assert F.load_result(tmp_path / "out.npz").n_links == 3


def test_settings_without_effect_are_said_not_dropped(rod_file, tmp_path, capsys):
    """--max-links with a fixed count and --p-max on a tracked scan are kept in the result (the one
    settings record the API and Blender share) and the command says they have no effect here."""
    code, out, err = run(capsys, "fit", rod_file, "--links", "3", "--max-links", "8", "--p-max", "4",
                         "-o", tmp_path / "o.npz")
    assert code == 0 and err == []
    assert "note: --max-links bounds the link-count search; it has no effect with a fixed --links" in out
    assert "note: --p-max (strain hardening under the probe loads) has no effect on a tracked scan" in out
    assert F.load_result(tmp_path / "o.npz").p_max == 4.0
    code, out, err = run(capsys, "fit", rod_file, "--links", "3", "--p-max", "4", "-q", "-o", tmp_path / "q.npz")
    assert code == 0 and out == "" and err == []


# ---------------------------------------------------------------- third QA pass
@pytest.mark.parametrize("value,says", [(2 ** 63 + 5, "max 9223372036854775813"),
                                        (2 ** 64 - 1, "max 18446744073709551615")])
def test_uint64_face_index_is_named_as_it_is(rod, tmp_path, capsys, value, says):
    """A uint64 index of 2**63 or more is out of range and named by its value, not by the negative
    number its cast to int64 gives."""
    faces = rod.faces.astype(np.uint64)
    faces[0, 0] = value
    p = raw_npz(tmp_path / "u64.npz", _members(rod, **{"faces.npy": npy(faces)}))
    code, _, err = run(capsys, "info", p)
    assert code == 2 and len(err) == 1 and "out of range" in err[0] and says in err[0], err
    assert "min 0," in err[0] and "-" not in err[0].split("min")[1], err


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf, 0.5, 0.0, -3.0])
@pytest.mark.parametrize("what", ["scan", "result"])
def test_format_version_must_be_a_version(rod, result_file, tmp_path, capsys, value, what):
    d = dict(np.load(result_file)) if what == "result" else files.scan_arrays(rod)
    d["format_version"] = np.float64(value)
    p = tmp_path / "v.npz"
    np.savez(p, **d)
    code, _, err = run(capsys, "info", p)
    assert code == 2 and len(err) == 1 and "v.npz: 'format_version' is" in err[0], err
    assert f"not a {what} format version" in err[0], err


def test_format_version_one_or_none_is_read(rod, result_file, tmp_path, capsys):
    d = dict(np.load(result_file))
    d["format_version"] = np.int64(1)
    np.savez(tmp_path / "r.npz", **d)
    d = files.scan_arrays(rod)
    d.pop("format_version")
    np.savez(tmp_path / "s.npz", **d)
    for name in ("r.npz", "s.npz"):
        code, _, err = run(capsys, "info", tmp_path / name)
        assert code == 0 and err == [], err


@pytest.mark.parametrize("links", ["3", "auto"])
def test_stdout_closed_early_still_writes_the_outputs(rod_file, tmp_path, links):
    """``fit ... | head -1``: the reader closing the pipe costs no output; no traceback, exit 0.
    (The pipe is closed before the command prints anything, so every line it prints meets it.)"""
    out = tmp_path / "out.npz"
    out.write_bytes(b"earlier result")
    env = dict(os.environ, PYTHONPATH=ROOT)
    r, w = os.pipe()
    os.close(r)
    try:
        p = subprocess.run([sys.executable, "-m", "artdef_addon", "fit", str(rod_file), "--links", links,
                            "-o", str(out)], stdout=w, stderr=subprocess.PIPE, env=env, text=True,
                           timeout=300)
    finally:
        os.close(w)
    assert p.returncode == 0 and p.stderr == "", p.stderr
    assert F.load_result(out).n_links >= 1 and leftovers(tmp_path) == []


@pytest.mark.parametrize("key,scale,says", [
    ("vertices", 1e61, "vertex coordinates reach 1e+61"),
    ("displacements", 1e61, "displacements reach 1e+61"),
    ("greens", 1e61, "Green's matrix entries (greens) reach 1e+61")])
def test_too_large_values_are_named_for_what_they_are(key, scale, says):
    """The message names the values that are too large (no 'squared distances' of a field or a
    Green's matrix, which are neither)."""
    sc = samples.make("greens_rod" if key == "greens" else "rod")
    arr = np.array(getattr(sc, key), dtype=float)
    arr.flat[0] = scale
    with pytest.raises(S.ScanError) as exc:
        S.validate_scan(S.Scan(**{**{k: getattr(sc, k) for k in ("vertices", "faces", "greens", "displacements",
                                                                 "load_vertices", "probe_load")}, key: arr}))
    msg = str(exc.value)
    assert says in msg and "1e+60" in msg and "squared distances" not in msg, msg


@pytest.mark.parametrize("bom,end", [(b"\xef\xbb\xbf", b"\n"), (b"", b"\r"), (b"\xef\xbb\xbf", b"\r\n")])
def test_obj_with_byte_order_mark_or_cr_line_ends_reads_every_vertex(tmp_path, bom, end):
    """A UTF-8 byte-order mark hid the first 'v' line (the mesh silently lost its first vertex and
    every face index pointed one vertex on); classic Mac line ends (CR only) read as one line ('no
    faces')."""
    seq = _sequence_module()
    lines = [b"v 9 8 7", b"v 0 0 0", b"# made on Windows", b"v 1 0 0", b"v 0 1 0", b"f 1 2 3", b"f -3 -2 -1"]
    p = tmp_path / "pose_000.obj"
    p.write_bytes(bom + end.join(lines) + end)
    mesh = seq.read_obj(str(p))
    assert mesh.vertices.tolist() == [[9, 8, 7], [0, 0, 0], [1, 0, 0], [0, 1, 0]]
    assert mesh.triangles.tolist() == [[0, 1, 2], [1, 2, 3]]


def test_too_long_output_name_is_refused_before_work(rod_file, tmp_path, capsys, monkeypatch):
    """A file name longer than the file system allows was found only when writing, after the fit:
    exit 1 and a line naming the hidden temporary (.artdef-tmp-.../xxx), not the user's path."""
    _no_fit(monkeypatch)
    out = tmp_path / ("x" * 300 + ".npz")
    for argv in (["fit", rod_file, "--links", "3", "-o", out], ["sample", "rod", "-o", out]):
        code, _, err = run(capsys, *argv)
        assert code == 2 and len(err) == 1 and "the file name is 304 bytes long" in err[0], err
        assert ".artdef-tmp" not in err[0] and leftovers(tmp_path) == []


@pytest.mark.parametrize("scale,says", [(1e-100, "the mesh is 3.6e-99 across, below 1e-60"),
                                        (1e-170, "the mesh is 3.6e-169 across, below 1e-60"),
                                        (0.0, "every vertex is at one point: the mesh has no extent")])
def test_a_mesh_too_small_for_the_arithmetic_says_so(rod, scale, says):
    """Before: 'every triangle is degenerate (zero area)' (areas underflowed), or 'the fields move
    vertices by up to 2.14e-169, over 1e+40 times the mesh's size (0)'."""
    sc = S.Scan(rod.vertices * scale, rod.faces, displacements=rod.displacements * (scale or 1.0))
    with pytest.raises(S.ScanError) as exc:
        S.validate_scan(sc)
    assert says in str(exc.value) and "degenerate" not in str(exc.value), str(exc.value)
    S.validate_scan(S.Scan(rod.vertices * 1e-50, rod.faces, displacements=rod.displacements * 1e-50))


@pytest.mark.parametrize("scale", [1e20, 1e38, 1e55])
def test_positions_beyond_blenders_floats_are_refused_before_work(rod, tmp_path, capsys, monkeypatch, scale):
    """--blend/--glb/--fbx/--png hold positions as 32-bit floats: a scan reaching 1e20 fitted, then
    failed in the glTF exporter (internal error: a NaN), and by 1e38 Blender's mesh held infinities."""
    p = tmp_path / "big.npz"
    files.write_scan(p, S.Scan(rod.vertices * scale, rod.faces, displacements=rod.displacements * scale))
    _no_fit(monkeypatch)
    fake = type("Headless", (), {"require_bpy": staticmethod(lambda: None),
                                 "build_outputs": staticmethod(lambda *a, **k: pytest.fail("Blender ran"))})
    monkeypatch.setattr(cli, "blender_layer", lambda: fake)
    code, _, err = run(capsys, "fit", p, "--links", "3", "-o", tmp_path / "o.npz", "--blend", tmp_path / "o.blend",
                       "--glb", tmp_path / "o.glb")
    assert code == 2 and len(err) == 1 and "--blend/--glb: the scan's positions reach" in err[0], err
    assert "32-bit floats" in err[0] and "internal error" not in err[0]
    assert sorted(os.listdir(tmp_path)) == ["big.npz"]


@pytest.mark.skipif(sys.platform != "linux", reason="a file name that is not UTF-8 (POSIX bytes)")
def test_a_name_blender_cannot_hold_is_refused_before_work(rod, tmp_path, capsys, monkeypatch):
    """A scan or an output named in bytes that are not UTF-8 reached Blender after the fit: exit 1,
    'internal error: TypeError: BlendDataMeshes.new(): ... surrogates not allowed'."""
    bad = os.fsdecode(b"r\xe9")
    files.write_scan(tmp_path / (bad + ".npz"), rod)
    files.write_scan(tmp_path / "rod.npz", rod)
    _no_fit(monkeypatch)
    fake = type("Headless", (), {"require_bpy": staticmethod(lambda: None),
                                 "build_outputs": staticmethod(lambda *a, **k: pytest.fail("Blender ran"))})
    monkeypatch.setattr(cli, "blender_layer", lambda: fake)
    for scan, blend in ((bad + ".npz", "o.blend"), ("rod.npz", bad + ".blend")):
        code, _, err = run(capsys, "fit", tmp_path / scan, "--links", "3", "--blend", tmp_path / blend)
        assert code == 2 and len(err) == 1 and "r\\xe9" in err[0] and "not: rename it" in err[0], err
    assert sorted(os.listdir(tmp_path)) == sorted([bad + ".npz", "rod.npz"])
