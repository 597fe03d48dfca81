"""Command line: ``python -m artdef_addon fit|sample|info ...``.

Exit codes: 0 success, 2 bad input (one line on stderr, nothing written), 1 failure while working
or writing (one line, earlier files intact), 130 interrupted. See docs/command_line.md.
"""
from __future__ import annotations

import argparse
import atexit
import contextlib
import os
import sys
import time

import numpy as np

from . import wording
from .options import LINKS, FitOptions, OptionError, OptionsError


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
        elif opt.auto:      # a count or "auto" (the default: chosen from the data), read in _cmd_fit
            helptext += " (default: auto)" + (" [tracked scans]" if opt.tracked_only else "")
            parser.add_argument(flag, default=None, help=helptext,
                                metavar="{auto,N}")
        else:       # None: not given, the declared default applies (max_links: see _cmd_fit)
            helptext += f" (default: {'off' if default is None else default})"
            parser.add_argument(flag, type=opt.type, default=None, help=helptext)


#: --links auto tries up to this many links unless --max-links says otherwise (then clamped to the
#: scan's triangles; an explicit --max-links above them is refused)
DEFAULT_MAX_LINKS = FitOptions().max_links   # --links auto: clamped to the scan's triangles


def _parser() -> argparse.ArgumentParser:
    p = _Parser(prog="python -m artdef_addon",
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
    f.add_argument("--mesh", action="append", default=[], metavar="NAME",
                   help="animated files: fit this mesh of the file (repeatable; default: every "
                        "animated mesh, fitted together as one rig)")
    f.add_argument("--frames", metavar="START:END[:STEP]",
                   help="animated files or sequences: frames to sample in each input, --clip "
                        "ones too (a sequence's file numbers are its frames; default: the "
                        "file's keys, every file of a sequence)")
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


#: outputs renamed into place by this run (so a late Ctrl-C is reported truthfully)
_committed: list = []


class _BadInput(Exception):
    pass


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors: ``artdef: error: ...``, exit 2 (no usage block)."""

    def error(self, message):
        raise _BadInput(message)


def _fail(msg: str, code: int = 2) -> int:
    print(f"artdef: error: {msg}", file=sys.stderr, flush=True)
    return code


def _check(rng, name, value):
    try:
        return rng.check(name, value)
    except OptionError as exc:
        raise _BadInput(str(exc)) from None


def _cmd_sample(a) -> int:
    from . import files, samples
    R = samples.RANGES
    files.check_outputs([], {"-o": a.output})
    if a.name not in samples.NAMES:
        raise _BadInput(f"unknown sample {a.name!r}; choose from {', '.join(samples.NAMES)}")
    kw = {}
    if a.fields is not None:
        if a.name == "greens_rod":
            raise _BadInput("--fields does not apply to greens_rod (its fields are its load columns)")
        kw["n_fields"] = _check(R["fields"], "--fields", a.fields)
    if a.seed is not None:
        if a.name == "greens_rod":
            raise _BadInput("--seed does not apply to greens_rod (it is not random)")
        kw["seed"] = _check(R["seed"], "--seed", a.seed)
    noise = _check(R["noise"], "--noise", a.noise)
    if a.name == "branching":
        kw.update(noise=noise, bulges=a.bulges, disconnected=a.disconnected)
    elif noise or a.bulges or a.disconnected:
        raise _BadInput("--noise, --bulges and --disconnected apply to the branching sample only")
    try:
        sc = samples.make(a.name, **kw)
    except (ValueError, TypeError) as exc:
        raise _BadInput(str(exc)) from None
    # a sample is checked where it is made (samples): it is written only if it can be fitted
    files.write_scan(a.output, sc)
    print(f"wrote {a.output}: {a.name}, {sc.n_vertices} vertices, {sc.n_faces} triangles, "
          f"{sc.n_fields} fields ({sc.kind})")
    return 0


def search_printer(out=None):
    """A ``progress(stage, fraction)`` callback that prints the link-count search's stage
    (``"links"``) as "choosing the link count: 40%" at 0 and every further tenth; other stages
    are not printed. Never cancels."""
    last = [-1]

    def progress(stage, fraction):
        if stage == "links":
            tenth = int(10 * min(max(float(fraction), 0.0), 1.0) + 1e-9)
            if tenth > last[0]:
                last[0] = tenth
                print(f"choosing the link count: {10 * tenth}%", file=out or sys.stdout, flush=True)
        return False
    return progress


def _cmd_info(a) -> int:
    from . import files
    d = files.read_npz(a.path)          # BadFile: one line naming the file
    if "face_labels" in d:
        from .result import FitResult
        res = FitResult.load(a.path)
        print(f"{a.path}: fit result")
        print(res.summary())
        return 0
    sc = files.read_scan(a.path)
    print(f"{a.path}: {sc.kind} scan, {sc.n_vertices} vertices, {sc.n_faces} triangles, "
          f"{sc.n_fields} fields, {sc.n_loads} loads, "
          f"{0 if sc.support_vertices is None else len(sc.support_vertices)} support vertices, "
          f"{len(sc.degenerate_faces)} degenerate triangles, probe load {sc.probe_load:g}")
    from .cost import estimate, resident_bytes
    print(estimate(sc.n_faces - len(sc.degenerate_faces), sc.n_fields, sc.n_vertices,
                   "paper" if sc.kind == "greens" else "summed").describe(resident_bytes()))
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


def input_files(path: str) -> list:
    """Every file a run reads through the input ``path``, for the outputs' "not an input" check:
    the file itself; a ``.gltf``'s external buffers and images; for a sequence (a folder, a pattern
    or one numbered file), every OBJ/PLY file of its folder (a superset of its frames, so that no
    output can replace one of them)."""
    out = [path]
    kind = input_kind(path)
    if kind == "sequence":
        folder = path if os.path.isdir(path) else (os.path.dirname(path) or ".")
        try:
            names = os.listdir(folder)
        except OSError:
            names = []
        out += [os.path.join(folder, n) for n in names
                if os.path.splitext(n)[1].lower() in SEQUENCE_EXTENSIONS]
    elif path.lower().endswith(".gltf") and os.path.isfile(path):
        import json
        from urllib.parse import unquote
        try:
            with open(path, "rb") as f:
                doc = json.loads(f.read())
            uris = [item.get("uri") for key in ("buffers", "images") for item in doc.get(key) or []
                    if isinstance(item, dict)]
        except (OSError, ValueError, AttributeError, TypeError):
            uris = []          # an unreadable .gltf is refused when it is read
        folder = os.path.dirname(path)
        out += [os.path.join(folder, unquote(u)) for u in uris
                if isinstance(u, str) and u and not u.startswith("data:")]
    return out


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
    if max(abs(start), abs(end), step) > FRAME_LIMIT:
        raise ValueError(f"--frames {text}: frames and step must lie within ±{FRAME_LIMIT:,} "
                         "(Blender's frame numbers are 32-bit)")
    return start, end, step


#: the largest frame number (and step) ``--frames`` takes: Blender's integer properties are 32-bit
FRAME_LIMIT = 2 ** 31 - 1


def blender_entry() -> str:
    """The Blender side's entry point of this command line, ``scripts/artdef_fit.py``.

    The core never imports the Blender layer (not even lazily, not by a file path): a command that
    needs Blender (--blend/--glb/--fbx/--png, or an input only Blender reads) is handed whole to
    this script (:func:`hand_to_blender`), which runs the same command line with the Blender layer
    (``operators/headless.py``) passed in (``main(argv, blender=...)``). Run inside Blender
    (``blender -b -P scripts/artdef_fit.py -- ...``) it is the entry point from the start."""
    path = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "scripts", "artdef_fit.py")
    if not os.path.isfile(path):
        raise _BadInput(f"--blend/--glb/--fbx/--png and animated inputs need the Blender side's entry point "
                        f"({path} is missing)")
    return path


def hand_to_blender(argv, replace: bool) -> int:
    """Run the command ``argv`` through :func:`blender_entry` with this Python: as this process
    (``replace``: the command line's own process, ``python -m artdef_addon``; the exit code, output
    and signals are the entry point's) or as a child whose exit code is returned (a caller of
    :func:`main` in its own process)."""
    args = [sys.executable, blender_entry(), "--", *argv]
    sys.stdout.flush()
    sys.stderr.flush()
    if replace and os.name == "posix":
        os.execv(sys.executable, args)
    import subprocess
    return subprocess.call(args)


#: the largest coordinate (rest position plus displacement) the Blender outputs take: Blender holds
#: positions as 32-bit floats, whose squares overflow beyond about 1.8e19 (the rod scaled by 3e18 fitted,
#: then its glTF export failed on NaN, as an internal error; scaled by 1e38 its mesh held infinities)
BLENDER_MAX = 1e19


def _check_for_blender(sc, a) -> None:
    """_BadInput (before the fit) when the Blender outputs cannot hold the scan: a vertex listed as two
    load points, or positions beyond what Blender's 32-bit floats hold."""
    from .scan import reach as reach_of, repeated_load_vertex
    what = "--" + "/--".join(k for k in ("blend", "glb", "fbx", "png") if getattr(a, k))
    repeated = repeated_load_vertex(sc)
    if repeated is not None:
        raise _BadInput(f"{what}: {repeated}, or fit without the Blender outputs")
    reach = reach_of(sc)
    if reach > BLENDER_MAX:
        raise _BadInput(f"{what}: the scan's positions reach {reach:.3g}; Blender holds them as 32-bit floats, "
                        f"whose squares overflow beyond about {BLENDER_MAX:.0e}: rescale the scan (other units), or fit "
                        f"without the Blender outputs")


def _utf8(path: str) -> bool:
    try:
        os.fsencode(path).decode("utf-8")
    except UnicodeDecodeError:
        return False
    return True


def _cmd_fit(a, headless=None, hand_over=None) -> int:
    """The fit command. ``headless``: the Blender layer; without it, once the command's own checks
    have passed, a command that needs Blender is run by ``hand_over()`` (:func:`hand_to_blender`)."""
    from . import api, files
    from . import cost as _cost
    from . import result as result_module
    R = {name: opt.range for name, (_, opt) in FitOptions.declaration().items() if not opt.choices}
    t0 = time.perf_counter()
    blender = bool(a.blend or a.glb or a.fbx or a.png)
    # every output checked before any work: writable directory, not an input, not each other
    read = [f for p in (a.scan, *a.clip) for f in input_files(p)]
    files.check_outputs(read, {"-o": a.output, "--blend": a.blend, "--glb": a.glb, "--fbx": a.fbx, "--png": a.png})
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
        if input_kind(clip) == "animated" and not os.path.isfile(clip):
            raise _BadInput(f"--clip {clip}: not a regular file")
    if frames is not None and kind == "npz":
        raise _BadInput("--frames applies to animated files and sequences, not to a .npz scan")
    if a.mesh and kind != "animated":
        raise _BadInput("--mesh applies to animated files, not to a .npz scan or a sequence")
    auto = str(a.links).strip().lower() == "auto"
    try:
        links = None if auto else LINKS.check("--links", a.links)
    except OptionError as exc:
        raise _BadInput(f"{exc} (or 'auto')") from None
    max_links = None if a.max_links is None else _check(R["max_links"], "--max-links", a.max_links)
    if a.p_max is not None:
        _check(R["p_max"], "--p-max", a.p_max)
    if a.memory_budget is not None:
        _check(R["memory_budget"], "--memory-budget", a.memory_budget)
    if a.jobs is not None:
        _check(R["jobs"], "--jobs", a.jobs)
    for name, (_, opt) in FitOptions.declaration().items():
        value = getattr(a, name)
        if opt.auto and value is not None:      # "auto" is the declared default (None)
            auto_value = str(value).strip().lower() == "auto"
            flag = "--" + name.replace("_", "-")
            try:
                setattr(a, name, None if auto_value else R[name].check(flag, value))
            except OptionError as exc:
                raise _BadInput(f"{exc} (or 'auto')") from None
    given = {name: getattr(a, name) for name in FitOptions.declaration() if getattr(a, name) is not None}
    try:
        options = FitOptions(**given)          # the one check of the settings
    except OptionsError as exc:
        raise _BadInput(str(exc)) from None
    if blender or kind != "npz":
        # Blender's names and file paths are UTF-8 text: a name that is not (bytes a POSIX file name
        # may hold) failed after the fit as "internal error: TypeError: BlendDataMeshes.new() ...
        # surrogates not allowed"
        seen = [a.scan, *a.clip] + [p for p in (a.blend, a.glb, a.fbx, a.png) if p]
        for path in seen:
            if not _utf8(os.path.abspath(path)):
                shown = os.fsencode(path).decode("utf-8", "backslashreplace")
                raise _BadInput(f"{shown}: Blender takes only file and folder names in UTF-8, and this one "
                                "is not: rename it")
        # Python finds its temporary folder by writing and removing a probe file there the first
        # time it is asked: ask now, not inside the Blender stage's output capture, where a Ctrl-C
        # could leave the probe behind (blender_output's log is a temporary file)
        import tempfile
        tempfile.gettempdir()
        if headless is None:
            return hand_over()
        try:
            headless.require_bpy()
        except RuntimeError as exc:
            what = ("--" + "/--".join(k for k in ("blend", "glb", "fbx", "png") if getattr(a, k))
                    if kind == "npz" else f"reading {os.path.basename(a.scan)}")
            raise _BadInput(str(exc).replace("this needs Blender", f"{what} needs Blender", 1)) from None
    prepared = None
    if kind == "npz":
        sc = files.read_scan(a.scan)    # BadFile: one line naming the file and the problem
    else:
        if not os.path.exists(a.scan) and kind == "animated":
            raise _BadInput(f"{a.scan}: no such file")
        if kind == "animated" and not os.path.isfile(a.scan):
            raise _BadInput(f"{a.scan}: not a regular file")
        try:
            with blender_output() as import_log:
                prepared, sc = headless.scan_from_file(a.scan, frames, clips=a.clip, meshes=a.mesh)
            if not a.quiet:
                for line in _warnings_of(import_log, {}):
                    print(line)
                dropped = prepared.data.get("artdef_dropped_faces") if prepared is not None else None
                if dropped:
                    print(f"note: {dropped} faces of {a.scan} were left out: {wording.DROPPED_FACES}")
                which = prepared.data.get("artdef_meshes") if prepared is not None else None
                if which:
                    print(f"note: {os.path.basename(a.scan)}: {which}")
        except RuntimeError as exc:
            line = str(exc).splitlines()[0] if str(exc) else "cannot read the file"
            for p in (a.scan, *a.clip):         # paths as the user typed them
                line = line.replace(os.path.abspath(p).rstrip(os.sep), p.rstrip(os.sep) or p)
            if not any(os.path.basename(p.rstrip("/")) in line for p in (a.scan, *a.clip)):
                line = f"{a.scan}: {line}"      # an importer's own message names no file
            raise _BadInput(line) from None
    if blender:
        _check_for_blender(sc, a)
    t_load = time.perf_counter() - t0
    if not a.quiet:
        # settings this fit does not use are kept in the result (one settings record for every
        # layer), and said to have no effect here rather than dropped silently
        if a.max_links is not None and not auto:
            print("note: --max-links bounds the link-count search; it has no effect with a fixed --links")
        if a.p_max is not None and sc.kind != "greens":
            print("note: --p-max (strain hardening under the probe loads) has no effect on a tracked scan")
    if a.rotation_only and sc.kind == "greens":
        raise _BadInput("--rotation-only applies to tracked scans (a Green's rig is posed by its load controls; "
                        "in Blender, Finalize it first)")
    usable = sc.n_faces - len(sc.degenerate_faces)
    why = f" (the scan's {usable} non-degenerate triangles)"
    if auto and max_links is None:
        max_links = min(FitOptions().max_links, usable)
    elif auto:
        max_links = _check(R["max_links"].within(usable, why), "--max-links", max_links)
    else:
        links = _check(LINKS.within(usable, why), "--links", links)
    if auto:
        options = options.replace(max_links=max_links)
    t_fit = time.perf_counter()
    if not a.quiet:
        # priced for this link count (or the --links auto search)
        est, _ = api.plan(usable, sc.n_fields, sc.n_vertices, sc.kind, options,
                          links=None if auto else links, auto=auto)
        loads_blender = blender and "bpy" not in sys.modules     # the outputs will load it after the fit
        print(est.describe(_cost.resident_bytes(), _cost.BLENDER_OUTPUT_BYTES if loads_blender else 0.0)
              + (f" with the link-count search up to {max_links} links" if auto else "")
              + (" -> reduced method" if est.reduced else ""), flush=True)
    # the link-count search is its own stage: its share done, in tenths (a search can take minutes)
    progress = search_printer() if auto and not a.quiet else None
    result = api.fit(sc, "auto" if auto else links, options, progress)     # sc and options checked above
    timings = {"load": t_load, **result.timings}
    timings["total"] = time.perf_counter() - t_fit
    result.timings = timings
    # all outputs are written to temporaries and renamed into place together at the end: a failure
    # or Ctrl-C anywhere before leaves every earlier file byte-identical and no partial file
    rot_err = None
    with files.Outputs() as out:
        if a.output:
            out.write_npz(a.output, result_module.result_arrays(result), compress=True)
        if blender:
            # temporaries first (registered for clean-up), then the Blender stage: the rig is built
            # from this result, one fit per command
            tmp = {k: v and out.path(v) for k, v in (("blend", a.blend), ("glb", a.glb), ("png", a.png),
                                                     ("fbx", a.fbx))}
            if not a.quiet:
                print("building the Blender outputs", flush=True)
            with blender_output() as stage_log:
                made = headless.build_outputs(a.scan, sc, result, tmp["blend"], tmp["glb"], tmp["png"],
                                              fbx=tmp["fbx"], mesh=prepared, rotation_only=a.rotation_only)
            rot_err = made.pop("rotation_only_error", None) if made else None
            if not a.quiet:
                for line in _warnings_of(stage_log, {v: getattr(a, k) for k, v in tmp.items() if v}):
                    print(line)
        try:
            out.commit()
        finally:
            _committed.extend(out.committed)
    if not a.quiet:
        print(f"{os.path.basename(a.scan)}: {sc.kind} scan, {sc.n_vertices} vertices, {sc.n_faces} triangles, "
              f"{sc.n_fields} fields")
        if result.link_reason:
            plain = wording.plain_link_reason(result.n_links, result.link_errors, result.articulation_error_percent)
            print(plain + "\n" + result.link_reason if plain else result.link_reason)
        print(result.summary())
        if sc.kind == "greens":
            f = sc.fields()
            expl = 100.0 * (1.0 - result.rms_articulation ** 2 / max(np.mean(np.sum(f * f, -1)), 1e-300))
            print(f"articulation explains {expl:.2f}% of the fields' energy")
        if rot_err is not None:
            print(f"rotation-only joints: added error max {rot_err[0]:.3f}%, "
                  f"rms {rot_err[1]:.3f}% of the diagonal")
        sources = read if kind != "npz" else []       # the vertex animation a rig replaces
        for path in (a.output, a.blend, a.glb, a.fbx, a.png):
            if path:
                print(f"wrote {path}" + _rig_report(path, sources if path in (a.glb, a.fbx) else None))
    return 0


def _rig_report(path: str, sources) -> str:
    """": what the exported rig holds and its size beside its source's" (``sources`` None: not a rig)."""
    from . import gltfinfo
    return "" if sources is None else ": " + gltfinfo.report(path, sources)


class _Terminated(KeyboardInterrupt):
    """SIGTERM (``kill``, ``timeout``, a cancelled job): the same clean-up as Ctrl-C."""


def _on_sigterm(signum, frame):
    raise _Terminated


def main(argv=None, blender=None) -> int:
    """Run the command line; returns the exit code (README, "Exit codes and guarantees"):
    0 success, 2 bad input or unusable output path (one line, nothing written), 1 a failure while
    working or writing (one line, earlier files intact), 130 interrupted (Ctrl-C; nothing written),
    143 terminated (SIGTERM, handled as Ctrl-C while the command runs).

    ``blender``: the Blender layer (``operators/headless.py``), passed by the Blender side's entry
    point (:func:`blender_entry`); without it a command that needs Blender is handed to that entry
    point (:func:`hand_to_blender`: with ``argv`` None, as this process)."""
    import signal
    try:
        old = signal.signal(signal.SIGTERM, _on_sigterm)
    except ValueError:              # not the main thread: the caller handles its signals
        old = None
    streams = sys.stdout, sys.stderr
    sys.stdout, sys.stderr = (s if s is None else _Unbroken(s) for s in streams)
    try:
        return _main(argv, blender)
    finally:
        sys.stdout, sys.stderr = streams
        if old is not None:         # the caller's handler again (tests and scripts call main in-process)
            signal.signal(signal.SIGTERM, old)


class _Unbroken:
    """``sys.stdout`` / ``sys.stderr`` while a command runs: once the reader has closed the pipe
    (``fit ... | head -1``) what is printed later is dropped, not raised as ``BrokenPipeError``.
    The lines are a report; the outputs are the work, and a reader that has seen enough must not
    cost the user them (the fit went on, the outputs are written, the exit code is the command's).
    The stream's descriptor is pointed at ``os.devnull``, so Blender's own printing and Python's
    flush at exit find no broken pipe either."""

    def __init__(self, stream):
        self._stream = stream
        self._broken = False

    def write(self, text):
        if not self._broken:
            try:
                return self._stream.write(text)
            except BrokenPipeError:
                self._break()
        return len(text)

    def flush(self):
        if not self._broken:
            try:
                self._stream.flush()
            except BrokenPipeError:
                self._break()

    def _break(self):
        self._broken = True
        try:
            null = os.open(os.devnull, os.O_WRONLY)
            try:
                os.dup2(null, self._stream.fileno())
            finally:
                os.close(null)
            self._stream.flush()        # what it still holds goes to os.devnull
        except (OSError, ValueError, AttributeError):   # no descriptor (a test's capture, an embedding host)
            pass

    def __getattr__(self, name):
        return getattr(self._stream, name)


def _main(argv, blender=None):
    from .files import OutputError
    from .scan import ScanError
    _committed.clear()
    import warnings
    replace = argv is None
    given, argv, i = list(sys.argv[1:] if argv is None else argv), [], 0
    while i < len(given):
        # a range starting below zero ("--frames -5:3") would read as an option to argparse
        if given[i] == "--frames" and i + 1 < len(given) and given[i + 1].startswith("-") and ":" in given[i + 1]:
            argv.append("--frames=" + given[i + 1])
            i += 2
        else:
            argv.append(given[i])
            i += 1
    try:
        a = _parser().parse_args(argv)
        with warnings.catch_warnings():
            # numpy's overflow / invalid-value notes on extreme but accepted scans (coordinates near
            # scan.MAX_MAGNITUDE) are not the user's to act on: the command prints its one line
            warnings.simplefilter("ignore", RuntimeWarning)
            if a.command == "fit":
                return _cmd_fit(a, blender, lambda: hand_to_blender(given, replace))
            return {"sample": _cmd_sample, "info": _cmd_info}[a.command](a)
    except (_BadInput, ScanError, OptionsError, OutputError, OptionError) as exc:
        return _fail(" ".join(str(exc).split()) or "bad input")
    except KeyboardInterrupt as exc:
        what, code = ("terminated", 143) if isinstance(exc, _Terminated) else ("interrupted", 130)
        if _committed:
            return _fail(f"{what} after writing {', '.join(_committed)}", code)
        return _fail(f"{what}; no file was written or changed", code)
    except BrokenPipeError:         # stdout closed by the reader (| head): not an error of ours
        try:
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        except (OSError, ValueError):
            pass
        return 141
    except SystemExit as exc:       # --help / --version
        return exc.code if isinstance(exc.code, int) else 0
    except OSError as exc:
        where = f" {exc.filename}" if exc.filename else ""
        kept = (f"; already written: {', '.join(_committed)}, the other files are unchanged" if _committed
                else "; earlier files are unchanged")
        return _fail(f"cannot write{where}: {exc.strerror or exc}{kept}", 1)
    except MemoryError:
        return _fail("out of memory; earlier files are unchanged", 1)
    except Exception as exc:
        if os.environ.get("ARTDEF_TRACEBACK"):
            raise
        msg = " ".join(str(exc).split())
        return _fail(f"internal error: {type(exc).__name__}: {msg} (earlier files are unchanged; "
                     "set ARTDEF_TRACEBACK=1 for the traceback)", 1)


class _BlenderLog:
    """What Blender printed during a stage of :func:`blender_output` (``text``, after it ends)."""
    text = ""


@contextlib.contextmanager
def blender_output():
    """Keep Blender's own printing off the terminal for a ``with`` block: its operators' reports,
    its importers' and exporters' logs, the GPU back end's warnings, written by C code and by its
    add-ons to the process's stdout and stderr. They go to a temporary file instead (both file
    descriptors), so ``-q`` prints nothing on success and the command line's own lines are all a
    user sees; yields a :class:`_BlenderLog` holding the text afterwards. With ``ARTDEF_TRACEBACK``
    set the output is left on the terminal (a failure's details, and a crash's, which would die with
    the temporary file), as it is where the process has no real stdout/stderr descriptors (an
    embedding host)."""
    import tempfile
    captured = _BlenderLog()
    sys.stdout.flush()
    sys.stderr.flush()
    try:
        saved = None if os.environ.get("ARTDEF_TRACEBACK") else (os.dup(1), os.dup(2))
    except OSError:
        saved = None
    if saved is None:
        yield captured
        return
    log = tempfile.TemporaryFile()
    try:
        os.dup2(log.fileno(), 1)
        os.dup2(log.fileno(), 2)
        yield captured
    finally:
        _flush_c_stdio()
        sys.stdout.flush()
        sys.stderr.flush()
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        os.close(saved[0])
        os.close(saved[1])
        log.seek(0)
        captured.text = log.read().decode("utf-8", "replace")
        log.close()


def _flush_c_stdio() -> None:
    """Flush the C library's stdio buffers (Blender's printf), so nothing written inside
    :func:`blender_output` reaches the terminal after it; best effort (POSIX)."""
    try:
        import ctypes
        ctypes.CDLL(None).fflush(None)
    except Exception:
        pass


def _warnings_of(log: _BlenderLog, paths: dict) -> list:
    """Blender's warning reports in ``log`` (lines ``Warning: ...``), the temporary output paths
    in them replaced by the final ones (``paths``: temporary -> final)."""
    out = []
    for line in log.text.splitlines():
        if line.startswith("Warning: "):
            for tmp, final in paths.items():
                line = line.replace(tmp, final)
            out.append(line)
    return out


def remove_blender_tempdir() -> None:
    """Remove Blender's session folder (``bpy.app.tempdir``, ``<temp>/blender_XXXXXX/``) if ``bpy``
    is loaded. Blender removes it in its C-level teardown, which :func:`exit_process` skips: without
    this every run that loads bpy leaves one behind in the system's temporary folder. Only a folder
    named ``blender_*`` is removed (the session's own, never a configured temporary folder)."""
    bpy = sys.modules.get("bpy")
    path = getattr(getattr(bpy, "app", None), "tempdir", "") if bpy is not None else ""
    path = os.path.normpath(path) if path else ""
    if os.path.basename(path).startswith("blender_") and os.path.isdir(path):
        import shutil
        shutil.rmtree(path, ignore_errors=True)


def exit_process(code) -> None:
    """End the process with ``code``.  With ``bpy`` loaded: run the Python exit
    handlers (the temporary extension repository's clean-up), remove Blender's session
    folder (:func:`remove_blender_tempdir`), flush, and ``os._exit``, skipping the C-level
    teardown, because the bpy 4.5 module can deadlock in its C++ static destructors at exit
    after a glTF import/export (outputs written, then a futex wait forever; see
    operators/compat.py). Only inspects ``sys.modules``: the core never imports bpy."""
    code = 0 if code is None else code
    if "bpy" not in sys.modules:
        sys.exit(code)
    atexit._run_exitfuncs()
    remove_blender_tempdir()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code if isinstance(code, int) else 1)
