"""Bad input never costs the user a file and always gets one clear line.

Here: malformed scan, result and sequence files, and legal but unusual meshes.

Every malformed file, unusable output path and out-of-range number ends with exit 2 and exactly one
stderr line naming the file or option; the input is never changed; a failed or interrupted write
leaves the earlier output byte-identical and no temporary behind; legal but unusual meshes fit.
"""
import os
import subprocess
import sys

import numpy as np
import pytest

import artdef_addon
from artdef_addon import cli, files, samples, scan as S
from artdef_addon import result as RS

from badinput import (CASES, ROOT, _huge_header, _members, _no_fit, _sequence_module, bad_scans,
    digest, leftovers, npy, raw_npz, result_file, rod, rod_file, run)


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
        RS.load_result(p)
    assert digest(p) == before


def test_result_round_trip_and_info(result_file, capsys):
    code, out, err = run(capsys, "info", result_file)
    assert code == 0 and err == [] and "fit result" in out and "links: 3" in out


# ---------------------------------------------------------------- legal but unusual meshes
def test_unreferenced_vertices_fit_with_sensible_weights(rod):
    """Vertices in no triangle (legal in the format) must not make a 0/0 skin row ('SVD did not
    converge'). Copies of mesh vertices, moving with them but in no triangle, get weights whose
    skin reproduces them as well as the originals."""
    src = np.array([5, 150, 290])
    v = np.vstack([rod.vertices, rod.vertices[src]])
    d = np.concatenate([rod.displacements, rod.displacements[:, src]], axis=1)
    for skin in ("refined", "seam"):
        r = artdef_addon.fit(S.Scan(v, rod.faces, displacements=d), 3, skin=skin)
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
        r = RS.load_result(tmp_path / f"{name}_r.npz")
        assert r.face_labels.shape == (sc.n_faces,) and np.isfinite(r.rms_articulation), name


def test_single_field_error_is_not_available_not_zero(rod, tmp_path, capsys):
    """One field: the Karni–Gotsman distortion (about each frame's centroid) is defined and
    reported; the per-vertex-mean figure divides by zero and is NaN, never 0."""
    p = tmp_path / "one.npz"
    files.write_scan(p, S.Scan(rod.vertices, rod.faces, displacements=rod.displacements[1:2]))
    code, out, err = run(capsys, "fit", p, "--links", "3", "-o", tmp_path / "r.npz")
    assert code == 0 and err == []
    r = RS.load_result(tmp_path / "r.npz")
    assert np.isfinite(r.articulation_error_percent) and f"{r.articulation_error_percent:.3g}% Karni" in out
    assert np.isnan(r.vertex_mean_error_percent)
    # a two-field fit reports both
    r2 = artdef_addon.fit(S.Scan(rod.vertices, rod.faces, displacements=rod.displacements[:2]), 3)
    assert np.isfinite(r2.articulation_error_percent) and f"{r2.articulation_error_percent:.3g}%" in r2.summary()
    assert np.isfinite(r2.vertex_mean_error_percent)
    # --links auto on one field stays bounded (the undefined error counts as nothing to explain)
    code, out, err = run(capsys, "fit", p, "--links", "auto", "--max-links", "8", "-q")
    assert code == 0 and err == []


# ---------------------------------------------------------------- mesh sequences
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


def test_extreme_but_accepted_scans_fit_quietly(rod, tmp_path):
    """Fields that are one rigid translation (every residual zero) and coordinates near the
    accepted bound: exit 0 and nothing on stderr with -q (no numpy overflow notes)."""
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


# ---------------------------------------------------------------- values at the edges of the formats
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
    code, _, err = run(capsys, "fit", p, "--links", "3", "-o", tmp_path / "o.npz", "--blend", tmp_path / "o.blend",
                       "--glb", tmp_path / "o.glb", blender=fake)
    assert code == 2 and len(err) == 1 and "--blend/--glb: the scan's positions reach" in err[0], err
    assert "32-bit floats" in err[0] and "internal error" not in err[0]
    assert sorted(os.listdir(tmp_path)) == ["big.npz"]
