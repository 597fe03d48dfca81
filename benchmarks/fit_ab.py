"""Two checkouts' fits side by side: CPU time and the answers.

For each set and repetition the fit of checkout A and of checkout B run one after the other, each in
a fresh process (so their module caches and the machine's load are shared alike), alternating which
goes first. Prints per set the median CPU seconds of each (``time.process_time`` of ``fit.fit`` with
its Segmenter: all threads) and the median wall seconds (the split trials run on two threads), their
ratios B/A, and the answers of one run of each: the Karni–Gotsman
articulation error, the ARI against the true face labels and the true joints found within 2 % of the
bounding-box diagonal (where the truth is known), and the number of weight solves
(``skinning._refine`` calls) and link-motion updates (``skinning.update_motions``) with their vertex
rows — so a change meant to cut work without moving the answers is shown to do exactly that.

Sets: ``name[:links]`` matched against ``--data/*name*.npz`` (default links: the number of true links,
10 for ``dembones_bone``); with ``--fresh SEED`` fresh random LBS poses of the true rig
(``samples.random_poses``, 20 fields, up to 45°) replace the set's own.

Usage (from the repository root)::

    .venv/bin/python benchmarks/fit_ab.py ../main . --sets CesiumMan:19,wolf:21,cheburashka:11,dembones_bone:10
    .venv/bin/python benchmarks/fit_ab.py ../main . --sets RobotExpressive:36 --fresh 6 --reps 2

Writes the Markdown table to ``benchmarks/results/fit_ab.md`` (``--out`` elsewhere, ``--out -`` nowhere).
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import subprocess
import sys
import time

import report

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
DATA = os.path.join(os.path.dirname(ROOT), "shared", "data")


def one(repo: str, name: str, links: int | None, fresh: int | None, data: str) -> dict:
    """Fit one set with the artdef of ``repo`` in this process; the answers and CPU time as a dict."""
    sys.path.insert(0, os.path.abspath(repo))
    import numpy as np
    from artdef_addon import quality as Q, samples, skinning as SK
    try:
        from artdef_addon.options import FitOptions
        from artdef_addon.pipeline import fit as pipeline_fit
        from artdef_addon.scan import validate_scan
        from artdef_addon.segmenter import Segmenter

        def fit_refined(scan, links):
            scan = validate_scan(scan)
            return pipeline_fit(scan, links, FitOptions(skin="refined"), segmenter=Segmenter(scan))
    except ImportError:         # a core from before the pipeline had its own module (an A/B of commits)
        from artdef_addon import fit as F

        def fit_refined(scan, links):
            return F.fit(scan, links, segmenter=F.Segmenter(scan), skin="refined")
    from artdef_addon.scan import Scan

    count = dict(solves=0, solve_rows=0, motions=0, motion_rows=0)
    refine, motions = SK._refine, SK.update_motions

    def counted_refine(v, *a, **k):
        count["solves"] += 1
        count["solve_rows"] += v.shape[0]
        return refine(v, *a, **k)

    def counted_motions(v, *a, **k):
        count["motions"] += 1
        count["motion_rows"] += v.shape[0]
        return motions(v, *a, **k)

    SK._refine, SK.update_motions = counted_refine, counted_motions
    path = sorted(glob.glob(os.path.join(data, f"*{name}*.npz")))[0]
    with np.load(path) as z:
        d = {a: z[a] for a in z.files}
    U = d["displacements"]
    if fresh is not None:
        U = samples.random_poses(d["vertices"], d["gt_weights"], d["gt_joints"], d["gt_parents"], n_fields=20,
                                 max_deg=45.0, seed=fresh)
    truth = "gt_face_labels" in d
    if links is None:
        links = len(np.unique(d["gt_face_labels"])) if truth else 10
    scan = Scan(d["vertices"], d["faces"], displacements=U)
    c0, t0 = time.process_time(), time.perf_counter()
    res = fit_refined(scan, links)
    out = dict(cpu=time.process_time() - c0, wall=time.perf_counter() - t0, links=links, **count)
    out["kg"] = float(Q.kg_distortion(d["vertices"][None] + U, Q.reproduce(res, d["vertices"])))
    if truth:
        out["ari"] = float(Q.adjusted_rand_index(res.face_labels, d["gt_face_labels"]))
        _, je = Q.true_joint_errors(res, d["gt_joints"], d["gt_parents"], d["gt_face_labels"])
        je = np.asarray(je, dtype=float)
        diag = np.linalg.norm(np.ptp(d["vertices"], axis=0))
        out["joints"] = f"{int(np.sum(np.isfinite(je) & (je / diag < 0.02)))}/{len(je)}"
    return out


def alternating(commands: dict, reps: int) -> dict:
    """Run each side's command (a list; it prints one fit's JSON dict last) ``reps`` times in fresh processes,
    alternating which side goes first; returns {side: [dict, ...]}."""
    sides = list(commands)
    runs = {s: [] for s in sides}
    for rep in range(reps):
        for side in (sides if rep % 2 == 0 else sides[::-1]):
            out = subprocess.run(commands[side], check=True, capture_output=True, text=True).stdout
            runs[side].append(json.loads(out.splitlines()[-1]))
    return runs


def median(runs: dict, key: str) -> dict:
    """{side: the median of ``key`` over its runs}."""
    return {s: sorted(r[key] for r in rs)[len(rs) // 2] for s, rs in runs.items()}


def answers(r: dict) -> str:
    s = f"KG {r['kg']:.4f} %"
    if "ari" in r:
        s += f", ARI {r['ari']:.4f}, joints {r['joints']}"
    return s + f", solves {r['solves']} ({r['solve_rows'] / 1e3:.0f}k rows), motions {r['motions']}"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("a", nargs="?", help="checkout A (the reference)")
    ap.add_argument("b", nargs="?", help="checkout B")
    ap.add_argument("--sets", default="CesiumMan:19,wolf:21,cheburashka:11,dembones_bone:10")
    ap.add_argument("--fresh", type=int, default=None, help="fresh random poses of this seed")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--data", default=DATA)
    ap.add_argument("--out", default=report.result_path("fit_ab.md"), help="Markdown file (- for none)")
    ap.add_argument("--one", nargs=3, metavar=("REPO", "NAME", "LINKS"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.one:
        repo, name, links = args.one
        print(json.dumps(one(repo, name, int(links) if links != "-" else None, args.fresh, args.data)))
        return
    rows = []
    for item in args.sets.split(","):
        name, _, links = item.partition(":")
        fresh = [] if args.fresh is None else ["--fresh", str(args.fresh)]
        runs = alternating({side: [sys.executable, __file__, "--one", getattr(args, side.lower()), name, links or "-",
                                   "--data", args.data] + fresh for side in "AB"}, args.reps)
        med, wall = median(runs, "cpu"), median(runs, "wall")
        same = answers(runs["A"][0]) == answers(runs["B"][0])
        label = name + ("" if args.fresh is None else f" (fresh seed {args.fresh})")
        rows.append((label, runs["A"][0]["links"], med["A"], med["B"], med["B"] / med["A"],
                     answers(runs["A"][0]), "same" if same else answers(runs["B"][0]),
                     wall["A"], wall["B"], wall["B"] / wall["A"]))
        print(f"{label}: A {med['A']:.2f} s, B {med['B']:.2f} s CPU (B/A {med['B'] / med['A']:.2f}), "
              f"wall A {wall['A']:.2f} s, B {wall['B']:.2f} s (B/A {wall['B'] / wall['A']:.2f}); "
              f"A: {answers(runs['A'][0])}; B: {'same' if same else answers(runs['B'][0])}", flush=True)
    table = ["| set | links | A CPU s | B CPU s | B/A CPU | A wall s | B wall s | B/A wall | answers of A | answers of B |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---|---|"]
    table += [f"| {r[0]} | {r[1]} | {r[2]:.2f} | {r[3]:.2f} | {r[4]:.2f} | {r[7]:.2f} | {r[8]:.2f} | {r[9]:.2f} | {r[5]} | {r[6]} |"
              for r in rows]
    print("\n".join(table))
    if args.out != "-":
        report.write(args.out, "Two checkouts' fits side by side (`benchmarks/fit_ab.py`)",
                     f"A = `{report.commit(args.a)}`, B = `{report.commit(args.b)}`, median of {args.reps}.\n\n"
                     + "\n".join(table))


if __name__ == "__main__":
    main()
