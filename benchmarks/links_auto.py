"""``--links auto`` on the shared rigged sets (issue 5): the link count the core chooses, against the truth.

For each set (own poses, and 20 fresh random LBS poses of the true rig, seed 1, for the glTF and
three.js models) this builds one Segmenter and runs ``linkcount.choose_links`` with up to
max(30, 1.5 × true) links, as ``compare_dembones.py`` does, and prints the tree rule's pick (the
re-cut tree's error curve), the pick after the whole fits upward, the final pick (after
interpolating links are dropped) and its distance from the true count, the seconds and the chooser's reason. Heavy: minutes per character; not a test.

    .venv/bin/python benchmarks/links_auto.py --data ../shared/data [--only Fox,Robot]
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from artdef_addon import fit as F, linkcount, samples, scan as S  # noqa: E402

SETS = ["gltf_RiggedSimple", "cragl_cylinder_gt", "gltf_RiggedFigure", "gltf_Fox", "cragl_cube_gt",
        "threejs_RobotExpressive", "gltf_CesiumMan", "cragl_cow_gt", "cragl_wolf_gt", "cragl_cheburashka_gt"]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data"))
    ap.add_argument("--only", default="", help="comma-separated substrings of the set names")
    a = ap.parse_args(argv)
    only = [s for s in a.only.split(",") if s]
    print("| set | poses | true links | tree rule | whole fits up | links auto | off by | seconds |")
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    for name in SETS:
        if only and not any(o in name for o in only):
            continue
        path = os.path.join(a.data, f"{name}.npz")
        if not os.path.exists(path):
            continue
        with np.load(path, allow_pickle=False) as z:
            d = {k: z[k] for k in z.files}
        L = len(np.unique(d["gt_face_labels"]))
        kinds = [("own", d["displacements"])]
        if not name.startswith("cragl"):
            kinds.append(("fresh", samples.random_poses(d["vertices"], d["gt_weights"], d["gt_joints"],
                                                        d["gt_parents"], 20, seed=1)))
        for kind, u in kinds:
            scan = S.Scan(d["vertices"], d["faces"], displacements=u)
            t0 = time.perf_counter()
            seg = F.Segmenter(scan)
            mx = max(30, int(1.5 * L))
            c = linkcount.choose_links(seg, max_links=mx)
            tree = c.tree_links
            dt = time.perf_counter() - t0
            print(f"| {name} | {kind} | {L} | {tree} | {c.upward_links} | {c.links} | {100 * (c.links - L) / L:+.0f} % | {dt:.0f} |",
                  flush=True)
            print(f"<!-- {c.reason} -->", flush=True)


if __name__ == "__main__":
    main()
