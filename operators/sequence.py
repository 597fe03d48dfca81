# SPDX-License-Identifier: GPL-3.0-or-later
"""Numbered mesh sequences (``pose_000.obj``, ``pose_001.obj``, ...) as poses.

Pure Python + numpy (no ``bpy``), so it can be used and tested anywhere.

Readers:

* ASCII OBJ: ``v x y z [...]`` and ``f a b c ...`` (``a``, ``a/t``, ``a//n``,
  ``a/t/n``; negative = relative indices); every other statement is ignored.
* PLY (``ascii``, ``binary_little_endian``, ``binary_big_endian``): element
  ``vertex`` with properties ``x y z`` (others skipped) and element ``face``
  with a list property ``vertex_indices`` (or ``vertex_index``); other
  elements are skipped.

Polygons are kept as ``(sizes, indices)`` and also triangulated as a fan
``(v0, v_i, v_i+1)``.

:func:`load_sequence` reads every file of a sequence, checks that they share
the connectivity of the first file, and returns the rest pose, the faces and
the displacement of every other pose.
"""

import os
import re
import warnings
from collections import namedtuple

import numpy as np

EXTENSIONS = (".obj", ".ply")

#: One mesh file: ``vertices`` (N, 3) float64, polygons as ``sizes`` (F,) and
#: flat ``indices`` (sum(sizes),), ``triangles`` (T, 3) int64 (fan).
MeshFile = namedtuple("MeshFile", "vertices sizes indices triangles")

#: What :func:`load_sequence` returns.  ``rest`` is index into ``paths`` of the
#: rest pose; ``displacements`` (P, N, 3) holds the other files in order
#: (``field_paths``).
Sequence = namedtuple("Sequence", "paths rest vertices sizes indices triangles "
                                  "displacements field_paths")

_NUMBERED = re.compile(r"^(.*?)(\d+)$")
_SLASHES = re.compile(r"/\S*")
_V_LINE = re.compile(r"^v[ \t]+([^\r\n]*)", re.M)
_F_LINE = re.compile(r"^f[ \t]+([^\r\n]*)", re.M)


def _numbers(text, dtype, expected):
    """Whitespace-separated numbers of ``text`` as a 1-D array (C speed), or None if
    some token is not a number of that type or the count is not ``expected``."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            out = np.fromstring(text, dtype=dtype, sep=" ")
        except (DeprecationWarning, ValueError):
            return None
    if expected is not None and out.size != expected:
        return None
    return out


class SequenceError(ValueError):
    """A problem with a mesh sequence; the message names the file and the problem."""


# --------------------------------------------------------------------------
# polygons
# --------------------------------------------------------------------------

def fan_triangles(sizes, indices, name=None):
    """Fan triangulation of polygons given as ``sizes`` and flat ``indices`` (``name``: the file,
    for the message)."""
    sizes = np.asarray(sizes, dtype=np.int64)
    indices = np.asarray(indices, dtype=np.int64)
    if sizes.size == 0:
        return np.zeros((0, 3), dtype=np.int64)
    if sizes.min() < 3:
        raise SequenceError((f"{name}: " if name else "")
                            + f"a face has {int(sizes.min())} vertices (at least 3 are needed)")
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    n_tri = sizes - 2
    poly = np.repeat(np.arange(len(sizes)), n_tri)           # polygon of each triangle
    first = np.repeat(np.cumsum(n_tri) - n_tri, n_tri)
    k = np.arange(len(poly)) - first + 1                      # 1 .. size-2 within its polygon
    s = starts[poly]
    return np.stack([indices[s], indices[s + k], indices[s + k + 1]], axis=1)


def _check_indices(name, indices, n_vertices, first=0):
    """``first``: the number the file format gives its first vertex (OBJ 1, PLY 0), so that the
    message repeats the number written in the file."""
    if indices.size and (indices.min() < 0 or indices.max() >= n_vertices):
        bad = int(indices.min() if indices.min() < 0 else indices.max())
        raise SequenceError(f"{name}: a face refers to vertex {bad + first}, but the file has "
                            f"{n_vertices} vertices")


# --------------------------------------------------------------------------
# OBJ
# --------------------------------------------------------------------------

def _read_bytes(path):
    """(file name, contents) of ``path``, or SequenceError naming the file."""
    name = os.path.basename(path)
    if os.path.exists(path) and not os.path.isfile(path):
        # a FIFO would block the read (Ctrl-C could not stop it), a device could be endless
        raise SequenceError(f"cannot read {name}: not a regular file")
    try:
        with open(path, "rb") as f:
            return name, f.read()
    except OSError as err:
        raise SequenceError(f"cannot read {name}: {err.strerror or err}") from None


def read_obj(path):
    """Read an ASCII OBJ file (vertices and faces) → :class:`MeshFile`."""
    name, data = _read_bytes(path)
    if b"\0" in data[:4096]:
        raise SequenceError(f"cannot read {name}: not a text OBJ file")
    if data.startswith(b"\xef\xbb\xbf"):
        data = data[3:]     # a UTF-8 byte-order mark (Windows editors): else the first 'v' line is not read
    text = data.decode("utf-8", errors="replace")
    if "\r" in text:       # Windows (CRLF) and classic Mac (CR only) line ends: one line per '\n' below
        text = text.replace("\r\n", "\n").replace("\r", "\n")
    vlines = _V_LINE.findall(text)
    flines = _F_LINE.findall(text)
    if not vlines:
        raise SequenceError(f"{name} has no vertices ('v' lines)")
    if not flines:
        raise SequenceError(f"{name} has no faces ('f' lines)")
    vertices = _numbers(" ".join(vlines), np.float64, 3 * len(vlines))
    if vertices is None:  # extra values on 'v' lines (w, colours), or a bad number
        coords = [ln.split()[:3] for ln in vlines]
        if min(map(len, coords)) < 3:
            raise SequenceError(f"{name}: a 'v' line has fewer than 3 coordinates")
        try:
            vertices = np.array(coords, dtype=np.float64)
        except ValueError:
            raise SequenceError(f"{name}: a vertex coordinate is not a number") from None
    vertices = vertices.reshape(-1, 3)
    ftext = " ".join(flines)
    if "/" in ftext:
        ftext = _SLASHES.sub("", ftext)  # keep the vertex index of v/vt/vn
    indices = _numbers(ftext, np.int64, None)
    if indices is None:
        raise SequenceError(f"{name}: a face index is not a number")
    big = np.iinfo(np.int64)
    if indices.size and (indices.max() == big.max or indices.min() == big.min):
        # numpy's reader saturates a number beyond 64 bits there: it would be named as 2**63 - 1
        raise SequenceError(f"{name}: a face refers to a vertex number beyond {big.max} (the file has "
                            f"{len(vertices)} vertices)")
    if len(indices) == 3 * len(flines):
        sizes = np.full(len(flines), 3, dtype=np.int64)
    else:
        sizes = np.fromiter((len(ln.split()) for ln in flines), dtype=np.int64,
                            count=len(flines))
        if sizes.sum() != len(indices):
            raise SequenceError(f"{name}: cannot read the faces")
    if sizes.min() < 3:
        raise SequenceError(f"{name}: a face has fewer than 3 vertices")
    if np.any(indices == 0):
        raise SequenceError(f"{name}: vertex index 0 in a face (OBJ counts from 1)")
    neg = indices < 0
    indices = indices - 1
    if np.any(neg):  # relative to the vertices read before that face
        seen, n_v = [], 0
        for line in text.split("\n"):    # the lines the patterns above read (splitlines knows more ends)
            if line.startswith(("v ", "v\t")):
                n_v += 1
            elif line.startswith(("f ", "f\t")):
                seen.append(n_v)
        seen = np.repeat(np.asarray(seen, dtype=np.int64), sizes)
        indices[neg] = seen[neg] + indices[neg] + 1
    _check_indices(name, indices, len(vertices), first=1)
    return MeshFile(vertices, sizes, indices, fan_triangles(sizes, indices))


# --------------------------------------------------------------------------
# PLY
# --------------------------------------------------------------------------

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def _ply_header(data, name):
    if not data.startswith(b"ply"):
        raise SequenceError(f"cannot read {name}: not a PLY file (no 'ply' magic)")
    end = data.find(b"end_header")
    if end < 0:
        raise SequenceError(f"cannot read {name}: the PLY header has no 'end_header'")
    nl = data.find(b"\n", end)
    body = nl + 1 if nl >= 0 else len(data)
    fmt = None
    elements = []  # [name, count, [(prop name, type, list count type or None)]]
    for line in data[:end].decode("ascii", errors="replace").splitlines()[1:]:
        parts = line.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        try:
            if parts[0] == "format":
                fmt = parts[1]
            elif parts[0] == "element":
                if int(parts[2]) < 0:
                    raise SequenceError(f"{name}: the PLY header gives {parts[1]} a negative count ({parts[2]})")
                elements.append([parts[1], int(parts[2]), []])
            elif parts[0] == "property":
                if not elements:
                    raise SequenceError(f"{name}: PLY property before any element")
                if parts[1] == "list":
                    elements[-1][2].append((parts[4], _PLY_TYPES[parts[3]], _PLY_TYPES[parts[2]]))
                else:
                    elements[-1][2].append((parts[2], _PLY_TYPES[parts[1]], None))
        except (IndexError, KeyError, ValueError):
            raise SequenceError(f"{name}: cannot read the PLY header line {line.strip()!r}") from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise SequenceError(f"{name}: unsupported PLY format {fmt!r}")
    return fmt, elements, body


def _vertex_xyz(props, columns, name):
    names = [p[0] for p in props]
    try:
        return np.stack([np.asarray(columns[names.index(a)], dtype=np.float64)
                         for a in "xyz"], axis=1)
    except ValueError:
        raise SequenceError(f"{name}: the PLY vertex element has no x, y, z properties") from None


def _face_prop(props, name):
    for i, (pname, _, count) in enumerate(props):
        if count is not None and pname in ("vertex_indices", "vertex_index"):
            return i
    raise SequenceError(f"{name}: the PLY face element has no 'vertex_indices' list")


def _read_ply_ascii(data, body, elements, name):
    lines = data[body:].decode("ascii", errors="replace").splitlines()
    pos = 0
    vertices = sizes = indices = None
    for ename, count, props in elements:
        rows = lines[pos:pos + count]
        if len(rows) < count:
            raise SequenceError(f"{name}: the file ends inside the PLY '{ename}' element "
                                f"({len(rows)} of {count} lines)")
        pos += count
        if ename == "vertex":
            if any(p[2] is not None for p in props):
                raise SequenceError(f"{name}: list properties on PLY vertices are not supported")
            table = _numbers(" ".join(rows), np.float64, count * len(props))
            if table is None:
                raise SequenceError(f"{name}: cannot read the PLY vertex lines")
            table = table.reshape(count, len(props))
            vertices = _vertex_xyz(props, table.T, name)
        elif ename == "face":
            which = _face_prop(props, name)
            if len(props) == 1 and count:  # fast path: lists of one length
                table = _numbers(" ".join(rows), np.int64, None)
                n = int(table[0]) if table is not None and table.size else -1
                if n >= 0 and table.size == count * (n + 1):
                    table = table.reshape(count, n + 1)
                    if np.all(table[:, 0] == n):
                        sizes = np.full(count, n, dtype=np.int64)
                        indices = table[:, 1:].reshape(-1)
                        continue
            sz, flat = [], []
            try:
                for row in rows:
                    vals = row.split()
                    at = 0
                    for i, (_, _, ctype) in enumerate(props):
                        if ctype is None:
                            at += 1
                            continue
                        n = int(vals[at])
                        if i == which:
                            sz.append(n)
                            flat.extend(int(v) for v in vals[at + 1:at + 1 + n])
                        at += 1 + n
            except (ValueError, IndexError):
                raise SequenceError(f"{name}: cannot read the PLY face lines") from None
            sizes = np.array(sz, dtype=np.int64)
            indices = np.array(flat, dtype=np.int64)
    return vertices, sizes, indices


def _check_length(n, name, ename):
    """A PLY list's length as read: negative only in a damaged file."""
    if n < 0:
        raise SequenceError(f"{name}: a PLY '{ename}' list has a negative length ({n})")


def _walk_lists(data, pos, count, ctype, itype, name, ename):
    """Sizes and start offsets of ``count`` lists (count type ``ctype``) from ``pos``."""
    sizes = np.empty(count, dtype=np.int64)
    starts = np.empty(count, dtype=np.int64)
    csize, isize = ctype.itemsize, itype.itemsize
    end = len(data)
    if csize == 1:
        for k in range(count):
            if pos >= end:
                raise SequenceError(f"{name}: the file ends inside the PLY '{ename}' element")
            n = data[pos]
            sizes[k] = n
            starts[k] = pos + 1
            pos += 1 + n * isize
    else:
        code = ctype.str  # e.g. '<i4'
        for k in range(count):
            if pos + csize > end:
                raise SequenceError(f"{name}: the file ends inside the PLY '{ename}' element")
            n = int(np.frombuffer(data, dtype=code, count=1, offset=pos)[0])
            _check_length(n, name, ename)
            sizes[k] = n
            starts[k] = pos + csize
            pos += csize + n * isize
    if pos > end:
        raise SequenceError(f"{name}: the file ends inside the PLY '{ename}' element")
    return sizes, starts, pos


def _gather(data, starts, sizes, itype):
    """The list items at ``starts`` (``sizes`` each, type ``itype``) as one int64 array."""
    isize = itype.itemsize
    first = np.repeat(starts, sizes)
    k = np.arange(len(first)) - np.repeat(np.cumsum(sizes) - sizes, sizes)
    at = first + k * isize
    buf = np.frombuffer(data, dtype=np.uint8)
    raw = buf[at[:, None] + np.arange(isize)]
    return np.ascontiguousarray(raw).view(itype).reshape(-1).astype(np.int64)


def _read_ply_binary(data, body, elements, name, endian):
    pos = body
    vertices = sizes = indices = None

    def need(nbytes, what):
        if pos + nbytes > len(data):
            raise SequenceError(f"{name}: the file ends inside the PLY '{what}' element")

    for ename, count, props in elements:
        # every element takes at least its fixed properties and its lists' counts: a count the file
        # cannot hold is refused before anything is allocated for it
        need(count * sum(np.dtype(t if c is None else c).itemsize for _, t, c in props), ename)
        if all(p[2] is None for p in props):
            dtype = np.dtype([(f"p{i}", endian + t) for i, (_, t, _) in enumerate(props)])
            need(dtype.itemsize * count, ename)
            table = np.frombuffer(data, dtype=dtype, count=count, offset=pos)
            pos += dtype.itemsize * count
            if ename == "vertex":
                vertices = _vertex_xyz(props, [table[f"p{i}"] for i in range(len(props))], name)
            continue
        if ename == "vertex":
            raise SequenceError(f"{name}: list properties on PLY vertices are not supported")
        which = _face_prop(props, name) if ename == "face" else -1
        # Fast path: a single list property whose lists all have the first one's length.
        if len(props) == 1 and count > 0:
            ctype, itype = np.dtype(endian + props[0][2]), np.dtype(endian + props[0][1])
            need(ctype.itemsize, ename)
            n = int(np.frombuffer(data, dtype=ctype, count=1, offset=pos)[0])
            _check_length(n, name, ename)
            dtype = np.dtype([("n", ctype), ("i", itype, (n,))])
            if pos + dtype.itemsize * count <= len(data):
                table = np.frombuffer(data, dtype=dtype, count=count, offset=pos)
                if np.all(table["n"] == n):
                    pos += dtype.itemsize * count
                    if which == 0:
                        sizes = np.full(count, n, dtype=np.int64)
                        indices = table["i"].astype(np.int64).reshape(-1)
                    continue
            # Lists of mixed lengths: walk the counts, then gather every index at once.
            sz, starts, pos = _walk_lists(data, pos, count, ctype, itype, name, ename)
            if which == 0:
                sizes = sz
                indices = _gather(data, starts, sz, itype)
            continue
        # General path: element by element.
        sz, flat = [], []
        for _ in range(count):
            for i, (_, t, ctype) in enumerate(props):
                if ctype is None:
                    itemsize = np.dtype(t).itemsize
                    need(itemsize, ename)
                    pos += itemsize
                    continue
                cdt = np.dtype(endian + ctype)
                need(cdt.itemsize, ename)
                n = int(np.frombuffer(data, dtype=cdt, count=1, offset=pos)[0])
                _check_length(n, name, ename)
                pos += cdt.itemsize
                idt = np.dtype(endian + t)
                need(idt.itemsize * n, ename)
                if i == which:
                    sz.append(n)
                    flat.append(np.frombuffer(data, dtype=idt, count=n, offset=pos))
                pos += idt.itemsize * n
        if which >= 0:
            sizes = np.array(sz, dtype=np.int64)
            indices = (np.concatenate(flat).astype(np.int64) if flat
                       else np.zeros(0, dtype=np.int64))
    return vertices, sizes, indices


def read_ply(path):
    """Read a PLY file (ASCII or binary) → :class:`MeshFile`."""
    name, data = _read_bytes(path)
    fmt, elements, body = _ply_header(data, name)
    if fmt == "ascii":
        vertices, sizes, indices = _read_ply_ascii(data, body, elements, name)
    else:
        endian = "<" if fmt == "binary_little_endian" else ">"
        vertices, sizes, indices = _read_ply_binary(data, body, elements, name, endian)
    if vertices is None or len(vertices) == 0:
        raise SequenceError(f"{name} has no vertices")
    if sizes is None or len(sizes) == 0:
        raise SequenceError(f"{name} has no faces")
    _check_indices(name, indices, len(vertices))
    return MeshFile(vertices, sizes, indices, fan_triangles(sizes, indices, name))


def read_mesh(path):
    """Read an OBJ or PLY file by its extension."""
    ext = os.path.splitext(path)[1].lower()
    if ext == ".obj":
        return read_obj(path)
    if ext == ".ply":
        return read_ply(path)
    raise SequenceError(f"{os.path.basename(path)}: unsupported file type {ext or '(none)'!r} "
                        f"(OBJ or PLY)")


# --------------------------------------------------------------------------
# sequences
# --------------------------------------------------------------------------

def split_number(filename):
    """``'pose_012.obj'`` → ``('pose_', 12, '.obj')``; None if the name is not numbered."""
    stem, ext = os.path.splitext(filename)
    m = _NUMBERED.match(stem)
    if m is None:
        return None
    return m.group(1), int(m.group(2)), ext


def find_sequence(path):
    """Every file of the numbered sequence that ``path`` belongs to, by number.

    ``path`` is one file of the sequence, or a directory holding exactly one
    sequence of OBJ or PLY files.
    """
    if os.path.isdir(path):
        groups = {}
        for fn in sorted(os.listdir(path)):
            parts = split_number(fn)
            if parts is not None and parts[2].lower() in EXTENSIONS:
                groups.setdefault((parts[0], parts[2].lower()), []).append(fn)
        if not groups:
            raise SequenceError(f"no numbered OBJ or PLY files (like pose_000.obj) in {path}")
        prefixes = {p for p, _ in groups}
        if len(groups) > 1 and len(prefixes) == 1:
            p0 = next(iter(prefixes))
            exts = " and ".join(sorted(e for _, e in groups))
            raise SequenceError(f"{path}: the sequence {p0}### mixes {exts} files; a sequence "
                                f"is one format (convert or move the others)")
        if len(groups) > 1:
            names = ", ".join(f"{p}###{e}" for p, e in sorted(groups))
            raise SequenceError(f"{path} holds several sequences ({names}): pick one file")
        (prefix, ext), _ = next(iter(groups.items()))
        directory = path
    else:
        directory, filename = os.path.split(path)
        if not os.path.isfile(path):
            raise SequenceError(f"cannot read {filename}: no such file")
        parts = split_number(filename)
        if parts is None:
            stem, ext = os.path.splitext(filename)
            ext = ext or ".obj"
            raise SequenceError(f"{filename} is not numbered: a sequence is files named like "
                                f"{stem}_000{ext}, {stem}_001{ext}, ...")
        prefix, _, ext = parts
        if ext.lower() not in EXTENSIONS:
            raise SequenceError(f"{filename}: unsupported file type {ext!r} (OBJ or PLY)")
    found = {}
    others = []
    for fn in sorted(os.listdir(directory or ".")):
        parts = split_number(fn)
        if parts is not None and parts[0] == prefix and parts[2].lower() == ext.lower():
            if parts[1] in found:
                raise SequenceError(f"{fn} and {found[parts[1]]} have the same number {parts[1]}")
            found[parts[1]] = fn
        elif parts is not None and parts[0] == prefix and parts[2].lower() in EXTENSIONS:
            others.append(fn)
    if others:   # frames of the other format would silently be left out
        raise SequenceError(f"the sequence {prefix}### mixes {ext.lower()} and "
                            f"{os.path.splitext(others[0])[1].lower()} files ({others[0]}, ...); "
                            f"a sequence is one format (convert or move the others)")
    return [os.path.join(directory, found[k]) for k in sorted(found)]


def select_frames(paths, rest, start=None, end=None, step=None):
    """The files of a sequence to sample (``paths`` by number, ``rest`` the index of the rest
    pose): the rest file, and the files numbered ``start``, ``start + step``, ... up to ``end``
    (a file's number is its frame; ``None``: the first or last number, step 1). Returns
    ``(paths, rest)`` with ``rest`` re-indexed; SequenceError when no other file is in range."""
    numbers = [split_number(os.path.basename(p))[1] for p in paths]
    lo = numbers[0] if start is None else start
    hi = numbers[-1] if end is None else end
    step = 1 if step is None else step
    if step < 1:
        raise SequenceError(f"frame step {step}: must be at least 1")
    keep = [i for i, n in enumerate(numbers)
            if i == rest or (lo <= n <= hi and (n - lo) % step == 0)]
    if len(keep) < 2:
        prefix, _, ext = split_number(os.path.basename(paths[0]))
        where = os.path.join(os.path.basename(os.path.dirname(paths[0])), f"{prefix}###{ext}")
        in_range = lo <= numbers[rest] <= hi and (numbers[rest] - lo) % step == 0
        raise SequenceError(f"{where}: no file is numbered within frames {lo}..{hi}"
                            + (f" every {step}" if step > 1 else "")
                            + (f" but the rest pose ({os.path.basename(paths[rest])}), which is not a field"
                               if in_range else "")
                            + f" (its files are numbered {numbers[0]}..{numbers[-1]})")
    return [paths[i] for i in keep], keep.index(rest)


def _same_connectivity(first, other, name, first_name):
    if len(other.vertices) != len(first.vertices):
        raise SequenceError(f"connectivity differs: {name} has {len(other.vertices)} vertices, "
                            f"expected {len(first.vertices)} (as in {first_name})")
    if len(other.sizes) != len(first.sizes):
        raise SequenceError(f"connectivity differs: {name} has {len(other.sizes)} faces, "
                            f"expected {len(first.sizes)}")
    if not (np.array_equal(other.sizes, first.sizes) and np.array_equal(other.indices, first.indices)):
        bad = int(np.flatnonzero(other.sizes != first.sizes)[0]) if not np.array_equal(
            other.sizes, first.sizes) else int(np.repeat(
                np.arange(len(first.sizes)), first.sizes)[np.flatnonzero(other.indices != first.indices)[0]])
        raise SequenceError(f"connectivity differs: face {bad} of {name} uses other vertices "
                            f"than in {first_name}")


def load_sequence(paths, rest=0, progress=None):
    """Read the files ``paths`` (one pose each) into a :class:`Sequence`.

    ``rest`` is the index (into ``paths``) of the rest pose; every other file
    becomes one displacement field, in order.  ``progress(i, n)`` is called
    after each file.
    """
    paths = list(paths)
    if len(paths) < 2:
        only = os.path.basename(paths[0]) if paths else "(none)"
        raise SequenceError(f"a sequence needs at least 2 numbered files; found only {only}")
    if not 0 <= rest < len(paths):
        raise SequenceError(f"rest pose {rest} is not one of the {len(paths)} files")
    first = read_mesh(paths[0])
    first_name = os.path.basename(paths[0])
    n = len(first.vertices)
    positions = np.empty((len(paths), n, 3), dtype=np.float64)
    positions[0] = first.vertices
    if progress is not None:
        progress(1, len(paths))
    for i, path in enumerate(paths[1:], 1):
        mesh = read_mesh(path)
        _same_connectivity(first, mesh, os.path.basename(path), first_name)
        positions[i] = mesh.vertices
        if progress is not None:
            progress(i + 1, len(paths))
    if not np.all(np.isfinite(positions)):
        bad = int(np.flatnonzero(~np.isfinite(positions).all(axis=(1, 2)))[0])
        raise SequenceError(f"{os.path.basename(paths[bad])} has NaN or infinite coordinates")
    others = [i for i in range(len(paths)) if i != rest]
    return Sequence(paths, rest, positions[rest], first.sizes, first.indices, first.triangles,
                    positions[others] - positions[rest][None], [paths[i] for i in others])
