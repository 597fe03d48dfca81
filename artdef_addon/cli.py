"""Command line: ``python -m artdef_addon fit|sample|info ...``.

Exit codes: 0 success, 2 bad input (one line on stderr, no output written), 1 other failure.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

from .options import FitOptions, OptionsError


def _option_arguments(parser) -> None:
    """One ``--name`` per :class:`FitOptions` field, from its declaration (type, default, choices,
    unit and description are not repeated here)."""
    for name, (default, opt) in FitOptions.declaration().items():
        flag = "--" + name.replace("_", "-")
        helptext = opt.description + (f" [{opt.unit}]" if opt.unit else "")
        if opt.choices:
            helptext += " (" + "; ".join(f"{c.value}: {c.description}" for c in opt.choices) + ")"
        if opt.greens_only:
            helptext += " [Green's scans]"
        helptext = helptext.replace("%", "%%")
        if opt.choices:
            parser.add_argument(flag, choices=opt.values, default=default, help=helptext,
                                metavar="{" + ",".join(opt.values) + "}")
        else:
            helptext += f" (default: {'off' if default is None else default})"
            parser.add_argument(flag, type=opt.type, default=default, help=helptext)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m artdef_addon",
                                description="Articulated deformation from displacement fields "
                                            "(Lang, Pai & Seidel, GI 2003).")
    sub = p.add_subparsers(dest="command", required=True)
    f = sub.add_parser("fit", help="segment a scan into links, fit joints, tree and model")
    f.add_argument("scan", help="scan .npz (format v1, see docs/formats.md), or an animated file Blender "
                                "imports (.glb/.gltf/.fbx/.abc/.usd/.usdc/.usda/.usdz) or an "
                                "OBJ/PLY sequence (folder, pattern or first file): sampled in "
                                "Blender over the file's own frames (needs bpy)")
    f.add_argument("--clip", action="append", default=[], metavar="FILE",
                   help="another clip of the same mesh (animated file or sequence; repeatable): "
                        "all clips are fitted as one rig with one action each")
    f.add_argument("--frames", metavar="START:END[:STEP]",
                   help="animated file or sequence: frames to sample (default: the file's keys)")
    f.add_argument("--links", required=True,
                   help="number of links, or 'auto' to choose it from the data")
    _option_arguments(f)
    f.add_argument("-o", "--output", help="result .npz")
    f.add_argument("--blend", help="also build the rig in Blender and save this .blend (needs bpy)")
    f.add_argument("--glb", help="also export the rig as glTF binary (needs bpy): the fitted mesh "
                                 "and its armature only, one clip at the source's frames")
    f.add_argument("--fbx", help="also export the rig as FBX (needs bpy), like --glb")
    f.add_argument("--rotation-only", action="store_true",
                   help="with --blend/--glb/--fbx: joints only rotate, bones keep their length, "
                        "only the root translates (engines); prints the error this adds")
    f.add_argument("--png", help="also render a preview PNG (needs bpy)")
    f.add_argument("-q", "--quiet", action="store_true", help="print nothing on success")
    s = sub.add_parser("sample", help="write a built-in sample scan")
    s.add_argument("name", help="rod | branching | greens_rod")
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
        from .fit import FitResult
        print(f"{a.path}: fit result")
        print(FitResult.load(a.path).summary())
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


#: Animated files Blender imports (fitted through ``artdef.fields_from_file``).
ANIMATED_EXTENSIONS = (".glb", ".gltf", ".fbx", ".abc", ".usd", ".usdc", ".usda", ".usdz")
SEQUENCE_EXTENSIONS = (".obj", ".ply")


def input_kind(path: str) -> str | None:
    """'npz' (a scan), 'animated' (a file Blender imports), 'sequence' (an OBJ/PLY
    sequence: a folder, a pattern or one numbered file), or None."""
    if os.path.isdir(path) or any(c in os.path.basename(path) for c in "*?["):
        return "sequence"
    ext = os.path.splitext(path)[1].lower()
    if ext == ".npz":
        return "npz"
    if ext in ANIMATED_EXTENSIONS:
        return "animated"
    if ext in SEQUENCE_EXTENSIONS:
        return "sequence"
    return None


def parse_frames(text: str | None):
    """``START:END[:STEP]`` -> (start, end, step); None for None.  ValueError
    with one line saying what is wrong."""
    if text is None:
        return None
    parts = text.split(":")
    try:
        if len(parts) not in (2, 3):
            raise ValueError
        start, end = int(parts[0]), int(parts[1])
        step = int(parts[2]) if len(parts) == 3 else 1
    except ValueError:
        raise ValueError(f"--frames must be START:END or START:END:STEP (whole numbers), "
                         f"got {text!r}") from None
    if end < start or step < 1:
        raise ValueError(f"--frames {text}: END must not be before START and STEP must be >= 1")
    return start, end, step


def blender_layer():
    """The Blender layer's headless module (``operators/headless.py``), for --blend/--glb/--png.

    The core never imports bpy (not even lazily): the Blender layer does. This command line only
    loads that module, by its place in the extension, when Blender is asked for (outputs, or an
    input only Blender reads) — as
    ``<extension>.operators.headless`` when the core runs inside the installed extension package,
    else from the file next to this package (a checkout run with ``python -m artdef_addon``).
    That module checks bpy, registers the extension and builds the rig from the result this
    command already fitted (one fit per command).
    """
    import importlib
    import importlib.util
    parent = __package__.rpartition(".")[0]
    if parent:
        return importlib.import_module(parent + ".operators.headless")
    path = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "operators", "headless.py")
    name = "artdef_headless_entry"
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or not os.path.isfile(path):
        raise _BadInput(f"--blend/--glb/--png need the Blender layer ({path} is missing)")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def _cmd_fit(a) -> int:
    from . import api, scan as S
    t0 = time.perf_counter()
    outputs = (a.output, a.blend, a.glb, a.fbx, a.png)
    for path in outputs:
        if path and os.path.isdir(path):
            raise _BadInput(f"output path is a directory: {path}")
        if path and os.path.abspath(path) == os.path.abspath(a.scan):
            raise _BadInput(f"output would overwrite the input: {path}")
    try:
        options = FitOptions(**{name: getattr(a, name) for name in FitOptions.declaration()})
    except OptionsError as exc:
        raise _BadInput(str(exc)) from None
    if a.rotation_only and not (a.blend or a.glb or a.fbx):
        raise _BadInput("--rotation-only applies to the rig: add --blend, --glb or --fbx")
    kind = input_kind(a.scan)
    if kind is None:
        raise _BadInput(f"{a.scan}: not a scan (.npz), an animated file "
                        f"({'/'.join(ANIMATED_EXTENSIONS)}) or an OBJ/PLY sequence")
    try:
        frames = parse_frames(a.frames)
    except ValueError as exc:
        raise _BadInput(str(exc)) from None
    if a.clip and kind == "npz":
        raise _BadInput("--clip applies to animated files and sequences, not to a .npz scan")
    for clip in a.clip:
        if input_kind(clip) not in ("animated", "sequence"):
            raise _BadInput(f"--clip {clip}: not an animated file or an OBJ/PLY sequence")
        if input_kind(clip) == "animated" and not os.path.exists(clip):
            raise _BadInput(f"--clip {clip}: no such file")
    if frames is not None and kind == "npz":
        raise _BadInput("--frames applies to animated files and sequences, not to a .npz scan")
    headless = None
    if a.blend or a.glb or a.fbx or a.png or kind != "npz":
        headless = blender_layer()
        try:
            headless.require_bpy()
        except RuntimeError as exc:
            raise _BadInput(str(exc) if kind == "npz" else
                            f"reading {os.path.basename(a.scan)} needs Blender: " + str(exc)) from None
    prepared = None
    if kind == "npz":
        try:
            sc = S.load_scan(a.scan)
        except S.ScanError as exc:
            raise _BadInput(str(exc)) from None
    else:
        if not os.path.exists(a.scan) and kind == "animated":
            raise _BadInput(f"{a.scan}: no such file")
        try:
            prepared, sc = headless.scan_from_file(a.scan, frames, clips=a.clip)
        except RuntimeError as exc:
            raise _BadInput(str(exc).splitlines()[0] if str(exc) else "cannot read the file") from None
    t_load = time.perf_counter() - t0
    auto = str(a.links).strip().lower() == "auto"
    if auto:
        links = "auto"
    else:
        try:
            links = int(a.links)
        except ValueError:
            raise _BadInput(f"--links must be a whole number or 'auto', got {a.links!r}") from None
    try:
        t_fit = time.perf_counter()
        if not a.quiet:
            est, _ = api.plan(sc.n_faces - len(sc.degenerate_faces), sc.n_fields, sc.n_vertices, sc.kind,
                              options)
            print(est.describe() + (" -> reduced method" if est.reduced else ""), flush=True)
        result = api.fit(sc, links, options)
    except (S.ScanError, OptionsError) as exc:
        raise _BadInput(str(exc)) from None
    timings = {"load": t_load, **result.timings}
    timings["total"] = time.perf_counter() - t_fit
    result.timings = timings
    if a.output:
        result.save(a.output)
    written = {}
    if a.blend or a.glb or a.fbx or a.png:
        written = headless.build_outputs(a.scan, sc, result, a.blend, a.glb, a.png, fbx=a.fbx,
                                         mesh=prepared, rotation_only=a.rotation_only)
    rot_err = written.pop("rotation_only_error", None) if written else None
    if not a.quiet:
        print(f"{os.path.basename(a.scan)}: {sc.kind} scan, {sc.n_vertices} vertices, {sc.n_faces} triangles, "
              f"{sc.n_fields} fields")
        if result.link_reason:
            print(result.link_reason)
        print(result.summary())
        if sc.kind == "greens":
            f = sc.fields()
            expl = 100.0 * (1.0 - result.rms_articulation ** 2 / max(np.mean(np.sum(f * f, -1)), 1e-300))
            print(f"articulation explains {expl:.2f}% of the fields' energy")
        if rot_err is not None:
            print(f"rotation-only joints: added error max {rot_err[0]:.3f}%, "
                  f"rms {rot_err[1]:.3f}% of the diagonal")
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
