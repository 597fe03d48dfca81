"""Scale: cost estimate, the reduced method on patches, streaming over fields."""
import numpy as np

from artdef_addon import cost, patches, quality, samples
import artdef_addon
from artdef_addon import pipeline as PL, segmenter as SG


def test_estimate_switches_to_reduced_above_budget():
    small = cost.estimate(2000, 20, 1000)
    assert not small.reduced and small.memory_bytes < cost.DEFAULT_BUDGET
    big = cost.estimate(1_000_000, 20, 500_000)
    assert big.reduced and big.units <= cost.MAX_UNITS
    assert big.memory_bytes < 4 * 2 ** 30
    assert "reduced method" in big.describe()
    # the full method's condensed matrix alone: 8·T(T−1)/2 bytes, twice
    assert cost.full_memory(20000, 1, 0) >= 2 * 8 * 20000 * 19999 / 2


def test_reduced_method_is_chosen_for_speed_and_the_estimate_prices_the_fit():
    # more than 2x the patches it would use: patches (CesiumMan's size), unless the reduced
    # method is switched off (unbounded budget); a small scan keeps every triangle
    assert cost.estimate(4672, 20, 2338).reduced
    assert not cost.estimate(4672, 20, 2338, budget=float("inf")).reduced
    assert not cost.estimate(1500, 20, 800).reduced
    assert cost.estimate(1504, 400, 754).reduced  # 400 fields: fewer patches, so earlier
    # tracked scans pay the articulation stage (more with more links); links auto several fits
    few, many = cost.estimate(4672, 20, 2338, links=5), cost.estimate(4672, 20, 2338, links=30)
    assert many.seconds > few.seconds
    # links auto: the tree's curve (a segmentation a count, up to max_links) and a few whole fits
    auto = cost.estimate(4672, 20, 2338, links=30, auto=True)
    assert auto.seconds > cost.AUTO_WHOLE_FITS * many.seconds
    assert cost.estimate(4672, 20, 2338, links=30, auto=True, max_links=60).seconds > auto.seconds
    assert auto.memory_bytes > many.memory_bytes     # the whole fits it keeps
    greens = cost.estimate(4672, 20, 2338, strategy="paper", links=30)
    assert greens.seconds < many.seconds


def test_estimate_time_reads_as_a_duration():
    """The estimate's time as the command line and the panel print it: no "0 s" for a fit that
    takes a fraction of a second, and none for a search of minutes."""
    assert cost.format_seconds(0.3) == "under 1 s"
    assert cost.format_seconds(45.4) == "45 s"
    assert cost.format_seconds(750.0) == "12 min"
    assert cost.format_seconds(9000.0) == "2.5 h"
    assert cost.estimate(584, 3, 297).describe().endswith("peak, under 1 s")


def test_reduced_method_agrees_with_full():
    scan, truth = samples.branching(noise=0.02, bulges=True)
    full = artdef_addon.fit(scan, 11)
    seg = SG.Segmenter(scan, reduce=True, max_units=300)
    assert seg.reduced and len(seg.unit_tri) <= 300
    assert any("reduced method" in n for n in seg.notes)
    red = PL.fit(scan, 11, None, segmenter=seg)
    assert quality.adjusted_rand_index(red.face_labels, full.face_labels) >= 0.99
    assert quality.adjusted_rand_index(red.face_labels, truth["face_labels"]) >= 0.99
    diag = np.linalg.norm(np.ptp(scan.vertices, axis=0))
    m = quality.match_links(red.face_labels, truth["face_labels"])
    for l in range(11):
        if truth["parents"][m[l]] >= 0:
            assert np.linalg.norm(red.joints[l] - truth["joints"][m[l]]) < 0.01 * diag


def test_auto_reduce_on_small_budget_says_so():
    scan = samples.make("branching")
    seg = SG.Segmenter(scan, budget=2 ** 20)
    assert seg.reduced and "reduced method" in " ".join(seg.notes)


def test_patches_are_connected_bounded_and_do_not_cross_links():
    scan, truth = samples.branching()
    seg = SG.Segmenter(scan, reduce=True, max_units=400)
    labels = seg.unit_of
    assert labels.max() + 1 == len(seg.unit_tri)
    sizes = np.bincount(labels)
    assert sizes.max() <= int(np.ceil(4.0 * len(labels) / 400))
    # patches do not cross links: giving every patch its majority link mislabels only a few
    # seam triangles (blended seams are where patches of two links meet)
    tl = truth["face_labels"][seg.valid]
    table = np.zeros((labels.max() + 1, tl.max() + 1))
    np.add.at(table, (labels, tl), 1)
    assert 1 - table.max(axis=1).sum() / len(tl) < 0.03
    # representatives belong to their patch
    assert np.all(labels[seg.unit_tri] == np.arange(len(seg.unit_tri)))


def _coarsen_by_definition(n, adjacency, agree, target, max_size):
    """The matching rounds of the patches' docstring read literally: every triangle edge in every
    round, a patch pair's distance the largest a over its shared edges, each patch's partner the
    least distance (on ties the first of its partners above it, then of those below it, each in
    ascending order), mutual partners merged within ``max_size``."""
    labels = np.arange(n)
    for _ in range(200):
        size = np.bincount(labels)
        if len(size) <= target:
            break
        pair = {}
        for (i, j), a in zip(labels[adjacency].tolist(), agree.tolist()):
            if i != j:
                key = (min(i, j), max(i, j))
                pair[key] = max(pair.get(key, -np.inf), a)
        best = {}
        ok = sorted((i, j, a) for (i, j), a in pair.items() if size[i] + size[j] <= max_size)
        # a patch's partners in order: those above it, then those below it (each ascending)
        for s, d, a in [(i, j, a) for i, j, a in ok] + [(j, i, a) for i, j, a in ok]:
            if s not in best or a < best[s][0]:
                best[s] = (a, d)
        merge = {max(s, d): s for s, (_, d) in best.items() if best.get(d, (0, -1))[1] == s and s < d}
        if not merge:
            break
        new = np.array([merge.get(p, p) for p in range(len(size))])
        labels = np.unique(new[labels], return_inverse=True)[1].reshape(-1)
    return labels


def test_patch_rounds_on_the_patch_graph_match_the_definition():
    """The rounds run on the patch graph (on every triangle edge they take half the features stage of
    a 1M-triangle scan); the patches are those of the definition, ties and size limits included."""
    rng = np.random.default_rng(3)
    scan = samples.make("branching")
    from artdef_addon import clustering
    adjacency = clustering.face_adjacency(scan.faces)
    n = len(scan.faces)
    for agree in (rng.random(len(adjacency)), rng.integers(0, 3, len(adjacency)).astype(float)):  # ties too
        for target, max_size in ((n // 20, 40), (50, 10 ** 6), (n // 4, 3)):
            got = patches._coarsen(n, adjacency, agree, target, max_size)
            want = _coarsen_by_definition(n, adjacency, agree, target, max_size)
            assert np.array_equal(got, want)


def test_patch_stream_in_blocks_is_the_whole_mesh_computation():
    """A field's neighbour distances and zero-velocity bound, a block of triangles at a time (the
    stream's memory at a million triangles), are the whole mesh's to the bit, blocks of any size."""
    from artdef_addon import clustering
    from artdef_addon.metric import field_features, rest_geometry
    scan = samples.make("branching")
    pairs = clustering.face_adjacency(scan.faces)
    rest = rest_geometry(scan.vertices, scan.faces)
    u = scan.displacements[1]
    f = field_features(scan.vertices, u, scan.faces, rest)
    want = patches.pair_distances(f, pairs)
    for block in (97, 1024, len(scan.faces), 10 ** 6):
        d, z = patches.neighbour_distances(scan.vertices, u, scan.faces, rest, pairs, block=block)
        assert np.array_equal(d, want) and z == f.zero_distance().max()


def test_pair_distances_match_block():
    scan = samples.make("rod")
    from artdef_addon.metric import distance_block, field_features
    f = field_features(scan.vertices, scan.displacements[0], scan.faces)
    pairs = np.array([[0, 5], [10, 200], [300, 301]])
    full = distance_block(f, pairs[:, 0], pairs[:, 1])
    assert np.allclose(patches.pair_distances(f, pairs), np.diag(full), atol=1e-5)


def test_reduced_method_counts_triangles_not_patches():
    """Few, large patches (60 for 4.3k triangles): the merge and the robust medoids weigh each
    patch by its triangle count, so a link made of a few big patches keeps its own motion and
    the links come out right (counting patches instead gave ARI 0.90 on this scan)."""
    import sys
    import os
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "benchmarks"))
    from generate import branching_scan
    scan, truth = branching_scan(4000, n_fields=12, seed=7)
    seg = SG.Segmenter(scan, reduce=True, max_units=60)
    assert len(seg.unit_tri) <= 60
    assert np.array_equal(np.bincount(seg.unit_of), seg.unit_size)
    assert seg.unit_size.max() > 2 * seg.unit_size.min()  # the patches really differ in size
    assert quality.adjusted_rand_index(seg.labels(11), truth["face_labels"]) >= 0.99


def test_estimate_prices_the_patch_streams_memory():
    """The reduced method streams every triangle's features, two fields at a time, which is a
    million-triangle fit's peak: the estimate's price of it (``cost.stream_bytes``) must match the
    measured rise of the peak RSS while the Segmenter builds its patches (the estimate within 2 x;
    one field's cached features per triangle would price it 2.3 x under the measured peak of the
    1.03M-triangle scan)."""
    import os
    import sys
    import pytest
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "benchmarks"))
    from generate import branching_scan
    from peak import reset_peak, status_kb
    scan, _ = branching_scan(100_000, n_fields=4, seed=7)
    before = status_kb("VmRSS")
    if not reset_peak() or before == 0:
        pytest.skip("no /proc/self/clear_refs: the peak cannot be reset here")
    seg = SG.Segmenter(scan)
    rise = (status_kb("VmHWM") - before) * 1024.0
    assert seg.reduced
    priced = cost.stream_bytes(scan.n_faces, scan.n_fields)
    assert 0.5 < priced / rise < 2.0, (priced / 2 ** 20, rise / 2 ** 20)


def test_command_line_estimate_is_the_process_peak(tmp_path):
    """The command line prints the peak of its own process: what it holds before the fit and the
    fit's estimate, both named; the process's measured peak (its ``VmHWM`` as it exits; ``ru_maxrss``
    would keep the forking parent's) is within 2 x of it. Without a base (the panel: a fit inside a
    running Blender) the fit's own is printed."""
    import os
    import re
    import subprocess
    import sys
    import pytest
    if not os.path.exists("/proc/self/status"):
        pytest.skip("the process's peak is read from /proc/self/status (its VmHWM)")
    est = cost.estimate(584, 3, 297)
    line = est.describe(100 * 2 ** 20, 200 * 2 ** 20)
    assert f"about {cost.format_bytes(300 * 2 ** 20 + est.memory_bytes)} peak (this process's 100 MB, " in line
    assert "for the fit and about 200 MB for Blender's outputs)" in line
    assert est.describe().startswith("estimate: full method on 584 triangles, 3 fields: about ")
    scan, res = tmp_path / "branching.npz", tmp_path / "res.npz"
    assert subprocess.run([sys.executable, "-m", "artdef_addon", "sample", "branching", "-o", str(scan)]).returncode == 0
    # the command line in a process that reports its own peak as it exits
    code = ("import runpy, sys\n"
            "sys.argv = ['artdef_addon', 'fit', sys.argv[1], '--links', '11', '-o', sys.argv[2]]\n"
            "try:\n    runpy.run_module('artdef_addon', run_name='__main__')\n"
            "finally:\n    print('PEAK', [l.split()[1] for l in open('/proc/self/status') if l.startswith('VmHWM')][0],"
            " file=sys.stderr)\n")
    p = subprocess.run([sys.executable, "-c", code, str(scan), str(res)], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    peak = float(re.search(r"PEAK (\d+)", p.stderr).group(1)) * 1024.0
    m = re.search(r"about ([\d.]+) (MB|GB) peak \(this process's", p.stdout)
    assert m, p.stdout
    printed = float(m.group(1)) * 2 ** (20 if m.group(2) == "MB" else 30)
    assert 0.5 < printed / peak < 2.0, (printed / 2 ** 20, peak / 2 ** 20)
