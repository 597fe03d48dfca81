"""Every true joint from few poses: fresh pose sets of 10 and 16 poses, every joint turned 10-40° about a
random axis in every pose (``samples.random_poses``), the true link count given."""

import numpy as np
import pytest

import artdef_addon
from artdef_addon import quality, samples, scan as S

from fresh_poses import DATA, fit_fresh_poses  # noqa: E402


#: RobotExpressive 16 poses seed 3 lost five finger joints (two finger bones in one link three times, the
#: spare links blends of the final skin) until the split stage ran again on a kept skin with a blend link
#: (stages.stage_split, SPLIT_PASSES); 12 poses seed 1000 lost two when
#: following the skin with no split kept shrank a link to a blend
@pytest.mark.parametrize("name,n_poses,seed", [("threejs_RobotExpressive", 16, 3), ("threejs_RobotExpressive", 10, 2),
                                               ("threejs_RobotExpressive", 12, 1000),
                                               ("gltf_CesiumMan", 16, 301), ("gltf_CesiumMan", 10, 1000)])
def test_every_joint_from_few_poses(name, n_poses, seed, capsys):
    """ARI ≥ 0.95, every true joint present and within 2 % of the diagonal, and the fit's self-check
    (``linkcheck``) silent on the right rig."""
    r, ari, err, diag = fit_fresh_poses(name, n_poses, seed, max_deg=40.0, min_deg=10.0)
    with capsys.disabled():
        print(f"\n{name} {n_poses} poses seed {seed}: ARI {ari:.4f}, joints within 2%: "
              f"{np.sum(err / diag < 0.02)}/{len(err)}, max {100 * np.max(err) / diag:.2f}%")
    assert ari >= 0.95
    assert np.all(err / diag < 0.02), np.round(100 * err / diag, 2)
    assert not any(n.startswith("check the rig") for n in r.notes), r.notes


def test_a_wrong_rig_from_few_poses_is_named_in_the_notes():
    """The same fit with the split stage held to one pass (SPLIT_PASSES = 1) ends with two finger
    bones in one link and the spare links blends of the skin: the notes say which links move as one."""
    from artdef_addon import stages
    with np.load(DATA / "threejs_RobotExpressive.npz", allow_pickle=False) as z:
        d = {k: z[k] for k in z.files}
    poses = samples.random_poses(d["vertices"], d["gt_weights"], d["gt_joints"], d["gt_parents"], 16,
                                 max_deg=40.0, min_deg=10.0, seed=3)
    old = stages.SPLIT_PASSES
    stages.SPLIT_PASSES = 1
    try:
        r = artdef_addon.fit(S.Scan(d["vertices"], d["faces"], displacements=poses), 36)
    finally:
        stages.SPLIT_PASSES = old
    diag = np.linalg.norm(np.ptp(d["vertices"], axis=0))
    _, err = quality.true_joint_errors(r, d["gt_joints"], d["gt_parents"], d["gt_face_labels"])
    assert not np.all(err / diag < 0.02)
    # the spare links: links that hold no true bone's majority
    C = np.zeros((r.n_links, d["gt_face_labels"].max() + 1), int)
    np.add.at(C, (r.face_labels, d["gt_face_labels"]), 1)
    held = set(C.argmax(axis=0)[C.sum(axis=0) > 0].tolist())
    spare = [l for l in range(r.n_links) if l not in held]
    note = [n for n in r.notes if "move as one" in n]
    assert spare and note and all(f"link {l} with link " in note[0] for l in spare), (spare, r.notes)
    assert "more poses" in note[0]
