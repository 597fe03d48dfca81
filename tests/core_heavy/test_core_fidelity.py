"""Fidelity you can quote: the Karni–Gotsman distortion, E_RMS, the model verdict."""
from pathlib import Path

import numpy as np
import pytest

from artdef_addon import quality, samples, scan as S
import artdef_addon
from artdef_addon import result as RS

DATA = Path(__file__).parent.parent / "data"


def test_karni_gotsman_distortion_on_a_hand_computed_case():
    """A 2×2 square in two frames (the second translated): each frame's centroid is the square's
    centre, so ‖X − X̄‖² = 2 frames × 4 vertices × 2 = 16. One vertex off by 0.04 in one frame:
    distortion 100·0.04/4 = 1 %, E_RMS 0.04/√(3·4·2). Against each vertex's mean over the frames
    (the old figure) the spread is only the translation: 8 × 0.5² = 2, so 100·0.04/√2 %."""
    x0 = np.array([[-1.0, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]])
    fields = np.zeros((2, 4, 3))
    fields[1] = [1.0, 0, 0]
    X = x0[None] + fields
    Xhat = X.copy()
    Xhat[1, 2, 2] += 0.04
    assert quality.kg_distortion(X, Xhat) == pytest.approx(1.0, rel=1e-12)
    fid = quality.fidelity(x0, fields, float(np.sum((X - Xhat) ** 2)))
    assert fid.kg_percent == pytest.approx(1.0, rel=1e-12)
    assert fid.e_rms == pytest.approx(0.04 / np.sqrt(24.0), rel=1e-12)
    assert fid.vertex_mean_percent == pytest.approx(100 * 0.04 / np.sqrt(2.0), rel=1e-12)


def test_rigid_and_linear_reference_models_known_answers():
    """Frames that are rigid motions of the rest shape leave nothing to one rigid motion per frame;
    fields spanned by two shapes leave nothing to a rank-2 linear model, and the rank-1 error is the
    smallest singular value's share (computed directly)."""
    from scipy.spatial.transform import Rotation
    rng = np.random.default_rng(0)
    x0 = rng.normal(size=(50, 3))
    Rs = Rotation.random(4, random_state=1).as_matrix()
    fields = np.stack([x0 @ R.T + rng.normal(size=3) - x0 for R in Rs])
    assert quality.rigid_error(x0, fields) < 1e-18 * np.sum(x0 ** 2) + 1e-20
    a, b = rng.normal(size=(2, 50, 3))
    c = rng.normal(size=(6, 2))
    fields = c[:, :1, None] * a + c[:, 1:, None] * b
    e = quality.linear_errors(fields)
    D = fields.reshape(6, -1)
    s = np.linalg.svd(D - D.mean(axis=0), compute_uv=False)
    assert e[0] == pytest.approx(np.sum(s ** 2)) and e[1] == pytest.approx(s[1] ** 2)
    assert abs(e[2]) < 1e-9 * e[0]


@pytest.mark.parametrize("name,kw,links", [("rod", {}, 3), ("branching", dict(noise=0.02, bulges=True), 11),
                                           ("elastic", {}, 8)])
def test_reported_error_is_the_distortion_of_the_result_itself(name, kw, links):
    """``articulation_error_percent`` equals the Karni–Gotsman distortion recomputed from the result's
    own weights and motions (pose parameters through forward kinematics, and the reported link motions)
    within 2 % relative; E_RMS likewise."""
    scan = samples.make(name, **kw)
    r = artdef_addon.fit(scan, links)
    X = scan.vertices[None] + scan.fields()
    for motions in ("pose", "links"):
        Xhat = quality.reproduce(r, scan.vertices, motions)
        assert r.articulation_error_percent == pytest.approx(quality.kg_distortion(X, Xhat), rel=0.02)
    e_rms = np.linalg.norm(X - quality.reproduce(r, scan.vertices)) / np.sqrt(X.size)
    assert r.e_rms == pytest.approx(e_rms, rel=0.02)
    assert r.vertex_mean_error_percent > r.articulation_error_percent   # the old figure read larger


def test_elastic_object_is_flagged_articulated_ones_are_not():
    """The jelly tube (smooth radial wobble, no rigid part) is flagged with its numbers in the notes,
    whatever the link count; the rod, the noisy branching object and the Green's rod are not."""
    scan = samples.make("elastic")
    for links in (4, 8):
        r = artdef_addon.fit(scan, links)
        assert not r.articulated
        note = [n for n in r.notes if "do not look articulated" in n]
        assert note and f"{r.articulation_error_percent:.3g}%" in note[0] and f"{r.rigid_error_percent:.3g}%" in note[0]
        assert r.articulation_error_percent / r.rigid_error_percent * links > quality.NOT_ARTICULATED
    for name, kw, links in [("rod", {}, 3), ("branching", dict(noise=0.02, bulges=True), 11), ("greens_rod", {}, 3)]:
        r = artdef_addon.fit(samples.make(name, **kw), links)
        assert r.articulated, r.notes
        assert not any("do not look articulated" in n for n in r.notes)
        assert r.rigid_error_percent > 5 * r.articulation_error_percent


def test_result_file_keeps_the_new_figures_and_old_files_still_load(tmp_path):
    scan = samples.make("elastic")
    r = artdef_addon.fit(scan, 4)
    path = tmp_path / "r.npz"
    RS.save_result(path, r)
    back = RS.load_result(path)
    for k in ("articulation_error_percent", "e_rms", "vertex_mean_error_percent", "rigid_error_percent",
              "linear_error_percent"):
        assert getattr(back, k) == pytest.approx(getattr(r, k), rel=1e-12)
    assert back.linear_rank == r.linear_rank and back.articulated is False and back.notes == r.notes
    with np.load(path) as z:       # a file of an older version: none of its keys
        old = {k: z[k] for k in z.files if k not in RS._FIDELITY + ("notes", "linear_rank", "articulated")}
    np.savez(tmp_path / "old.npz", **old)
    o = RS.load_result(tmp_path / "old.npz")
    assert np.isnan(o.e_rms) and o.articulated and o.notes == []
    assert o.articulation_error_percent == pytest.approx(r.articulation_error_percent)


#: seeds that each need one of the rules of docs/metrics.md, "Every true joint": RobotExpressive's seed 24
#: loses a finger joint unless the faces follow the kept skin (fit._dominant_skin_labels), seeds 41 and 69
#: without the split trials' wider drop candidates (the cut link's neighbour, the link the skin uses least);
#: the claw (tests/data/README.md: bones 1.65 % of the diagonal long) loses two claw joints on seed 4 unless
#: the link its skin dominates least is a drop candidate (splits.DOMINATED_SHARE)

@pytest.mark.parametrize("name,seed", [("gltf_CesiumMan", 4), ("threejs_RobotExpressive", 6),
                                       ("threejs_RobotExpressive", 24), ("threejs_RobotExpressive", 41),
                                       ("threejs_RobotExpressive", 69), ("generated_claw", 4)])
def test_shared_rigs_fresh_seeds(name, seed, capsys):
    """Fresh poses of the shared rigs with seeds the rest of the suite does not use: ARI ≥ 0.95, every
    true joint present and within 2 % of the diagonal, the reported error equal to the distortion of the
    result's own reproduction, and the verdict articulated."""
    with np.load(DATA / f"{name}.npz", allow_pickle=False) as z:
        d = {k: z[k] for k in z.files}
    poses = samples.random_poses(d["vertices"], d["gt_weights"], d["gt_joints"], d["gt_parents"], 20, seed=seed)
    scan = S.Scan(d["vertices"], d["faces"], displacements=poses)
    r = artdef_addon.fit(scan, len(np.unique(d["gt_face_labels"])))
    ari = quality.adjusted_rand_index(r.face_labels, d["gt_face_labels"])
    diag = np.linalg.norm(np.ptp(d["vertices"], axis=0))
    _, err = quality.true_joint_errors(r, d["gt_joints"], d["gt_parents"], d["gt_face_labels"])
    kg = quality.kg_distortion(d["vertices"][None] + poses, quality.reproduce(r, d["vertices"]))
    with capsys.disabled():
        print(f"\n{name} seed {seed}: ARI {ari:.4f}, joints within 2%: {np.sum(err / diag < 0.02)}/{len(err)}, "
              f"max {100 * np.max(err) / diag:.2f}%, distortion {r.articulation_error_percent:.4f}% "
              f"(recomputed {kg:.4f}%), E_RMS {r.e_rms:.3g}, one rigid motion {r.rigid_error_percent:.3g}%")
    assert ari >= 0.95
    assert r.articulation_error_percent == pytest.approx(kg, rel=0.02)
    assert r.articulated and not any("do not look articulated" in n for n in r.notes)
    assert np.all(err / diag < 0.02), np.round(100 * err / diag, 2)
