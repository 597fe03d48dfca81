"""The fit's named stages (paper §5–§7; docs/method_notes.md §2–§5, docs/method_notes_model.md §6–§10) on
one :class:`FitState`.

The fit after the :class:`~.segmenter.Segmenter`'s cached features and trees is a fixed list of
named stages (:data:`STAGES`), each a module-level function of one :class:`FitState` that reads
the arrays earlier stages left there and adds its own; :func:`run_stages` runs them in order,
reports each stage's name to ``progress`` as it starts (cancel: FitCancelled) and times it.
A new step slots in as one more (name, function) pair, e.g. after "skin".
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np

from . import joints as _joints
from . import linkcheck as _linkcheck
from . import merge as _merge
from . import model as _model
from . import quality as _quality
from . import splits as _splits
from . import swaps as _swaps
from .metric import rest_geometry, triangle_motions
from .result import FitResult, report as _report
from .scan import Scan
from .segmenter import Segmenter, select_fields
from .skinning import alternate, blend_weights, field_sample, vertex_sample


#: a joint whose robust motions agree to this fraction of the bounding-box diagonal is exact
#: (round-off, also of single-precision input: Blender meshes hold float32, about 1e-7 of the
#: extent): the refined skin keeps it instead of refitting it to the decomposition's motions
EXACT_JOINT = 1e-6


@dataclasses.dataclass
class FitState:
    """What the stages hand on (N vertices, T triangles, P fields fitted, L links).

    Inputs: ``scan``, ``seg`` (its Segmenter), ``links`` (k), ``motion``, ``skin``
    (``"seam"``/``"refined"``), ``field_idx`` (the P scan fields fitted, in order) and
    ``seg_fields`` (the field subset the segmentation uses; None: all)."""
    scan: Scan
    seg: "Segmenter"
    links: int
    motion: str
    skin: str
    field_idx: list
    seg_fields: list | None = None
    fields: np.ndarray | None = None          # (P, N, 3) displacements fitted
    # segment
    labels_valid: np.ndarray | None = None    # (T_valid,) link per non-degenerate triangle
    medoids: np.ndarray | None = None         # (L, P_used) medoid unit per link and used field
    used_fields: list | None = None           # the fields the segmentation used
    labels: np.ndarray | None = None          # (T,) link per triangle
    n_links: int = 0                          # L
    # motions / relabel
    R: np.ndarray | None = None               # (P, L, 3, 3) link rotations
    t: np.ndarray | None = None               # (P, L, 3) link translations
    trial_fields: object = None               # the fields the relabel and split trials use (_trial_fields)
    swaps: int | None = 0                     # link swaps made (None: over budget, skipped)
    splits: int = 0                           # links split in two (the split stage)
    # skin
    weights: np.ndarray | None = None         # (N, L) skin weights
    Rs: np.ndarray | None = None              # (P, L, 3, 3) the refined skin's motions (None: seam)
    ts: np.ndarray | None = None              # (P, L, 3)
    # joints and tree
    centroid: np.ndarray | None = None        # (L, 3) area-weighted link centroids
    link_vids: list | None = None             # L arrays of vertex ids per link
    diag: float = 0.0                         # bounding-box diagonal
    parents: np.ndarray | None = None         # (L,) parent link, -1 root / grounded
    joints: np.ndarray | None = None          # (L, 3) joint centres (NaN: none)
    joint_errors: np.ndarray | None = None    # (L,) joint fit RMS
    grounded: np.ndarray | None = None        # (L,) joined to the fixed world
    # bones
    heads: np.ndarray | None = None           # (L, 3)
    tails: np.ndarray | None = None           # (L, 3)
    frames: np.ndarray | None = None          # (L, 3, 3) rest frames (columns x, y, z)
    # pose model
    params: np.ndarray | None = None          # (P, L, 6) angles, locations
    Rf: np.ndarray | None = None              # (P, L, 3, 3) the rig's bone motions
    tf: np.ndarray | None = None              # (P, L, 3)
    Ro: np.ndarray | None = None              # (P, L, 3, 3) link motions reported
    to: np.ndarray | None = None              # (P, L, 3)
    # residuals
    residual: np.ndarray | None = None        # (P, N, 3) rest-space residual
    link_residuals: np.ndarray | None = None  # (P, L) rigid-motion RMS of each link's own motion
    rms_articulation: float = 0.0
    rms_total: float = 0.0
    fidelity: object = None                   # quality.fidelity(...) figures
    # a state fit_until ran: the wall seconds and the Segmenter's merge seconds it spent (fit(resume=) adds them)
    spent_total: float = 0.0
    spent_merge: float = 0.0


#: entries of a chunk's (fields, clustered fields, probe coordinates) block in :func:`link_motions`' nearest-field
#: search (and its units' vertex displacements): about 32 MB of work arrays however long the capture
NEAR_BLOCK = 4_000_000


def link_motions(x0, fields, faces, labels, L, motion, seg, medoids, used_fields, field_idx):
    """Link motions ``R (P, L, 3, 3)``, ``t (P, L, 3)`` (§6): ``"lsq"``: least squares over each
    link's triangles; else the robust one, the motion ν of each link's medoid unit (Eq. 4)
    in every field the segmentation used (identity elsewhere). ``x0 (N, 3)``, ``fields
    (P, N, 3)``, ``faces (T, 3)``, ``labels (T,)``, ``medoids (L, P_used)``."""
    if motion == "lsq":
        return _joints.lsq_motions(x0, fields, faces, labels, L)
    P = len(field_idx)
    R = np.tile(np.eye(3), (P, L, 1, 1))
    t = np.zeros((P, L, 3))
    col = {p: i for i, p in enumerate(used_fields)}
    missing = []
    for i, p in enumerate(field_idx):
        if p in col:
            m = medoids[:, col[p]]
            R[i] = seg.features[p].R[m]
            t[i] = seg.features[p].t[m]
        elif seg.features[p] is None and len(used_fields):
            missing.append(i)
    if missing:
        # a field left out of the clustering (Segmenter.clustered): the motion ν of each link's
        # medoid unit in the clustered field nearest to it in displacement; such fields in chunks
        # (a long capture has thousands), each chunk's nearest fields and motions at once
        missing = np.asarray(missing)
        key = (tuple(int(p) for p in used_fields), tuple(int(field_idx[i]) for i in missing))
        near = seg.nearest_field.get(key)
        U = seg.scan.fields()
        D = None
        units = np.unique(medoids)
        unit_faces = seg.faces[seg.unit_tri[units]]
        rest = rest_geometry(x0, unit_faces)
        step = max(1, NEAR_BLOCK // max(len(used_fields) * len(seg.probe) * 3, unit_faces.size * 24, 1))
        found = np.empty(len(missing), dtype=np.int64) if near is None else near
        for s in range(0, len(missing), step):
            chunk = missing[s:s + step]
            if near is None:
                # (the same for every call of a fit: the relabel and split stages ask again)
                if D is None:
                    D = U[np.asarray(used_fields)][:, seg.probe].reshape(len(used_fields), -1)
                X = U[np.asarray(field_idx)[chunk][:, None], seg.probe[None, :]].reshape(len(chunk), -1)
                found[s:s + step] = np.argmin(np.sum((D[None] - X[:, None]) ** 2, axis=2), axis=1)
            Rm, tm = triangle_motions(fields[chunk[:, None, None], unit_faces[None]], rest)   # (chunk, units, …)
            idx = np.searchsorted(units, medoids[:, found[s:s + step]].T)                    # (chunk, L)
            pick = np.arange(len(chunk))[:, None]
            R[chunk], t[chunk] = Rm[pick, idx], tm[pick, idx]
        if near is None:
            seg.nearest_field = {key: found}      # one entry: a fit asks for one set of fields
    return R, t


def stage_segment(st: FitState) -> None:
    """segment (§5, docs/method_notes.md §2–§5): ``labels (T,)`` and the link medoids for k links from the
    Segmenter (ν Eq. 4, ε Eq. 5, average linkage cut to k, seam split and Λ merge, §5.2)."""
    st.fields = select_fields(st.scan.fields(), st.field_idx)
    st.labels_valid, st.medoids, st.used_fields = st.seg.segment(st.links, fields=st.seg_fields)
    st.labels = st.seg.full_labels(st.labels_valid)
    st.n_links = int(st.labels.max()) + 1


def stage_motions(st: FitState) -> None:
    """link motions (§6): ``R (P, L, 3, 3)``, ``t (P, L, 3)`` by :func:`link_motions`."""
    st.R, st.t = link_motions(st.scan.vertices, st.fields, st.scan.faces, st.labels, st.n_links, st.motion,
                              st.seg, st.medoids, st.used_fields, st.field_idx)


def stage_relabel(st: FitState) -> None:
    """relabel (docs/method_notes_model.md §6, a deviation for tracked scans): faces to the link that dominates
    their skin, link swaps, then the links' motions again; ``labels (T,)``, ``R``, ``t``.
    Green's scans keep the paper's segmentation."""
    scan, seg, L, P = st.scan, st.seg, st.n_links, len(st.field_idx)
    st.swaps = 0
    if not (scan.kind != "greens" and L > 1 and P > 0):
        return
    # only the labels leave this stage: its decompositions may run on a sample of the fields
    pick = _trial_fields(st)
    new, st.swaps = _merge.dominant_labels(scan.vertices, st.fields[pick], scan.faces, st.labels, st.R[pick],
                                           st.t[pick], units=seg.valid[seg.unit_tri])
    if np.any(new != st.labels):
        relabelled(st, new)


def _trial_fields(st: FitState):
    """The fields the relabelling's and the split trials' decompositions use: a spread of at most
    ``skinning.SAMPLE_FIELDS`` of them (:func:`skinning.field_sample`) as an
    index array, or ``slice(None)`` for every field; chosen once per fit."""
    if st.trial_fields is None:
        fsel = field_sample(st.fields)
        st.trial_fields = slice(None) if fsel is None else fsel
    return st.trial_fields


def _n_trial_fields(st: FitState) -> int:
    """How many fields the trials' decompositions use (:func:`_trial_fields`)."""
    pick = _trial_fields(st)
    return st.fields.shape[0] if isinstance(pick, slice) else len(pick)


def relabelled(st: FitState, labels: np.ndarray) -> None:
    """New ``labels (T,)``: the links' medoid units and their robust motions again (relabel, split)."""
    seg = st.seg
    st.labels = labels
    if st.motion != "lsq":
        st.medoids = _merge.link_medoids([seg.features[p] for p in st.used_fields], seg.weights[st.used_fields],
                                         st.labels[seg.valid][seg.unit_tri], st.n_links, unit_size=seg.unit_size)
    stage_motions(st)


def _refined_skin(st: FitState, R: np.ndarray, t: np.ndarray, w_init: np.ndarray | None = None) -> None:
    """The refined skin from link motions ``R``, ``t`` (every field): its decomposition on the vertex
    sample, polished on every vertex (:func:`skinning.alternate`); ``weights``, ``Rs``, ``ts``."""
    x0, faces = st.scan.vertices, st.scan.faces
    rows = vertex_sample(faces, st.labels, x0.shape[0])
    st.weights, st.Rs, st.ts = alternate(x0, st.fields, faces, st.labels, R, t, w_init=w_init, rows=rows)


def stage_skin(st: FitState) -> None:
    """skin (§7, docs/method_notes_model.md §8): ``weights (N, L)``. ``"seam"``: the paper's linear blend across
    each seam's one-ring. ``"refined"``: the skin decomposition (convex per-vertex weights, at
    most 4 influences) with its own link motions ``Rs (P, L, 3, 3)``, ``ts (P, L, 3)``.

    Why before the joints: where a short link is blended with its neighbours on every vertex (a
    finger's first segment) its robust motion is itself a blend and a joint fitted to it lands off
    the true centre; the decomposition's motions are the ones whose blend explains those
    vertices, so joints are fitted to them unless the robust motions already share an exact
    joint (:func:`joint_of`). The pose parameters and the reported link motions are then the
    decomposition's (bone offsets absorb what the joints do not explain), so its weights stay valid.
    """
    x0, faces = st.scan.vertices, st.scan.faces
    if st.skin == "refined":
        _refined_skin(st, st.R, st.t)
    else:
        st.Rs = st.ts = None
        st.weights = blend_weights(x0, faces, st.labels, st.n_links)


def stage_split(st: FitState) -> None:
    """split (an addition to the paper, for tracked scans with the refined skin): links holding two
    bones are cut in two and the link the skin misses least dropped while the decomposition error
    falls (:func:`splits.split_links`); then, as after the relabel, the links' robust motions of
    the new labels and the skin again (from the split's motions). ``labels``, ``R``, ``t``,
    ``weights``, ``Rs``, ``ts``; ``splits`` counts the kept splits. Scans above the swaps' budget
    (``swaps.SWAP_BUDGET`` vertices × the fields the trials use, at most ``skinning.SAMPLE_FIELDS``),
    scans with support vertices and Green's scans are not split. Last, on every tracked scan with
    the refined skin, the faces follow the skin the rig keeps (:func:`_dominant_skin_labels`).

    The stage runs again (at most ``SPLIT_PASSES`` passes in all) while the skin the rig keeps uses a
    link as a blend, not as a part: its own weight dominates under ``splits.DOMINATED_SHARE`` of its
    faces (:func:`linkcheck.dominated_share`). The skin decomposed after a kept split is not the
    split's, and following it can hand such a link's faces to its neighbours; with fewer poses that
    left two finger bones in one link and the spare link a blend beside them (RobotExpressive, 16
    fresh poses of 10-40° a joint, seed 3: the split stage ended with one pair merged, the faces
    following the final skin shrank three links to 3-6 faces and merged three pairs; a second
    pass, whose drop candidates include that blend link, found every joint). The skin is judged on the
    labels before the faces follow it as well as after: on 12 poses, seed 1000, no split was kept and
    following the skin shrank a link from 22 faces to 7 (32 % of its faces dominated by its own weight
    before) and put two finger bones in one link (28/30); the second pass finds 30/30. A fit whose
    kept skin has no blend link runs one pass."""
    _split_links(st)
    blend = _has_blend_link(st)
    _dominant_skin_labels(st)
    total = st.splits
    for _ in range(SPLIT_PASSES - 1):
        if not (blend or _has_blend_link(st)):
            break
        _split_links(st)
        if not st.splits:
            break
        total += st.splits
        blend = _has_blend_link(st)
        _dominant_skin_labels(st)
    st.splits = total


#: passes of the split stage at most (:func:`stage_split`)
SPLIT_PASSES = 3


def _has_blend_link(st: FitState) -> bool:
    """Does the refined skin use a link as a blend (its weight dominating under ``splits.DOMINATED_SHARE``
    of its own faces)?"""
    if st.skin != "refined" or st.weights is None or st.n_links < 3:
        return False
    share, _ = _linkcheck.dominated_share(st.weights, st.scan.faces, st.labels, st.n_links)
    n = np.bincount(st.labels, minlength=st.n_links)
    return bool(np.any((n > 0) & (share < _splits.DOMINATED_SHARE)))


def _dominant_skin_labels(st: FitState) -> None:
    """Every face to the link that dominates the final skin (:func:`merge.dominant_faces`), the
    relabelling's rule applied once more to the skin the rig keeps: the split's and the
    relabelling's last labels come from earlier decompositions, and on a blended finger chain they
    can leave a seam half a bone off where the final skin puts it (on RobotExpressive's fingers that
    loses a finger joint). The skin and its motions stay as they are
    (the decomposition does not depend on the labels, only its candidate links do); the links'
    robust motions follow the new labels."""
    if not (st.skin == "refined" and st.scan.kind != "greens" and st.n_links > 1
            and st.fields.shape[0] > 0):
        return
    new = _merge.dominant_faces(st.weights, st.scan.faces, st.labels, units=st.seg.valid[st.seg.unit_tri],
                                keep_units_only=True)
    if np.any(new != st.labels):
        relabelled(st, new)


def _split_links(st: FitState) -> None:
    """The split of :func:`stage_split` (:func:`splits.split_links`) and the skin after it."""
    scan, seg, L = st.scan, st.seg, st.n_links
    st.splits = 0
    # a scan with support vertices: the decomposition has no world link, so part of its error is the
    # support's blend that no split can explain (a split would then cut a rod's true partition).
    # The budget is the relabelling's swaps' (:func:`merge.dominant_labels`), on the fields the trials use:
    # a scan given more poses than the sample keeps its split stage as it keeps its swaps
    if not (st.skin == "refined" and scan.kind != "greens" and L > 2 and st.fields.shape[0] > 0
            and scan.support_vertices is None
            and _swaps.within_budget(scan.n_vertices, _n_trial_fields(st))):
        return
    x0, faces = scan.vertices, scan.faces
    # the trials decide labels only where the scan has many fields: then on a spread of them, and
    # the skin is decomposed again on every field from the new labels' robust motions
    pick = _trial_fields(st)
    labels, w, Rs, ts, st.splits = _splits.split_links(x0, st.fields[pick], faces, st.labels, st.weights,
                                                       st.Rs[pick], st.ts[pick], units=seg.valid[seg.unit_tri])
    if not st.splits:
        return
    relabelled(st, labels)
    if isinstance(pick, slice):     # from the split's own decomposition
        _refined_skin(st, Rs, ts, w_init=w)
    else:                # the split's motions cover the sampled fields only: from the robust ones
        _refined_skin(st, st.R, st.t)


def joint_of(R, t, Rs, ts, a, b, c_ref, diag):
    """Joint ``(c (3,), rms, rank)`` of links ``a`` and ``b`` (``b`` None: the fixed world) from
    the motions ``R (P, L, 3, 3)``, ``t (P, L, 3)`` (§4, §6) when they share an exact joint (to
    round-off, :data:`EXACT_JOINT`), else from the refined skin's ``Rs``, ``ts`` (if any)."""
    P = R.shape[0]
    I3, Z3 = np.tile(np.eye(3), (P, 1, 1)), np.zeros((P, 3))
    Ra, ta, Rb, tb = R[:, a], t[:, a], *((I3, Z3) if b is None else (R[:, b], t[:, b]))
    c, rms, rank = _joints.fit_joint(Ra, ta, Rb, tb, c_ref)
    if Rs is None or rms <= EXACT_JOINT * diag:
        return c, rms, rank
    Ra, ta = Rs[:, a], ts[:, a]
    if b is not None:
        Rb, tb = Rs[:, b], ts[:, b]
    return _joints.fit_joint(Ra, ta, Rb, tb, c_ref)


def stage_joints(st: FitState) -> None:
    """joints and tree (§4, §6): a joint per pair of links (seam mean as reference for adjacent
    ones) and per link with the support, the minimum spanning tree over joint RMS preferring
    adjacent pairs (rooted at the ground, else the largest link), the root's world joint when
    it fits. Sets ``parents (L,)``, ``joints (L, 3)``, ``joint_errors (L,)``, ``grounded (L,)``,
    ``centroid (L, 3)``, ``link_vids``, ``diag``."""
    x0, faces, labels, L = st.scan.vertices, st.scan.faces, st.labels, st.n_links
    R, t, Rs, ts = st.R, st.t, st.Rs, st.ts
    # adjacency of links (shared vertices) and seam reference points
    N = x0.shape[0]
    inc = np.zeros((N, L))
    np.add.at(inc, (faces.reshape(-1), np.repeat(labels, 3)), 1.0)
    inc = (inc > 0).astype(np.float64)
    shared = inc.T @ inc
    seam_sum = np.einsum("na,nb,nd->abd", inc, inc, x0)
    areas = 0.5 * np.linalg.norm(np.cross(x0[faces[:, 1]] - x0[faces[:, 0]],
                                          x0[faces[:, 2]] - x0[faces[:, 0]]), axis=1)
    centroid = np.zeros((L, 3))
    link_vids = [np.unique(faces[labels == l]) for l in range(L)]
    for l in range(L):
        m = labels == l
        w = areas[m]
        c = x0[faces[m]].mean(axis=1)
        centroid[l] = (w[:, None] * c).sum(0) / w.sum() if w.sum() > 0 else c.mean(0)
    diag = float(np.linalg.norm(np.ptp(x0, axis=0)))
    support = st.scan.support_vertices
    G = L  # ground node index
    nodes = L + (1 if support is not None else 0)
    edges, costs, pref, centres = [], [], [], []
    for a in range(L):
        for b in range(a + 1, L):
            adj = shared[a, b] > 0
            c_ref = seam_sum[a, b] / shared[a, b] if adj else 0.5 * (centroid[a] + centroid[b])
            c, rms, _ = joint_of(R, t, Rs, ts, a, b, c_ref, diag)
            edges.append((a, b)); costs.append(rms); pref.append(adj); centres.append(c)
    if support is not None:
        sup_in = inc[support].sum(axis=0) > 0
        for a in range(L):
            sv = support[inc[support, a] > 0] if sup_in[a] else support
            c, rms, _ = joint_of(R, t, Rs, ts, a, None, x0[sv].mean(axis=0), diag)
            edges.append((a, G)); costs.append(rms); pref.append(bool(sup_in[a])); centres.append(c)
    edges = np.array(edges, dtype=np.int64).reshape(-1, 2)
    costs = np.array(costs)
    pref = np.array(pref, dtype=bool)
    centres = np.array(centres).reshape(-1, 3)
    sizes = np.bincount(labels, minlength=L)
    root = G if support is not None else int(np.argmax(sizes))
    parents_all = _joints.spanning_tree(nodes, edges, costs, pref, root)
    lookup = {(int(a), int(b)): i for i, (a, b) in enumerate(edges)}
    parents = np.full(L, -1, dtype=np.int64)
    joint = np.full((L, 3), np.nan)
    jerr = np.full(L, np.nan)
    grounded = np.zeros(L, dtype=bool)
    for l in range(L):
        p = int(parents_all[l])
        if p < 0:
            continue
        i = lookup[(min(l, p), max(l, p))]
        joint[l] = centres[i]
        jerr[l] = costs[i]
        if p == G and support is not None:
            grounded[l] = True
        else:
            parents[l] = p
    if support is None:
        # the root's joint with the fixed world frame, reported when it fits (paper's Joint 1)
        r = root
        c, rms, rank = joint_of(R, t, Rs, ts, r, None, centroid[r], diag)
        tree_err = jerr[np.isfinite(jerr)]
        tol = max(2.0 * (tree_err.max() if tree_err.size else 0.0), 1e-6 * diag)
        if rms <= tol and rank > 0:
            joint[r] = c
            jerr[r] = rms
            grounded[r] = True
    st.centroid, st.link_vids, st.diag = centroid, link_vids, diag
    st.parents, st.joints, st.joint_errors, st.grounded = parents, joint, jerr, grounded


def stage_bones(st: FitState) -> None:
    """bones (§7): ``heads``, ``tails (L, 3)`` and rest ``frames (L, 3, 3)`` by :func:`_bones`."""
    st.heads, st.tails, st.frames = _bones(st.scan.vertices, st.scan.faces, st.labels, st.parents, st.joints,
                                           st.centroid, st.diag)


def stage_pose(st: FitState) -> None:
    """pose model (§7, docs/method_notes_model.md §7): pose parameters ``params (P, L, 6)`` from the link
    motions (the refined skin's when it ran), the rig's motions ``Rf``, ``tf`` by forward kinematics, and the
    link motions reported ``Ro``, ``to`` (the ones the rig reproduces)."""
    R, t = (st.R, st.t) if st.Rs is None else (st.Rs, st.ts)
    st.params = _model.params_from_motions(st.parents, st.heads, st.frames, st.grounded, R, t)
    st.Rf, st.tf = _model.forward_kinematics(st.parents, st.heads, st.frames, st.params)
    st.Ro, st.to = R, t


def stage_residuals(st: FitState) -> None:
    """residuals (§7, docs/method_notes_model.md §9–§10): rest-space residual ``(P, N, 3)``, each link's own rigid
    RMS ``(P, L)``, the articulation and total RMS and the Karni–Gotsman figures
    (docs/metrics.md). Blocks of fields at once (:data:`RESIDUAL_BLOCK_BYTES`): the skin of a
    field is its blended transform B_v x + T_v, B_v = Σ_l w_vl R_l (N, 3, 3), T_v = Σ_l w_vl t_l,
    two matrix products for the whole block."""
    x0, fields, weights, L = st.scan.vertices, st.fields, st.weights, st.n_links
    P, N = len(st.field_idx), x0.shape[0]
    residual = np.zeros((P, N, 3))
    art_err = np.zeros(P)
    tot_err = np.zeros(P)
    link_res = np.zeros((P, L))
    step = max(1, int(RESIDUAL_BLOCK_BYTES // (8 * 9 * 4 * max(N, 1))))
    for s in range(0, P, step):
        c = slice(s, min(P, s + step))
        x1 = x0[None] + fields[c]                                                   # (n, N, 3)
        B = _model.blended_linear(weights, st.Rf[c])                                  # Σ_l w_l R_l
        T = np.matmul(weights, st.tf[c])                                              # Σ_l w_l t_l
        art = np.einsum("pnij,nj->pni", B, x0) + T
        res = _model.blended_residual(B, x1 - art)
        back = art + np.einsum("pnij,pnj->pni", B, res)
        residual[c] = res
        art_err[c] = np.einsum("pni,pni->p", art - x1, art - x1)
        tot_err[c] = np.einsum("pni,pni->p", back - x1, back - x1)
        # rigid-motion residual of each link's own motion over its vertices (fit quality): a product a
        # link for the block's fields (gathering every (vertex, link) pair's rotation cost a quarter
        # of the stage)
        for l, v in enumerate(st.link_vids):
            if len(v):
                d = np.matmul(x0[v], np.swapaxes(st.Ro[c, l], -1, -2)) + st.to[c, l][:, None, :] - x1[:, v]
                link_res[c, l] = np.sqrt(np.einsum("pni,pni->p", d, d) / len(v))
    st.residual, st.link_residuals = residual, link_res
    st.rms_articulation = float(np.sqrt(art_err.sum() / (P * N)))
    st.rms_total = float(np.sqrt(tot_err.sum() / (P * N)))
    st.fidelity = _quality.fidelity(x0, fields, float(art_err.sum()))   # Karni–Gotsman, E_RMS


#: bytes of the blended transforms of one block of fields in :func:`stage_residuals`
RESIDUAL_BLOCK_BYTES = 32 * 2 ** 20


#: the fit's stages in order: (name for progress and ``FitResult.timings``, function of a FitState)
STAGES = (
    ("segment", stage_segment),
    ("motions", stage_motions),
    ("relabel", stage_relabel),
    ("skin", stage_skin),
    ("split", stage_split),
    ("joints", stage_joints),
    ("bones", stage_bones),
    ("pose", stage_pose),
    ("residuals", stage_residuals),
)


def run_stages(state: FitState, progress=None, stages=STAGES) -> dict:
    """Run ``stages`` on ``state`` in order; report each stage's name to ``progress`` as it
    starts (fraction 0; a True answer cancels: :class:`FitCancelled`). Returns the seconds
    per stage name."""
    timings = {}
    for name, stage in stages:
        _report(progress, name, 0.0)
        t0 = time.perf_counter()
        stage(state)
        timings[name] = time.perf_counter() - t0
    return timings


def to_result(st: FitState, timings: dict) -> FitResult:
    """The FitResult of a state all stages have run on."""
    scan, fid, N, P = st.scan, st.fidelity, st.scan.n_vertices, len(st.field_idx)
    res = FitResult(face_labels=st.labels, parents=st.parents, joints=st.joints, joint_errors=st.joint_errors,
                    heads=st.heads, tails=st.tails, frames=st.frames, grounded=st.grounded, weights=st.weights,
                    rotations=st.Ro, translations=st.to, angles=st.params[..., :3], locations=st.params[..., 3:],
                    residual=st.residual, link_residuals=st.link_residuals, rms_articulation=st.rms_articulation,
                    rms_total=st.rms_total, articulation_error_percent=fid.kg_percent, motion=st.motion,
                    timings=timings, probe_load=scan.probe_load, e_rms=fid.e_rms,
                    vertex_mean_error_percent=fid.vertex_mean_percent)
    if st.swaps is None:
        K = _n_trial_fields(st)
        res.notes.append(f"link swaps and splits skipped: {N:,} vertices × {K} fields"
                         + (f" (a spread of the {P})" if K < P else "")
                         + f" is above their budget of {_swaps.SWAP_BUDGET:,} (each trial re-runs the skin decomposition)")
    if st.swaps:
        res.notes.append(f"{st.swaps} link swap(s): links that explained little were re-seeded where the skin "
                         f"fitted worst (tracked scans)")
    if st.splits:
        res.notes.append(f"{st.splits} link split(s): a link holding two bones was cut in two and the link the skin "
                         f"missed least dropped (tracked scans)")
    if scan.kind == "greens":
        res.kappa = np.transpose(st.params, (1, 2, 0)) / scan.probe_load
        loads = np.asarray(st.field_idx) // 3
        res.load_vertices = scan.load_vertices[np.unique(loads)]
    return res


def _bones(x0, faces, labels, parents, joint, centroid, diag):
    """Bone head (joint, or link centroid for a free root), tail and rest frame per link."""
    L = len(parents)
    heads = np.where(np.isnan(joint).any(axis=1)[:, None], centroid, joint)
    tails = np.zeros((L, 3))
    frames = np.zeros((L, 3, 3))
    for l in range(L):
        h = heads[l]
        kids = np.flatnonzero(parents == l)
        vid = np.unique(faces[labels == l])
        pts = x0[vid]
        tail = None
        if kids.size:
            target = heads[kids].mean(axis=0)
            if np.linalg.norm(target - h) > 1e-3 * diag:
                tail = target
        if tail is None:
            q = pts - pts.mean(axis=0)
            axis = np.linalg.svd(q, full_matrices=False)[2][0] if len(pts) > 1 else np.array([0, 0, 1.0])
            if np.dot(centroid[l] - h, axis) < 0:
                axis = -axis
            length = float(np.max((pts - h) @ axis)) if len(pts) else 0.0
            if length < 1e-3 * diag:
                length = max(0.05 * diag, 1e-6)
            tail = h + axis * length
        tails[l] = tail
        y = (tail - h) / np.linalg.norm(tail - h)
        zref = np.array([0.0, 0.0, 1.0]) if abs(y[2]) < 0.99 else np.array([0.0, -1.0, 0.0])
        z = zref - y * np.dot(zref, y)
        z /= np.linalg.norm(z)
        x = np.cross(y, z)
        frames[l] = np.stack([x, y, z], axis=1)
    return heads, tails, frames


def new_state(seg: Segmenter, links: int, motion: str, skin: str) -> FitState:
    """The state a fit of ``links`` links over every field starts from."""
    return FitState(scan=seg.scan, seg=seg, links=links, motion=motion, skin=skin,
                    field_idx=list(range(seg.scan.n_fields)))

