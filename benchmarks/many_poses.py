"""artdef against Dem Bones on fresh poses of the shared rigs, at chosen pose counts.

Held-back performance captures have many more poses (87) than the shared sets (9-27)
and than the trials' field spread (``skinning.SAMPLE_FIELDS``, 64), where the swaps' budget
(``swaps.SWAP_BUDGET``, vertices × trial fields) decides whether the swaps and the split stage run.
This poses each rig ``--poses`` times (``samples.random_poses``: every bone up to 45°, roots moving)
for each ``--seeds`` seed, fits artdef (the true link count, one process, after a warm-up fit) and
Dem Bones (the same bone count, 4 influences, 30 iterations, as ``compare_dembones.py``) and prints
time, articulation-only error (Karni–Gotsman %), their ratios and artdef's true joints within 2 % of
the diagonal, as a Markdown table, written to ``benchmarks/results/many_poses.md`` (``--out`` elsewhere, ``-``
nowhere).

Usage (py-dem-bones lives in the 4.5 venv: ``.venv-4.5/bin/pip install -r requirements-bench.txt``)::

    .venv-4.5/bin/python benchmarks/many_poses.py --sets cow,cheburashka,wolf --poses 40,87 --seeds 3,4,5
    .venv-4.5/bin/python benchmarks/many_poses.py --sets cow --poses 87 --seeds 3,4,5 --swap-budget 500000
"""
from __future__ import annotations

import argparse
import glob
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)
sys.path.insert(0, HERE)

from artdef_addon import api, quality, samples  # noqa: E402
from artdef_addon.scan import Scan  # noqa: E402
import report  # noqa: E402


def fit_artdef(d: dict, U: np.ndarray, links: int) -> dict:
    """artdef's fit of the posed rig: seconds, KG error %, true joints within 2 %, and whether the
    swap and split trials ran (no "skipped" note)."""
    scan = Scan(d["vertices"], d["faces"], displacements=U)
    t0 = time.perf_counter()
    r = api.fit(scan, links)
    secs = time.perf_counter() - t0
    X = d["vertices"][None] + U
    kg = float(quality.kg_distortion(X, quality.reproduce(r, d["vertices"])))
    _, je = quality.true_joint_errors(r, d["gt_joints"], d["gt_parents"], d["gt_face_labels"])
    je = np.asarray(je, dtype=float)
    diag = float(np.linalg.norm(np.ptp(d["vertices"], axis=0)))
    found = int(np.sum(np.isfinite(je) & (je / diag < 0.02)))
    trials = not any("skipped" in n for n in r.notes)
    return dict(seconds=secs, error=kg, joints=f"{found}/{len(je)}", trials=trials)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=os.path.join(ROOT, "..", "shared", "data"))
    ap.add_argument("--sets", default="cow,cheburashka,wolf", help="comma-separated name substrings")
    ap.add_argument("--poses", default="87", help="comma-separated pose counts")
    ap.add_argument("--seeds", default="3", help="comma-separated seeds of the random poses")
    ap.add_argument("--swap-budget", type=int, default=None,
                    help="swaps.SWAP_BUDGET for this run (vertices × trial fields; default the core's)")
    ap.add_argument("--out", default=report.result_path("many_poses.md"), help="Markdown file (- for none)")
    a = ap.parse_args(argv)
    if a.swap_budget is not None:
        from artdef_addon import swaps
        swaps.SWAP_BUDGET = a.swap_budget
    import compare_dembones as C
    api.fit(samples.make("rod"), 3)           # warm-up: the first fit of a process loads modules
    rows = []
    for name in a.sets.split(","):
        paths = sorted(glob.glob(os.path.join(a.data, f"*{name}*.npz")))
        if not paths:
            print(f"many_poses: no set matches {name!r} under {a.data}", file=sys.stderr)
            continue
        with np.load(paths[0], allow_pickle=False) as z:
            d = {k: z[k] for k in z.files}
        if "gt_weights" not in d:
            print(f"many_poses: {name} has no true rig to pose", file=sys.stderr)
            continue
        links = int(len(np.unique(d["gt_face_labels"])))
        for P in (int(p) for p in a.poses.split(",")):
            for seed in (int(s) for s in a.seeds.split(",")):
                U = samples.random_poses(d["vertices"], d["gt_weights"], d["gt_joints"], d["gt_parents"],
                                         n_fields=P, max_deg=45.0, seed=seed)
                art = fit_artdef(d, U, links)
                db = C.run_dembones(d["vertices"], d["faces"], d["vertices"][None] + U, links, 4, 30)
                row = (f"| {os.path.basename(paths[0])[:-4]} | {len(d['vertices']):,} | {P} | {seed} | {links} | "
                       f"{'yes' if art['trials'] else 'no'} | {art['seconds']:.1f} | {db['seconds']:.1f} | "
                       f"{art['seconds'] / db['seconds']:.2f} | {art['error']:.3f} | {db['error']:.3f} | "
                       f"{art['error'] / db['error']:.2f} | {art['joints']} |")
                print(row, flush=True)
                rows.append(row)
    head = ("| set | vertices | poses | seed | links | swaps and splits | artdef (s) | Dem Bones (s) | time ratio | "
            "artdef error (%) | Dem Bones error (%) | error ratio | artdef joints ≤ 2 % |\n"
            "|---|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---|")
    table = head + "\n" + "\n".join(rows)
    print(table)
    if a.out != "-":
        report.write(a.out, "artdef against Dem Bones at many poses (`benchmarks/many_poses.py`)", table)


if __name__ == "__main__":
    main()
