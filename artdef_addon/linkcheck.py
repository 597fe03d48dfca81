"""The fit's self-check of its links: a link that needs two rigid motions, two links that move as one.

With a fixed link count a fit can end with two bones in one link and one bone in two links: the link
count is right and the agreement figures look perfect while two fingers move as one. This check
judges the links from the data alone (the scan's rest vertices and fields, the fit's face labels),
with least-squares rigid motions (Kabsch/Arun, :func:`joints.lsq_motions`):

* **needs two motions**: a link's vertices are cut in two at the median of their faces' centroids
  along the link's principal axis; ``split_gain`` = the link's one-motion error / the two halves'
  error. A link holding two bones that turn against each other gains a large factor; a link of one
  bone gains little (only its blended ends move apart). Flagged when the gain is at least
  ``SPLIT_GAIN`` and the link's one-motion error per vertex is at least ``ABOVE_NEIGHBOURS`` × the
  median of its neighbours' in the fitted tree (or of all links when it has none). Measured: the
  merged link of the branching sample fitted with one link too few gains 3.4 (2.4 with noise and
  bulges), the rod's with 2 links 4.1; the links of correct fits at most 1.6 (RobotExpressive,
  16 fresh poses; the branching sample, the rod) — its blended finger links gain little either
  way, so there the next check is the one that speaks;
* **move as one**: two links joined in the fitted tree whose motions (the fit's) turn against each other
  by less than ``MOVE_AS_ONE_DEG`` in every field: the data do not show them moving apart, so one link
  would do and the spare one belongs elsewhere (a blended skin makes one rigid motion for two
  finger links nearly as good as two, so the fit's own motions judge this, not the rigid error);
* **a blend, not a part** (refined skin): a link whose own skin weight dominates less than
  ``DOMINATED_SHARE`` of its own faces. The decomposition uses it to blend its neighbours, not as a
  part of its own: on RobotExpressive with fewer poses such a link is the spare one left where two
  finger bones share a link (16 fresh poses, seed 3: three links at 0 %, 0 % and 33 % while two
  finger bones shared a link three times; the correct fits' lowest share 0.83).

Each flagged link or pair becomes a note (:func:`notes`) with its numbers and what to do.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .joints import lsq_motions

#: a link is "needs two motions" when cutting it in two lowers its rigid error by at least this factor ...
SPLIT_GAIN = 2.0
#: ... and its rigid error per vertex is this many times its neighbours' median
ABOVE_NEIGHBOURS = 1.0
#: two joined links "move as one" when they turn against each other by less than this in every field
MOVE_AS_ONE_DEG = 3.0
#: a link is "a blend, not a part" when its skin dominates less than this share of its own faces
DOMINATED_SHARE = 0.5
#: the rigid errors' floor: this share of the fields' mean squared displacement (noise-free data)
FLOOR = 1e-12


@dataclasses.dataclass
class LinkCheck:
    rigid_rms: np.ndarray       # (L,) one rigid motion per field: RMS error per vertex and field
    split_gain: np.ndarray      # (L,) one-motion error / two halves' error
    two_motions: list           # links that need two rigid motions
    pairs: list                 # (parent, child, degrees): joined links that move as one
    pair_degrees: np.ndarray    # (L,) most the edge (l, parent l) turns over the fields; NaN for roots
    dominated: np.ndarray       # (L,) share of a link's faces its own skin weight dominates (NaN: seam skin)
    blends: list                # (link, the link the skin gives most of its faces to, that share)


def _sse(x0, fields, faces, labels, K):
    """Σ over fields and each group's vertices of the squared error of its least-squares rigid motion,
    and each group's vertex count: ``(sse (K,), n (K,))``."""
    present, compact = np.unique(labels, return_inverse=True)     # groups without faces: no motion
    R, t = lsq_motions(x0, fields, faces, compact, len(present))
    P = fields.shape[0]
    # each (vertex, group) membership once
    memb = np.unique(np.stack([faces.reshape(-1), np.repeat(compact, 3)], axis=1), axis=0)
    v, k = memb[:, 0], memb[:, 1]
    g = present[k]
    pred = np.einsum("pkij,kj->pki", R[:, k], x0[v]) + t[:, k]
    err = np.sum((pred - (x0[v][None] + fields[:, v])) ** 2, axis=(0, 2))
    return np.bincount(g, err, minlength=K), np.bincount(g, minlength=K) * P


def _halves(x0, faces, labels, L):
    """Face labels 2l, 2l+1: each link's faces cut at the median of their centroids along its principal axis."""
    c = x0[faces].mean(axis=1)
    half = np.zeros(len(labels), dtype=int)
    for l in range(L):
        f = np.flatnonzero(labels == l)
        if len(f) < 2:
            continue
        d = c[f] - c[f].mean(axis=0)
        axis = np.linalg.svd(d, full_matrices=False)[2][0]
        s = d @ axis
        half[f] = s > np.median(s)
    return 2 * labels + half


def dominated_share(weights: np.ndarray, faces: np.ndarray, labels: np.ndarray, L: int):
    """``(share (L,), face_owner (T,))``: the share of each link's faces whose mean skin weight its own
    link dominates, and the link dominating each face's mean weight. weights (N, L)."""
    fl = weights[faces].mean(axis=1).argmax(axis=1)
    n = np.bincount(labels, minlength=L)
    return np.bincount(labels, (fl == labels).astype(float), minlength=L) / np.maximum(n, 1), fl


def check(x0: np.ndarray, fields: np.ndarray, faces: np.ndarray, labels: np.ndarray, parents: np.ndarray,
          rotations: np.ndarray, weights: np.ndarray | None = None) -> LinkCheck:
    """The self-check of one fit: x0 (N, 3), fields (P, N, 3), faces (T, 3), labels (T,) links
    0..L−1, parents (L,) of the fitted tree (−1 roots), rotations (P, L, 3, 3) the fit's link
    motions; weights (N, L) a refined skin (None: not judged)."""
    L = int(parents.shape[0])
    labels = np.asarray(labels)
    e1, n1 = _sse(x0, fields, faces, labels, L)
    e2, _ = _sse(x0, fields, faces, _halves(x0, faces, labels, L), 2 * L)
    e2 = e2[0::2] + e2[1::2]
    floor = FLOOR * float(np.mean(fields ** 2)) if fields.size else 0.0
    rms = np.sqrt(e1 / np.maximum(n1, 1))
    gain = np.where(e1 > floor * n1, e1 / np.maximum(e2, floor * np.maximum(n1, 1)), 1.0)
    kids = np.flatnonzero(parents >= 0)
    nb = [[] for _ in range(L)]
    for a in kids:
        nb[a].append(int(parents[a]))
        nb[int(parents[a])].append(int(a))
    med_all = float(np.median(rms)) if L else 0.0
    two = [l for l in range(L) if gain[l] >= SPLIT_GAIN and
           rms[l] >= ABOVE_NEIGHBOURS * (float(np.median(rms[nb[l]])) if nb[l] else med_all)]
    deg = np.full(L, np.nan)
    if len(kids) and rotations.shape[0]:
        M = np.einsum("pkji,pkjl->pkil", rotations[:, parents[kids]], rotations[:, kids])
        c = np.clip((np.trace(M, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
        deg[kids] = np.degrees(np.arccos(c)).max(axis=0)
    pairs = [(int(parents[a]), int(a), float(deg[a])) for a in kids if deg[a] < MOVE_AS_ONE_DEG]
    dom = np.full(L, np.nan)
    blends = []
    if weights is not None and L > 1:
        dom, fl = dominated_share(weights, faces, labels, L)
        own = fl == labels
        n = np.bincount(labels, minlength=L)
        for l in np.flatnonzero((n > 0) & (dom < DOMINATED_SHARE)):
            other = np.bincount(fl[(labels == l) & ~own], minlength=L)
            blends.append((int(l), int(other.argmax()), float(other.max() / n[l])))
    return LinkCheck(rms, gain, two, pairs, deg, dom, blends)


def notes(c: LinkCheck) -> list:
    """The check's sentences for the fit's notes (empty when nothing is flagged)."""
    out = []
    if c.two_motions:
        which = ", ".join(f"link {l} (one rigid motion leaves {c.split_gain[l]:.3g}× the error of two, "
                          f"{c.rigid_rms[l] / max(np.median(c.rigid_rms), 1e-300):.3g}× the links' median)"
                          for l in c.two_motions)
        out.append(f"check the rig: links that need two rigid motions: {which}; each may hold two bones — fit "
                   f"with more links, or with more poses that move them")
    if c.pairs:
        which = ", ".join(f"links {a} and {b} (at most {d:.2g}° apart in any pose)" for a, b, d in c.pairs)
        out.append(f"check the rig: links that move as one: {which}; one link would do — fit with fewer links, "
                   f"or the spare link belongs where a link holds two bones")
    if c.blends:
        which = ", ".join(f"link {l} with link {m} (the skin gives {100 * s:.0f}% of link {l}'s faces to link {m})"
                          for l, m, s in c.blends)
        out.append(f"check the rig: links that move as one: {which}; a spare link — if the rig has no bone "
                   f"to spare, two bones share a link nearby: fit with more poses that move every joint, or "
                   f"with more links; otherwise with fewer links")
    return out
