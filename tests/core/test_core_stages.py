"""Stage-level checks with known answers: frames, ε, clustering, joints, tree, model, hardening."""
import numpy as np
import pytest
from scipy.cluster.hierarchy import linkage
from scipy.spatial.transform import Rotation

from artdef_addon import segmenter as SG, stages as ST
from artdef_addon import clustering, joints, metric, model, quality, samples
from artdef_addon.frames import relative_motions
import artdef_addon
from artdef_addon import pipeline as PL, result as RS


def _rigid(x, seed=0):
    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=seed).as_matrix()
    t = rng.normal(size=3) * 5
    return x @ R.T + t, R, t


def test_rigid_motion_frames_exact_and_epsilon_zero():
    scan = samples.make("branching")
    x1, R, t = _rigid(scan.vertices)
    Rn, tn = relative_motions(scan.vertices, x1, scan.faces)
    assert np.allclose(Rn, R, atol=1e-12) and np.allclose(tn, t, atol=1e-10)
    f = metric.field_features(scan.vertices, x1 - scan.vertices, scan.faces)
    # zero up to the round-off of the expanded (GEMM) form: about sqrt(machine eps) x object size
    rigid_max = metric.condensed_distance(f).max()
    assert rigid_max < 1e-6 * np.linalg.norm(np.ptp(scan.vertices, axis=0))
    articulated = metric.field_features(scan.vertices, scan.displacements[0], scan.faces)
    assert metric.condensed_distance(articulated).max() > 1e5 * rigid_max
    r = artdef_addon.fit(artdef_addon.Scan(scan.vertices, scan.faces, displacements=(x1 - scan.vertices)[None]), 1)
    assert r.n_links == 1 and r.rms_articulation < 1e-9


def _direct_r(f, x0, x1, faces, b, a):
    A0 = x0[faces[a]]
    A1 = x1[faces[a]]
    return np.linalg.norm(A0 @ f.R[b].T + f.t[b] - A1)


def test_epsilon_gemm_matches_definition_and_is_symmetric():
    scan = samples.make("branching", noise=0.02, bulges=True)
    u = scan.displacements[0]
    f = metric.field_features(scan.vertices, u, scan.faces)
    rng = np.random.default_rng(3)
    idx = rng.choice(f.n, 40, replace=False)
    block = metric.distance_block(f, idx, idx)
    x1 = scan.vertices + u
    for i in range(0, 40, 7):
        for j in range(0, 40, 5):
            a, b = idx[i], idx[j]
            r = lambda m, tri: _direct_r(f, scan.vertices, x1, scan.faces, m, tri)  # noqa: E731
            eps = abs(r(b, a) - r(a, a)) + abs(r(a, b) - r(b, b))
            assert block[i, j] == pytest.approx(eps, abs=1e-9)
    assert np.allclose(block, block.T, atol=1e-12)
    assert np.abs(np.diag(block)).max() < 1e-9
    cond = metric.condensed_distance(f, block_entries=5000)  # many blocks
    from scipy.spatial.distance import squareform
    full = squareform(cond)
    assert np.allclose(full[np.ix_(idx, idx)], block - np.diag(np.diag(block)), atol=1e-9)


@pytest.mark.parametrize("width", [1, 2, 7, 50, 51])
def test_row_medians_are_numpys_medians_to_the_bit(width):
    """The link medoids' row medians (one partition at the upper middle) are np.median's, exactly:
    the medoid choice must not move (ties included: a rigid core's zero distances)."""
    rng = np.random.default_rng(width)
    a = rng.random((30, width))
    a[:10] = np.round(a[:10], 1)          # repeated values
    a[10:13] = 0.0                       # a rigid core
    assert np.array_equal(metric.row_medians(a), np.median(a, axis=1))


def test_triangle_motions_are_the_field_features_motions():
    """ν = (R, t) of many fields at once (the fields left out of the clustering) equal each field's
    own :func:`metric.field_features` motions to the bit."""
    scan = samples.make("branching", noise=0.02, bulges=True)
    faces = scan.faces[::3]
    rest = metric.rest_geometry(scan.vertices, faces)
    U = scan.displacements[:, faces]                                   # (P, T, 3, 3)
    R, t = metric.triangle_motions(U, rest)
    for p in range(scan.displacements.shape[0]):
        f = metric.field_features(scan.vertices, scan.displacements[p], faces, rest)
        assert np.array_equal(R[p], f.R) and np.array_equal(t[p], f.t)


def test_link_motions_of_unclustered_fields_are_their_medoid_units_motions(monkeypatch):
    """A scan with more fields than the segmentation clusters: every other field's link motion is
    the motion ν (field_features) of the link's medoid unit in the clustered field nearest to it in
    displacement — the same arrays whether those fields are done one at a time or in one chunk."""
    monkeypatch.setattr(SG, "SEGMENT_FIELDS", 4)
    scan = samples.make("branching", n_fields=12, noise=0.01)
    seg = SG.Segmenter(scan)
    assert len(seg.clustered) == 4
    labels, medoids, used = seg.segment(11)
    idx = np.arange(scan.n_fields)
    fields = scan.fields()
    args = (scan.vertices, fields, scan.faces, seg.full_labels(labels), medoids.shape[0], "robust", seg, medoids,
            used, idx)
    R, t = ST.link_motions(*args)
    monkeypatch.setattr(ST, "NEAR_BLOCK", 1)            # one field a chunk, the nearest fields searched again
    seg.nearest_field = {}
    R1, t1 = ST.link_motions(*args)
    assert np.array_equal(R, R1) and np.array_equal(t, t1)
    units = np.unique(medoids)
    unit_faces = seg.faces[seg.unit_tri[units]]
    D = fields[np.asarray(used)][:, seg.probe].reshape(len(used), -1)
    for p in sorted(set(idx) - set(used)):
        near = np.argmin(np.sum((D - fields[p][seg.probe].reshape(1, -1)) ** 2, axis=1))
        f = metric.field_features(scan.vertices, fields[p], unit_faces)
        k = np.searchsorted(units, medoids[:, near])
        assert np.array_equal(R[p], f.R[k]) and np.array_equal(t[p], f.t[k])


def test_average_linkage_heights_monotone():
    scan = samples.make("rod")
    f = metric.field_features(scan.vertices, scan.displacements[0], scan.faces)
    Z = linkage(metric.condensed_distance(f), "average")
    assert np.all(np.diff(Z[:, 2]) >= -1e-12)
    lab = clustering.cut(Z, f.n, 3)
    assert len(np.unique(lab)) == 3


def test_hinge_only_joint_on_axis_nearest_reference():
    # two links, every field rotates link b about the same axis through (5, 1, 0) along z
    P = 4
    ang = np.radians([10, -20, 30, 15])
    Rb = Rotation.from_rotvec(np.outer(ang, [0, 0, 1])).as_matrix()
    c_true = np.array([5.0, 1.0, 0.0])
    tb = c_true - np.einsum("pij,j->pi", Rb, c_true)
    Ra = np.tile(np.eye(3), (P, 1, 1))
    ta = np.zeros((P, 3))
    c, rms, rank = joints.fit_joint(Ra, ta, Rb, tb, c_ref=np.array([4.0, 0.0, 7.0]))
    assert rank == 2 and rms < 1e-12
    assert np.allclose(c, [5.0, 1.0, 7.0], atol=1e-9)  # on the axis, nearest the reference


def test_hinge_only_fit_does_not_crash():
    scan, truth = samples.rod(n_fields=2)
    # make every field a rotation about z only
    x0 = scan.vertices
    fields = []
    for a in (0.3, -0.2):
        R = Rotation.from_rotvec([0, 0, a]).as_matrix()
        w = np.clip((x0[:, 0] - 11) / 2, 0, 1)[:, None]
        c = np.array([12.0, 0, 0])
        fields.append(w * ((x0 - c) @ R.T + c - x0))
    r = artdef_addon.fit(artdef_addon.Scan(x0, scan.faces, displacements=np.array(fields)), 2)
    j = r.joints[1]
    assert abs(j[0] - 12) < 1e-6 and abs(j[1]) < 1e-6  # on the hinge line x=12, y=0


def test_spanning_tree_keeps_exact_zero_cost_edges():
    # a chain 0-1-2-3 whose joints are exact (cost 0) and a costly shortcut 0-3
    edges = np.array([[0, 1], [1, 2], [2, 3], [0, 3], [0, 2]])
    cost = np.array([0.0, 0.0, 1e-13, 5.0, 3.0])
    parents = joints.spanning_tree(4, edges, cost, np.ones(5, bool), root=0)
    assert parents.tolist() == [-1, 0, 1, 2]


def test_forward_kinematics_roundtrip():
    rng = np.random.default_rng(0)
    parents = np.array([-1, 0, 1, 0])
    heads = rng.normal(size=(4, 3))
    frames = Rotation.random(4, random_state=1).as_matrix()
    grounded = np.array([False, False, False, False])
    params = np.concatenate([rng.uniform(-1, 1, (5, 4, 3)), np.zeros((5, 4, 3))], axis=-1)
    params[:, 0, 3:] = rng.normal(size=(5, 3))
    R, t = model.forward_kinematics(parents, heads, frames, params)
    back = model.params_from_motions(parents, heads, frames, grounded, R, t)
    R2, t2 = model.forward_kinematics(parents, heads, frames, back)
    assert np.allclose(R, R2, atol=1e-10) and np.allclose(t, t2, atol=1e-10)
    # a child's joint moves with its parent: G_parent c = G_child c
    for p_, c_ in [(0, 1), (1, 2), (0, 3)]:
        a = np.einsum("pij,j->pi", R[:, p_], heads[c_]) + t[:, p_]
        b = np.einsum("pij,j->pi", R[:, c_], heads[c_]) + t[:, c_]
        assert np.allclose(a, b, atol=1e-10)


def test_euler_matches_blender_xyz_convention():
    x, y, z = 0.3, -0.5, 1.1
    Rx = Rotation.from_rotvec([x, 0, 0]).as_matrix()
    Ry = Rotation.from_rotvec([0, y, 0]).as_matrix()
    Rz = Rotation.from_rotvec([0, 0, z]).as_matrix()
    assert np.allclose(model.euler_to_matrix([x, y, z]), Rz @ Ry @ Rx)
    assert np.allclose(model.matrix_to_euler(Rz @ Ry @ Rx), [x, y, z])


@pytest.mark.parametrize("p_max,s,expected", [(2, 2, 1.5), (2, 10, 1.998), (5, 2, 1.8), (5, 10, 4.463)])
def test_hardening_table(p_max, s, expected):
    assert model.harden(s, p_max) == pytest.approx(expected, abs=1e-3)
    assert model.harden(1.0, p_max) == pytest.approx(1.0)
    assert model.harden(0.0, p_max) == 0.0


@pytest.mark.parametrize("skin", ["seam", "refined"])
def test_weights_rows_sum_to_one_and_blend_at_seams(skin):
    scan, truth = samples.rod()
    r = artdef_addon.fit(scan, 3, skin=skin)
    assert np.allclose(r.weights.sum(axis=1), 1.0)
    x = scan.vertices[:, 0]
    inner = (x > 3) & (x < 9)
    # the seam skin (paper Eq. 2) is pure inside a link; the refined skin is a least-squares fit,
    # and the rod's ground blend (x < 1), which its links cannot follow, leaves a trace inside
    assert np.all(r.weights[inner, 0] == 1.0) if skin == "seam" else np.all(r.weights[inner, 0] > 0.95)
    seam = np.isclose(x, 12.0)
    assert np.all((r.weights[seam, 0] > 0) & (r.weights[seam, 1] > 0))


def test_result_roundtrip(tmp_path):
    scan = samples.make("greens_rod")
    r = artdef_addon.fit(scan, 3, mode="pseudo", p_max=2.0)
    RS.save_result(tmp_path / "r.npz", r)
    back = RS.load_result(tmp_path / "r.npz")
    for name in ("face_labels", "joints", "parents", "weights", "angles", "residual", "kappa", "frames"):
        assert np.array_equal(getattr(back, name), getattr(r, name), equal_nan=True), name
    assert back.p_max == 2.0 and back.mode == "pseudo" and len(back.pseudo) == len(r.pseudo)
    loads = np.random.default_rng(0).normal(size=(scan.n_loads, 3))
    assert np.allclose(model.evaluate_loads(back, scan.vertices, loads),
                       model.evaluate_loads(r, scan.vertices, loads))
    with np.load(tmp_path / "r.npz", allow_pickle=False) as z:
        assert z["pseudo_face_labels"].shape == (scan.n_loads, scan.n_faces)


def test_segmenter_recut_does_not_recompute_distances():
    scan = samples.make("branching")
    seg = SG.Segmenter(scan)
    a = seg.labels(11)
    trees = dict(seg._trees)
    b = seg.labels(5)
    assert len(np.unique(a)) == 11 and len(np.unique(b)) == 5
    assert all(seg._trees[p] is trees[p] for p in trees)


@pytest.mark.parametrize("strategy,stop_at", [("summed", "cluster"), ("paper", "merge")])
def test_cancel_from_progress(strategy, stop_at):
    scan = samples.make("branching")
    calls = []

    def progress(stage, frac):
        calls.append(stage)
        return stage == stop_at

    with pytest.raises(RS.FitCancelled):
        artdef_addon.fit(scan, 11, progress=progress, strategy=strategy)
    assert calls[0] == "features" and calls[-1] == stop_at


@pytest.mark.parametrize("name,ks", [("branching", [3, 5, 11, 12]), ("greens_rod", [2, 3, 4])])
def test_link_count_sweep_reuses_cluster_sums_and_matches_fresh_fits(name, ks):
    """Segmenting one scan at several link counts (links auto, Preview Links) reuses the cached
    distance sums of clusters it has seen, and gives bit-identical links and medoids to a
    Segmenter that starts from nothing for each count."""
    scan = samples.make(name)
    seg = SG.Segmenter(scan)
    swept = [seg.segment(k) for k in ks]
    assert seg.sum_cache.hits > 0
    for k, (lab, med, _) in zip(ks, swept):
        fresh = SG.Segmenter(scan)
        fresh.sum_cache = None
        lab1, med1, _ = fresh.segment(k)
        assert np.array_equal(lab, lab1) and np.array_equal(med, med1), k


def test_merge_rows_of_all_fields_at_once_equal_each_fields_distances_to_the_bit():
    """The merge's new Λ row after a merge (every cluster's medoid distance to the merged one,
    summed over the weighted fields) comes from products stacked over the fields; it equals the sum
    of each field's ε block (metric.distance_block) in field order, bit for bit, also after a
    cluster's medoids moved and with a field of weight 0 left out."""
    from artdef_addon import merge
    scan = samples.make("branching", noise=0.02, bulges=True)
    feats = [metric.field_features(scan.vertices, u, scan.faces) for u in scan.displacements]
    w = np.linspace(0.5, 2.0, len(feats))
    w[1] = 0.0
    rng = np.random.default_rng(4)
    T = feats[0].n
    medoid = rng.integers(0, T, size=(13, len(feats)))
    rows = merge._MedoidRows(feats, w, medoid)

    def per_field(a):
        row = np.zeros(len(medoid))
        for p, f in enumerate(feats):
            if w[p]:
                row += w[p] * metric.distance_block(f, medoid[[a], p], medoid[:, p])[0]
        return row

    for a in (0, 7, 12):
        assert np.array_equal(rows.distances(a), per_field(a))
    medoid[7] = rng.integers(0, T, size=len(feats))
    rows.move(7, medoid[7])
    for a in (7, 3):
        assert np.array_equal(rows.distances(a), per_field(a))
    assert per_field(3)[3] < 1e-6 * per_field(3).max()      # ε of a medoid with itself: round-off


def _rod_decomposition(labels, scan):
    from artdef_addon import skinning
    x0, f, u = scan.vertices, scan.faces, scan.displacements
    R, t = joints.lsq_motions(x0, u, f, labels, int(labels.max()) + 1)
    return skinning.alternate(x0, u, f, labels, R, t)


def test_split_repairs_two_bones_in_one_link_and_keeps_a_right_rig():
    """Known answer: the blended three-link rod labelled wrongly — bone 1 in two
    links, bones 2 and 3 in one — gets its true partition back from one split (the merged link cut
    in two, one of bone 1's links dropped); labelled rightly, nothing is split."""
    from artdef_addon import quality, splits
    scan, truth = samples.make_with_truth("rod", n_fields=8, blend=2.0, seed=3)
    x0, f, u = scan.vertices, scan.faces, scan.displacements
    cx = x0[f].mean(axis=1)[:, 0]
    wrong = np.where(cx < 6, 0, np.where(cx < 12, 1, 2))
    assert quality.adjusted_rand_index(wrong, truth["face_labels"]) < 0.5
    lab, w, R, t, n = splits.split_links(x0, u, f, wrong, *_rod_decomposition(wrong, scan))
    assert n >= 1 and quality.adjusted_rand_index(lab, truth["face_labels"]) > 0.99
    assert np.bincount(lab).min() > 0 and w.shape == (x0.shape[0], 3)
    right = truth["face_labels"]
    lab, _, _, _, n = splits.split_links(x0, u, f, right, *_rod_decomposition(right, scan))
    assert n == 0 and np.array_equal(lab, right)


def test_principal_cut_halves_a_chain_at_its_median():
    from artdef_addon import splits
    pts = np.c_[np.linspace(0.0, 10.0, 11), np.zeros(11), np.zeros(11)]
    far = splits.principal_cut(pts)
    assert far.sum() == 5 and ((far == (pts[:, 0] > 5.0)).all() or (far == (pts[:, 0] < 5.0)).all())
    assert splits.principal_cut(pts[:1]).sum() == 0


def test_dominant_faces_gives_a_starved_link_back_its_units_only():
    """merge.dominant_faces: faces go to the link of largest summed corner weight; a link left without
    a face of ``units`` keeps its faces — all of them by default, only its unit faces with
    ``keep_units_only`` (the final relabel of the skin the rig keeps)."""
    from artdef_addon import merge
    faces = np.array([[0, 1, 2], [1, 2, 3], [2, 3, 4], [3, 4, 5], [4, 5, 6], [5, 6, 7]])
    labels = np.array([0, 0, 1, 1, 2, 2])
    w = np.zeros((8, 3))
    w[:4, 0] = 1.0
    w[4:, 1] = 1.0                       # the skin has no use for link 2
    units = np.array([0, 3, 4])
    assert np.array_equal(merge.dominant_faces(w[:, :2], faces, labels), [0, 0, 0, 1, 1, 1])
    assert np.array_equal(merge.dominant_faces(w, faces, labels), [0, 0, 0, 1, 2, 2])
    assert np.array_equal(merge.dominant_faces(w, faces, labels, units), [0, 0, 0, 1, 2, 2])
    assert np.array_equal(merge.dominant_faces(w, faces, labels, units, keep_units_only=True), [0, 0, 0, 1, 2, 1])


def test_fitted_faces_belong_to_the_link_dominating_the_kept_skin():
    """Tracked scans with the refined skin: every face of the result goes to the link with the largest
    summed weight over its corners in the skin the rig keeps (a seam left half a bone off by an
    earlier decomposition loses a finger joint on RobotExpressive). A heavily blended branching
    object, where the relabelling's and the split's last labels left 8 faces off that rule."""
    from artdef_addon import merge
    scan, truth = samples.make_with_truth("branching", n_fields=12, blend=4.0, seed=2)
    r = artdef_addon.fit(scan, int(truth["face_labels"].max()) + 1, skin="refined")
    dom = merge.dominant_faces(r.weights, scan.faces, r.face_labels)
    assert np.array_equal(r.face_labels, dom)
    assert r.articulation_error_percent < 0.1


def _rod_runs(seed=3):
    """The blended three-link rod and three starts for its decomposition: the true labels, and two
    wrong ones (bone 1 in two links, bones 2 and 3 in one; and the seams swapped round)."""
    from artdef_addon import skinning
    scan, truth = samples.make_with_truth("rod", n_fields=8, blend=2.0, seed=seed)
    x0, f, u = scan.vertices, scan.faces, scan.displacements
    cx = x0[f].mean(axis=1)[:, 0]
    starts = [truth["face_labels"], np.where(cx < 6, 0, np.where(cx < 12, 1, 2)),
              np.where(cx < 3, 2, np.where(cx < 16, 0, 1))]

    def runs(**kw):
        out = []
        for lab in starts:
            R, t = joints.lsq_motions(x0, u, f, lab, 3)
            out.append(skinning.Alternation(x0, u, f, lab, R, t, iterations=10, **kw))
        return out
    return scan, starts, runs


def test_lockstep_trials_give_up_the_far_behind_and_keep_the_best_as_run_alone():
    """splits.run_lockstep: after ``behind_round`` rounds a run above ``behind`` x the lowest error is
    stopped there; the best run (the true labels) goes on to the same weights and error as alone
    (skinning.alternate_scored)."""
    from artdef_addon import skinning, splits
    scan, starts, runs = _rod_runs()
    x0, f, u = scan.vertices, scan.faces, scan.displacements
    rs = runs()
    splits.run_lockstep(rs, behind_round=2, behind=1.5, keep=3)
    assert min(range(3), key=lambda i: rs[i].e) == 0
    # the wrong starts stood far behind after 2 rounds: stopped there
    assert all(r.finished and r.rounds == 2 and r.e > 1.5 * rs[0].e for r in rs[1:])
    R, t = joints.lsq_motions(x0, u, f, starts[0], 3)
    w, _, _, e = skinning.alternate_scored(x0, u, f, starts[0], R, t, iterations=10)
    assert rs[0].e == e and np.array_equal(rs[0].w, w)
    # keep=1: only the lowest goes on after round 2, whatever the ratio
    rs = runs()
    splits.run_lockstep(rs, behind_round=2, behind=1e9, keep=1)
    assert rs[0].e == e and all(r.rounds == 2 for r in rs[1:])


def test_far_gives_up_a_trial_still_far_above_its_target_after_its_rounds():
    """skinning.Alternation's ``far`` pairs (rounds, factor): a run still ``factor`` x above its
    target after ``rounds`` rounds stops there; without them it goes on (the slack rule cannot
    stop it: 1000 rounds left)."""
    from artdef_addon import skinning
    scan, starts, _ = _rod_runs()
    x0, f, u = scan.vertices, scan.faces, scan.displacements
    R, t = joints.lsq_motions(x0, u, f, starts[1], 3)
    e0 = skinning.alternate_scored(x0, u, f, starts[1], R, t, iterations=0)[3]
    for far, stop in ((((1, 8.0),), 1), (((3, 8.0), (1, 1e12)), 3), (None, None)):
        run = skinning.Alternation(x0, u, f, starts[1], R, t, iterations=1000, target=e0 / 1e6, far=far)
        run.start()
        while not run.finished and run.rounds < 6:
            run.step()
        assert run.rounds == (6 if stop is None else stop) and run.e > 8.0 * e0 / 1e6


def test_residual_blocks_reproduce_every_field_exactly():
    """stage_residuals in blocks of fields (one field a block, or all at once): the rig skinning the
    rest shape plus its residual gives each field back, and the blocks do not change the answer."""
    from artdef_addon import model
    scan = samples.make("branching")
    res = {}
    for nbytes in (1, 2 ** 30):
        old = ST.RESIDUAL_BLOCK_BYTES
        ST.RESIDUAL_BLOCK_BYTES = nbytes
        try:
            res[nbytes] = artdef_addon.fit(scan, 5)
        finally:
            ST.RESIDUAL_BLOCK_BYTES = old
    a, b = res[1], res[2 ** 30]
    assert np.allclose(a.residual, b.residual, rtol=0, atol=1e-12)
    assert np.allclose(a.link_residuals, b.link_residuals, rtol=0, atol=1e-12)
    x0 = scan.vertices
    Rf, tf = model.forward_kinematics(a.parents, a.heads, a.frames, a.params)
    for p in range(scan.n_fields):
        back = model.skin(a.weights, Rf[p], tf[p], x0 + a.residual[p])
        assert np.allclose(back, x0 + scan.displacements[p], atol=1e-9)


def test_big_weight_solves_on_the_pool_give_the_same_skin(monkeypatch):
    """skinning._refine sends the vertex blocks of a solve of at least POOL_ROWS rows to the fit's
    pool: each row's weights depend on its own normal equations only, so the weights, the convex
    optimum handed to the next round and the error are those of the solve in this process (to
    round-off: the workers' products run on arrays mapped from files, aligned differently)."""
    from artdef_addon import procs, skinning
    scan, truth = samples.make_with_truth("rod", n_fields=8, blend=2.0, seed=3)
    x0, f, u = scan.vertices, scan.faces, scan.displacements
    lab = truth["face_labels"]
    R, t = joints.lsq_motions(x0, u, f, lab, 3)
    monkeypatch.setattr(skinning, "SOLVE_BLOCK", 64)        # several blocks on the rod
    monkeypatch.setattr(skinning, "POOL_ROWS", 8)
    res = []
    for jobs in (1, 2):
        with procs.pooled(jobs) as pool:
            free = {}
            w, e = skinning._refine(x0, u, f, lab, R, t, free_out=free)
            res.append((w, e, free["w"]))
            assert (pool is None) == (jobs == 1) and (jobs == 1 or len(pool.workers) == 2)
    (w1, e1, f1), (w2, e2, f2) = res
    assert np.abs(w1 - w2).max() <= 1e-12 and np.abs(f1 - f2).max() <= 1e-12
    assert abs(e1 - e2) <= 1e-12 * e1 and np.array_equal(w1 > 0, w2 > 0)
    assert np.allclose(w1.sum(axis=1), 1.0) and (np.count_nonzero(w1, axis=1) <= 4).all()


def test_resumed_fit_is_the_whole_fit_and_its_timings_count_the_first_stages():
    """A fit finished from :func:`fit.fit_until`'s state (links auto's partial fits) is the fit run
    whole, and its ``timings`` count the stages the partial ran: the merge share and a total at
    least the sum of every stage's seconds (the panel and Auto Links report them)."""
    scan = samples.make("branching")
    whole = PL.fit(scan, 5, None, segmenter=SG.Segmenter(scan))
    seg = SG.Segmenter(scan)
    state, done = PL.fit_until(seg, 5, "split")
    assert "relabel" in done and "split" not in done
    resumed = PL.fit(scan, 5, None, segmenter=seg, resume=(state, done))
    assert np.array_equal(resumed.face_labels, whole.face_labels)
    assert np.allclose(resumed.weights, whole.weights, atol=1e-12)
    tm = resumed.timings
    assert tm["merge"] > 0 and tm["merge"] == pytest.approx(seg.timings["merge"])
    stages = sum(v for k, v in tm.items() if k not in ("features", "cluster", "total"))
    assert tm["total"] >= stages


def test_fit_from_given_labels_keeps_their_links_and_finishes_into_a_fit():
    """:func:`fit.fit_until` from given labels (links auto's counts climbed to from grown links) starts the fit's
    relabelling from the given labels instead of the tree's cut: from the branching object's true
    links, one link's faces moved to the next link's index (the order a grown link has), the
    finished fit keeps the true partition at the floor's error, with joints and timings like a fit
    of the Segmenter's own cut; a cut one link short, given as labels, stays one link short."""
    scan, truth = samples.branching()
    seg = SG.Segmenter(scan)
    labels = truth["face_labels"].copy()
    labels = np.where(labels == 3, 10, np.where(labels == 10, 3, labels))     # another link order
    state, done = PL.fit_until(seg, 11, "split", labels=labels)
    assert list(done) == ["segment", "motions", "relabel", "skin"] and state.n_links == 11
    r = PL.fit(scan, 11, None, segmenter=seg, resume=(state, done))
    assert r.n_links == 11 and quality.adjusted_rand_index(r.face_labels, truth["face_labels"]) == 1.0
    assert r.articulation_error_percent < 0.01
    assert np.mean(r.face_labels[labels == 10] == 10) > 0.9 and np.mean(r.face_labels[labels == 3] == 3) > 0.9
    assert np.isfinite(r.joints).all(axis=1).sum() == 10 and r.timings["total"] >= r.timings["relabel"]
    short = PL.fit(scan, 10, None, segmenter=seg, resume=PL.fit_until(seg, 10, "split", labels=seg.full_labels(seg.segment(10)[0])))
    assert short.n_links == 10 and short.articulation_error_percent > 1.0
    gap = np.where(labels == 10, 11, labels)              # link 10 owns nothing
    with pytest.raises(ValueError, match="each owning a clustered triangle"):
        PL.fit_until(seg, 11, "split", labels=gap)


@pytest.mark.parametrize("block_bytes", [1, 2 ** 30])
def test_skin_errors_are_each_fields_skin_error_in_any_blocks(monkeypatch, block_bytes):
    """``model.skin_errors`` (blocks of fields as blended transforms) is Σ_p ‖skin_p − X_p‖² of the
    per-pose skin, one field a block or all at once, with weights over the first links only."""
    rng = np.random.default_rng(3)
    N, L, P = 300, 6, 7
    w = rng.random((N, L - 1)) * (rng.random((N, L - 1)) < 0.4)
    w[np.arange(N), rng.integers(0, L - 1, N)] += 0.2
    w /= w.sum(axis=1, keepdims=True)
    R = Rotation.random(P * L, random_state=4).as_matrix().reshape(P, L, 3, 3)
    t, x0, u = rng.normal(size=(P, L, 3)), rng.normal(size=(N, 3)), rng.normal(size=(P, N, 3))
    want = sum(np.sum((model.skin(w, R[p], t[p], x0) - (x0 + u[p])) ** 2, axis=1) for p in range(P))
    monkeypatch.setattr(model, "SKIN_BLOCK_BYTES", block_bytes)
    assert np.allclose(model.skin_errors(w, R, t, x0, u), want, rtol=1e-12, atol=0)


def test_residual_solve_of_blended_transforms():
    """model.blended_residual solves B δ = rhs for blends of rotations in closed form (the residual
    stage at a million vertices): LAPACK's answer to round-off on well and badly conditioned blends,
    the pseudo-inverse's where B is singular (two opposite rotations blended half and half)."""
    rng = np.random.default_rng(5)
    n = 4000
    R1 = Rotation.from_rotvec(rng.normal(size=(n, 3))).as_matrix()
    R2 = Rotation.from_rotvec(rng.normal(size=(n, 3))).as_matrix()
    w = rng.random((n, 1, 1))
    B = w * R1 + (1 - w) * R2
    flip = Rotation.from_rotvec(np.pi * np.array([0.0, 0.0, 1.0])).as_matrix()
    B[:10] = 0.5 * np.eye(3) + 0.5 * flip                   # singular: rank 1
    rhs = rng.normal(size=(n, 3))
    d = model.blended_residual(B.reshape(4, n // 4, 3, 3), rhs.reshape(4, n // 4, 3)).reshape(n, 3)
    ok = np.abs(np.linalg.det(B)) > 1e-10
    assert not ok[:10].any() and ok[10:].all()
    want = np.linalg.solve(B[ok], rhs[ok][..., None])[..., 0]
    scale = np.linalg.cond(B[ok])[:, None] * np.abs(want).max(axis=1, keepdims=True)
    assert np.all(np.abs(d[ok] - want) <= 1e-13 * scale)
    assert np.allclose(d[:10], np.einsum("nij,nj->ni", np.linalg.pinv(B[:10]), rhs[:10]))


def test_more_poses_than_the_trials_use_keep_the_split_stage(monkeypatch):
    """The split stage's budget is the relabelling swaps' on the fields the trials use (a spread of
    ``skinning.SAMPLE_FIELDS``): a scan given more poses than that keeps its splits as it keeps its
    swaps, and above the budget both are skipped with one note naming the fields counted; the
    estimate's price of the trials follows the same boundary (``cost.NO_TRIALS_SHARE``)."""
    from artdef_addon import cost, skinning, splits, swaps
    P = skinning.SAMPLE_FIELDS + 16
    scan = samples.make("branching", n_fields=P)
    N = scan.n_vertices
    calls = []
    real = splits.split_links

    def spy(*a, **k):
        calls.append(a[1].shape[0])           # the fields the trials got
        return real(*a, **k)
    monkeypatch.setattr(splits, "split_links", spy)
    monkeypatch.setattr(swaps, "SWAP_BUDGET", N * skinning.SAMPLE_FIELDS)   # below N × P
    r = artdef_addon.fit(scan, 11)
    assert calls == [skinning.SAMPLE_FIELDS]
    assert not any("skipped" in n for n in r.notes)
    within, _ = cost.articulation_cost(N, P, 11)
    monkeypatch.setattr(swaps, "SWAP_BUDGET", N * skinning.SAMPLE_FIELDS - 1)
    calls.clear()
    r = artdef_addon.fit(scan, 11)
    assert calls == []
    # the estimate stops pricing the trials exactly where the fit stops running them
    above, _ = cost.articulation_cost(N, P, 11)
    assert above < within
    assert f"link swaps and splits skipped: {N:,} vertices × {skinning.SAMPLE_FIELDS} fields (a spread of the {P})" \
        in " ".join(r.notes)
