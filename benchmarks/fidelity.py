"""Fidelity figures (docs/metrics.md): fresh-seed sweeps of the shared rigs and the model verdict.

Per rig and seed (``samples.random_poses``, 20 fields, the true link count): ARI against the true face
labels, true joints within 2 % of the diagonal (``quality.true_joint_errors``) and the missing ones, the
reported Karni–Gotsman distortion and the one recomputed from the result's own weights and pose motions
(``quality.reproduce``), E_RMS, and the verdict's ρ·L. Then the verdict on the generated samples, the
elastic one at several link counts.

Usage (from the repository root):

    .venv/bin/python benchmarks/fidelity.py [--seeds 4,5,6,7,8,9] [--rigs gltf_CesiumMan,threejs_RobotExpressive]

Writes a Markdown table to ``benchmarks/results/fidelity.md`` (``--out``).
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)

import artdef_addon  # noqa: E402
from artdef_addon import quality, samples  # noqa: E402
from artdef_addon.scan import Scan  # noqa: E402


def rig_row(name, d, seed):
    poses = samples.random_poses(d["vertices"], d["gt_weights"], d["gt_joints"], d["gt_parents"], 20, seed=seed)
    scan = Scan(d["vertices"], d["faces"], displacements=poses)
    t0 = time.perf_counter()
    r = artdef_addon.fit(scan, len(np.unique(d["gt_face_labels"])))
    secs = time.perf_counter() - t0
    diag = np.linalg.norm(np.ptp(d["vertices"], axis=0))
    bones, err = quality.true_joint_errors(r, d["gt_joints"], d["gt_parents"], d["gt_face_labels"])
    kg = quality.kg_distortion(d["vertices"][None] + poses, quality.reproduce(r, d["vertices"]))
    ok = err / diag < 0.02
    fin = err[np.isfinite(err)]
    return (f"| {name} | {seed} | {quality.adjusted_rand_index(r.face_labels, d['gt_face_labels']):.4f} | "
            f"{ok.sum()}/{len(err)} | {100 * fin.max() / diag:.2f} | {bones[~np.isfinite(err)].tolist() or '—'} | "
            f"{r.articulation_error_percent:.4f} | {kg:.4f} | {r.e_rms:.3g} | {r.rigid_error_percent:.3g} | "
            f"{r.articulation_error_percent / r.rigid_error_percent * r.n_links:.3g} | {r.articulated} | {secs:.0f} |")


def sample_row(name, kw, links):
    r = artdef_addon.fit(samples.make(name, **kw), links)
    return (f"| {name} {kw or ''} | {links} | {r.articulation_error_percent:.3g} | {r.rigid_error_percent:.3g} | "
            f"{r.linear_rank}: {r.linear_error_percent:.3g} | "
            f"{r.articulation_error_percent / r.rigid_error_percent * links:.3g} | {r.articulated} |")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="4,5,6,7,8,9")
    ap.add_argument("--rigs", default="gltf_CesiumMan,threejs_RobotExpressive")
    ap.add_argument("--data", default=os.path.join(ROOT, "tests", "data"))
    ap.add_argument("--out", default=os.path.join(HERE, "results", "fidelity.md"))
    a = ap.parse_args(argv)
    md = ["# Fidelity on fresh poses (`benchmarks/fidelity.py`)", "", "Fresh random poses, true link count. Distortion: Karni–Gotsman %, reported "
          "by the fit and recomputed from its own weights and pose motions. ρ·L: the verdict's figure (> 1: flagged).",
          "", "| rig | seed | ARI | joints ≤ 2 % | max joint % diag | missing | distortion % | recomputed % | "
          "E_RMS | one rigid motion % | ρ·L | articulated | s |", "|---|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|---|---:|"]
    for name in a.rigs.split(","):
        with np.load(os.path.join(a.data, f"{name}.npz"), allow_pickle=False) as z:
            d = {k: z[k] for k in z.files}
        for seed in [int(s) for s in a.seeds.split(",")]:
            md.append(rig_row(name, d, seed))
            print(md[-1], flush=True)
    md += ["", "| sample | links | distortion % | one rigid motion % | linear rank: % | ρ·L | articulated |",
           "|---|---:|---:|---:|---:|---:|---|"]
    for name, kw, links in [("rod", {}, 3), ("branching", {}, 11), ("branching", dict(noise=0.02, bulges=True), 11),
                            ("greens_rod", {}, 3), ("elastic", {}, 4), ("elastic", {}, 8), ("elastic", {}, 16),
                            ("elastic", dict(seed=1), 8), ("elastic", dict(bend_deg=30.0), 8)]:
        md.append(sample_row(name, kw, links))
        print(md[-1], flush=True)
    os.makedirs(os.path.dirname(a.out), exist_ok=True)
    with open(a.out, "w") as f:
        f.write("\n".join(md) + "\n")
    print("wrote", a.out)


if __name__ == "__main__":
    main()
