"""Command line: ``python -m artdef_addon fit|sample|info ...``.

Exit codes: 0 success, 2 bad input (one line on stderr, no output written), 1 other failure.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m artdef_addon",
                                description="Articulated deformation from displacement fields "
                                            "(Lang, Pai & Seidel, GI 2003).")
    sub = p.add_subparsers(dest="command", required=True)
    f = sub.add_parser("fit", help="segment a scan into links, fit joints, tree and model")
    f.add_argument("scan", help="scan .npz (format v1, see README)")
    f.add_argument("--links", required=True,
                   help="number of links, or 'auto' to choose it from the data")
    f.add_argument("--mode", choices=("global", "pseudo"), default="global",
                   help="one articulation for all fields, or one per Green's block column")
    f.add_argument("--motion", choices=("robust", "lsq"), default="robust",
                   help="link motion: motion centroid (paper) or least squares (comparison)")
    f.add_argument("--p-max", type=float, default=None,
                   help="strain hardening limit (> 1, in probe loads); off by default")
    f.add_argument("--max-links", type=int, default=30, help="upper bound for --links auto")
    f.add_argument("--memory-budget", type=float, default=2.0,
                   help="GB; above it the fit switches to the reduced method on patches")
    f.add_argument("--reduce", choices=("auto", "on", "off"), default="auto",
                   help="reduced method on patches: automatic by memory budget, always, never")
    f.add_argument("--strategy", choices=("auto", "summed", "paper"), default="auto",
                   help="how fields are combined: the paper's per-field trees with split-and-merge, "
                        "or one tree over the summed distances (auto: paper for Green's scans)")
    f.add_argument("--skin", choices=("auto", "seam", "refined"), default="auto",
                   help="skin weights: seam blend (paper) or refined by least squares "
                        "(auto: refined for tracked scans)")
    f.add_argument("-o", "--output", help="result .npz")
    f.add_argument("--blend", help="also build the rig in Blender and save this .blend (needs bpy)")
    f.add_argument("--glb", help="also export the rig as glTF binary (needs bpy)")
    f.add_argument("--png", help="also render a preview PNG (needs bpy)")
    f.add_argument("-q", "--quiet", action="store_true", help="print nothing on success")
    s = sub.add_parser("sample", help="write a built-in sample scan")
    s.add_argument("name", help="rod | branching | greens_rod | elastic")
    s.add_argument("-o", "--output", required=True)
    s.add_argument("--fields", type=int, help="number of fields (tracked samples)")
    s.add_argument("--noise", type=float, default=0.0, help="branching: noise relative to field RMS")
    s.add_argument("--bulges", action="store_true", help="branching: add local bulges")
    s.add_argument("--disconnected", action="store_true", help="branching: arms as separate pieces")
    s.add_argument("--seed", type=int, help="random seed")
    i = sub.add_parser("info", help="describe a scan or result file (and estimate a scan's fit)")
    i.add_argument("path")
    return p


class _BadInput(Exception):
    pass


def _fail(msg: str, code: int = 2) -> int:
    print(f"artdef: error: {msg}", file=sys.stderr)
    return code


def _cmd_sample(a) -> int:
    from . import samples, scan as S
    kw = {}
    if a.fields is not None:
        kw["n_fields"] = a.fields
    if a.seed is not None:
        kw["seed"] = a.seed
    if a.name == "branching":
        kw.update(noise=a.noise, bulges=a.bulges, disconnected=a.disconnected)
    try:
        sc = samples.make(a.name, **kw)
    except (ValueError, TypeError) as exc:
        raise _BadInput(str(exc)) from None
    S.save_scan(a.output, sc)
    print(f"wrote {a.output}: {a.name}, {sc.n_vertices} vertices, {sc.n_faces} triangles, "
          f"{sc.n_fields} fields ({sc.kind})")
    return 0


def _cmd_info(a) -> int:
    from . import scan as S
    try:
        with np.load(a.path, allow_pickle=False) as z:
            is_result = "face_labels" in z.files
    except (OSError, ValueError, EOFError) as exc:
        raise _BadInput(f"cannot read {a.path}: {exc}") from None
    if is_result:
        from . import fit as F
        print(f"{a.path}: fit result")
        print(F.load_result(a.path).summary())
        return 0
    try:
        sc = S.load_scan(a.path)
    except S.ScanError as exc:
        raise _BadInput(str(exc)) from None
    print(f"{a.path}: {sc.kind} scan, {sc.n_vertices} vertices, {sc.n_faces} triangles, "
          f"{sc.n_fields} fields, {sc.n_loads} loads, "
          f"{0 if sc.support_vertices is None else len(sc.support_vertices)} support vertices, "
          f"{len(sc.degenerate_faces)} degenerate triangles, probe load {sc.probe_load:g}")
    from .cost import estimate
    print(estimate(sc.n_faces - len(sc.degenerate_faces), sc.n_fields, sc.n_vertices,
                   "paper" if sc.kind == "greens" else "summed").describe())
    return 0


def _cmd_fit(a) -> int:
    from . import fit as F, scan as S
    t0 = time.perf_counter()
    for path in (a.output, a.blend, a.glb, a.png):
        if path and os.path.isdir(path):
            raise _BadInput(f"output path is a directory: {path}")
    if a.blend or a.glb or a.png:
        from . import headless
        try:
            headless.require_bpy()
        except RuntimeError as exc:
            raise _BadInput(str(exc)) from None
    try:
        sc = S.load_scan(a.scan)
    except S.ScanError as exc:
        raise _BadInput(str(exc)) from None
    t_load = time.perf_counter() - t0
    if (a.blend or a.glb or a.png) and a.strategy != "auto":
        raise _BadInput("--strategy cannot be combined with --blend/--glb/--png: the Blender fit uses "
                        "strategy auto")
    auto = str(a.links).strip().lower() == "auto"
    if not auto:
        try:
            links = int(a.links)
        except ValueError:
            raise _BadInput(f"--links must be a whole number or 'auto', got {a.links!r}") from None
    try:
        t_fit = time.perf_counter()
        reduce = {"auto": None, "on": True, "off": False}[a.reduce]
        seg = F.Segmenter(sc, strategy=a.strategy, reduce=reduce, budget=a.memory_budget * 2 ** 30)
        if not a.quiet:
            print(seg.estimate.describe() + (" -> reduced method" if seg.reduced else ""), flush=True)
        t_auto = 0.0
        if auto:
            from .linkcount import choose_links
            t0 = time.perf_counter()
            choice = choose_links(seg, max_links=a.max_links)
            links = choice.links
            t_auto = time.perf_counter() - t0
        result = choice.reusable(a.mode, a.motion, a.skin) if auto else None
        if result is not None:      # the chooser fitted this count already
            result.p_max = a.p_max
        else:
            result = F.fit(sc, links, mode=a.mode, motion=a.motion, p_max=a.p_max, segmenter=seg,
                           strategy=a.strategy, skin=a.skin)
    except S.ScanError as exc:
        raise _BadInput(str(exc)) from None
    timings = {"load": t_load, **result.timings}
    if auto:
        timings["links auto"] = t_auto
    timings["total"] = time.perf_counter() - t_fit
    result.timings = timings
    if a.output:
        F.save_result(a.output, result)
    written = {}
    if a.blend or a.glb or a.png:
        from . import headless
        kwargs = dict(links=int(links), mode=a.mode.upper(), motion=a.motion.upper(),
                      p_max=float(a.p_max or 0.0), skin=a.skin.upper(), reduce=a.reduce.upper(),
                      memory_budget=float(a.memory_budget))
        written = headless.build_outputs(a.scan, kwargs, a.blend, a.glb, a.png)
    if not a.quiet:
        print(f"{os.path.basename(a.scan)}: {sc.kind} scan, {sc.n_vertices} vertices, {sc.n_faces} triangles, "
              f"{sc.n_fields} fields")
        if auto:
            print(choice.reason)
        print(result.summary())
        if sc.kind == "greens":
            f = sc.fields()
            expl = 100.0 * (1.0 - result.rms_articulation ** 2 / max(np.mean(np.sum(f * f, -1)), 1e-300))
            print(f"articulation explains {expl:.2f}% of the fields' energy")
        for path in (a.output, *written.values()):
            if path:
                print(f"wrote {path}")
    return 0


def main(argv=None) -> int:
    a = _parser().parse_args(argv)
    try:
        return {"fit": _cmd_fit, "sample": _cmd_sample, "info": _cmd_info}[a.command](a)
    except _BadInput as exc:
        return _fail(str(exc).splitlines()[0] if str(exc) else "bad input")
    except KeyboardInterrupt:
        return _fail("interrupted", 130)
