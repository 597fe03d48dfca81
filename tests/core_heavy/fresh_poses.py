"""A shared rig fitted on fresh poses of its true skeleton, scored against its ground truth (the heavy
known-answer tests' one recipe)."""
from pathlib import Path

import numpy as np

import artdef_addon
from artdef_addon import quality, samples, scan as S

DATA = Path(__file__).parent.parent / "data"


def fit_fresh_poses(name, n_poses, seed, **pose_options):
    """Fit the shared rig ``name`` on ``n_poses`` fresh poses (``samples.random_poses`` with ``seed`` and
    ``pose_options``), the true link count given. Returns ``(result, ARI, joint errors (J,), diagonal)``."""
    with np.load(DATA / f"{name}.npz", allow_pickle=False) as z:
        d = {k: z[k] for k in z.files}
    poses = samples.random_poses(d["vertices"], d["gt_weights"], d["gt_joints"], d["gt_parents"], n_poses,
                                 seed=seed, **pose_options)
    r = artdef_addon.fit(S.Scan(d["vertices"], d["faces"], displacements=poses), len(np.unique(d["gt_face_labels"])))
    ari = quality.adjusted_rand_index(r.face_labels, d["gt_face_labels"])
    diag = np.linalg.norm(np.ptp(d["vertices"], axis=0))
    _, err = quality.true_joint_errors(r, d["gt_joints"], d["gt_parents"], d["gt_face_labels"])
    return r, ari, err, diag
