"""Tracked scans: refined weights, automatic link count, real rigs, no collapse."""
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import minimize

from artdef_addon import pipeline, stages as ST
from artdef_addon import files, joints, linkcount, quality, samples, scan as S, skinning
import artdef_addon
from artdef_addon import pipeline as PL, result as RS, segmenter as SG

from fresh_poses import fit_fresh_poses  # noqa: E402

DATA = Path(__file__).parent.parent / "data"


def _random_normal_equations(seed, N, m, k, drop):
    """A (N, k, m), b (N, k) of random least-squares problems, their normal equations Q (N, m, m),
    q (N, m) and a validity mask with about ``drop`` of the candidates off (the first always on)."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(N, k, m))
    b = rng.normal(size=(N, k))
    valid = rng.random((N, m)) > drop
    valid[:, 0] = True
    return A, b, np.einsum("nka,nkb->nab", A, A), np.einsum("nka,nk->na", A, b), valid


def test_simplex_least_squares_is_exact():
    N, m = 40, 4
    A, b, Q, q, valid = _random_normal_equations(0, N, m, 9, 0.2)
    w = skinning.simplex_least_squares(Q, q, valid)
    assert np.allclose(w.sum(1), 1) and (w >= 0).all() and not w[~valid].any()
    for n in range(0, N, 5):
        idx = np.flatnonzero(valid[n])
        res = minimize(lambda x: np.sum((A[n][:, idx] @ x - b[n]) ** 2), np.ones(len(idx)) / len(idx),
                       bounds=[(0, 1)] * len(idx), constraints=({"type": "eq", "fun": lambda x: x.sum() - 1},),
                       method="SLSQP", options={"ftol": 1e-14})
        ours = np.sum((A[n] @ w[n] - b[n]) ** 2)
        assert ours <= res.fun + 1e-9


def _best_subset(Q, q, idx, limit):
    """Brute force: the best convex weights on every subset of ``idx`` of at most ``limit`` links."""
    from itertools import combinations
    best = np.inf
    for n in range(1, limit + 1):
        for S in combinations(idx, n):
            S = list(S)
            res = minimize(lambda x: x @ Q[np.ix_(S, S)] @ x - 2 * q[S] @ x, np.ones(n) / n,
                           bounds=[(0, 1)] * n, constraints=({"type": "eq", "fun": lambda x: x.sum() - 1},),
                           method="SLSQP", options={"ftol": 1e-14})
            best = min(best, res.fun)
    return best


@pytest.mark.parametrize("rank", [12, 3])
def test_simplex_least_squares_with_an_influence_limit(rank):
    """Eight candidates, at most four non-zero weights: where the convex optimum needs at most four
    links it is returned (checked against every subset); elsewhere the weights stay feasible and
    no worse than the best four single candidates' own optimum (the old candidate choice)."""
    rng = np.random.default_rng(rank)
    N, m = 60, 8
    A = rng.normal(size=(N, rank, m))
    b = rng.normal(size=(N, rank))
    Q = np.einsum("nka,nkb->nab", A, A)
    q = np.einsum("nka,nk->na", A, b)
    Q[:10, 1], Q[:10, :, 1], q[:10, 1] = Q[:10, 0], Q[:10, :, 0], q[:10, 0]   # identical candidates
    valid = rng.random((N, m)) > 0.25
    valid[:, 0] = True
    w = skinning.simplex_least_squares(Q, q, valid, max_support=4)
    assert np.allclose(w.sum(1), 1) and (w >= 0).all() and not w[~valid].any()
    assert ((w > 0).sum(1) <= 4).all()
    free = skinning.simplex_least_squares(Q, q, valid)            # no limit: the convex optimum
    obj = lambda n, x: x @ Q[n] @ x - 2 * q[n] @ x
    exact = 0
    for n in range(0, N, 4):
        idx = np.flatnonzero(valid[n])
        if (free[n] > 0).sum() <= 4:
            assert obj(n, w[n]) <= _best_subset(Q[n], q[n], idx, 4) + 1e-9
            exact += 1
        single = idx[np.argsort(np.diag(Q[n])[idx] - 2 * q[n][idx])[:4]]
        assert obj(n, w[n]) <= _best_subset(Q[n], q[n], single, 4) + 1e-9
    assert exact >= 3


def test_simplex_least_squares_hands_back_its_convex_optimum_as_the_next_start():
    """With ``convex`` it also returns the convex optimum (the weights without the influence limit); started from
    it, the limited solve gives the same weights as from a cold start (what the alternation's warm
    start relies on), and a batch of single-candidate rows hands back their one weight."""
    N, m = 80, 8
    _, _, Q, q, valid = _random_normal_equations(5, N, m, 12, 0.25)
    w, free = skinning.simplex_least_squares(Q, q, valid, max_support=4, convex=True)
    assert np.allclose(free, skinning.simplex_least_squares(Q, q, valid), atol=1e-12)
    assert ((free > 0).sum(1) > 4).any()              # the limit binds on some rows
    warm = skinning.simplex_least_squares(Q, q, valid, max_support=4, w0=free)
    assert np.allclose(warm, w, atol=1e-10)
    one = np.zeros((3, m), dtype=bool)
    one[:, 2] = True
    _, free = skinning.simplex_least_squares(Q[:3], q[:3], one, max_support=4, convex=True)
    assert np.array_equal(free, one.astype(float))


def test_refined_skin_reproduces_a_rig_from_its_true_motions():
    """RobotExpressive's fresh LBS poses with the true links and the true bone motions: the refined
    weights reproduce the poses (Karni–Gotsman error below 0.001 %). Choosing each vertex's four
    links by their single-link error alone (the old rule) leaves 0.29 %: a vertex blended over
    four bones can be explained better, one at a time, by a neighbouring bone it does not use."""
    with np.load(DATA / "threejs_RobotExpressive.npz", allow_pickle=False) as z:
        d = {k: z[k] for k in z.files}
    poses, R, t = samples.random_poses(d["vertices"], d["gt_weights"], d["gt_joints"], d["gt_parents"], 20,
                                       seed=1, motions=True)
    gl = d["gt_face_labels"]
    bones = np.unique(gl)
    X = d["vertices"][None] + poses
    den = np.sqrt(sum(np.sum((X[i] - X.mean(0)) ** 2) for i in range(len(X))))
    errors = {}
    for pool in (4, skinning.POOL):
        w, e = skinning._refine(d["vertices"], poses, d["faces"], np.searchsorted(bones, gl), R[:, bones],
                                t[:, bones], radius=skinning.SKIN_RADIUS, pool=pool)
        errors[pool] = 100 * np.sqrt(e) / den
    assert errors[skinning.POOL] < 1e-3 < 0.1 < errors[4]
    assert np.abs(w - d["gt_weights"][:, bones]).max() < 0.01


def test_refined_weights_reproduce_linear_blends():
    scan, truth = samples.branching()
    seam = artdef_addon.fit(scan, 11, skin="seam")
    refined = artdef_addon.fit(scan, 11, skin="refined")
    assert refined.skin == "refined"
    assert refined.articulation_error_percent < 0.01 < seam.articulation_error_percent
    assert np.allclose(refined.weights.sum(1), 1) and (refined.weights >= 0).all()
    assert ((refined.weights > 0).sum(1) <= 4).all()
    m = quality.match_links(refined.face_labels, truth["face_labels"])
    assert np.abs(refined.weights - truth["weights"][:, m]).max() < 1e-6


@pytest.mark.parametrize("name,kw,expected", [("rod", {}, 3), ("branching", {}, 11),
                                               ("branching", dict(noise=0.02, bulges=True), 11),
                                               ("branching", dict(disconnected=True), 11)])
def test_auto_link_count_on_generated_samples(name, kw, expected):
    choice = linkcount.choose_links(SG.Segmenter(samples.make(name, **kw)), max_links=16)
    assert choice.links == expected, choice.reason
    assert f"chose {expected}" in choice.reason


def test_descending_curve_reads_the_counts_the_rule_needs():
    """The search reads the tree curve from Max Links down (linkcount.descending_curve): every
    count it computes has the whole curve's value, it stops under two counts in a row above the
    tau bar of the counts it read, and the tree rule picks the same count from it (the noisy
    branching sample: a big drop to 11 links)."""
    seg = SG.Segmenter(samples.make("branching", noise=0.02, bulges=True))
    full = linkcount.articulation_error_curve(seg, 16)
    part = linkcount.descending_curve(seg, 16)
    read = ~np.isnan(part)
    assert np.allclose(part[read], full[read]) and read[0] and read[-1] and not read.all()
    low = int(np.flatnonzero(read[1:])[0]) + 2            # the lowest count read after e(1)
    floor = part[read].min()
    bar = floor * (part[0] / floor) ** 0.15
    assert part[low - 1] > bar and part[low] > bar and read[low - 1:].all() and not read[1:low - 1].any()
    choice = linkcount.choose_links(seg, max_links=16, whole_fits=False)
    assert choice.links == 11 and np.array_equal(np.isnan(choice.errors), ~read)


def test_panel_words_for_a_curve_with_counts_the_search_skipped():
    """The counts the search did not read are NaN in the curve: the panel's curve shows a dash
    there and its sentence reads the counts it has (the command line prints the same sentence)."""
    from artdef_addon import wording
    nan = float("nan")
    errors = [50.0, nan, nan, 3.0, 2.0, 2.5]
    assert wording.error_curve_lines(errors, 4) == [" 1 links   50.00%", " 2 links       —", " 3 links       —",
                                                    " 4 links    3.00%  <", " 5 links    2.00%", " 6 links    2.50%"]
    assert wording.plain_link_reason(4, errors) == (
        "4 links leave 3% of the motion unexplained (one bone leaves 50%); even 6 would lower that by only 33%, "
        "so more bones would mostly add clutter.")
    # the fit's own error is said where known (the curve's is a quick segmentation's); above 100 % "all of it"
    assert wording.plain_link_reason(4, [104.8] + errors[1:], fitted=0.0261) == (
        "4 links leave 0.026% of the motion unexplained (one bone leaves all of it); even 6 would lower that by "
        "only 33%, so more bones would mostly add clutter.")


def test_whole_fits_climb_to_the_true_link_count():
    """Started below the truth (8 of 11 links on the branching object), the whole fits' error
    keeps falling faster than k^-2 until every arm segment has its link, then stays at the floor."""
    seg = SG.Segmenter(samples.make("branching"))
    k, errors = linkcount._whole_fits_upward(seg, 8, 16, 4)
    assert k == 11
    assert errors[10] > 1.0 > 0.01 > errors[11]


def test_grown_links_spare_whole_fits_and_climb_to_the_true_link_count():
    """The upward search with grown links (linkcount._grown_upward) makes the whole fits' choice
    from 8 links (11, as test_whole_fits_climb_to_the_true_link_count) with one whole fit where
    the whole-fit rule fits 8..15: 8, 9 and 10 are passed on links grown on each count's fit up to
    its split stage (linkcount.partial_fit), and only 11, where the error reaches the floor, is
    fitted whole (finishing its partial fit). 9, 10 and 11 are fitted from the links grown on the
    count below (linkcount's start_fit), and the fit handed back at 11 is the true partition,
    as the fit fit.fit makes there. A link grown on the 10-link fit (one arm segment short) finds
    that segment: the error drops from over 1 % to the floor's order."""
    scan, truth = samples.branching()
    seg = SG.Segmenter(scan)
    fits = {}
    work = {}
    k, whole, grown, decisions = linkcount._grown_upward(seg, 8, 16, 4, linkcount.SearchProgress(None, 1.0), fits,
                                                         work)
    assert k == 11 and decisions == [(8, "grown continue"), (9, "grown continue"), (10, "grown continue"),
                                     (11, "explained")], decisions
    assert set(whole) == set(fits) == {11} and whole[11] < 0.01 and work["grown_links"] >= 3
    assert work["partial_fits"] == 4 and work["climbed_fits"] == 3
    # the finished fit, climbed to from grown links, finds the true links as the fit fit.fit makes does
    again = PL.fit(scan, 11, None, segmenter=seg)
    for r in (again, fits[11]):
        assert r.n_links == 11 and quality.adjusted_rand_index(r.face_labels, truth["face_labels"]) == 1.0
    assert fits[11].articulation_error_percent <= 1.05 * again.articulation_error_percent + 1e-9
    r = PL.fit(scan, 10, None, segmenter=seg)
    assert r.articulation_error_percent > 1.0
    X = scan.vertices[None] + scan.fields()
    spread = float(np.sum((X - X.mean(axis=1, keepdims=True)) ** 2))
    labels, w, R, t, err = linkcount.grow_link(scan.vertices, scan.fields(), scan.faces, r.face_labels,
                                               r.weights[:, :10], r.rotations, r.translations,
                                               seg.valid[seg.unit_tri], spread)
    assert w.shape == (scan.n_vertices, 11) and R.shape[1] == 11 and err < 0.1 < 1.0 < r.articulation_error_percent
    # the new link is one true link (the segment the 10-link fit had merged into a neighbour)
    true_of_new = truth["face_labels"][labels == 10]
    assert np.bincount(true_of_new).max() >= 0.9 * true_of_new.size


def test_interpolating_links_known_ratios():
    """ρ of a chain's middle link: 0 when its motion is a convex blend of its neighbours', 1/2 for
    a translation half-way off their segment, 1 when both neighbours move alike; the ends have
    one neighbour each (ρ = 1)."""
    scan, truth = samples.rod(n_fields=3)
    lab = truth["face_labels"]
    x0, faces = scan.vertices, scan.faces
    P = 3
    R = np.tile(np.eye(3), (P, 3, 1, 1))
    rng = np.random.default_rng(0)
    t0, t2 = rng.normal(size=(P, 3)), rng.normal(size=(P, 3))
    t = np.stack([t0, 0.3 * t0 + 0.7 * t2, t2], axis=1)
    rho = linkcount.interpolating_links(x0, faces, lab, R, t)
    assert rho[1] < 1e-12 and rho[0] == rho[2] == 1.0
    t = np.zeros((P, 3, 3))
    t[:, 2] = [2.0, 0, 0]
    t[:, 1] = [1.0, 1.0, 0]
    assert np.isclose(linkcount.interpolating_links(x0, faces, lab, R, t)[1], 0.5)
    from scipy.spatial.transform import Rotation
    R[:, 1] = Rotation.from_rotvec([0.0, 0.0, 0.4]).as_matrix()
    t[:] = 0.0
    assert np.isclose(linkcount.interpolating_links(x0, faces, lab, R, t)[1], 1.0)


def _rod_links(n_links):
    """The rod of three fields with ``n_links`` link motions for the non-bone rules: every link at rest
    but link 1 (shifted off the line, ρ = 1/2: not interpolating) and link 2 (shifted along it); the
    scan, its truth, the true face labels (a copy), R (3, n_links, 3, 3) and t (3, n_links, 3)."""
    scan, truth = samples.rod(n_fields=3)
    R = np.tile(np.eye(3), (3, n_links, 1, 1))
    t = np.zeros((3, n_links, 3))
    t[:, 2] = [2.0, 0, 0]
    t[:, 1] = [1.0, 1.0, 0]
    return scan, truth, truth["face_labels"].copy(), R, t


def test_blend_handles_are_not_bones():
    """A link whose skin weights reach far beyond its own triangles (here: it keeps the rod's
    middle third's weights but owns two triangles) is a blend handle; with its third it is a bone."""
    from types import SimpleNamespace
    scan, truth, lab, R, t = _rod_links(3)
    fit = SimpleNamespace(face_labels=lab, rotations=R, translations=t, weights=truth["weights"])
    assert not linkcount.spurious_links(scan.vertices, scan.faces, fit).any()
    middle = np.flatnonzero(lab == 1)
    lab[middle[2:]] = 0
    assert linkcount.spurious_links(scan.vertices, scan.faces, fit).tolist() == [False, True, False]


def test_unused_links_are_not_bones():
    """A link that no vertex's skin follows by a quarter (a sliver of two triangles at weight 0.1, as the
    search kept on new rigs) is not a bone; the same sliver at weight 0.5 is (it moves its vertices)."""
    from types import SimpleNamespace
    scan, truth, lab, R, t = _rod_links(4)
    t[:, 3] = [0.0, 0.0, 3.0]                    # a motion of its own: not interpolating
    sliver = np.flatnonzero(lab == 1)[:2]
    lab[sliver] = 3
    corners = np.unique(scan.faces[sliver])
    for weight, unused in ((0.1, True), (0.5, False)):
        w = np.concatenate([truth["weights"], np.zeros((len(scan.vertices), 1))], axis=1)
        w[corners, 3] = weight * w[corners].sum(axis=1)
        w[corners, :3] *= 1.0 - weight
        fit = SimpleNamespace(face_labels=lab, rotations=R, translations=t, weights=w)
        assert linkcount.spurious_links(scan.vertices, scan.faces, fit).tolist() == [False, False, False, unused]


def test_links_auto_drops_interpolating_links_on_smooth_blends():
    """With wide blends (most of each inner arm segment shared with the hub and the outer
    segment), a 12th link is spent inside a blend and moves as a blend of its neighbours: the
    drop takes it off and the 11-link fit has no link that is not a bone."""
    scan, truth = samples.branching(blend=2.5)
    k, steps = linkcount._drop_non_bones(SG.Segmenter(scan), 12, {})
    assert (k, steps) == (11, [(12, 1), (11, 0)])


def test_upward_search_stops_where_the_fit_already_has_a_link_that_is_not_a_bone(monkeypatch):
    """A close call of the upward search (grown links neither clearly below nor above the bar) is
    decided by whole fits of the counts above k, unless k's own whole fit already has a link that
    is not a bone (linkcount.spurious_links): then k is past the bones, the search stops right
    after that fit and the drop of non-bones takes it down. The wide-blend branching object from 12
    links (one more than its 11 bones: a link spent inside a blend), the margins opened so that no
    grown chain settles a stop: the 12-link fit is the search's only whole fit, and the drop lands
    on the 11 bones."""
    monkeypatch.setattr(linkcount, "GROWN_MARGIN", 1e9)
    monkeypatch.setattr(linkcount, "FLOOR_MARGIN", 1e9)
    scan, truth = samples.branching(blend=2.5)
    seg = SG.Segmenter(scan)
    fits = {}
    k, whole, grown, decisions = linkcount._grown_upward(seg, 12, 16, 4, linkcount.SearchProgress(None, 1.0), fits)
    assert (k, decisions) == (12, [(12, "non-bones")]) and set(fits) == {12}
    assert np.count_nonzero(linkcount.spurious_links(scan.vertices, scan.faces, fits[12])) == 1
    assert linkcount._drop_non_bones(seg, 12, fits)[0] == 11


def test_links_auto_hands_back_its_own_fit(tmp_path, capsys, monkeypatch):
    """The chooser's fit at the chosen count is the one ``fit`` would make (same segmenter), so the
    command line uses it instead of fitting that count again; other fit options refit."""
    scan = samples.make("branching")
    seg = SG.Segmenter(scan)
    reports = []
    choice = linkcount.choose_links(seg, max_links=16, progress=lambda s, f: reports.append((s, f)) and False)
    # the search is one stage whose fraction only grows, from 0 to 1 (its fits' stages inside it)
    assert {s for s, _ in reports} == {"links"}
    fractions = [f for _, f in reports]
    assert fractions[0] == 0.0 and fractions[-1] == 1.0 and fractions == sorted(fractions)
    assert len(set(fractions)) > 16                   # each count of the curve and each fit moves it
    mine = choice.reusable()
    again = PL.fit(scan, choice.links, None, segmenter=seg)
    assert mine is not None and mine.n_links == choice.links == 11
    assert np.array_equal(mine.face_labels, again.face_labels)
    assert np.allclose(mine.weights, again.weights) and np.allclose(mine.joints, again.joints, equal_nan=True)
    assert choice.reusable(skin="seam") is None and choice.reusable(mode="pseudo") is None
    assert choice.reusable(motion="lsq") is None
    from artdef_addon import cli
    path = tmp_path / "branching.npz"
    files.write_scan(path, scan)
    calls = []
    real_fit = PL.fit
    monkeypatch.setattr(pipeline, "fit", lambda *a, **k: calls.append(a[1]) or real_fit(*a, **k))
    assert cli.main(["fit", str(path), "--links", "auto", "--max-links", "16", "-o", str(tmp_path / "r.npz")]) == 0
    out = capsys.readouterr().out
    assert "links auto: chose 11" in out and "with the link-count search up to 16 links" in out   # priced
    assert "11 links leave " in out and "% of the motion unexplained" in out    # the panel's plain sentence too
    shown = [int(l.split()[-1][:-1]) for l in out.splitlines() if l.startswith("choosing the link count: ")]
    assert shown[0] == 0 and shown[-1] == 100 and shown == sorted(set(shown))   # the search, in tenths
    assert RS.load_result(tmp_path / "r.npz").n_links == 11
    assert 11 in calls and len(calls) == len(set(calls))   # no count fitted twice: the CLI reused it


def test_auto_link_count_rigid_is_one():
    scan = samples.make("rod")
    from scipy.spatial.transform import Rotation
    R = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    d = np.stack([scan.vertices @ R.T + [1, 2, 3] - scan.vertices, scan.vertices @ R.T @ R.T - scan.vertices])
    choice = linkcount.choose_links(SG.Segmenter(S.validate_scan(S.Scan(scan.vertices, scan.faces, displacements=d))), 8)
    assert choice.links == 1


def test_never_collapses_on_random_rods():
    found = 0
    for seed in range(20):
        n_fields = 3 + seed % 8
        scan, truth = samples.rod(n_fields=n_fields, seed=100 + seed)
        r = artdef_addon.fit(scan, 3)
        found += len(np.unique(r.face_labels)) == 3 and \
            quality.adjusted_rand_index(r.face_labels, truth["face_labels"]) > 0.99
    assert found == 20


@pytest.mark.parametrize("name", ["gltf_CesiumMan", "threejs_RobotExpressive"])
def test_real_rig_fresh_poses(name, capsys):
    r, ari, err, diag = fit_fresh_poses(name, 20, 1)
    with capsys.disabled():
        print(f"\n{name}: ARI {ari:.3f}, joints within 2% of the diagonal: {np.mean(err / diag < 0.02):.0%} "
              f"of {len(err)}, articulation error {r.articulation_error_percent:.2f}%")
    assert ari >= 0.95
    assert r.articulation_error_percent < 3.0
    # the bar: every joint between two links that own faces within 2% of the diagonal
    assert np.all(err / diag < 0.02), np.round(100 * err / diag, 2)


def test_refined_skin_fits_joints_of_fully_blended_links(monkeypatch):
    """With RobotExpressive's true links given, the joints fitted to the robust (medoid) motions
    miss the finger bases, links blended with the hand on every vertex (their medoid moves with a
    blend), while the refined skin's decomposition motions put every joint within 2%."""
    from artdef_addon import merge
    with np.load(DATA / "threejs_RobotExpressive.npz", allow_pickle=False) as z:
        d = {k: z[k] for k in z.files}
    poses = samples.random_poses(d["vertices"], d["gt_weights"], d["gt_joints"], d["gt_parents"], 20, seed=1)
    scan = S.Scan(d["vertices"], d["faces"], displacements=poses)
    gl = d["gt_face_labels"]
    bones = np.unique(gl)
    truth = np.searchsorted(bones, gl)
    monkeypatch.setattr(merge, "dominant_labels", lambda *a, **k: (truth.copy(), 0))
    # and the labels stay the true ones to the end (the faces do not follow the fitted skin, which
    # moves a few seam faces of the true labels, and no link is split: on some machines' round-off
    # a split of a finger link lowered the sampled error by its margin): the joints alone are under test
    monkeypatch.setattr(ST, "_dominant_skin_labels", lambda st: None)
    monkeypatch.setattr(ST, "_split_links", lambda st: setattr(st, "splits", 0))
    diag = np.linalg.norm(np.ptp(d["vertices"], axis=0))
    within = {}
    for skin in ("seam", "refined"):
        r = artdef_addon.fit(scan, len(bones), skin=skin)
        assert quality.adjusted_rand_index(r.face_labels, gl) == 1.0
        _, err = quality.true_joint_errors(r, d["gt_joints"], d["gt_parents"], gl)
        within[skin] = int(np.sum(err / diag < 0.02))
    assert within["refined"] == len(err)
    assert within["seam"] < len(err)


def test_link_swaps_repair_a_merged_pair_and_a_split_link(monkeypatch):
    """A segmentation with two true links merged and another cut in two (same link count) is
    repaired by the swaps inside the skin decomposition; without them the dominant relabel alone
    cannot move a link across the object."""
    from artdef_addon import merge, swaps as swaps_module
    scan, truth = samples.branching()
    gl = truth["face_labels"]
    x0, faces, fields = scan.vertices, scan.faces, scan.fields()
    lab = gl.copy()
    lab[gl == 2] = 1                                   # arm 0: both segments in one link
    tip = np.flatnonzero(gl == 4)                      # arm 1's outer segment cut in two
    cen = x0[faces[tip]].mean(axis=1)
    along = cen @ (cen.mean(0) / np.linalg.norm(cen.mean(0)))
    lab[tip[along > np.median(along)]] = 2
    R, t = joints.lsq_motions(x0, fields, faces, lab, 11)
    new, swaps = merge.dominant_labels(x0, fields, faces, lab, R, t)
    assert swaps >= 1
    assert quality.adjusted_rand_index(new, gl) > 0.99
    assert sorted(quality.match_links(new, gl)) == list(range(11))
    monkeypatch.setattr(swaps_module, "SWAP_BUDGET", 0)          # no swaps: the scan above their budget
    old, none = merge.dominant_labels(x0, fields, faces, lab, R, t)
    assert none is None and quality.adjusted_rand_index(old, gl) < 0.97


@pytest.mark.parametrize("P", [1, 3])
def test_skin_statistics_match_direct_sums_and_leave_fields_alone(P, monkeypatch):
    """The SSDR-form data pass (vertex blocks × all fields in one product) equals the sums it
    replaces, for one field (where the block reshape is a view) and several, across blocks."""
    rng = np.random.default_rng(P)
    N, L = 700, 3
    monkeypatch.setattr(skinning, "PASS_BLOCK_BYTES", 8 * 3 * P * 256)  # several blocks
    x = rng.standard_normal((N, 3))
    f = rng.standard_normal((P, N, 3))
    f0 = f.copy()
    R = np.stack([[np.linalg.qr(rng.standard_normal((3, 3)))[0] for _ in range(L)] for _ in range(P)])
    t = rng.standard_normal((P, L, 3))
    m, xh, A = skinning._homogeneous(x, R, t)
    w = rng.random((N, L))
    Y = (w[:, :, None] * xh[:, None, :]).reshape(N, 4 * L)
    out = skinning._data_pass(xh, f, A=A, Y=Y)
    X = xh[None, :, :3] + f
    assert np.array_equal(f, f0)
    assert np.allclose(out["q"], np.einsum("pni,plij,nj->nl", X, A, xh), atol=1e-10)
    assert np.allclose(out["M"], np.einsum("nlj,pni->plji", Y.reshape(N, L, 4), X), atol=1e-10)
    assert np.allclose(out["xx"], (X ** 2).sum(axis=(0, 2)), atol=1e-10)
    # and the homogeneous motions are the original ones, moved to centred coordinates
    moved = np.einsum("plij,nj->pnli", A, xh) + m
    assert np.allclose(moved, np.einsum("plij,nj->pnli", R, x) + t[:, None], atol=1e-10)
