"""What is wrong with an animated file, in words a user acts on (no bpy here).

Blender's importers report a damaged file in their own terms ("Bad GLB: file size doesn't match",
"list index out of range", "Couldn't open file '/tmp/…/walk.fbx' (92)"). :func:`importer_error`
turns such a message into one line that says what is wrong with the file first, the importer's
own words after it, and the file as the user named it. :func:`gltf_not_finite` finds NaN or
infinite numbers in a glTF file's float data before Blender imports it: Blender's mesh validation
quietly replaces non-finite vertex positions by zeros, so after the import nothing would show.
"""
from __future__ import annotations

import base64
import json
import os
import re
import struct

import numpy as np

#: format names by extension
FORMATS = {".glb": "glTF", ".gltf": "glTF", ".fbx": "FBX", ".abc": "Alembic",
           ".usd": "USD", ".usdc": "USD", ".usda": "USD", ".usdz": "USD"}

#: (pattern in the importer's words, what it means for the file); the first match is used
_MEANINGS = [
    (r"file size doesn't match|unpack requires a buffer|failed to read complete|ends inside|"
     r"unexpected end|truncated", "it is cut short or damaged"),
    (r"json error|Bad glTF|no asset in json", "it is not a glTF file, or its JSON part is damaged"),
    (r"buffer is smaller than requested|past the end|out of bounds",
     "it is damaged: its data refer past the end of its binary buffer"),
    (r"Missing resource,? '([^']*)'", "its binary data file '{0}' is missing (a .gltf needs the files it "
                                      "names beside it)"),
    (r"index out of range|KeyError|invalid index", "it is damaged: it refers to data it does not hold"),
    (r"cannot reshape|assign sequence of size|could not broadcast",
     "it is damaged: its data do not fit the meshes they belong to"),
    (r"ASCII FBX", "it is not a binary FBX file (Blender reads binary FBX only), or it is damaged"),
    (r"Invalid header|Couldn't open file|nested block|sentinel",
     "it is not an FBX file, or it is damaged"),
    (r"Could not open USD", "it is not a USD file, or it is damaged"),
    (r"could not read", "it is not an {fmt} file, or it is damaged"),
]


def _plain(words: str, path: str, shown: str) -> str:
    """``words`` with the file's absolute path (quoted or not) written as ``shown``."""
    for p in {os.path.abspath(path), path}:
        words = words.replace(f"'{p}'", shown).replace(p, shown)
    return " ".join(words.split()).rstrip(".")


def importer_error(path: str, words: str, shown: str | None = None) -> str:
    """One line for Blender's importer failing on ``path`` with ``words``: ``"walk.glb: it is cut
    short or damaged (Blender's glTF importer: Bad GLB: file size doesn't match)"``. ``shown``:
    the file as the user named it (default: its name)."""
    shown = shown or os.path.basename(path)
    fmt = FORMATS.get(os.path.splitext(path)[1].lower(), "animated")
    words = _plain(words, path, shown)
    meaning = f"it is damaged or not a valid {fmt} file"
    for pattern, text in _MEANINGS:
        m = re.search(pattern, words, flags=re.IGNORECASE)
        if m:
            meaning = text.format(*m.groups(), fmt=fmt)
            break
    importer = f"Blender's {fmt} importer"
    return f"{shown}: {meaning} ({importer}: {words})" if words else f"{shown}: {meaning}"


# ------------------------------------------------------------------------- glTF float data

_COMPONENTS = {5126: "<f4"}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


def _gltf_parts(path: str):
    """``(json dict, [buffer bytes or None])`` of a .glb or .gltf; ValueError when unreadable."""
    with open(path, "rb") as f:
        raw = f.read()
    blobs = []
    if raw[:4] == b"glTF":
        n, _ = struct.unpack_from("<II", raw, 12)
        doc = json.loads(raw[20:20 + n].decode("utf-8"))
        if len(raw) >= 28 + n:
            m, kind = struct.unpack_from("<II", raw, 20 + n)
            blobs.append(raw[28 + n:28 + n + m] if kind == 0x004E4942 else None)
    else:
        doc = json.loads(raw.decode("utf-8"))
    if not isinstance(doc, dict):
        raise ValueError("not a glTF document")
    folder = os.path.dirname(os.path.abspath(path))
    for i, buf in enumerate(doc.get("buffers", [])):
        uri = buf.get("uri")
        if uri is None:
            if i >= len(blobs):
                blobs.append(None)
            continue
        if uri.startswith("data:"):
            data = base64.b64decode(uri.split(",", 1)[1]) if "," in uri else None
        else:
            try:
                with open(os.path.join(folder, uri), "rb") as f:
                    data = f.read()
            except OSError:
                data = None
        if i < len(blobs):
            blobs[i] = data
        else:
            blobs.append(data)
    return doc, blobs


def _uses(doc) -> dict:
    """What each float accessor of ``doc`` holds, by accessor index: the words for a message."""
    out = {}
    for mesh in doc.get("meshes", []):
        name = mesh.get("name", "a mesh")
        for prim in mesh.get("primitives", []):
            for key, index in prim.get("attributes", {}).items():
                if key in ("POSITION", "NORMAL", "TANGENT") or key.startswith("WEIGHTS"):
                    out.setdefault(index, f"the {key.lower()}s of mesh '{name}'")
            for k, target in enumerate(prim.get("targets", [])):
                if "POSITION" in target:
                    out.setdefault(target["POSITION"], f"morph target {k} of mesh '{name}'")
    for skin in doc.get("skins", []):
        if "inverseBindMatrices" in skin:
            out.setdefault(skin["inverseBindMatrices"], f"the bind matrices of skin '{skin.get('name', '')}'")
    for anim in doc.get("animations", []):
        name = anim.get("name", "an animation")
        for s in anim.get("samplers", []):
            out.setdefault(s.get("input"), f"the keyframe times of animation '{name}'")
            out.setdefault(s.get("output"), f"the keyed values of animation '{name}'")
    return out


def gltf_not_finite(path: str) -> str | None:
    """The first float data of the glTF file ``path`` that holds NaN or infinite numbers, in words
    (``"NaN or infinite numbers in the keyframe times of animation 'Walk' (accessor 12)"``), or
    None: all finite, or the file too damaged to tell (its importer then says why)."""
    try:
        doc, blobs = _gltf_parts(path)
        uses = _uses(doc)
        views = doc.get("bufferViews", [])
        for index, acc in enumerate(doc.get("accessors", [])):
            if index not in uses or acc.get("componentType") not in _COMPONENTS or "bufferView" not in acc:
                continue
            view = views[acc["bufferView"]]
            blob = blobs[view.get("buffer", 0)]
            if blob is None:
                continue
            width = _WIDTH[acc.get("type", "SCALAR")]
            start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
            stride = view.get("byteStride") or 4 * width
            count = int(acc["count"])
            if count <= 0 or start + stride * (count - 1) + 4 * width > len(blob):
                continue                     # past the buffer: the importer reports it
            rows = np.ndarray((count, width), dtype="<f4", buffer=blob, offset=start, strides=(stride, 4))
            if not np.isfinite(rows).all():
                return f"NaN or infinite numbers in {uses[index]} (accessor {index})"
    except (ValueError, KeyError, IndexError, TypeError, OSError, struct.error, UnicodeDecodeError):
        return None
    return None
