# SPDX-License-Identifier: GPL-3.0-or-later
"""Scans stored on Blender meshes.

The scan attached to a mesh is the source of truth for fitting: it lives in
the mesh data so that it is saved with the .blend file and undone with it.

Layout on ``Mesh`` (all names are public, documented in docs/blender.md):

* point attribute ``artdef_field_000`` ... (FLOAT_VECTOR): one per field.  For
  a Green's scan this is the raw Green's column ``greens[:, c].reshape(N, 3)``
  (displacement per unit load, *not* multiplied by the probe load); for a
  tracked scan it is the displacement of pose ``c``;
* point attribute ``artdef_load_index`` (INT): ``k`` on load vertex ``k``,
  -1 elsewhere (Green's scans only);
* point attribute ``artdef_support`` (BOOLEAN): support vertices (if any);
* custom properties ``artdef_kind`` ('greens' | 'tracked'), ``artdef_n_fields``,
  ``artdef_probe_load``, ``artdef_n_loads``, ``artdef_n_support`` and
  ``artdef_scan_version``.

The rest shape is the mesh's own vertex positions; the faces are the mesh's
triangulation (``loop_triangles``), so quads and n-gons work too.
"""

import hashlib
import os
from collections import namedtuple

import bpy
import numpy as np

from ..artdef_addon import files as _files
from ..artdef_addon import scan as _scan

FIELD_PREFIX = "artdef_field_"
LOAD_ATTR = "artdef_load_index"
SUPPORT_ATTR = "artdef_support"
SCAN_VERSION = 1
_PROPS = ("artdef_kind", "artdef_n_fields", "artdef_probe_load", "artdef_n_loads",
          "artdef_n_support", "artdef_scan_version")

#: What :func:`read_scan` returns.  ``tri_polygons[t]`` is the polygon of scan
#: face ``t``; ``fingerprint`` identifies the scan data (geometry and fields).
StoredScan = namedtuple("StoredScan", "scan tri_polygons fingerprint")


def has_scan(mesh):
    """True if ``mesh`` (a bpy Mesh) carries an ArtDef scan."""
    return mesh is not None and mesh.get("artdef_kind") in ("greens", "tracked")


def scan_info(mesh):
    """Cheap summary for the UI (reads only custom properties; a damaged one reads as its default,
    so the panel still draws: reading the scan itself reports the damage)."""
    def number(key, kind, default):
        try:
            return kind(mesh.get(key, default))
        except (TypeError, ValueError):
            return default
    return {
        "kind": str(mesh.get("artdef_kind", "")),
        "fields": number("artdef_n_fields", int, 0),
        "loads": number("artdef_n_loads", int, 0),
        "support": number("artdef_n_support", int, 0),
        "probe_load": number("artdef_probe_load", float, 1.0),
    }


def _field_index(name):
    if not name.startswith(FIELD_PREFIX):
        return None
    tail = name[len(FIELD_PREFIX):]
    return int(tail) if tail.isdigit() else None


def _remove_attribute(mesh, name):
    attr = mesh.attributes.get(name)
    if attr is not None:
        mesh.attributes.remove(attr)


def clear_scan(mesh):
    """Remove the scan attributes and properties from ``mesh``."""
    for name in [a.name for a in mesh.attributes if _field_index(a.name) is not None]:
        _remove_attribute(mesh, name)
    _remove_attribute(mesh, LOAD_ATTR)
    _remove_attribute(mesh, SUPPORT_ATTR)
    for key in _PROPS:
        if key in mesh:
            del mesh[key]


# --------------------------------------------------------------------------
# fast bulk access.  ``Mesh.vertices.foreach_*("co")``, ``Mesh.loops`` and
# ``Mesh.loop_triangles`` go through RNA item by item (1M triangles: 0.2-0.7 s
# each); the generic attributes behind them ("position", ".corner_vert") and
# ``Mesh.loop_triangle_polygons`` are plain arrays (a few ms).  Each falls back
# to the RNA path where the attribute is missing or refuses the access.
# --------------------------------------------------------------------------

def _attr_set(mesh, name, value_prop, data, collection, prop):
    attr = mesh.attributes.get(name)
    if attr is not None:
        try:
            attr.data.foreach_set(value_prop, data)
            return
        except (AttributeError, TypeError, RuntimeError):
            pass
    collection.foreach_set(prop, data)


def _attr_get(mesh, name, value_prop, out, collection, prop):
    attr = mesh.attributes.get(name)
    if attr is not None:
        try:
            attr.data.foreach_get(value_prop, out)
            return out
        except (AttributeError, TypeError, RuntimeError):
            pass
    collection.foreach_get(prop, out)
    return out


def _positions(mesh, n):
    """Rest positions (n, 3) float32."""
    out = np.empty(3 * n, dtype=np.float32)
    return _attr_get(mesh, "position", "vector", out, mesh.vertices, "co").reshape(n, 3)


def _new_attribute(mesh, name, type_, domain):
    attr = mesh.attributes.new(name, type_, domain)
    if attr is None or attr.name != name:  # too long, or renamed on a clash
        raise RuntimeError(f"could not create mesh attribute {name!r}")
    return attr


def _field_arrays(scan):
    """(P, N, 3) float32 arrays exactly as stored (raw Green's columns)."""
    n = len(scan.vertices)
    if scan.kind == "greens":
        g = np.asarray(scan.greens)
        return g.T.reshape(g.shape[1], n, 3)  # column c -> (N, 3)
    return np.asarray(scan.displacements)


def write_scan(mesh, scan):
    """Store ``scan``'s fields, loads and supports on ``mesh`` (replacing any).

    The mesh must already have the scan's vertices (same count and order).
    """
    n = len(mesh.vertices)
    if n != len(scan.vertices):
        raise _scan.ScanError(
            f"the scan has {len(scan.vertices)} vertices but the mesh has {n}")
    repeated = _scan.repeated_load_vertex(scan)
    if repeated is not None:
        raise _scan.ScanError(repeated)   # else a later load point overwrote the vertex's mark
    clear_scan(mesh)
    fields = _field_arrays(scan)
    width = max(3, len(str(len(fields) - 1)))
    buf = np.empty((n, 3), dtype=np.float32)  # contiguous float32: the fast foreach_set
    for c in range(len(fields)):
        # Use each attribute right away: creating the next one may reallocate.
        attr = _new_attribute(mesh, f"{FIELD_PREFIX}{c:0{width}d}", "FLOAT_VECTOR", "POINT")
        buf[...] = fields[c]
        attr.data.foreach_set("vector", buf.reshape(-1))
    n_loads = 0
    if scan.load_vertices is not None and len(scan.load_vertices):
        index = np.full(n, -1, dtype=np.int32)
        index[np.asarray(scan.load_vertices)] = np.arange(len(scan.load_vertices), dtype=np.int32)
        _new_attribute(mesh, LOAD_ATTR, "INT", "POINT").data.foreach_set("value", index)
        n_loads = len(scan.load_vertices)
    n_support = 0
    if scan.support_vertices is not None and len(scan.support_vertices):
        support = np.zeros(n, dtype=bool)
        support[np.asarray(scan.support_vertices)] = True
        _new_attribute(mesh, SUPPORT_ATTR, "BOOLEAN", "POINT").data.foreach_set("value", support)
        n_support = int(support.sum())
    mesh["artdef_kind"] = scan.kind
    mesh["artdef_n_fields"] = len(fields)
    mesh["artdef_probe_load"] = float(scan.probe_load)
    mesh["artdef_n_loads"] = n_loads
    mesh["artdef_n_support"] = n_support
    mesh["artdef_scan_version"] = SCAN_VERSION


def repeated_vertex_faces(faces):
    """(T,) bool: triangles that use a vertex twice. The scan format allows them (degenerate,
    zero area, as on the command line: the fit gives them their neighbours' link), but a Blender
    polygon cannot repeat a vertex, so the imported mesh leaves them out; they carry no area,
    hence no weight in the fit."""
    f = np.asarray(faces)
    return (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])


def new_mesh_from_scan(name, scan):
    """A new mesh datablock with the scan's geometry and stored fields (triangles that repeat a
    vertex left out: :func:`repeated_vertex_faces`)."""
    verts = np.ascontiguousarray(scan.vertices, dtype=np.float32)
    faces = np.ascontiguousarray(scan.faces, dtype=np.int32)
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise _scan.ScanError("faces must be a non-empty (T, 3) array of triangles")
    if faces.min() < 0 or faces.max() >= len(verts):
        raise _scan.ScanError("a face refers to a vertex that does not exist")
    faces = np.ascontiguousarray(faces[~repeated_vertex_faces(faces)])
    if len(faces) == 0:
        raise _scan.ScanError("every triangle repeats a vertex (zero area)")
    t = len(faces)
    mesh = bpy.data.meshes.new(name)
    try:
        mesh.vertices.add(len(verts))
        _attr_set(mesh, "position", "vector", verts.ravel(), mesh.vertices, "co")
        mesh.loops.add(3 * t)
        _attr_set(mesh, ".corner_vert", "value", faces.ravel(), mesh.loops, "vertex_index")
        mesh.polygons.add(t)
        mesh.polygons.foreach_set("loop_start", np.arange(0, 3 * t, 3, dtype=np.int32))
        mesh.update(calc_edges=True)
        write_scan(mesh, scan)
    except Exception:
        bpy.data.meshes.remove(mesh)
        raise
    return mesh


def new_mesh_from_polygons(name, vertices, sizes, indices):
    """A new mesh datablock with polygons given as ``sizes`` and flat ``indices``.

    Invalid polygons (repeated vertices, ...) are removed by ``Mesh.validate``;
    the vertices are kept as given.
    """
    verts = np.ascontiguousarray(vertices, dtype=np.float32)
    sizes = np.asarray(sizes, dtype=np.int64)
    indices = np.ascontiguousarray(indices, dtype=np.int32)
    if len(sizes) == 0 or sizes.min() < 3 or sizes.sum() != len(indices):
        raise _scan.ScanError("the polygons are malformed")
    if indices.min() < 0 or indices.max() >= len(verts):
        raise _scan.ScanError("a face refers to a vertex that does not exist")
    mesh = bpy.data.meshes.new(name)
    try:
        mesh.vertices.add(len(verts))
        _attr_set(mesh, "position", "vector", verts.ravel(), mesh.vertices, "co")
        mesh.loops.add(len(indices))
        _attr_set(mesh, ".corner_vert", "value", indices, mesh.loops, "vertex_index")
        mesh.polygons.add(len(sizes))
        starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int32)
        mesh.polygons.foreach_set("loop_start", starts)
        mesh.update(calc_edges=True)
        mesh.validate(clean_customdata=False)
        if len(mesh.vertices) != len(verts) or len(mesh.polygons) == 0:
            raise _scan.ScanError("the faces are not valid polygons")
    except Exception:
        bpy.data.meshes.remove(mesh)
        raise
    return mesh


def import_scan_file(context, filepath):
    """Load a scan file and add it as a new selected, active mesh object.

    Raises ``ScanError`` (with a message naming the problem) before anything
    is created if the file is not a valid scan.
    """
    scan = _files.read_scan(filepath)
    name = os.path.splitext(os.path.basename(filepath))[0] or "scan"
    mesh = new_mesh_from_scan(name, scan)
    obj = bpy.data.objects.new(mesh.name, mesh)
    context.collection.objects.link(obj)
    for other in context.view_layer.objects:
        if other.select_get():
            other.select_set(False)
    obj.select_set(True)
    context.view_layer.objects.active = obj
    return obj, scan


def _get(collection, prop, count, dtype, width=1):
    out = np.empty(count * width, dtype=dtype)
    collection.foreach_get(prop, out)
    return out.reshape(count, width) if width > 1 else out


def _triangles(mesh):
    """``(faces (T, 3), polygon of each triangle (T,))`` of Blender's triangulation."""
    tris = mesh.loop_triangles
    t = len(tris)
    n_loops, n_polys = len(mesh.loops), len(mesh.polygons)
    corner = None
    if mesh.attributes.get(".corner_vert") is not None:
        corner = _attr_get(mesh, ".corner_vert", "value", np.empty(n_loops, dtype=np.int32),
                           mesh.loops, "vertex_index")
    if corner is not None and n_loops == 3 * n_polys and t == n_polys:
        # Only triangles: face i owns corners 3i..3i+2 (face offsets are sorted) and its
        # loop triangle is those corners in order.
        return corner.reshape(t, 3), np.arange(t, dtype=np.int32)
    if corner is not None:
        faces = corner[_get(tris, "loops", t, np.int32, 3)]
    else:
        faces = _get(tris, "vertices", t, np.int32, 3)
    ltp = getattr(mesh, "loop_triangle_polygons", None)
    if ltp is not None:
        polys = _get(ltp, "value", t, np.int32)
    else:
        polys = _get(tris, "polygon_index", t, np.int32)
    return faces, polys


def read_scan(obj):
    """Read the scan stored on mesh object ``obj`` back into an ``S.Scan``.

    Raises ``ScanError`` if the object carries no scan or the stored data is
    inconsistent (e.g. vertices were added after import).
    """
    if obj is None or obj.type != 'MESH':
        raise _scan.ScanError("the active object is not a mesh")
    mesh = obj.data
    if not has_scan(mesh):
        raise _scan.ScanError(
            f"'{obj.name}' carries no ArtDef scan: import a scan or use Fields from Shape Keys")
    kind = mesh["artdef_kind"]
    try:
        n_fields = int(mesh.get("artdef_n_fields", -1))
    except (TypeError, ValueError):
        n_fields = None
    if n_fields is None or n_fields < 1:
        raise _scan.ScanError(f"'{obj.name}': the scan record is damaged: its field count is "
                              f"{mesh.get('artdef_n_fields', 'missing')!r}; import the scan again")
    n = len(mesh.vertices)
    stored = {}
    for attr in mesh.attributes:
        c = _field_index(attr.name)
        if c is not None:
            if attr.domain != 'POINT' or attr.data_type != 'FLOAT_VECTOR':
                raise _scan.ScanError(f"attribute '{attr.name}' is not a per-vertex vector")
            stored[c] = attr.name
    if sorted(stored) != list(range(n_fields)) or n_fields < 1:
        raise _scan.ScanError(
            f"'{obj.name}': the scan data is damaged (expected {n_fields} field attributes "
            f"'{FIELD_PREFIX}...', found {len(stored)})")
    # sha256 (hardware-accelerated where available): twice as fast as blake2b here; the
    # fingerprint only names the scan for the in-memory Segmenter cache.
    digest = hashlib.sha256()
    verts = _positions(mesh, n)
    faces, polys = _triangles(mesh)
    if len(faces) == 0:
        raise _scan.ScanError(f"'{obj.name}' has no faces")
    digest.update(np.ascontiguousarray(verts))
    digest.update(np.ascontiguousarray(faces))
    # One field at a time through a float32 buffer (the fast foreach_get) into the float64
    # array the core works on: no second full-size float32 copy.
    fields = np.empty((n_fields, 3 * n), dtype=np.float64)
    buf = np.empty(3 * n, dtype=np.float32)
    for c in range(n_fields):
        mesh.attributes[stored[c]].data.foreach_get("vector", buf)
        digest.update(buf)
        fields[c] = buf
    load_vertices = support = None
    attr = mesh.attributes.get(LOAD_ATTR)
    if attr is not None:
        index = _get(attr.data, "value", n, np.int32)
        digest.update(index)
        vert = np.nonzero(index >= 0)[0]
        order = np.argsort(index[vert], kind="stable")
        load_vertices = vert[order].astype(np.int64)
        if not np.array_equal(index[load_vertices], np.arange(len(load_vertices))):
            raise _scan.ScanError(f"'{obj.name}': the load vertex numbering is damaged")
    attr = mesh.attributes.get(SUPPORT_ATTR)
    if attr is not None:
        flags = _get(attr.data, "value", n, bool)
        digest.update(flags)
        support = np.nonzero(flags)[0].astype(np.int64)
    probe = float(mesh.get("artdef_probe_load", 1.0))
    digest.update(repr((kind, probe)).encode())
    verts64 = verts.astype(np.float64)
    faces64 = faces.astype(np.int64)
    if kind == "greens":
        if load_vertices is None or 3 * len(load_vertices) != n_fields:
            raise _scan.ScanError(
                f"'{obj.name}': a Green's scan needs {n_fields // 3 if n_fields % 3 == 0 else '?'} "
                f"load vertices marked in '{LOAD_ATTR}'")
        greens = fields.T  # (3N, P): column c is field c (the layout astype gave before)
        scan = _scan.Scan(verts64, faces64, greens=greens, load_vertices=load_vertices,
                          support_vertices=support, probe_load=probe)
    else:
        scan = _scan.Scan(verts64, faces64, displacements=fields.reshape(n_fields, n, 3),
                          load_vertices=None, support_vertices=support, probe_load=probe)
    scan = _scan.validate_scan(scan)
    return StoredScan(scan, polys, digest.hexdigest())


def key_points(kb):
    """Fast foreach access to a shape key's coordinates (``points``, else ``data``)."""
    return kb.points if "points" in kb.bl_rna.properties else kb.data


def shape_key_poses(obj, skip=()):
    """(reference key, [pose keys]) of ``obj``'s relative shape keys.

    Keys whose names are in ``skip`` (the residual keys a fit made) are left out.
    """
    keys = obj.data.shape_keys
    if keys is None or not keys.use_relative:
        return None, []
    ref = keys.reference_key
    poses = [kb for kb in keys.key_blocks if kb != ref and kb.name not in skip]
    return ref, poses


def scan_from_shape_keys(obj, skip=()):
    """A tracked ``S.Scan`` whose fields are the shape keys minus the basis."""
    ref, poses = shape_key_poses(obj, skip)
    if ref is None or not poses:
        raise _scan.ScanError(
            f"'{obj.name}' needs relative shape keys: a basis and at least one pose")
    mesh = obj.data
    n = len(mesh.vertices)
    verts = _positions(mesh, n).astype(np.float64)
    basis = _get(key_points(ref), "co", n, np.float32, 3).astype(np.float64)
    disp = np.empty((len(poses), n, 3))
    for p, kb in enumerate(poses):
        disp[p] = _get(key_points(kb), "co", n, np.float32, 3) - basis
    faces, _ = _triangles(mesh)
    if len(faces) == 0:
        raise _scan.ScanError(f"'{obj.name}' has no faces")
    scan = _scan.Scan(verts, faces.astype(np.int64), displacements=disp)
    return _scan.validate_scan(scan), [kb.name for kb in poses]
