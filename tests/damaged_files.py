"""Damaged variants of small valid animated files and OBJ/PLY sequences, made in the tests.

Each function takes the bytes (or the pieces) of a valid file and returns ``{case name: (file name,
{relative path: bytes})}``: the file a damaged-file test hands to the fit and every file written
for the case (a .gltf's .bin beside it, the frames of a sequence). Damage is of the kinds a user's
disk, a download or an exporter produces: cut short, flipped bits, empty, random bytes, another
format under the extension, broken glTF JSON, accessors and views past their buffers, NaN in
morph targets, keyframe times and animated values, times that are not times, no animation, a
.gltf without its .bin, and sequences with a frame of another size, NaN, a bad face index,
garbage, a single frame or no frame at all. numpy and the standard library only.
"""
from __future__ import annotations

import json
import random
import struct

import numpy as np

_GLB_MAGIC, _JSON, _BIN = b"glTF", 0x4E4F534A, 0x004E4942
_COMPONENT = {5126: "<f4", 5125: "<u4", 5123: "<u2", 5121: "u1", 5122: "<i2", 5120: "i1"}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


def generic(raw: bytes, ext: str, seed: int, other: bytes) -> dict:
    """Damage any file: empty, cut to a half, to its first 24 bytes and by its last tenth, bits
    flipped (a few in its header, and one in 20 bytes everywhere), random bytes of its size, a line of text, ``other`` (a file of
    another format) under this extension."""
    rng = random.Random(seed)
    name = f"clip{ext}"

    def flipped(count, first=16, last=None):
        b = bytearray(raw)
        span = range(first, len(b) if last is None else min(last, len(b)))
        for i in rng.sample(span, min(count, len(span))):
            b[i] ^= 1 << rng.randrange(8)
        return bytes(b)

    cases = {
        "empty": b"",
        "half": raw[: len(raw) // 2],
        "head": raw[:24],
        "tail_cut": raw[: len(raw) - max(len(raw) // 10, 1)],
        # bytes 8-15, after each format's magic: a glb's length and chunk header, an FBX's magic,
        # an Alembic (Ogawa) file's root offset, a usdc's version (a few bits flipped anywhere may
        # only nudge a number, which no reader can tell from the truth)
        "header_bits": flipped(4, 8, 16),
        "many_bits": flipped(len(raw) // 20),
        "random": bytes(rng.getrandbits(8) for _ in range(len(raw))),
        "text": b"this is not an animation file\n",
        "other_format": other,
    }
    return {f"{ext[1:]}_{k}": (name, {name: v}) for k, v in cases.items()}


# ------------------------------------------------------------------------------------------ glTF

def split_glb(raw: bytes):
    """``(json dict, bin bytes)`` of a .glb."""
    magic, _, _ = struct.unpack_from("<4sII", raw, 0)
    assert magic == _GLB_MAGIC
    n, kind = struct.unpack_from("<II", raw, 12)
    assert kind == _JSON
    doc = json.loads(raw[20:20 + n].decode("utf-8"))
    m, kind = struct.unpack_from("<II", raw, 20 + n)
    assert kind == _BIN
    return doc, raw[28 + n:28 + n + m]


def join_glb(doc, binary: bytes, text: bytes | None = None) -> bytes:
    """A .glb of ``doc`` (or the raw JSON ``text``) and ``binary``, each chunk padded to 4 bytes."""
    js = text if text is not None else json.dumps(doc).encode("utf-8")
    js += b" " * (-len(js) % 4)
    binary = binary + b"\0" * (-len(binary) % 4)
    body = struct.pack("<II", len(js), _JSON) + js + struct.pack("<II", len(binary), _BIN) + binary
    return struct.pack("<4sII", _GLB_MAGIC, 2, 12 + len(body)) + body


def _accessor_view(doc, index):
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    dtype = np.dtype(_COMPONENT[acc["componentType"]])
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    count = acc["count"] * _WIDTH[acc["type"]]
    return start, dtype, count


def _poke(doc, binary: bytes, indices, value=np.nan, every=1) -> bytes:
    """``binary`` with float accessors ``indices`` set to ``value`` (every ``every``-th number)."""
    b = bytearray(binary)
    for index in indices:
        start, dtype, count = _accessor_view(doc, index)
        a = np.frombuffer(bytes(b[start:start + count * dtype.itemsize]), dtype=dtype).copy()
        a[::every] = value
        b[start:start + a.nbytes] = a.tobytes()
    return bytes(b)


def _copy(doc):
    return json.loads(json.dumps(doc))


def glb_skinned(raw: bytes) -> dict:
    """Damage that only a glTF's structure allows, on a skinned, keyed .glb."""
    doc, binary = split_glb(raw)
    samplers = [s for a in doc.get("animations", []) for s in a["samplers"]]
    times = sorted({s["input"] for s in samplers})
    values = sorted({s["output"] for s in samplers})
    position = doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]
    cases = {}
    js = json.dumps(doc).encode("utf-8")
    cases["broken_json"] = join_glb(None, binary, js[: len(js) // 2])
    cases["json_not_object"] = join_glb(None, binary, b"[1, 2, 3]")
    d = _copy(doc)
    for acc in d["accessors"]:
        acc["count"] = 10**9
    cases["huge_counts"] = join_glb(d, binary)
    d = _copy(doc)
    for view in d["bufferViews"]:
        view["byteOffset"] = len(binary) + 64
    cases["views_past_buffer"] = join_glb(d, binary)
    cases["nan_key_times"] = join_glb(doc, _poke(doc, binary, times[:1], every=3))
    cases["nan_key_values"] = join_glb(doc, _poke(doc, binary, values, every=7))
    d = _copy(doc)
    for a in d["animations"]:
        for s in a["samplers"]:
            s["input"] = position                 # times that are not times (3 numbers each)
    cases["times_not_times"] = join_glb(d, binary)
    d = _copy(doc)
    d.pop("animations", None)
    cases["no_animation"] = join_glb(d, binary)
    d = _copy(doc)
    d["meshes"][0]["primitives"][0]["attributes"]["POSITION"] = len(d["accessors"]) + 5
    cases["bad_accessor_index"] = join_glb(d, binary)
    d = _copy(doc)
    d["meshes"][0]["primitives"][0]["indices"] = position    # floats as vertex indices
    cases["positions_as_indices"] = join_glb(d, binary)
    cases["nan_positions"] = join_glb(doc, _poke(doc, binary, [position], every=5))
    return {f"glb_{k}": ("clip.glb", {"clip.glb": v}) for k, v in cases.items()}


def glb_morph(raw: bytes) -> dict:
    """NaN in a morph-target animation's targets and in its keyed weights."""
    doc, binary = split_glb(raw)
    prim = doc["meshes"][0]["primitives"][0]
    targets = [t["POSITION"] for t in prim.get("targets", [])]
    weights = sorted({s["output"] for a in doc["animations"] for s in a["samplers"]})
    cases = {"nan_morph_targets": join_glb(doc, _poke(doc, binary, targets[len(targets) // 2:][:1], every=4)),
             "inf_morph_weights": join_glb(doc, _poke(doc, binary, weights, value=np.inf, every=11))}
    return {f"glb_{k}": ("clip.glb", {"clip.glb": v}) for k, v in cases.items()}


def gltf_separate(text: bytes, binary: bytes, bin_name: str) -> dict:
    """A .gltf whose .bin is missing, cut short, or named wrong, and a .gltf of broken JSON."""
    doc = json.loads(text)
    wrong = _copy(doc)
    wrong["buffers"][0]["uri"] = "elsewhere.bin"
    return {
        "gltf_without_bin": ("clip.gltf", {"clip.gltf": text}),
        "gltf_short_bin": ("clip.gltf", {"clip.gltf": text, bin_name: binary[: len(binary) // 3]}),
        "gltf_wrong_uri": ("clip.gltf", {"clip.gltf": json.dumps(wrong).encode(), bin_name: binary}),
        "gltf_broken_json": ("clip.gltf", {"clip.gltf": text[: len(text) // 2], bin_name: binary}),
    }


# ------------------------------------------------------------------------------------------- USD

def usda_nan(text: bytes) -> dict:
    """A .usda whose animation holds NaN (every number of one time sample of its animated points
    or skeleton rotations), and a .usda cut in half."""
    import re
    s = text.decode("utf-8")
    at = max(s.find("points.timeSamples"), s.find("rotations.timeSamples"))
    assert at >= 0, "no animated points or rotations in the .usda"
    sample = s.find("[", s.find(",", s.find("[", at)))     # the second time sample's values
    end = s.find("]", sample)
    damaged = re.sub(r"-?\d+(\.\d+)?(e-?\d+)?", "nan", s[sample:end])
    return {"usda_nan_keys": ("clip.usda", {"clip.usda": (s[:sample] + damaged + s[end:]).encode()}),
            "usda_half": ("clip.usda", {"clip.usda": text[: len(text) // 2]})}


# ------------------------------------------------------------------------------------- sequences

def _obj(verts, faces) -> bytes:
    lines = [f"v {float(x):.9g} {float(y):.9g} {float(z):.9g}" for x, y, z in verts]
    lines += ["f " + " ".join(str(i + 1) for i in f) for f in faces]
    return ("\n".join(lines) + "\n").encode()


def _ply_binary(verts, faces) -> bytes:
    head = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(verts)}\n"
            "property float x\nproperty float y\nproperty float z\n"
            f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n").encode()
    body = np.asarray(verts, "<f4").tobytes()
    f = np.asarray(faces, np.int64)
    rows = np.zeros(len(f), dtype=[("n", "u1"), ("i", "<i4", (f.shape[1],))])
    rows["n"], rows["i"] = f.shape[1], f
    return head + body + rows.tobytes()


def sequences(rest, faces, poses) -> dict:
    """Damaged numbered OBJ and PLY sequences of ``rest (N, 3)`` posed as ``poses (P, N, 3)``
    with ``faces (T, k)``: one frame of another size, a NaN coordinate, a face index past the
    vertices, a frame of garbage, a single frame, an empty folder (the case's file is the folder),
    a binary PLY frame cut short, a PLY frame with an infinite coordinate."""
    frames = [np.asarray(rest)] + [np.asarray(p) for p in poses]

    def seq(ext, make, damage=None):
        out = {}
        for i, v in enumerate(frames):
            out[f"seq/pose_{i:03d}{ext}"] = make(v, faces)
        if damage:
            damage(out)
        return out

    k = len(frames) // 2
    key = f"seq/pose_{k:03d}"
    nan = [v.copy() for v in frames]
    nan[k][3, 1] = np.nan
    inf = [v.copy() for v in frames]
    inf[k][5, 2] = np.inf
    bad_face = np.array(faces, copy=True)
    bad_face[len(bad_face) // 2, 0] = len(rest) + 7
    cases = {
        "obj_other_size": seq(".obj", _obj, lambda o: o.update({key + ".obj": _obj(frames[k][:-4], faces[:-8])})),
        "obj_nan": {f"seq/pose_{i:03d}.obj": _obj(v, faces) for i, v in enumerate(nan)},
        "obj_bad_face_index": seq(".obj", _obj, lambda o: o.update({key + ".obj": _obj(frames[k], bad_face)})),
        "obj_garbage": seq(".obj", _obj, lambda o: o.update({key + ".obj": bytes(range(256)) * 8})),
        "obj_single_frame": {"seq/pose_000.obj": _obj(frames[0], faces)},
        "ply_cut_short": seq(".ply", _ply_binary, lambda o: o.update({key + ".ply": o[key + ".ply"][:-40]})),
        "ply_inf": {f"seq/pose_{i:03d}.ply": _ply_binary(v, faces) for i, v in enumerate(inf)},
    }
    out = {name: ("seq/pose_000" + (".ply" if name.startswith("ply") else ".obj"), files)
           for name, files in cases.items()}
    out["seq_empty_folder"] = ("seq", {})
    return out
