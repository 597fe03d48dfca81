"""A real character as files store it (split at UV islands, along hard edges, as triangle soup) fits
exactly as the same mesh welded (seams.py)."""
from pathlib import Path

import numpy as np
import pytest

import artdef_addon
from artdef_addon.scan import Scan
from seam_files import split, welded

DATA = Path(__file__).parent.parent / "data"
LINKS = 19


@pytest.fixture(scope="module")
def cesium():
    d = np.load(DATA / "gltf_CesiumMan.npz")
    return d["vertices"], d["faces"], d["displacements"], d["gt_face_labels"]


def _islands(kind, v, f, gt_labels):
    if kind == "uv_islands":          # one island per body part
        return gt_labels
    if kind == "hard_edges":          # split wherever the face normal's main direction changes
        n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        axis = np.abs(n).argmax(1)
        return 2 * axis + (n[np.arange(len(n)), axis] > 0)
    return np.arange(len(f))          # triangle soup


@pytest.mark.parametrize("kind", ["uv_islands", "hard_edges", "soup"])
def test_cesium_man_split_fits_as_welded(cesium, kind):
    v, f, d, gt = cesium
    sv, sf, sd, source = split(v, f, d, _islands(kind, v, f, gt))
    assert len(sv) > len(v)
    ref_scan, to_ref = welded(sv, sd, source, sf)
    ref = artdef_addon.fit(ref_scan, LINKS)
    r = artdef_addon.fit(Scan(sv, sf, displacements=sd), LINKS)
    diag = float(np.linalg.norm(np.ptp(v, axis=0)))
    assert np.array_equal(r.face_labels, ref.face_labels)
    assert np.array_equal(r.parents, ref.parents)
    np.testing.assert_allclose(r.joints, ref.joints, rtol=0, atol=1e-6 * diag)
    assert abs(r.articulation_error_percent - ref.articulation_error_percent) <= 0.01 * ref.articulation_error_percent
    # every stored vertex carries its point's skin and residual: the copies of a seam move together
    np.testing.assert_array_equal(r.weights, ref.weights[to_ref])
    np.testing.assert_array_equal(r.residual, ref.residual[:, to_ref])
    assert r.notes[0].startswith(f"{len(sv):,} vertices, {len(v):,} distinct")
