"""Agreement and error measures used by the tests, benchmarks and the fit summary."""
from __future__ import annotations

import numpy as np
from scipy.special import comb


def adjusted_rand_index(a, b) -> float:
    """Adjusted Rand index of two labellings (Hubert & Arabie 1985); 1 = identical partitions."""
    a = np.unique(np.asarray(a), return_inverse=True)[1]
    b = np.unique(np.asarray(b), return_inverse=True)[1]
    n = a.size
    table = np.zeros((a.max() + 1, b.max() + 1))
    np.add.at(table, (a, b), 1)
    sum_ij = comb(table, 2).sum()
    sum_a = comb(table.sum(axis=1), 2).sum()
    sum_b = comb(table.sum(axis=0), 2).sum()
    expected = sum_a * sum_b / comb(n, 2) if n > 1 else 0.0
    top = 0.5 * (sum_a + sum_b)
    if top == expected:
        return 1.0
    return float((sum_ij - expected) / (top - expected))


def match_links(pred, truth) -> np.ndarray:
    """For every predicted link, the true link it overlaps most (by triangle count)."""
    pred = np.asarray(pred)
    truth = np.asarray(truth)
    table = np.zeros((pred.max() + 1, truth.max() + 1))
    np.add.at(table, (pred, truth), 1)
    return table.argmax(axis=1)


def true_joint_errors(result, gt_joints, gt_parents, gt_face_labels):
    """Distance from each true joint between two face-owning bones to the fitted joint.

    For a true bone b with parent q (both owning faces), the fitted links that overlap them most
    are la and lb. If one is the other's parent in the fitted tree the fitted joint is used;
    otherwise the joint of the two links' motions is fitted directly. ``inf`` when both true
    bones fall into the same link. Returns ``(bones, errors)``.
    """
    from .joints import fit_joint
    owners = set(np.unique(gt_face_labels).tolist())
    m = match_links(result.face_labels, gt_face_labels)
    best = {}
    for l, b in enumerate(m):  # the predicted link that holds most of each true bone
        n = np.count_nonzero((result.face_labels == l) & (gt_face_labels == b))
        if b not in best or n > best[b][1]:
            best[b] = (l, n)
    bones, errs = [], []
    for b in sorted(owners):
        q = int(gt_parents[b])
        if q < 0 or q not in owners:
            continue
        bones.append(b)
        if b not in best or q not in best or best[b][0] == best[q][0]:
            errs.append(np.inf)
            continue
        la, lb = best[b][0], best[q][0]
        if result.parents[la] == lb:
            c = result.joints[la]
        elif result.parents[lb] == la:
            c = result.joints[lb]
        else:
            c, _, _ = fit_joint(result.rotations[:, la], result.translations[:, la],
                                result.rotations[:, lb], result.translations[:, lb],
                                0.5 * (result.heads[la] + result.heads[lb]))
        errs.append(float(np.linalg.norm(c - gt_joints[b])))
    return np.array(bones, dtype=int), np.array(errs)
