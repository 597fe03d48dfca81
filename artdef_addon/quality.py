"""Agreement and error measures used by the tests, benchmarks and the fit summary."""
from __future__ import annotations

import dataclasses

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


# ------------------------------------------------------------------ fidelity
@dataclasses.dataclass
class Fidelity:
    """Reconstruction error of the articulation in the literature's two forms (docs/metrics.md).

    ``kg_percent``: the Karni–Gotsman distortion 100·‖X − X̂‖_F / ‖X − X̄‖_F, X (F, N, 3) the absolute
    positions x0 + u_p, X̂ the rig's reproduction, X̄ each frame's centroid broadcast over its vertices.
    ``e_rms``: ‖X − X̂‖_F / sqrt(3·N·F) in scene units (the RMS over coordinates). ``vertex_mean_percent``:
    the same numerator over ‖X − X̄_v‖_F with X̄_v each vertex's mean over the frames (the figure of older
    result files; it leaves out the shape's own extent, so it reads larger).
    """
    kg_percent: float
    e_rms: float
    vertex_mean_percent: float


def fidelity(x0: np.ndarray, fields: np.ndarray, sq_error: float) -> Fidelity:
    """:class:`Fidelity` from the summed squared error Σ_p ‖X_p − X̂_p‖² (a scalar), the rest x0 (N, 3) and
    the fields (F, N, 3); streamed over frames (no F·N·3 temporary)."""
    F, N = fields.shape[0], x0.shape[0]
    fs = frame_spread(x0, fields)
    vs = vertex_spread(fields)
    num = float(np.sqrt(max(sq_error, 0.0)))
    # NaN where a denominator vanishes: the per-vertex mean for one field (or identical fields), the
    # distortion only for frames whose vertices all coincide
    return Fidelity(kg_percent=100.0 * num / np.sqrt(fs) if fs > 0 else float("nan"),
                    e_rms=num / np.sqrt(3.0 * N * F) if N * F else float("nan"),
                    vertex_mean_percent=100.0 * num / np.sqrt(vs) if vs > 0 else float("nan"))


def frame_spread(x0, fields) -> float:
    """‖X − X̄‖_F² with X̄ each frame's centroid (the Karni–Gotsman denominator), streamed over frames."""
    total = 0.0
    for p in range(fields.shape[0]):
        X = x0 + fields[p]
        total += float(np.sum((X - X.mean(axis=0)) ** 2))
    return total


def vertex_spread(fields) -> float:
    """‖U − Ū‖_F² with Ū each vertex's mean over the fields ``(F, N, 3)``, streamed over fields."""
    mean = fields.mean(axis=0)
    return sum(float(np.sum((fields[p] - mean) ** 2)) for p in range(fields.shape[0]))


def kg_distortion(X: np.ndarray, Xhat: np.ndarray) -> float:
    """Karni–Gotsman distortion (percent) of ``Xhat`` against ``X``, both (F, N, 3) absolute positions:
    100·‖X − X̂‖_F / ‖X − X̄‖_F with X̄ each frame's centroid (Karni & Gotsman 2004)."""
    X = np.asarray(X, dtype=np.float64)
    spread = np.linalg.norm(X - X.mean(axis=1, keepdims=True))
    return float(100.0 * np.linalg.norm(X - Xhat) / spread) if spread > 0 else 0.0


def reproduce(result, x0: np.ndarray, motions: str = "pose") -> np.ndarray:
    """The rig's articulation (F, N, 3), no residual shapes: linear blend skinning of the result's weights
    with the forward kinematics of its pose parameters (``motions="pose"``) or with its reported link
    motions ``rotations``/``translations`` (``"links"``)."""
    from . import model
    if motions == "pose":
        R, t = model.forward_kinematics(result.parents, result.heads, result.frames, result.params)
    else:
        R, t = result.rotations, result.translations
    return np.stack([model.skin(result.weights, R[p], t[p], x0) for p in range(R.shape[0])])


def rigid_error(x0: np.ndarray, fields: np.ndarray) -> float:
    """Σ_p min over one rigid motion (R_p, t_p) of Σ_n ‖R_p x0_n + t_p − X_pn‖², X_p = x0 + u_p (F, N, 3):
    the squared error of the best single rigid motion per frame (Kabsch/Arun), streamed over frames."""
    a = x0 - x0.mean(axis=0)
    aa = float(np.sum(a * a))
    total = 0.0
    for p in range(fields.shape[0]):
        b = x0 + fields[p]
        b = b - b.mean(axis=0)
        U, s, Vt = np.linalg.svd(a.T @ b)
        d = np.sign(np.linalg.det(U @ Vt))
        total += max(aa + float(np.sum(b * b)) - 2.0 * (s[0] + s[1] + d * s[2]), 0.0)
    return total


def linear_errors(fields: np.ndarray) -> np.ndarray:
    """e[k] = Σ_p ‖X_p − X̂_p‖² of the best rank-k linear model X_p ≈ X̄_v + Σ_{i<k} c_pi B_i (the fields' PCA
    about each vertex's mean over frames), for k = 0..F−1; from the F×F Gram matrix (no F·3N copy)."""
    F = fields.shape[0]
    D = fields.reshape(F, -1)
    G = D @ D.T
    m = D.sum(axis=0)
    G = G - np.outer(D @ m, np.ones(F)) / F - np.outer(np.ones(F), D @ m) / F + float(m @ m) / F ** 2
    lam = np.clip(np.sort(np.linalg.eigvalsh(G))[::-1], 0.0, None)
    return np.concatenate([np.cumsum(lam[::-1])[::-1], [0.0]])[:F]


#: flag "not articulated" when ρ·L exceeds this, ρ = e_art / e_rigid (Karni–Gotsman errors of the fit and of
#: one rigid motion per frame), L the links. A smooth (elastic) deformation cut into L rigid pieces leaves an
#: error falling like 1/L, so ρ·L stays of order one however many links are spent; articulated data drop to
#: their floor once every part has its link. Measured (docs/metrics.md): shared rigs at their true count
#: ρ·L ≤ 0.57, articulated samples ≤ 0.54, the elastic sample ≥ 1.7 for 4–16 links.
NOT_ARTICULATED = 1.0
#: "few links explain it" when one rigid motion per frame leaves less than this factor times the fit's error
FEW_LINKS = 2.0


@dataclasses.dataclass
class Verdict:
    """Is an articulated rig the right model? (docs/metrics.md)"""
    articulation_percent: float   # the fit's Karni–Gotsman distortion
    rigid_percent: float          # one rigid motion per frame
    linear_percent: float         # the fields' best rank-k linear model with about the rig's parameters
    linear_rank: int
    rig_parameters: int           # 6 per link and frame + the non-zero skin weights
    per_link: float               # ρ·L
    articulated: bool
    note: str


def verdict(x0: np.ndarray, fields: np.ndarray, weights: np.ndarray, n_links: int,
            articulation_percent: float) -> Verdict:
    """Compare the fit's articulation error with one rigid motion per frame and with a linear model.

    Linear model: the best rank-k subspace of the fields (PCA about each vertex's mean over frames), k ≥ 1
    chosen so that its parameters k·(3N + F) match the rig's 6·L·F pose parameters plus its non-zero
    weights. Not articulated (``articulated=False``, a note saying so with the numbers) when

    * ρ·L > ``NOT_ARTICULATED``, ρ = e_art / e_rigid: the links leave as much of the motion beyond one rigid
      motion as a smooth deformation cut into L pieces would (or there are too few links for the data);
    * or the linear model of about the same size fits at least as well as the rig.

    When one rigid motion per frame leaves less than ``FEW_LINKS`` × e_art, the note says that few links
    explain the data. x0 (N, 3), fields (F, N, 3), weights (N, L'). All errors Karni–Gotsman percent.
    """
    F, N = fields.shape[0], x0.shape[0]
    fs = frame_spread(x0, fields)

    def pct(sq):
        return 100.0 * np.sqrt(max(sq, 0.0) / fs) if fs > 0 else 0.0
    e_rigid = pct(rigid_error(x0, fields))
    n_par = int(6 * n_links * F + np.count_nonzero(weights))
    k = int(np.clip(n_par // (3 * N + F), 1, max(F - 1, 1)))
    e_lin = pct(linear_errors(fields)[min(k, F - 1)]) if F > 1 else 0.0
    e_art = float(articulation_percent)
    rho = e_art / e_rigid if e_rigid > 0 else 0.0
    figures = (f"articulation with {n_links} links {e_art:.3g}%, one rigid motion per frame {e_rigid:.3g}%, "
               f"a rank-{k} linear model of about the rig's size {e_lin:.3g}% (Karni–Gotsman)")
    linear_better = F > 1 and e_lin <= e_art and e_art > 0
    if e_rigid <= 1e-9:
        ok, note = True, f"one rigid motion per frame explains the data ({figures})"
    elif rho * n_links > NOT_ARTICULATED or linear_better:
        ok = False
        note = (f"the data do not look articulated: {figures}. The links leave {100 * rho:.0f}% of what one rigid "
                f"motion leaves (ρ·L = {rho * n_links:.2g} > {NOT_ARTICULATED:g})" if not linear_better else
                f"the data do not look articulated: {figures}; the linear model fits at least as well")
        note += ". An articulated rig may be the wrong model (elastic or smooth deformation), or it has too few links"
    elif e_rigid < FEW_LINKS * e_art:
        ok, note = True, f"few links explain the data: {figures}"
    else:
        ok, note = True, ""
    return Verdict(e_art, e_rigid, e_lin, k, n_par, rho * n_links, ok, note)


def judge(result, x0: np.ndarray, fields: np.ndarray) -> Verdict:
    """Attach :func:`verdict`'s figures to a :class:`fit.FitResult` (``rigid_error_percent``,
    ``linear_error_percent``, ``linear_rank``, ``articulated``) and its sentence to the notes."""
    v = verdict(x0, fields, result.weights, result.n_links, result.articulation_error_percent)
    result.rigid_error_percent = v.rigid_percent
    result.linear_error_percent = v.linear_percent
    result.linear_rank = v.linear_rank
    result.articulated = v.articulated
    if v.note:
        result.notes.append(v.note)
    return v
