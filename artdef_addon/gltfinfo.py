"""What an exported glTF rig holds, read from its JSON (no ``bpy``): for the export's report.

A hand-off rig replaces a vertex animation, so the report says what it is made of — meshes,
vertices, bones, influences per vertex, morph targets, animation keys — and its size beside the
size of the file it replaces.
"""
from __future__ import annotations

import json
import os
import struct


def read_json(path) -> dict:
    """The JSON of a .glb (its first chunk) or a .gltf; ValueError for anything else."""
    with open(path, "rb") as fh:
        head = fh.read(12)
        if len(head) == 12 and head[:4] == b"glTF":
            length, kind = struct.unpack("<I4s", fh.read(8))
            if kind != b"JSON":
                raise ValueError(f"{os.fspath(path)}: the first chunk is not JSON")
            return json.loads(fh.read(length))
        return json.loads(head + fh.read())


def contents(path) -> dict:
    """Counts of a glTF file: ``meshes``, ``skins``, ``vertices`` (of every primitive of every
    mesh), ``bones`` (joints of the skins), ``influences`` (bone weights a vertex may have: 4 per
    JOINTS_n set), ``morph_targets`` (the most a primitive has), ``animations``, ``keys`` (the most
    times a sampler keys), ``channels`` and ``bytes`` (the file's size, a .gltf's buffers included)."""
    g = read_json(path)
    acc = g.get("accessors", [])
    prims = [p for m in g.get("meshes", []) for p in m.get("primitives", [])]
    size = os.path.getsize(path)
    for buf in g.get("buffers", []):
        uri = buf.get("uri")
        if uri and not uri.startswith("data:"):
            other = os.path.join(os.path.dirname(os.fspath(path)), uri)
            size += os.path.getsize(other) if os.path.isfile(other) else 0
    anims = g.get("animations", [])
    return dict(
        meshes=len(g.get("meshes", [])),
        skins=len(g.get("skins", [])),
        vertices=sum(acc[p["attributes"]["POSITION"]]["count"] for p in prims if "POSITION" in p["attributes"]),
        bones=sum(len(s.get("joints", [])) for s in g.get("skins", [])),
        influences=4 * max((sum(1 for k in p["attributes"] if k.startswith("JOINTS_")) for p in prims), default=0),
        morph_targets=max((len(p.get("targets", [])) for p in prims), default=0),
        animations=len(anims),
        keys=max((acc[s["input"]]["count"] for a in anims for s in a.get("samplers", [])), default=0),
        channels=sum(len(a.get("channels", [])) for a in anims),
        bytes=size)


def size_text(n: float) -> str:
    """Bytes as text: 912 B, 98.6 kB, 2.67 MB (powers of 1000, as file browsers show them)."""
    for unit, scale in (("MB", 1e6), ("kB", 1e3)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{int(n)} B"


def describe(path, source=None) -> str:
    """One line: what the glTF rig ``path`` holds, and its size beside the ``source`` file's (the
    vertex animation it replaces; a list of files: their sum), when given."""
    c = contents(path)
    text = (f"{c['meshes']} mesh{'es' if c['meshes'] != 1 else ''}, {c['vertices']:,} vertices, "
            f"{c['bones']} bones, up to {c['influences']} influences a vertex, "
            f"{c['morph_targets']} morph targets, {c['animations']} animation"
            f"{'s' if c['animations'] != 1 else ''} of {c['keys']} keys ({c['channels']} channels), "
            f"{size_text(c['bytes'])}")
    return text + replaces(c["bytes"], source)


def report(path, source=None) -> str:
    """:func:`describe` for a glTF file; for another format (FBX) its size beside the source's."""
    if os.fspath(path).lower().endswith((".glb", ".gltf")):
        return describe(path, source)
    size = os.path.getsize(path)
    return size_text(size) + replaces(size, source)


def replaces(size: int, source) -> str:
    """", the source X.glb 182 kB (0.54 x)": the size of the file(s) ``source`` a rig of ``size``
    bytes replaces, or "" when there is none to compare with."""
    paths = [source] if isinstance(source, (str, os.PathLike)) else list(source or [])
    paths = [p for p in paths if os.path.isfile(p)]
    if not paths:
        return ""
    total = sum(os.path.getsize(p) for p in paths)
    name = os.path.basename(os.fspath(paths[0])) + (f" and {len(paths) - 1} more" if len(paths) > 1 else "")
    return f"; the source {name} {size_text(total)} ({size / total:.2g} x)" if total else ""
