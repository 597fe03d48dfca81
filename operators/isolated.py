# SPDX-License-Identifier: GPL-3.0-or-later
"""Blender's importers first run in a child process, where their crash cannot take Blender down.

Blender's Alembic and USD importers are compiled code: a damaged file can abort them, and with
them the process they run in (the user's Blender session, unsaved work and all, or the command
line with no message). So *Fields from File* first reads the file in a worker process
(:class:`artdef_addon.procs.Worker`, started with :func:`interpreter`): the child imports it into
its own empty scene and samples it exactly as the operator would (:func:`sample_file`). Only a file
the child read cleanly is then imported into the user's scene; otherwise the scene is unchanged
and :func:`read_in_child` raises one line naming the file and what happened: the importer crashed,
ran out of memory, took longer than :func:`time_limit`, or the file's own problem (the child's
error line).

The cost is a process start (Blender's Python and the extension's operators) and a second import
of the file: ``benchmarks/bench_import_check.py`` measures it.
"""
import os
import sys

import bpy

from ..artdef_addon import procs as _procs

#: what each importer is called in a message
IMPORTER_NAMES = {".glb": "glTF", ".gltf": "glTF", ".fbx": "FBX", ".abc": "Alembic",
                  ".usd": "USD", ".usdc": "USD", ".usda": "USD", ".usdz": "USD"}
#: the child's time limit: this many seconds, plus :data:`SECONDS_PER_MB` per megabyte of the file
BASE_SECONDS = 60.0
SECONDS_PER_MB = 4.0
#: the child's memory limit, as a fraction of the machine's physical memory
MEMORY_FRACTION = 0.6
#: the function the child runs
FUNCTION = "artdef_child.operators.isolated:sample_file"


def interpreter() -> list:
    """The command line that starts a child with Blender and this extension (:mod:`.child`):
    Blender itself in the background when this is Blender, else this Python (the bpy module)."""
    script = os.path.join(os.path.dirname(os.path.abspath(__file__)), "child.py")
    binary = getattr(bpy.app, "binary_path", "")
    if binary:
        # factory preferences and startup file: not the user's add-ons (this one among them: the
        # child registers its own copy); the child needs only Blender's bundled modules
        return [binary, "-b", "--factory-startup", "--python", script, "--"]
    return [sys.executable, script, "--"]


def time_limit(path: str) -> float:
    """Seconds the child may take to read ``path`` (and its .bin, for a .gltf)."""
    size = 0
    try:
        size = os.path.getsize(path)
    except OSError:
        pass
    return BASE_SECONDS + SECONDS_PER_MB * size / 2**20


def memory_limit() -> float | None:
    """Bytes the child may map beyond Blender's own (Linux; None where unknown)."""
    try:
        return MEMORY_FRACTION * os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def importer_of(path: str) -> str:
    return f"Blender's {IMPORTER_NAMES.get(os.path.splitext(path)[1].lower(), '')} importer".replace("  ", " ")


def read_in_child(path: str, meshes: str = "", frames: dict | None = None, shown: str | None = None) -> dict:
    """Import and sample ``path`` in a child process (nothing of this process is touched);
    returns the child's counts ``{"vertices", "fields", "meshes"}``. RuntimeError with one line
    naming the file (``shown``: as the user gave it; default its name) otherwise."""
    name = shown or os.path.basename(path)
    params = {"path": os.path.abspath(path), "meshes": meshes, "frames": dict(frames or {})}
    limit = time_limit(path)
    try:
        with _procs.Worker(interpreter=interpreter(), memory_limit=memory_limit(),
                           name="artdef-import", inherit_path=False) as worker:
            values, _ = worker.submit(FUNCTION, {}, params, timeout=limit).wait()
    except _procs.WorkerError as err:
        raise RuntimeError(_line(err, path, name, limit)) from None
    except OSError as err:
        raise RuntimeError(f"cannot start a process to read {name}: {err}") from None
    return values


def _line(err, path: str, name: str, limit: float) -> str:
    importer = importer_of(path)
    if err.kind == "error":
        line = str(err)
        return line if name in line or os.path.basename(path) in line else f"{name}: {line}"
    if err.kind == "memory":
        return f"{importer} ran out of memory reading {name} (the file may be damaged)"
    if err.kind == "timeout":
        return f"{importer} did not finish reading {name} within {limit:.0f} s (the file may be damaged)"
    if err.kind == "cancelled":
        return f"reading {name} was cancelled"
    return f"{importer} crashed reading {name} (the file may be damaged)"


# ----------------------------------------------------------------------------- in the child

def sample_file(arrays, params, report):
    """The child's half: *Fields from File* on ``params["path"]`` in the child's empty scene,
    without a child of its own. ValueError with the operator's one line when it fails."""
    from . import animfile
    try:
        result = bpy.ops.artdef.fields_from_file(filepath=params["path"], meshes=params["meshes"],
                                                 isolate=False, **params["frames"])
    except RuntimeError as err:        # the operator's ERROR report
        raise ValueError(animfile.operator_error(err)) from None
    if 'FINISHED' not in result:
        raise ValueError(f"cannot sample {os.path.basename(params['path'])}")
    obj = bpy.context.view_layer.objects.active
    return {"vertices": len(obj.data.vertices), "meshes": obj.data.get("artdef_meshes", ""),
            "pid": os.getpid()}
