"""Helpers and fixtures of the bad-input tests (tests/core/test_core_bad*.py)."""
import gzip
import hashlib
import importlib.util
import io
import os
import zipfile

import numpy as np
import pytest

from artdef_addon import segmenter as SG
from artdef_addon import cli, files, samples
import artdef_addon
from artdef_addon import result as RS


ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def digest(path):
    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


def run(capsys, *argv, blender=None):
    """cli.main in-process: (exit code, stdout, stderr lines); ``blender``: a Blender layer to pass."""
    code = cli.main([str(a) for a in argv], blender=blender)
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


@pytest.fixture(scope="module")
def result_file(rod, tmp_path_factory):
    p = tmp_path_factory.mktemp("res") / "res.npz"
    RS.save_result(p, artdef_addon.fit(rod, 3))
    return p


def _no_fit(monkeypatch):
    def boom(*a, **k):
        raise AssertionError("the fit ran before the output paths were checked")
    monkeypatch.setattr(SG, "Segmenter", boom)


def _sequence_module():
    spec = importlib.util.spec_from_file_location("artdef_seq", os.path.join(ROOT, "operators", "sequence.py"))
    m = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(m)
    return m
