"""Files as they are stored: vertices split at seams are one point to the fit, the outputs on the
file's own vertices (seams.py)."""
import numpy as np
import pytest

import artdef_addon
from artdef_addon import samples, seams
from artdef_addon.scan import Scan, validate_scan
from seam_files import split


@pytest.fixture(scope="module")
def rod():
    return samples.make("rod", n_fields=6, seed=3)


def test_weld_finds_exactly_the_copies(rod):
    sc = validate_scan(rod)
    islands = (sc.vertices[sc.faces].mean(1)[:, 0] > 12).astype(int)
    v, f, d, source = split(sc.vertices, sc.faces, sc.displacements, islands)
    stored = validate_scan(Scan(v, f, displacements=d))
    w = seams.weld(stored)
    assert w.n_distinct == sc.n_vertices and w.copies == len(v) - sc.n_vertices > 0
    # two stored vertices are one point exactly when they come from one original vertex
    assert np.array_equal(w.index[:sc.n_vertices], np.arange(sc.n_vertices))
    assert np.array_equal(w.index, source)
    assert np.array_equal(w.index[w.first], np.arange(w.n_distinct))


def test_points_that_touch_at_rest_but_move_apart_stay_apart(rod):
    """Lips: copies at one rest point whose motion differs in a single field by 1e-3 of the size."""
    sc = validate_scan(rod)
    soup = sc.faces.ravel()
    v, d = sc.vertices[soup], np.array(sc.displacements[:, soup])
    diag = float(np.linalg.norm(np.ptp(sc.vertices, axis=0)))
    lips = np.flatnonzero(sc.vertices[soup][:, 0] > 30)       # these corners open in field 4
    d[4, lips] += 1e-3 * diag * np.array([0.0, 0.0, 1.0]) * (lips % 2 == 0)[:, None]
    w = seams.weld(validate_scan(Scan(v, np.arange(soup.size).reshape(-1, 3), displacements=d)))
    moved = (np.arange(soup.size) % 2 == 0) & (sc.vertices[soup][:, 0] > 30)
    # a corner that opened and one that did not are never one point; the rest weld as before
    opened = np.zeros(w.n_distinct, bool)
    opened[w.index[moved]] = True
    closed = np.zeros(w.n_distinct, bool)
    closed[w.index[~moved]] = True
    assert not np.any(opened & closed)
    left = sc.vertices[:, 0] <= 30
    assert w.n_distinct == np.count_nonzero(left) + 2 * np.count_nonzero(~left)


def test_copies_within_float32_rounding_are_one_point(rod):
    sc = validate_scan(rod)
    soup = sc.faces.ravel()
    rng = np.random.default_rng(5)
    v = (sc.vertices[soup] * (1 + 1e-7 * rng.standard_normal((soup.size, 3))))
    d = sc.displacements[:, soup] * (1 + 1e-7 * rng.standard_normal((sc.n_fields, soup.size, 3)))
    w = seams.weld(validate_scan(Scan(v, np.arange(soup.size).reshape(-1, 3), displacements=d)))
    assert w.n_distinct == sc.n_vertices


def test_a_fit_of_a_split_mesh_is_the_welded_fit_on_every_copy(rod):
    sc = validate_scan(rod)
    islands = (sc.vertices[sc.faces].mean(1)[:, 0] // 6).astype(int)     # 6 islands across the rod
    v, f, d, source = split(sc.vertices, sc.faces, sc.displacements, islands)
    stored = Scan(v, f, displacements=d, support_vertices=sc.support_vertices)
    welded = artdef_addon.fit(sc, 3)
    r = artdef_addon.fit(stored, 3)
    assert np.array_equal(r.face_labels, welded.face_labels)
    np.testing.assert_array_equal(r.joints, welded.joints)
    assert r.articulation_error_percent == welded.articulation_error_percent
    # on the file's own vertices, every copy its point's values
    assert r.weights.shape == (len(v), 3) and r.residual.shape == (sc.n_fields, len(v), 3)
    np.testing.assert_array_equal(r.weights, welded.weights[source])
    np.testing.assert_array_equal(r.residual, welded.residual[:, source])
    assert r.notes[0].startswith(f"{len(v):,} vertices, {sc.n_vertices:,} distinct ({len(v) - sc.n_vertices:,} copies at seams)")
    assert not any("copies at seams" in n for n in welded.notes)
    labels, _, _ = artdef_addon.segment(stored, 3)
    assert np.array_equal(labels, welded.face_labels)


def test_result_file_of_a_split_mesh_reads_back_on_the_stored_vertices(rod, tmp_path):
    sc = validate_scan(rod)
    v, f, d, source = split(sc.vertices, sc.faces, sc.displacements, np.arange(sc.n_faces) % 2)
    r = artdef_addon.fit(Scan(v, f, displacements=d, support_vertices=sc.support_vertices), 3)
    r.save(tmp_path / "r.npz")
    back = artdef_addon.FitResult.load(tmp_path / "r.npz")
    np.testing.assert_array_equal(back.weights, r.weights)
    assert back.weights.shape[0] == len(v) and back.notes[0] == r.notes[0]


def test_greens_scan_split_keeps_its_load_points():
    sc = validate_scan(samples.make("greens_rod"))
    N = sc.n_vertices
    soup = sc.faces.ravel()                       # the triangle soup of the Green's rod
    G = sc.greens.reshape(N, 3, -1)[soup].reshape(3 * soup.size, -1)
    # the load points are stored copies, not the first ones
    last = np.zeros(N, dtype=np.int64)
    last[soup] = np.arange(soup.size)
    stored = Scan(sc.vertices[soup], np.arange(soup.size).reshape(-1, 3), greens=G,
                  load_vertices=last[sc.load_vertices],
                  support_vertices=None if sc.support_vertices is None else last[sc.support_vertices])
    welded = artdef_addon.fit(sc, 3)
    r = artdef_addon.fit(stored, 3)
    assert np.array_equal(r.face_labels, welded.face_labels)
    assert np.array_equal(r.load_vertices, last[sc.load_vertices])
    np.testing.assert_allclose(r.kappa, welded.kappa, rtol=0, atol=1e-9 * np.abs(welded.kappa).max())
    assert r.articulation_error_percent == pytest.approx(welded.articulation_error_percent, rel=0.01)
