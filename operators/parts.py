# SPDX-License-Identifier: GPL-3.0-or-later
"""Every animated mesh of a file: which meshes are fitted, and their scans joined into one.

A character is often several meshes (body, head, clothes, props) moved by one armature. Fields
from File fits all of them together as one scan: each mesh is sampled by Fields from Animation
over the same frames, the copies are put in world space and joined into one mesh object (its
materials and UV maps kept), whose scan holds every mesh's vertices. One fit, one armature.
The joined mesh records its parts (``artdef_parts``: the source mesh names in vertex order,
``artdef_part_sizes``: their vertex counts). After the fit, :func:`write_parts` writes the rig
on one object per source mesh (``<source>_rigged``, pointing back at the joined mesh with
``artdef_part_of``), and the joined mesh, which keeps the scan, is hidden.
"""

import bpy
import numpy as np

from ..artdef_addon import scan as _scan

#: the temporary per-vertex attribute that tells the joined mesh's vertices apart by part
PART_ATTR = "artdef_part_tag"


def _is_custom_shape(obj):
    """A mesh used only to draw bones (the glTF importer adds one)."""
    for arm in bpy.data.objects:
        if arm.type == 'ARMATURE' and arm.pose is not None:
            if any(pb.custom_shape == obj for pb in arm.pose.bones):
                return True
    return False


#: why a mesh that could be fitted was left out: the user chose others
NOT_CHOSEN = "not chosen"


def animated_meshes(objects, moving, chosen=()):
    """``(fitted, left_out)`` among ``objects``: the meshes to fit, largest first, and
    ``(name, why)`` of every other mesh (a bone's custom shape, no faces, static, not chosen).
    ``moving(obj) -> bool``: whether something animates it. ``chosen``: mesh names to fit (empty:
    every animated one); ValueError naming a chosen mesh that is not in ``objects`` or cannot
    be fitted."""
    fitted, left_out = [], []
    names = {o.name for o in objects if o.type == 'MESH'}
    missing = [n for n in chosen if n not in names]
    if missing:
        raise ValueError(f"no mesh named {', '.join(repr(n) for n in missing)} in the file "
                         f"(its meshes: {', '.join(sorted(names)) or 'none'})")
    for obj in objects:
        if obj.type != 'MESH':
            continue
        if _is_custom_shape(obj):
            why = "a bone's custom shape"
        elif len(obj.data.polygons) == 0:
            why = "no faces"
        elif not moving(obj):
            why = "static"
        elif chosen and obj.name not in chosen:
            why = NOT_CHOSEN
        else:
            fitted.append(obj)
            continue
        if obj.name in chosen:
            raise ValueError(f"mesh {obj.name!r} cannot be fitted: {why}")
        left_out.append((obj.name, why))
    fitted.sort(key=lambda o: (-len(o.data.vertices), o.name))
    return fitted, left_out


def describe(fitted_names, left_out) -> str:
    """The report's words: "meshes fitted: Body, Head; left out: Icosphere (a bone's custom shape)"."""
    text = "meshes fitted: " + ", ".join(fitted_names)
    if left_out:
        text += "; left out: " + ", ".join(f"{n} ({why})" for n, why in left_out)
    return text


def _world_scan(obj, scan, frames, all_frames):
    """``(rest (N, 3), fields (F, N, 3))`` of a copy's scan in world space, over ``all_frames``
    (F): a frame the copy left out (it equalled the rest there) has a zero field."""
    m = np.array(obj.matrix_world, dtype=np.float64)
    lin, shift = m[:3, :3], m[:3, 3]
    rest = np.asarray(scan.vertices) @ lin.T + shift
    fields = np.zeros((len(all_frames), scan.n_vertices, 3))
    at = {f: i for i, f in enumerate(all_frames)}
    fields[[at[f] for f in frames]] = np.asarray(scan.displacements) @ lin.T
    return rest, fields


def join_scans(context, copies, names):
    """Join the tracked scans on ``copies`` (one per source mesh, ``names``; each sampled over the
    same frames by Fields from Animation) into the first: one mesh in world space whose scan
    holds every copy's vertices and fields over the union of their frames. The other copies are
    removed. Returns the joined object."""
    from . import io
    scans = [io.read_scan(o).scan for o in copies]
    kept = [[int(f) for f in o.data.get("artdef_frames", [])] for o in copies]
    frames = sorted(set().union(*kept))
    world = [_world_scan(o, s, k, frames) for o, s, k in zip(copies, scans, kept)]
    sampled = [int(f) for f in copies[0].data.get("artdef_sampled_frames", frames)]
    for k, (o, (rest, _)) in enumerate(zip(copies, world)):
        mesh = o.data
        mesh.vertices.foreach_set("co", rest.astype(np.float32).ravel())
        o.matrix_world.identity()
        attr = mesh.attributes.new(PART_ATTR, 'INT', 'POINT')
        attr.data.foreach_set("value", np.full(len(mesh.vertices), k, dtype=np.int32))
        io.clear_scan(mesh)
        mesh.update()
    target = copies[0]
    for o in context.view_layer.objects:
        o.select_set(o in copies)
    context.view_layer.objects.active = target
    with context.temp_override(active_object=target, object=target, selected_objects=list(copies),
                               selected_editable_objects=list(copies)):
        bpy.ops.object.join()
    mesh = target.data
    n = len(mesh.vertices)
    part = np.empty(n, dtype=np.int32)
    mesh.attributes[PART_ATTR].data.foreach_get("value", part)
    mesh.attributes.remove(mesh.attributes[PART_ATTR])
    order = np.argsort(part, kind="stable")             # each part's vertices keep their order
    rest = np.empty((n, 3))
    fields = np.empty((len(frames), n, 3))
    start = 0
    for k, (r, f) in enumerate(world):
        at = order[start:start + len(r)]
        rest[at], fields[:, at] = r, f
        start += len(r)
    faces, _ = io._triangles(mesh)
    scan = _scan.validate_scan(_scan.Scan(rest, faces.astype(np.int64), displacements=fields))
    io.write_scan(mesh, scan)
    mesh["artdef_frames"] = frames
    mesh["artdef_sampled_frames"] = sampled
    starts = np.r_[0, np.flatnonzero(np.diff(part)) + 1]
    mesh["artdef_parts"] = [names[int(k)] for k in part[starts]]
    mesh["artdef_part_sizes"] = [int(c) for c in np.diff(np.r_[starts, n])]
    mesh["artdef_source"] = names[0]       # the largest: its armature names the bones
    return target


#: the ID property on a source mesh's rigged object that points at the joined mesh it was cut from
PART_OF = "artdef_part_of"
#: the name of the object a fit writes for each source mesh: ``Body_rigged``
PART_NAME = "{}_rigged"


def _part_ranges(obj):
    """``(names, starts, ends)`` of the joined mesh ``obj``'s parts, or None for a scan of one mesh."""
    names = list(obj.data.get("artdef_parts", []))
    sizes = [int(s) for s in obj.data.get("artdef_part_sizes", [])]
    if len(names) < 2 or len(sizes) != len(names) or sum(sizes) != len(obj.data.vertices):
        return None
    ends = np.cumsum(sizes)
    return names, ends - np.asarray(sizes), ends


def _keep_only(obj, start, end):
    """Delete every vertex of ``obj``'s own mesh outside ``start..end`` (bmesh keeps the rest's
    vertex groups, shape keys and attributes, in order)."""
    import bmesh
    n = len(obj.data.vertices)
    out_of_part = np.flatnonzero((np.arange(n) < start) | (np.arange(n) >= end))
    bm = bmesh.new()
    try:
        bm.from_mesh(obj.data)
        bm.verts.ensure_lookup_table()
        bmesh.ops.delete(bm, geom=[bm.verts[int(i)] for i in out_of_part], context='VERTS')
        bm.to_mesh(obj.data)
    finally:
        bm.free()
    obj.data.update()


def _copy_object(obj, name):
    part = obj.copy()
    part.data = obj.data.copy()
    for coll in obj.users_collection:
        coll.objects.link(part)
    part.name = part.data.name = name
    return part


def split_parts(context, obj):
    """Cut the export copy ``obj`` of a joined scan back into its source meshes: ``obj`` keeps the
    first part, a new object per other part (named after its source mesh, with ``_scan``) holds
    that part's vertices with their vertex groups, shape keys, modifiers and parent. Returns the
    new objects (none for a scan of one mesh). Each is exported as its own mesh."""
    ranges = _part_ranges(obj)
    if ranges is None:
        return []
    names, starts, ends = ranges
    out = [_copy_object(obj, f"{name}_scan") for name in names[1:]]   # all copied before any cut
    for k, part in enumerate([obj, *out]):
        _keep_only(part, starts[k], ends[k])
    return out


def parts_of(obj):
    """The rigged objects written for the source meshes of the joined mesh ``obj`` (in part order)."""
    found = [o for o in bpy.data.objects if o.get(PART_OF) == obj]
    order = {n: i for i, n in enumerate(obj.data.get("artdef_parts", []))} if obj.type == 'MESH' else {}
    return sorted(found, key=lambda o: (order.get(o.get("artdef_part_name"), len(order)), o.name))


def owner_of(obj):
    """The joined mesh a source mesh's rigged object was cut from, else ``obj`` itself."""
    owner = obj.get(PART_OF) if obj is not None else None
    return owner if isinstance(owner, bpy.types.Object) and owner.name in bpy.data.objects else obj


def detach_parts(obj):
    """Set the rigged objects of ``obj``'s previous fit aside (no longer counted as its parts)
    while a re-fit builds its own; :func:`attach_parts` puts them back, :func:`remove_parts` removes them."""
    old = parts_of(obj)
    for part in old:
        del part[PART_OF]
    return old


def attach_parts(obj, old):
    for part in old:
        part[PART_OF] = obj
    if old:
        obj.hide_set(True)


def settle_names(obj):
    """Give the rigged objects of ``obj`` their own names (:data:`PART_NAME`) once the previous fit's
    are gone (made beside them, they got a ``.001``)."""
    for part in parts_of(obj):
        name = PART_NAME.format(part.get("artdef_part_name", part.name))
        if part.name != name and name not in bpy.data.objects:
            part.name = name
        if part.data.name != name and name not in bpy.data.meshes:
            part.data.name = name


def remove_parts(objects):
    for part in list(objects):
        data = part.data
        bpy.data.objects.remove(part, do_unlink=True)
        if data is not None and data.users == 0:
            bpy.data.meshes.remove(data)


def write_parts(context, obj):
    """Write the rig of the joined mesh ``obj`` onto one object per source mesh: a copy holding that
    mesh's vertices (in the source's order) with their vertex groups, residual shape keys (their
    replay action shared), the Armature modifier and the parent (the one armature), named
    :data:`PART_NAME` of the source. ``obj`` keeps the scan (a re-fit, Clear Rig) and is hidden.
    Replaces the parts written before. Returns the new objects (none for a scan of one mesh)."""
    from . import io
    remove_parts(parts_of(obj))
    ranges = _part_ranges(obj)
    if ranges is None:
        return []
    names, starts, ends = ranges
    out = []
    try:
        for name in names:
            part = _copy_object(obj, PART_NAME.format(name))
            part[PART_OF] = obj
            part["artdef_part_name"] = name
            out.append(part)
        for part, start, end in zip(out, starts, ends):
            _keep_only(part, start, end)
            io.clear_scan(part.data)          # the scan stays the joined mesh's: a re-fit fits it
            for key in ("artdef_parts", "artdef_part_sizes"):
                if key in part.data:
                    del part.data[key]
            part.hide_set(False)
    except Exception:
        remove_parts(out)
        raise
    obj.hide_set(True)
    return out
