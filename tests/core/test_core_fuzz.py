"""Property-based fuzzing of the file boundary and the command line .

Scans of random shapes, dtypes, NaN/inf and index errors, and damaged scan files (truncated,
bytes flipped, members renamed or dropped, garbage appended): the only outcomes allowed are a
successful fit (exit 0, a readable result) or the one clear error (exit 2, exactly one stderr
line); never another exception, never a change to the input file, never a temporary left behind.

Runs derandomized with a bounded number of examples (tens of seconds); set ARTDEF_FUZZ_EXAMPLES
to run more (and ARTDEF_FUZZ_RANDOM=1 for fresh random examples).
"""
import hashlib
import io
import os
import zipfile

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings, strategies as st  # noqa: E402

from artdef_addon import cli, files, scan as S  # noqa: E402
from artdef_addon import result as RS

N_EXAMPLES = int(os.environ.get("ARTDEF_FUZZ_EXAMPLES", "40"))
FUZZ = settings(max_examples=N_EXAMPLES, deadline=None, database=None,
                derandomize=not os.environ.get("ARTDEF_FUZZ_RANDOM"),
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture,
                                       HealthCheck.data_too_large])


def digest(path):
    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


def check_outcome(path, workdir, capsys, links="2"):
    """Run fit and info on ``path``; assert the only outcomes are success or the one clear error."""
    before = digest(path)
    out = os.path.join(workdir, "out.npz")
    if os.path.exists(out):
        os.remove(out)
    code = cli.main(["fit", str(path), "--links", links, "-q", "-o", out])
    _, err = capsys.readouterr()
    lines = [line for line in err.splitlines() if line.strip()]
    assert code in (0, 2), (code, err)
    if code == 0:
        assert lines == [] and RS.load_result(out).face_labels.ndim == 1
    else:
        assert len(lines) == 1 and lines[0].startswith("artdef: error: "), err
        assert not os.path.exists(out)
    code_info = cli.main(["info", str(path)])
    _, err = capsys.readouterr()
    lines = [line for line in err.splitlines() if line.strip()]
    assert code_info in (0, 2) and (code_info == 0) == (lines == []), (code_info, err)
    if code_info == 2:
        assert len(lines) == 1, err
    assert digest(path) == before
    assert [n for n in os.listdir(workdir) if n.startswith(".artdef-tmp")] == []
    try:
        hypothesis.event("fitted" if code == 0 else "refused")
    except Exception:       # outside a hypothesis test
        pass
    return code


# ---------------------------------------------------------------- random arrays
DTYPES = st.sampled_from([np.float64, np.float32, np.float16, np.int64, np.int32, np.uint8, np.bool_,
                          np.complex128, "U3", "S2"])


@st.composite
def arrays(draw, shape):
    dtype = np.dtype(draw(DTYPES))
    size = int(np.prod(shape))
    if dtype.kind in "US":
        return np.array(draw(st.lists(st.text("ab1.", max_size=3), min_size=size, max_size=size)),
                        dtype=dtype).reshape(shape)
    values = draw(st.lists(st.one_of(st.floats(-5, 5), st.sampled_from([np.nan, np.inf, -np.inf, 0.0])),
                           min_size=size, max_size=size))
    a = np.array(values, dtype=np.float64).reshape(shape)
    if dtype.kind in "iub":
        a = np.nan_to_num(a, nan=0.0, posinf=7, neginf=-7)
    with np.errstate(all="ignore"):
        return a.astype(dtype)


POINTS = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, 0, 1], [0, 1, 1], [1, 1, 1]], float)


@st.composite
def good_scans(draw):
    """A legal small scan: random triangles (degenerate and repeated ones included) over up to 8
    points, some of them perhaps in no triangle, and 1–3 finite displacement fields."""
    n = draw(st.integers(3, 8))
    t = draw(st.integers(1, 6))
    faces = np.array(draw(st.lists(st.integers(0, n - 1), min_size=3 * t, max_size=3 * t))).reshape(t, 3)
    p = draw(st.integers(1, 3))
    disp = np.array(draw(st.lists(st.floats(-1, 1), min_size=3 * p * n, max_size=3 * p * n))).reshape(p, n, 3)
    return {"vertices": POINTS[:n].copy(), "faces": faces, "displacements": disp}


@st.composite
def bad_scans(draw):
    """Random shapes, dtypes, NaN/inf, index errors, missing or extra arrays."""
    n = draw(st.integers(0, 7))
    d = {"vertices": draw(arrays((n, draw(st.sampled_from([3, 3, 2, 4])))))}
    t = draw(st.integers(0, 6))
    fw = draw(st.sampled_from([3, 3, 4, 2]))
    faces = np.array(draw(st.lists(st.integers(-2, n + 1), min_size=t * fw, max_size=t * fw)),
                     dtype=np.int64).reshape(t, fw)
    d["faces"] = faces.astype(draw(st.sampled_from([np.int64, np.int32, np.uint16, np.float64, "U2"])))
    kind = draw(st.sampled_from(["displacements", "greens", "both", "neither"]))
    if kind in ("displacements", "both"):
        p = draw(st.integers(0, 3))
        d["displacements"] = draw(arrays((p, draw(st.sampled_from([n, n, n + 1])), 3)))
    if kind in ("greens", "both"):
        m = draw(st.integers(0, 2))
        d["greens"] = draw(arrays((3 * n, 3 * m + draw(st.sampled_from([0, 0, 1])))))
        d["load_vertices"] = np.array(draw(st.lists(st.integers(-1, n + 1), min_size=m, max_size=m + 1)))
    return d


@st.composite
def scans(draw):
    """A legal scan, one legal scan with one defect, or random arrays."""
    how = draw(st.sampled_from(["good", "one defect", "one defect", "random"]))
    if how == "random":
        d = draw(bad_scans())
    else:
        d = draw(good_scans())
    if how == "one defect":
        key = draw(st.sampled_from(["vertices", "faces", "displacements"]))
        a = d[key]
        defect = draw(st.sampled_from(["nan", "inf", "index", "dtype", "shape", "drop", "huge"]))
        if defect in ("nan", "inf") and a.dtype.kind == "f":
            a = a.copy()
            a.flat[draw(st.integers(0, a.size - 1))] = np.nan if defect == "nan" else -np.inf
        elif defect == "index" and key == "faces":
            a = a.copy()
            a.flat[draw(st.integers(0, a.size - 1))] = draw(st.sampled_from([-1, len(d["vertices"]), 10 ** 9]))
        elif defect == "dtype":
            a = a.astype(draw(DTYPES))
        elif defect == "shape":
            a = a.reshape(-1) if draw(st.booleans()) else a[..., :2]
        elif defect == "huge":
            with np.errstate(over="ignore"):
                a = a * 1e308
        elif defect == "drop":
            del d[key]
            a = None
        if a is not None:
            d[key] = a
    if draw(st.integers(0, 3)) == 0:
        d["probe_load"] = draw(st.sampled_from([np.float64(2.0), np.float64(-1), np.float64(np.nan),
                                                np.array("x"), np.array([1.0, 2.0]), np.int64(3)]))
    if draw(st.integers(0, 3)) == 0:
        d["support_vertices"] = np.array(draw(st.lists(st.integers(-1, 9), max_size=3)))
    return d


@FUZZ
@given(data=scans(), links=st.sampled_from(["1", "2", "3"]))
def test_fuzz_scan_arrays(tmp_path, capsys, data, links):
    path = tmp_path / "scan.npz"
    np.savez(path, **data)
    check_outcome(path, tmp_path, capsys, links)


# ---------------------------------------------------------------- damaged files
def _small_scan():
    """A 2×6 strip of quads (two links' worth) bending at its middle: fits in milliseconds."""
    xs, ys = np.meshgrid(np.arange(6.0), np.arange(2.0), indexing="ij")
    v = np.stack([xs.ravel(), ys.ravel(), np.zeros(12)], axis=1)
    q = np.array([[2 * i, 2 * i + 2, 2 * i + 3, 2 * i + 1] for i in range(5)])
    f = np.vstack([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    disp = np.zeros((3, 12, 3))
    for p, ang in enumerate((0.2, 0.4, -0.3)):
        right = v[:, 0] > 2.5
        c, s = np.cos(ang), np.sin(ang)
        rel = v[right] - [2.5, 0, 0]
        disp[p, right, 0] = rel[:, 0] * c - rel[:, 0] + 0 * s
        disp[p, right, 2] = rel[:, 0] * s
    return S.Scan(v, f, displacements=disp)


@pytest.fixture(scope="module")
def good_bytes(tmp_path_factory):
    p = tmp_path_factory.mktemp("good") / "good.npz"
    files.write_scan(p, _small_scan())
    assert files.read_scan(p).n_vertices == 12
    return p.read_bytes()


def _rezip(raw, rename=None, drop=None, compress=False):
    src = zipfile.ZipFile(io.BytesIO(raw))
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED) as z:
        for info in src.infolist():
            if info.filename == drop:
                continue
            name = rename.get(info.filename, info.filename) if rename else info.filename
            z.writestr(name, src.read(info))
    return buf.getvalue()


@st.composite
def damage(draw, raw):
    kind = draw(st.sampled_from(["truncate", "flip", "flip", "rename", "drop", "append", "compress+flip"]))
    members = [i.filename for i in zipfile.ZipFile(io.BytesIO(raw)).infolist()]
    if kind == "truncate":
        return raw[: draw(st.integers(0, len(raw) - 1))]
    if kind == "rename":
        m = draw(st.sampled_from(members))
        new = draw(st.sampled_from(["x.npy", "vertices", "faces.npy.bak", m.upper(), "a/" + m]))
        return _rezip(raw, rename={m: new})
    if kind == "drop":
        return _rezip(raw, drop=draw(st.sampled_from(members)))
    if kind == "append":
        return raw + draw(st.binary(min_size=1, max_size=64))
    data = bytearray(_rezip(raw, compress=True) if kind == "compress+flip" else raw)
    for _ in range(draw(st.integers(1, 6))):
        i = draw(st.integers(0, len(data) - 1))
        data[i] ^= draw(st.integers(1, 255))
    return bytes(data)


@FUZZ
@given(data=st.data())
def test_fuzz_damaged_files(tmp_path, capsys, good_bytes, data):
    path = tmp_path / "damaged.npz"
    path.write_bytes(data.draw(damage(good_bytes)))
    check_outcome(path, tmp_path, capsys)


def test_undamaged_small_scan_fits(tmp_path, capsys, good_bytes):
    """The fuzzed file itself is fitted (so 'exit 0' above is a real outcome)."""
    path = tmp_path / "good.npz"
    path.write_bytes(good_bytes)
    assert check_outcome(path, tmp_path, capsys) == 0
