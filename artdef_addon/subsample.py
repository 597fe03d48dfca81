"""Vertex and field samples the skin decompositions are solved on (bounded cost on big scans)."""
from __future__ import annotations

import numpy as np

#: vertices the relabelling's, the swap trials' and most of the refined skin's decompositions are
#: solved on (:func:`vertex_sample`): a round's cost is about 3 ms plus 6 µs a vertex at 20 fields
#: (CesiumMan), so below ~1,000 vertices a smaller sample saves little
SAMPLE_VERTICES = 800
#: every link keeps at least this many of its vertices in the sample (a finger segment's link)
SAMPLE_PER_LINK = 32
#: a sample above this share of the vertices is not used (the whole mesh is): on RobotExpressive
#: (1,820 vertices, 36 links, a sample of 956) the sampled relabelling lost 3-4 of the 30 finger
#: joints on fresh poses that the whole mesh finds, for a saving under 2x
SAMPLE_SHARE = 0.5


def vertex_sample(faces: np.ndarray, labels: np.ndarray, n_vertices: int, size: int | None = None,
                  per_link: int | None = None, seed: int = 0, share: float | None = None):
    """Sorted vertex ids (S,) to solve skin decompositions on, or None when the sample would not be
    much smaller than the mesh (S > :data:`SAMPLE_SHARE` · N).

    Every vertex with probability ``size / N``, plus the ``per_link`` vertices of lowest key of every
    link (its triangles' corners), so that a short link keeps enough vertices to move on its own.
    The keys are drawn from a fixed seed: the same scan and labels give the same sample. The link
    motions of a decomposition are sums over vertices (:func:`update_motions`), so a sample that
    covers every link estimates them at a fraction of the cost; the weights of the other vertices
    then follow from one solve with those motions (:func:`full_skin`)."""
    N = int(n_vertices)
    size = SAMPLE_VERTICES if size is None else size
    per_link = SAMPLE_PER_LINK if per_link is None else per_link
    if N <= size:
        return None
    key = np.random.default_rng(seed).random(N)
    pick = key < size / N
    ok = labels >= 0
    pairs = np.unique(np.repeat(labels[ok].astype(np.int64), 3) * N + faces[ok].reshape(-1))
    pl, pv = pairs // N, pairs % N
    order = np.lexsort((key[pv], pl))
    pl, pv = pl[order], pv[order]
    rank = np.arange(pl.size) - np.searchsorted(pl, pl, side="left")
    pick[pv[rank < per_link]] = True
    rows = np.flatnonzero(pick)
    return rows if rows.size <= (SAMPLE_SHARE if share is None else share) * N else None


#: fields the relabelling's decompositions use at most (:func:`field_sample`): a long capture's
#: consecutive frames repeat each other, and a decomposition's cost is linear in the fields. Only
#: the relabelling's labels leave it; the refined skin uses every field (on dembones_bone's 400
#: frames, 48 sampled fields for its first rounds left 0.55 % error instead of 0.47 %)
SAMPLE_FIELDS = 64


def field_sample(fields: np.ndarray, size: int | None = None, rows: np.ndarray | None = None):
    """Sorted field ids (K,) spread over the poses, or None when the scan has at most ``size`` fields.

    Farthest-point sampling in displacement space (on the vertices ``rows``, default all): the field
    that moves the object most, then repeatedly the field farthest from every field chosen, so that
    the extreme poses that decide a link's motion and its joints are kept while near-repeats of them
    (a long capture's consecutive frames) are not. ``fields (P, N, 3)``."""
    size = SAMPLE_FIELDS if size is None else size
    P = fields.shape[0]
    if P <= size:
        return None
    D = (fields if rows is None else fields[:, rows]).reshape(P, -1)
    sq = np.einsum("pi,pi->p", D, D)
    pick = [int(np.argmax(sq))]
    dist = np.full(P, np.inf)
    for _ in range(size - 1):       # K steps of one (P,)-vector each, not a loop over data
        d = D @ D[pick[-1]]
        dist = np.minimum(dist, sq - 2 * d + sq[pick[-1]])
        dist[pick] = -np.inf
        pick.append(int(np.argmax(dist)))
    return np.sort(np.array(pick))
