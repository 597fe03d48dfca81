"""The :class:`Segmenter`: what a fit of a scan can reuse across link counts (paper §5.2).

Per field and triangle the motion ν (Eq. 4) and what ε (Eq. 5) needs; per field (or over the
summed fields) the average-linkage tree; ``segment(k)`` cuts the trees to k links, splits them
along the seams and merges them on Λ, then refines the seams.
"""
from __future__ import annotations

import contextlib
import time

import numpy as np

from . import clustering
from . import cost as _cost
from . import merge as _merge
from . import patches as _patches
from . import procs as _procs
from .blas import single_threaded
from .metric import field_features, rest_geometry
from .parallel import neighbour_stream
from .result import FitCancelled, report as _report
from .scan import Scan, ScanError, is_checked
from .skinning import field_sample

#: tracked scans with more fields are segmented on this many of them (:func:`skinning.field_sample`)
SEGMENT_FIELDS = 64

STRATEGIES = ("summed", "paper")  # "auto": paper for Green's scans, summed for tracked ones

class Segmenter:
    """Distances and clustering trees of a scan, cached so that the link count can change.

    ``labels(k)`` re-cuts the cached trees and re-runs split and merge; the pairwise distances
    are computed once (the expensive O(T²) stage).

    Two strategies:

    * ``"paper"`` — §5.2 as written: an average-linkage tree per field, each cut to k, the
      surface split along every seam of every field, the pieces merged on Λ (two levels for a
      Green's scan: per block column, then across columns).
    * ``"summed"`` — one average-linkage tree over Σ_p w_p ε_p, the fields' distances
      on the unit scale of §5.3 summed, cut to k, split into connected pieces and merged on Λ as
      above. One linkage instead of P, streamed over fields (memory: one condensed matrix), and
      measurably better on smoothly skinned characters (docs/method.md, "Deviations from the paper").

    ``"auto"`` (default) uses the paper's two levels for Green's scans — there a field that only
    dents the surface near its load would dominate a plain sum — and the sum for tracked scans.
    Both end with the seam refinement of :func:`merge.refine_seams` unless ``refine_seams=False``.
    """

    def __init__(self, scan: Scan, progress=None, refine_seams: bool = True, strategy: str = "auto",
                 reduce: bool | None = None, budget: float = _cost.DEFAULT_BUDGET, max_units: int | None = None):
        with single_threaded():    # small products (see :func:`pipeline.fit`)
            self._build(scan, progress, refine_seams, strategy, reduce, budget, max_units)

    def _build(self, scan, progress, refine_seams, strategy, reduce, budget, max_units):
        if strategy not in STRATEGIES + ("auto",):
            raise ScanError(f"strategy must be one of {STRATEGIES + ('auto',)}, got {strategy!r}")
        if not is_checked(scan):     # checked where it entered (artdef_addon.fit, load_scan, samples)
            raise ScanError("the Segmenter takes a checked scan (scan.validate_scan, artdef_addon.load_scan)")
        if strategy == "auto":
            strategy = "paper" if scan.kind == "greens" else "summed"
        self.refine = refine_seams
        self.strategy = strategy
        self.overcut = 1.5
        self.scan = scan
        self.progress = progress
        # distance sums of clusters, reused when the same scan is segmented again (link sweeps);
        # filled from the second segmentation on, so a single fit holds no extra memory
        self.sum_cache = _merge.SumCache()
        # each unclustered field's nearest clustered field (link_motions), by the fields' ids
        self.nearest_field = {}
        self._segmentations = 0
        self._remembered = None      # (k, fields) -> segment()'s answer, inside remembering()
        self.notes = []
        T = scan.n_faces
        bad = np.zeros(T, dtype=bool)
        bad[scan.degenerate_faces] = True
        self.valid = np.flatnonzero(~bad)
        self.faces = scan.faces[self.valid]
        x0 = scan.vertices
        self.timings = {}
        t0 = time.perf_counter()
        fields = scan.fields()
        # a tracked scan with many fields is segmented on a spread of them (its consecutive frames
        # repeat each other); every field's link motions still come from the links' medoid units
        self.clustered = np.arange(scan.n_fields)
        # about 2,000 triangles' vertices: enough to tell poses apart by their displacements
        self.probe = np.unique(self.faces[:: max(1, len(self.valid) // 2000)])
        if scan.kind != "greens" and SEGMENT_FIELDS and scan.n_fields > SEGMENT_FIELDS:
            self.clustered = field_sample(fields, SEGMENT_FIELDS, rows=self.probe)
        self.tri_adjacency = clustering.face_adjacency(self.faces)
        Tv = len(self.valid)
        pool = _procs.current()
        est = _cost.estimate(Tv, scan.n_fields, scan.n_vertices, strategy, budget,
                             jobs=1 if pool is None else pool.jobs)
        self.estimate = est
        if reduce is None:
            reduce = est.reduced
            need = _cost.full_memory(Tv, scan.n_fields, scan.n_vertices)
            if reduce and need > budget:
                self.notes.append(f"the full method needs about {_cost.format_bytes(need)} "
                                  f"(budget {_cost.format_bytes(budget)}): using the reduced method on patches")
        self.reduced = bool(reduce)
        self.unit_size = None  # triangles per clustered unit (reduced method: patch sizes)
        if not self.reduced:
            self.features = [None] * scan.n_fields
            rest = rest_geometry(x0, self.faces)
            for i, p in enumerate(self.clustered):
                _report(progress, "features", i / len(self.clustered))
                self.features[p] = field_features(x0, fields[p], self.faces, rest)
            del rest
            self.weights = np.zeros(scan.n_fields)
            self.weights[self.clustered] = _merge.field_weights([self.features[p] for p in self.clustered])
            self.unit_of = np.arange(Tv)
            self.unit_tri = np.arange(Tv)
            self.adjacency = self.tri_adjacency
        else:
            self._build_patches(x0, fields, max_units or _cost.reduced_units(budget, scan.n_fields))
        if scan.kind == "greens":
            self.groups = [[3 * k, 3 * k + 1, 3 * k + 2] for k in range(scan.n_loads)]
        else:
            self.groups = [[int(p)] for p in self.clustered]
        self.timings["features"] = time.perf_counter() - t0
        self._trees = {}

    def _build_patches(self, x0, fields, max_units):
        """Reduced method (see :mod:`patches`): units are patch representatives."""
        P = self.scan.n_fields
        Tv = len(self.valid)
        weights = np.zeros(P)
        rest = rest_geometry(x0, self.faces)
        clustered = self.clustered
        Pc = len(clustered)

        def stream():
            # one field at a time, or a few in flight on the fit's pool (:mod:`parallel`)
            fields_d = neighbour_stream(x0, fields, self.faces, rest, self.tri_adjacency, clustered,
                                        lambda i: _report(self.progress, "features", 0.5 * i / Pc))
            for p, (d, z) in zip(clustered, fields_d):
                weights[p] = 1.0 / z if z > 1e-300 else 0.0
                yield weights[p] * d

        centroids = x0[self.faces].mean(axis=1)
        size = max(2, int(np.ceil(4.0 * Tv / max_units)))
        labels, reps = _patches.make_patches(stream(), Tv, self.tri_adjacency, centroids, size, max_units)
        self.weights = weights
        self.unit_of = labels
        self.unit_tri = reps
        self.unit_size = np.bincount(labels, minlength=len(reps)).astype(np.float64)
        a = labels[self.tri_adjacency]
        a = a[a[:, 0] != a[:, 1]]
        self.adjacency = np.unique(np.sort(a, axis=1), axis=0)
        del rest
        self.features = [None] * P
        rest = rest_geometry(x0, self.faces[reps])
        for i, p in enumerate(clustered):
            _report(self.progress, "features", 0.5 + 0.5 * i / Pc)
            self.features[p] = field_features(x0, fields[p], self.faces[reps], rest)
        self.notes.append(f"reduced method: {len(reps)} patches of at most {size} triangles "
                          f"(from {Tv} triangles)")

    def summed_tree(self, fields) -> np.ndarray:
        """Average-linkage tree of Σ_p w_p ε_p over ``fields`` (cached per field set)."""
        key = ("sum",) + tuple(fields)
        if key not in self._trees:
            t0 = time.perf_counter()
            acc = None
            for i, p in enumerate(fields):
                _report(self.progress, "distances", i / len(fields))
                acc = clustering.condensed_distance(self.features[p], out=acc, accumulate=self.weights[p])
            _report(self.progress, "cluster", 0.0)
            self._trees[key] = clustering.linkage(acc, method="average") if len(self.unit_tri) > 1 \
                else np.zeros((0, 4))
            del acc
            self.timings["cluster"] = self.timings.get("cluster", 0.0) + time.perf_counter() - t0
        return self._trees[key]

    def tree(self, p: int) -> np.ndarray:
        if p not in self._trees:
            self._trees[p] = clustering.field_linkage(self.features[p])
        return self._trees[p]

    def _ensure_trees(self, fields):
        t0 = time.perf_counter()
        todo = [p for p in fields if p not in self._trees and self.weights[p] > 0]
        for i, p in enumerate(todo):
            _report(self.progress, "cluster", i / max(len(todo), 1))
            self.tree(p)
        self.timings["cluster"] = self.timings.get("cluster", 0.0) + time.perf_counter() - t0

    def _merge(self, init, fields, k, stage):
        feats = [self.features[p] for p in fields]
        w = self.weights[fields]
        cb = None if self.progress is None else (lambda f: self.progress(stage, f))
        try:
            return _merge.merge_clusters(feats, w, init, k, progress=cb, unit_size=self.unit_size,
                                         cache=self._cache(), tag=_merge.member_key(np.asarray(fields)))
        except _merge.MergeCancelled:
            raise FitCancelled(f"cancelled during {stage}") from None

    def _cache(self):
        return self.sum_cache if self._segmentations > 1 else None

    def _check_k(self, k):
        if k < 1:
            raise ScanError(f"the number of links must be at least 1, got {k}")
        if k > len(self.valid):
            raise ScanError(f"more links requested ({k}) than triangles ({len(self.valid)})")
        if k > len(self.unit_tri):
            raise ScanError(f"more links requested ({k}) than patches of the reduced method "
                            f"({len(self.unit_tri)}); raise the memory budget")

    @contextlib.contextmanager
    def remembering(self):
        """Within the block, :meth:`segment` computes each ``(k, fields)`` once (a link-count
        search segments every count up to Max Links for its curve, and its whole fits ask for the
        same counts again: the merge, the links' medoids and the seam refinement, about a tenth of a
        fit each). A segmentation does not depend on what was segmented before, so the answers are
        the same; every caller gets its own copies. Nested blocks share the outer one's memory."""
        if self._remembered is not None:
            yield self
            return
        self._remembered = {}
        try:
            yield self
        finally:
            self._remembered = None

    def segment(self, k: int, fields=None):
        """Links over ``fields`` (default all): ``(labels (Tv,), medoids (k, P_sel), fields)``.

        One level over all fields for tracked scans; for a Green's scan two levels: each block
        column's three fields, then the union of their seams merged over all fields (A-9).
        Inside :meth:`remembering`, each ``(k, fields)`` is computed once.
        """
        memo = self._remembered
        if memo is None:
            return self._segment(k, fields)
        key = (int(k), None if fields is None else tuple(int(p) for p in fields))
        if key not in memo:
            memo[key] = self._segment(k, fields)
        lab, med, used = memo[key]
        return lab.copy(), med.copy(), list(used)

    def segment_fields(self, fields=None) -> list:
        """The fields a segmentation over ``fields`` (default all) clusters: those that move the mesh."""
        groups = self.groups if fields is None else [list(fields)]
        all_fields = [p for g in groups for p in g if self.weights[p] > 0]
        if not all_fields:
            raise ScanError("too few fields: no field moves the mesh")
        return all_fields

    def _segment(self, k: int, fields=None):
        """:meth:`segment` without the memory."""
        self._check_k(k)
        self._segmentations += 1
        groups = self.groups if fields is None else [list(fields)]
        all_fields = self.segment_fields(fields)
        n = len(self.unit_tri)
        if self.strategy == "summed":
            Z = self.summed_tree(all_fields)
            t0 = time.perf_counter()
            # over-cut, so that stray small clusters at the top of the tree are absorbed by the
            # size-weighted merge instead of costing a link
            k_cut = min(n, int(np.ceil(self.overcut * k)))
            init = clustering.split(clustering.cut(Z, n, k_cut)[None], self.adjacency)
            return self._finish(init, all_fields, k, t0)
        self._ensure_trees(all_fields)
        t0 = time.perf_counter()
        cuts = {p: clustering.cut(self._trees[p], n, k) for p in all_fields}
        if len(groups) > 1 and any(len(g) > 1 for g in groups):
            level1 = []
            for gi, g in enumerate(groups):
                gf = [p for p in g if self.weights[p] > 0]
                if not gf:
                    continue
                init = clustering.split(np.stack([cuts[p] for p in gf]), self.adjacency)
                lab, _, _ = self._merge(init, gf, min(k, len(np.unique(init))), f"merge column {gi}")
                level1.append(lab)
            init = clustering.split(np.stack(level1), self.adjacency)
        else:
            init = clustering.split(np.stack([cuts[p] for p in all_fields]), self.adjacency)
        return self._finish(init, all_fields, k, t0)

    def _finish(self, init, all_fields, k, t0):
        """Merge units to k links, take their motion centroids, refine seams per triangle.

        Returns ``(labels over the clustered triangles, medoids (k, P) as unit indices, fields)``.
        """
        labels_u, medoids, sums = self._merge(init, all_fields, k, "merge")
        k = medoids.shape[0]
        feats = [self.features[p] for p in all_fields]
        tag = _merge.member_key(np.asarray(all_fields))
        # the links the seams' refinement leaves as they were keep their medoids (a link's medoids
        # depend on its members only), also in a Segmenter's first segmentation
        cache = self._cache()
        if cache is None:
            cache = _merge.SumCache()
        medoids = _merge.link_medoids(feats, self.weights[all_fields], labels_u, k, unit_size=self.unit_size,
                                      cache=cache, tag=tag)
        labels = labels_u[self.unit_of]
        if self.refine:
            R = np.stack([self.features[p].R[medoids[:, i]] for i, p in enumerate(all_fields)])
            t = np.stack([self.features[p].t[medoids[:, i]] for i, p in enumerate(all_fields)])
            labels = _merge.refine_seams(self.scan.vertices, select_fields(self.scan.fields(), all_fields), self.faces,
                                         R, t, self.weights[all_fields], labels, self.tri_adjacency,
                                         fixed=self.unit_tri[np.unique(medoids)],
                                         iterations=200 if self.reduced else 10, cache=self._cache(), tag=tag)
            medoids = _merge.link_medoids(feats, self.weights[all_fields], labels[self.unit_tri], k,
                                          unit_size=self.unit_size, cache=cache, tag=tag)
        self.timings["merge"] = self.timings.get("merge", 0.0) + time.perf_counter() - t0
        return labels, medoids, all_fields

    def labels(self, k: int, fields=None) -> np.ndarray:
        """Face labels (T,) for ``k`` links, degenerate triangles taking their neighbours' link."""
        lab, _, _ = self.segment(k, fields)
        return self.full_labels(lab)

    def full_labels(self, lab_valid: np.ndarray) -> np.ndarray:
        T = self.scan.n_faces
        out = np.full(T, -1, dtype=np.int64)
        out[self.valid] = lab_valid
        if len(self.valid) < T:
            adj = clustering.face_adjacency(self.scan.faces)
            for _ in range(T):
                missing = out < 0
                if not missing.any():
                    break
                a, b = adj[:, 0], adj[:, 1]
                src = np.concatenate([b[missing[a] & ~missing[b]], a[missing[b] & ~missing[a]]])
                dst = np.concatenate([a[missing[a] & ~missing[b]], b[missing[b] & ~missing[a]]])
                if src.size == 0:
                    out[missing] = 0
                    break
                # majority of labelled neighbours: take the most frequent (dst, label) pair
                pairs = np.unique(np.stack([dst, out[src]], 1), axis=0, return_counts=True)
                keys, counts = pairs
                order = np.lexsort((-counts, keys[:, 0]))
                keys = keys[order]
                first = np.unique(keys[:, 0], return_index=True)[1]
                out[keys[first, 0]] = keys[first, 1]
        return out


def select_fields(fields: np.ndarray, idx) -> np.ndarray:
    """``fields[idx]`` without a copy when ``idx`` is every field in order (a P·N·3 copy at scale)."""
    idx = list(idx)
    if idx == list(range(fields.shape[0])):
        return fields
    return fields[idx]

