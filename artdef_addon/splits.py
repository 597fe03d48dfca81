"""Split links that hold two bones: cut a link in two, drop the link the skin misses least.

An addition to the paper for tracked scans (docs/metrics.md, "Every true joint"). With a
fixed link count the greedy merge of §5.2 and the swaps of :mod:`swaps` can end with two short,
fully blended bones (two finger segments) in one link while another bone holds two links. No
triangle of such a finger moves rigidly with one bone, so its own-motion residual does not single
it out (blended seams give every finger link about the same one), and the decomposition explains
the merged pair's vertices nearly as well with blended motions: the error per link points at it
only among a few. The decomposition error E (:func:`skinning.alternate_scored`) of the whole
rig does tell: on the rigged models it falls to a third to a half when the pair is cut.

A split trial

1. takes one of the ``SPLIT_CANDIDATES`` links whose vertices hold most of E and cuts its faces in two at the
   median of their centroids along the link's principal axis (a chain of two segments is cut near
   their joint; the decomposition and the relabelling below move the seam to where the skin puts it);
2. drops one of the ``DROP_CANDIDATES`` links cheapest to remove (:func:`swaps.removal_costs`), the
   smallest link, the link the skin uses least (its summed weight per vertex of its own faces), the
   link the skin dominates on the smallest share of its own faces (below ``DOMINATED_SHARE``), or
   — for the ``NEIGHBOUR_DROPS`` cut links holding most error — the cut link's neighbour cheapest
   to remove (where a chain's seams are shifted, the bone held by two links is next to the link
   holding two bones); its faces go to their best other candidate link and its index to the cut's
   far half;
3. starts both halves from the least-squares motions of their faces (Kabsch/Arun, docs/method_notes_model.md §6) and
   runs ``swaps.TRIAL_ROUNDS`` rounds of the decomposition.

A round's trials run in lockstep (:func:`run_lockstep`): a trial still far above its
target after 1-3 rounds (``FAR``) or, after ``BEHIND_ROUND`` rounds, far behind the round's best
(``BEHIND``, ``KEEP``) is given up. The best trial of a round is kept when it lowers E by at least
``MIN_GAIN`` (in candidate order, a later trial only when it lowers the kept one's E by as much); the faces then go to
the link dominating their skin while that lowers E (as :func:`merge.dominant_labels` does), and the
next round starts from there. The link count never changes and E falls at every kept split.
"""
from __future__ import annotations

import numpy as np

from .joints import lsq_motions
from .merge import dominant_faces
from .quality import vertex_spread
from .swaps import reassign_faces

#: links tried for a cut per round: those whose vertices hold most of the decomposition error
SPLIT_CANDIDATES = 4
#: links tried for dropping per round: those cheapest to remove (:func:`swaps.removal_costs`)
DROP_CANDIDATES = 2
#: a link whose skin dominates less than this share of its own faces is also tried for dropping (the
#: lowest such share): the skin keeps it as a blend where a bone's link should be. On a claw of short
#: bones (tests/data/generated_claw.npz, seed 4: two claw bones in one link) that link dominated 18 % of
#: its faces and dropping it found the two missing joints; on the shared sets the lowest share that no
#: other drop rule already tried stood at 0.63-0.94, where the trial would cost weight solves and not be kept
DOMINATED_SHARE = 0.5
#: a split is kept when it lowers the decomposition error by at least this fraction
MIN_GAIN = 0.05
#: the trials' vertex sample is used up to this share of the mesh (wider than the relabelling's:
#: on RobotExpressive's fresh poses, seeds 5-13, the sampled split trials found every joint where
#: the whole mesh missed one on seed 5)
SAMPLE_SHARE = 0.8
#: a trial still this many times above its target after this many rounds is given up: on
#: RobotExpressive's fresh poses (seeds 6, 9, 10, 12, 14, 23), the wolf and cheburashka every kept
#: trial stood at most 3.0 x its target after 3 rounds, the losing ones at 12-47 x (CesiumMan's ~150 x)
FAR = ((1, 8.0), (2, 5.5), (3, 4.5))
#: the first this many cut links (by the error they hold) are also tried with their neighbour cheapest to drop
NEIGHBOUR_DROPS = 1
#: after this many rounds of a round's trials in lockstep, a trial whose error is above ``BEHIND``
#: times the lowest of them is given up (see :func:`run_lockstep`)
BEHIND_ROUND = 2
BEHIND = 1.5
#: ... and so is every trial but the ``KEEP`` lowest then
KEEP = 3
#: rounds of splits at most (each keeps one)
MAX_SPLITS = 4


def principal_cut(points: np.ndarray) -> np.ndarray:
    """Cut points ``(n, 3)`` in two at the median of their projections on the principal axis;
    returns the far half as a (n,) bool mask (empty for fewer than two points)."""
    if len(points) < 2:
        return np.zeros(len(points), dtype=bool)
    q = points - points.mean(axis=0)
    s = q @ np.linalg.svd(q, full_matrices=False)[2][0]
    return s > np.median(s)


def run_lockstep(runs, behind_round: int | None = None, behind: float | None = None,
                 keep: int | None = None) -> None:
    """Run the :class:`skinning.Alternation` ``runs`` (one round's split trials) to their end in
    lockstep: all start, then every unfinished one steps a round at a time. After
    ``behind_round`` rounds (default :data:`BEHIND_ROUND`) a run whose error is above ``behind``
    (default :data:`BEHIND`) times the lowest error of the runs, or above the ``keep``-th lowest
    (default :data:`KEEP`), is stopped: on the rigged models (18 fits of RobotExpressive's and
    CesiumMan's fresh poses, the wolf, cheburashka and dembones_bone: 41 rounds, 509 trials) the
    trial a round kept never stood above 1.5x the lowest error nor below third after 2 rounds,
    while most losing ones stood at 1.5-20x."""
    behind_round = BEHIND_ROUND if behind_round is None else behind_round
    behind = BEHIND if behind is None else behind
    keep = KEEP if keep is None else keep
    if not runs:
        return
    for a in runs:
        a.start()
    r = 0
    while True:
        live = [a for a in runs if not a.finished]
        if not live:
            break
        for a in live:
            a.step()
        r += 1
        if r == behind_round:
            low = min(a.e for a in runs)
            ahead = sorted(a.e for a in runs)[keep - 1] if len(runs) >= keep else np.inf
            for a in runs:
                if not a.finished and (a.e > behind * low or a.e > ahead):
                    a.stop()


def _relabel(x0, fields, faces, labels, w, R, t, e, units, rows=None):
    """Faces to the link of largest summed weight, decomposed again, while E falls (as
    :func:`merge.dominant_labels` does after its swaps). ``w (N, L)`` every vertex's weights; with
    ``rows`` the decompositions run on that vertex sample (E is the sample's) and each kept one is
    extended to every vertex. Returns ``(labels, w, R, t, e)``."""
    from .merge import RELABEL_ROUNDS
    from .skinning import alternate_scored, full_skin
    from .swaps import TRIAL_ROUNDS
    for _ in range(RELABEL_ROUNDS):
        new = dominant_faces(w, faces, labels, units)
        if np.array_equal(new, labels):
            break
        w1, R1, t1, e1 = alternate_scored(x0, fields, faces, new, R, t, iterations=TRIAL_ROUNDS, w_init=w,
                                          rows=rows)
        if not e1 < e:
            break
        if rows is not None:
            w1 = full_skin(x0, fields, faces, new, R1, t1, rows=rows, w_rows=w1)[0]
        labels, w, R, t, e = new, w1, R1, t1, e1
    return labels, w, R, t, e


def split_links(x0: np.ndarray, fields: np.ndarray, faces: np.ndarray, labels: np.ndarray,
                weights: np.ndarray, R: np.ndarray, t: np.ndarray, units: np.ndarray | None = None,
                max_splits: int = MAX_SPLITS, sample: bool = True):
    """Split links holding two bones (see module docstring), starting from a decomposition.

    ``x0 (N, 3)``, ``fields (P, N, 3)``, ``faces (T, 3)``, ``labels (T,)``; ``weights (N, L)``,
    ``R (P, L, 3, 3)``, ``t (P, L, 3)`` the decomposition of those labels (the refined skin);
    ``units`` the faces that carry the links' robust motions (each link must keep one; default
    all). With ``sample`` the trials decompose on a vertex sample (:func:`skinning.vertex_sample`,
    where the mesh is large enough for one). Returns ``(labels (T,), weights, R, t, splits)``:
    unchanged inputs and 0 when no split lowered the error by ``MIN_GAIN``.
    """
    from .skinning import Alternation, alternate_scored, full_skin, vertex_sample
    from .swaps import EXACT, TRIAL_ROUNDS, removal_costs
    labels = np.array(labels, copy=True)
    L = R.shape[1]
    P = fields.shape[0]
    units = np.arange(len(labels)) if units is None else np.asarray(units)
    if L < 3 or P == 0:
        return labels, weights, R, t, 0
    w, R, t, e, info = alternate_scored(x0, fields, faces, labels, R, t, iterations=0, details=True,
                                        w_init=weights)
    spread = vertex_spread(fields)
    # the trials decompose on a vertex sample where the mesh is large (as the relabelling does),
    # compared with the current skin's error on the same vertices
    rows = vertex_sample(faces, labels, x0.shape[0], share=SAMPLE_SHARE) if sample else None
    splits = 0
    while splits < max_splits and e > EXACT ** 2 * spread:
        cost, cur = removal_costs(info, L)
        base = e if rows is None else float(cur[rows].sum())
        vert_link = np.zeros((x0.shape[0], L), dtype=bool)
        vert_link[faces.reshape(-1), np.repeat(labels, 3)] = True
        held = cur @ vert_link                                    # (L,) E on each link's vertices
        drops = [int(l) for l in np.argsort(cost)[:DROP_CANDIDATES] if np.isfinite(cost[l])]
        # the smallest link, and the link the skin uses least: its summed weight per vertex of its own
        # faces (a link the skin no longer needs, a sliver or a palm patch of bits of several bones,
        # weighs about 0.1 there where the others weigh about 0.5)
        used = w[:, :L].sum(axis=0) / np.maximum(vert_link.sum(axis=0), 1)
        sizes = np.bincount(labels, minlength=L)
        extra = [int(np.argmin(sizes)), int(np.argmin(used))]
        # and the link that dominates the skin on the smallest share of its own faces, when that is
        # under DOMINATED_SHARE: a link the skin keeps as a blend where a bone's link should be
        top = w[:, :L][faces].sum(axis=1).argmax(axis=1)                   # (T,) each face's dominant link
        share = np.bincount(labels, weights=top == labels, minlength=L) / np.maximum(sizes, 1)
        if share.min() < DOMINATED_SHARE:
            extra.append(int(np.argmin(share)))
        for small in extra:
            if small not in drops:
                drops.append(small)
        cands = [int(l) for l in np.argsort(-held)[:SPLIT_CANDIDATES]]
        near = (vert_link.T.astype(np.int64) @ vert_link) > 0             # (L, L) links sharing a vertex
        target = (1.0 - MIN_GAIN) * base
        trials = []
        for i, s in enumerate(cands):
            # and for the first NEIGHBOUR_DROPS cut links, their neighbour cheapest to drop: where a
            # chain's seams are shifted, the bone split over two links is next to the link holding two
            nb = np.flatnonzero(near[s] & np.isfinite(cost))
            nb = nb[nb != s]
            extra = [int(nb[np.argmin(cost[nb])])] if i < NEIGHBOUR_DROPS and nb.size else []
            for d in drops + [x for x in extra if x not in drops]:
                if d == s:
                    continue
                new = reassign_faces(labels, d, faces, info["err"][:L], fallback=s)
                part = np.flatnonzero(new == s)
                far = principal_cut(x0[faces[part]].mean(axis=1))
                if far.sum() == 0 or far.sum() == len(part):
                    continue
                new[part[far]] = d
                if np.any(np.bincount(new[units], minlength=L) == 0):
                    continue
                R1, t1 = R.copy(), t.copy()
                for l in (s, d):
                    own = faces[new == l]
                    Rr, tr = lsq_motions(x0, fields, own, np.zeros(len(own), dtype=np.int64), 1, corner_weights=True)
                    R1[:, l], t1[:, l] = Rr[:, 0], tr[:, 0]
                trials.append((new, Alternation(x0, fields, faces, new, R1, t1, iterations=TRIAL_ROUNDS, w_init=w,
                                                target=target, rows=rows, far=FAR)))
        run_lockstep([a for _, a in trials])
        best = None
        for new, a in trials:       # in order, each kept if it lowers the best error so far by MIN_GAIN
            if a.e < (1.0 - MIN_GAIN) * (base if best is None else min(base, best[0])):
                best = (a.e, new) + a.result()[:3]
        if best is None:
            break
        e1, new, w1, R1, t1 = best
        if rows is not None:
            w1 = full_skin(x0, fields, faces, new, R1, t1, rows=rows, w_rows=w1)[0]
        labels, w, R, t, e = _relabel(x0, fields, faces, new, w1, R1, t1, e1, units, rows=rows)
        splits += 1
        w, R, t, e, info = alternate_scored(x0, fields, faces, labels, R, t, iterations=0, details=True, w_init=w)
    return labels, w, R, t, splits
