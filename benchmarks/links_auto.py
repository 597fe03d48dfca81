"""``--links auto`` on the shared rigged sets: the link count the core chooses, against the truth.

For each set (own poses, and 20 fresh random LBS poses of the true rig, seed 1, for the glTF and
three.js models) this builds one Segmenter and runs ``linkcount.choose_links`` with up to
max(30, 1.5 × true) links, as ``compare_dembones.py`` does, and prints the tree rule's pick (the
re-cut tree's error curve), the pick after the whole fits upward, the final pick (after
interpolating links are dropped) and its distance from the true count, the seconds and the chooser's reason. Heavy: minutes per character; not a test.

Side by side in one process (one process a set and pose kind), each with a new Segmenter: the
search, then the fixed-count fit at the true count (``fit.fit``); "× fixed" is their time ratio (the bar: at most 3). The search's
seconds split into the tree curve, the upward pass and the drop of links that are not bones;
"stops" says how each upward decision was made (``linkcount._grown_upward``): "grown" when the
links grown on a whole fit levelled off (no whole fit of the counts ahead), "whole" when whole
fits did, "grown continue" when the grown links fell far below the bar (the count passed without a
whole fit), "non-bones" when the count's whole fit already had links that are not bones (the drop
decides from there). With ``--verify`` every "grown" stop is checked against the whole fits of the counts
ahead (the whole-fit rule's own decision). "whole / partial fits / grown links": the whole fits the
search made (the upward pass and the drop), the fits it ran up to their split stage
(``linkcount.partial_fit``; those it finished are among the whole fits) and the links it grew.

The estimate: "est. (s)" is what ``fit --links auto`` prints before the search
(``api.plan(..., auto=True)``), "peak MB" the rise of the process's peak RSS during the search
(the peak reset before it through ``/proc/self/clear_refs``), "est. MB" the estimate's memory.

    .venv/bin/python benchmarks/links_auto.py --data ../shared/data [--only Fox,Robot] [--seeds 1-12]
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from artdef_addon import api, linkcount, samples, scan as S  # noqa: E402
from artdef_addon import pipeline as PL, segmenter as SG  # noqa: E402
from peak import reset_peak, status_kb  # noqa: E402


SETS = ["gltf_RiggedSimple", "cragl_cylinder_gt", "gltf_RiggedFigure", "gltf_Fox", "cragl_cube_gt",
        "threejs_RobotExpressive", "gltf_CesiumMan", "cragl_cow_gt", "cragl_wolf_gt", "cragl_cheburashka_gt"]


def row(data: str, name: str, kind: str, verify: bool, seed: int = 1) -> None:
    """One set and pose kind (fresh poses: of ``seed``), in a process of its own: the search first
    (its peak memory is the process's from there), then the fixed fit at the true count; prints the
    table row."""
    with np.load(os.path.join(data, f"{name}.npz"), allow_pickle=False) as z:
        d = {k: z[k] for k in z.files}
    L = len(np.unique(d["gt_face_labels"]))
    u = d["displacements"] if kind == "own" else samples.random_poses(d["vertices"], d["gt_weights"], d["gt_joints"],
                                                                      d["gt_parents"], 20, seed=seed)
    scan = S.validate_scan(S.Scan(d["vertices"], d["faces"], displacements=u))
    mx = max(30, int(1.5 * L))
    est, _ = api.plan(scan.n_faces - len(scan.degenerate_faces), scan.n_fields, scan.n_vertices, scan.kind,
                      auto=True, max_links=mx)
    reset_peak()
    rss = 1024.0 * status_kb("VmRSS")
    t0 = time.perf_counter()
    seg = SG.Segmenter(scan)
    c = linkcount.choose_links(seg, max_links=mx)
    dt = time.perf_counter() - t0
    peak = max(1024.0 * status_kb("VmHWM") - rss, 0.0)
    t0 = time.perf_counter()
    PL.fit(scan, L, None, segmenter=SG.Segmenter(scan))
    fixed = time.perf_counter() - t0
    stops = ", ".join(f"{k} {how}" for k, how in c.decisions if how != "continue")
    if verify:
        for k, how in c.decisions:
            if how == "grown":
                j = min(mx, k + 4)
                bar = min(v for q, v in c.whole_errors.items() if q <= k) * (k / j) ** linkcount.WHOLE_FIT_SLOPE
                low = min(float(PL.fit(scan, i, None, segmenter=seg).articulation_error_percent) for i in range(k + 1, j + 1))
                stops += " (whole fits agree)" if low >= bar else f" (WHOLE FITS DISAGREE: {low:.4g} < {bar:.4g})"
    parts = " / ".join(f"{c.timings.get(p, 0.0):.1f}" for p in ("curve", "upward", "drop"))
    work = f"{c.work.get('whole_fits', 0)} / {c.work.get('partial_fits', 0)} / {c.work.get('grown_links', 0)}"
    mb = 2.0 ** 20
    kind = kind if kind == "own" or seed == 1 else f"fresh {seed}"
    print(f"| {name} | {kind} | {L} | {c.tree_links} | {c.upward_links} | {c.links} | {100 * (c.links - L) / L:+.0f} % "
          f"| {fixed:.1f} | {dt:.1f} | {dt / fixed:.2f} | {parts} | {work} | {est.seconds:.1f} "
          f"| {dt / est.seconds:.2f} | {peak / mb:.0f} | {est.memory_bytes / mb:.0f} "
          f"| {peak / est.memory_bytes:.2f} | {stops} |", flush=True)
    ratios = ", ".join(f"{k}: {r:.2f}" for k, r in c.work.get("low_over_bar", []))
    print(f"<!-- {c.reason}. Grown links' lowest error over the bar at each decision: {ratios} -->", flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data"))
    ap.add_argument("--only", default="", help="comma-separated substrings of the set names")
    ap.add_argument("--verify", action="store_true", help="check each stop on grown links with whole fits")
    ap.add_argument("--seeds", default="", help="fresh poses of these seeds only (e.g. 1-12): the search's spread "
                    "over pose sets (CesiumMan's own poses are one draw)")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "links_auto.md"),
                    help="Markdown file for the table (- for none)")
    ap.add_argument("--row", nargs=3, metavar=("SET", "POSES", "SEED"), help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.row:
        row(a.data, a.row[0], a.row[1], a.verify, int(a.row[2]))
        return
    only = [s for s in a.only.split(",") if s]
    lines = ["| set | poses | true links | tree rule | whole fits up | links auto | off by | fixed fit (s) | links auto (s) "
             "| × fixed | curve / up / drop (s) | whole / partial fits / grown links | est. (s) | × est. | peak MB | est. MB "
             "| × est. | stops |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---|---|---:|---:|---:|---:|---:|---|"]
    print("\n".join(lines), flush=True)
    for name in SETS:
        if only and not any(o in name for o in only):
            continue
        if not os.path.exists(os.path.join(a.data, f"{name}.npz")):
            continue
        runs = [("own", 1)] if name.startswith("cragl") else [("own", 1), ("fresh", 1)]
        if a.seeds:
            lo, _, hi = a.seeds.partition("-")
            runs = [] if name.startswith("cragl") else [("fresh", s) for s in range(int(lo), int(hi or lo) + 1)]
        for kind, seed in runs:
            proc = subprocess.run([sys.executable, os.path.abspath(__file__), "--data", a.data, "--row", name, kind,
                                   str(seed)] + (["--verify"] if a.verify else []), check=False, stdout=subprocess.PIPE,
                                  text=True)
            print(proc.stdout, end="", flush=True)
            lines += [ln for ln in proc.stdout.splitlines() if ln.startswith("|")]
    if a.out != "-":
        sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
        import report
        report.write(a.out, "links auto on the shared rigged sets (`benchmarks/links_auto.py`)", "\n".join(lines))


if __name__ == "__main__":
    main()
