# SPDX-License-Identifier: GPL-3.0-or-later
"""More ways in: tracked scans from animated meshes and from mesh sequences.

* ``artdef.fields_from_animation`` — samples the active mesh over a frame range
  through the depsgraph, so whatever Blender animates counts (Armature
  modifiers, shape-key animation, Mesh Cache / Alembic, baked simulations,
  geometry nodes that keep the topology).  The scan goes on a **new** object,
  a copy of the mesh without the modifiers that move it, its shape keys and
  its animation: fitting the source itself would stack ArtDef's Armature on
  the deformation that is being measured (the user's rig, cache or
  simulation), and the source stays exactly as it was.
* ``artdef.import_mesh_sequence`` — numbered OBJ/PLY files with shared
  connectivity (parsed by :mod:`.sequence`, no ``bpy``).

Both end in the same representation as an imported scan (:mod:`.io`).
"""

import os
import time

import bpy
import numpy as np
from bpy.props import EnumProperty, IntProperty, StringProperty
from bpy_extras.io_utils import ImportHelper

from ..artdef_addon import scan as _scan, wording
from . import io, menus, rig, sequence
from .ops import in_object_mode, mesh_in_object_mode

#: Modifiers that change the topology (Blender's "Generate" group).  They are
#: switched off while sampling (and switched back on after), so the sampled
#: vertices are the base mesh's, and they stay on the copy.
GENERATE_MODIFIERS = frozenset((
    'ARRAY', 'BEVEL', 'BOOLEAN', 'BUILD', 'DECIMATE', 'EDGE_SPLIT', 'MASK', 'MIRROR',
    'MESH_TO_VOLUME', 'MULTIRES', 'REMESH', 'SCREW', 'SKIN', 'SOLIDIFY', 'SUBSURF',
    'TRIANGULATE', 'VOLUME_TO_MESH', 'WELD', 'WIREFRAME', 'EXPLODE', 'PARTICLE_INSTANCE',
))
#: Modifiers that never move vertices: left alone while sampling, kept on the copy.
STILL_MODIFIERS = frozenset((
    'DATA_TRANSFER', 'NORMAL_EDIT', 'WEIGHTED_NORMAL', 'UV_PROJECT', 'UV_WARP',
    'VERTEX_WEIGHT_EDIT', 'VERTEX_WEIGHT_MIX', 'VERTEX_WEIGHT_PROXIMITY',
))
# Every other modifier (Armature, Mesh Cache, Mesh Sequence Cache, Lattice,
# Cloth, Soft Body, Geometry Nodes, ...) may move the vertices: it is sampled
# and left off the copy.

#: More fields than this makes the fit slow and the .blend big: say so.
MANY_FIELDS = 120


def _select_only(context, obj):
    for other in context.view_layer.objects:
        if other.select_get():
            other.select_set(False)
    obj.select_set(True)
    context.view_layer.objects.active = obj


def _link_like(context, new, like=None):
    colls = list(like.users_collection) if like is not None else []
    colls = [c for c in colls if c.library is None] or [context.collection]
    for coll in colls:
        coll.objects.link(new)


# --------------------------------------------------------------------------
# fields from animation
# --------------------------------------------------------------------------

def _topology(mesh):
    """(vertex count, polygon count, corner vertex indices) of a mesh."""
    n_loops = len(mesh.loops)
    corners = np.empty(n_loops, dtype=np.int32)
    attr = mesh.attributes.get(".corner_vert")  # 0.1 ms per 400k corners, vs 70 ms via loops
    if attr is not None and attr.domain == 'CORNER' and len(attr.data) == n_loops:
        attr.data.foreach_get("value", corners)
    else:
        mesh.loops.foreach_get("vertex_index", corners)
    return len(mesh.vertices), len(mesh.polygons), corners


def _read_positions(mesh, out):
    """Vertex positions into the float32 (N*3,) array ``out`` (fast attribute path)."""
    attr = mesh.attributes.get("position")
    if attr is not None and attr.data_type == 'FLOAT_VECTOR' and len(attr.data) == len(mesh.vertices):
        attr.data.foreach_get("vector", out)
    else:
        mesh.vertices.foreach_get("co", out)


#: the farthest a sampled frame may move a vertex, in sizes of the mesh: beyond it the animation is
#: damaged (a flipped exponent bit in a file's numbers), not a motion to fit
MAX_FRAME_REACH = 1e6


def sample_positions(context, obj, frames):
    """Object-space vertex positions of ``obj`` evaluated at ``frames``: (F, N, 3) float32.

    Modifiers that change the topology are switched off meanwhile; the scene
    frame and the modifiers are restored afterwards.  Raises ``ScanError``
    ("connectivity differs at frame F: ...") when a frame's evaluated mesh
    does not have the base mesh's vertices and faces, and ("frame F: ...")
    at the first frame whose positions are not all finite.
    """
    scene = context.scene
    n, base_polys, base_corners = _topology(obj.data)
    out = np.empty((len(frames), n, 3), dtype=np.float32)
    frame_before, subframe_before = scene.frame_current, scene.frame_subframe
    switched = [m for m in obj.modifiers if m.type in GENERATE_MODIFIERS and m.show_viewport]
    moving = [m.name for m in obj.modifiers
              if m.type not in GENERATE_MODIFIERS | STILL_MODIFIERS and m.show_viewport]
    try:
        for m in switched:
            m.show_viewport = False
        for i, frame in enumerate(frames):
            scene.frame_set(int(frame))
            depsgraph = context.evaluated_depsgraph_get()
            ev = obj.evaluated_get(depsgraph)
            me = ev.to_mesh()
            try:
                nv, n_polys, corners = _topology(me)
                if nv != n:
                    hint = (f" (check the modifier{'s' if len(moving) > 1 else ''} "
                            f"{', '.join(repr(m) for m in moving)})" if moving else "")
                    raise _scan.ScanError(f"connectivity differs at frame {frame}: {nv} vertices, "
                                          f"expected {n}{hint}")
                if n_polys != base_polys or not np.array_equal(corners, base_corners):
                    raise _scan.ScanError(
                        f"connectivity differs at frame {frame}: the faces changed "
                        f"({n_polys} faces, expected {base_polys})")
                _read_positions(me, out[i].reshape(-1))
                if not np.isfinite(out[i]).all():     # a damaged file's NaN morph targets or keys
                    bad = int(np.count_nonzero(~np.isfinite(out[i]).all(axis=1)))
                    raise _scan.ScanError(f"frame {frame}: {bad} of {n} vertex positions are NaN or infinite "
                                          "(the file's animation holds values that are not numbers)")
            finally:
                ev.to_mesh_clear()
    finally:
        for m in switched:
            m.show_viewport = True
        scene.frame_set(frame_before, subframe=subframe_before)
    return out


def copy_without_motion(context, obj, rest, name):
    """A new object: ``obj``'s mesh at ``rest`` without what moves it.

    Dropped: modifiers that may move vertices, shape keys, object animation,
    constraints, parent (the world transform is kept), ArtDef's own rig data.
    Also dropped: the vertex groups of the dropped Armature modifiers' bones (the
    source's skinning: input data, it would ride along into an export).
    Kept: materials, UVs, other vertex groups, and modifiers that change topology
    or only normals/weights.  Returns (object, names of dropped modifiers).
    """
    new = obj.copy()                        # modifiers with all their settings
    mesh = obj.data.copy()
    new.data = mesh                         # before touching shape keys!
    try:
        dropped = _strip_copy(context, obj, new, rest, name)
    except Exception:
        bpy.data.objects.remove(new)
        bpy.data.meshes.remove(mesh)
        raise
    return new, dropped


def _strip_copy(context, obj, new, rest, name):
    src = obj.artdef
    new.name = name
    new.data.name = name
    new.property_unset("artdef")            # the source's fit record is not this object's
    for key in [k for k in new.keys() if k.startswith("artdef")]:
        del new[key]
    new.animation_data_clear()
    new.constraints.clear()
    dropped = []
    skin_groups = set()  # the source's skinning: groups of bones of a dropped Armature modifier
    for m in list(new.modifiers):
        if m.type not in GENERATE_MODIFIERS | STILL_MODIFIERS:
            if m.type == 'ARMATURE' and m.object is not None and m.object.type == 'ARMATURE':
                skin_groups.update(b.name for b in m.object.data.bones)
            dropped.append(m.name)
            new.modifiers.remove(m)
    for vg in [g for g in new.vertex_groups if g.name in skin_groups]:
        new.vertex_groups.remove(vg)
    world = obj.matrix_world.copy()
    new.parent = None
    new.matrix_world = world
    _link_like(context, new, obj)
    if new.data.shape_keys is not None:
        new.shape_key_clear()
    mesh = new.data
    mesh.vertices.foreach_set("co", np.ascontiguousarray(rest, dtype=np.float32).ravel())
    for item in src.groups:  # ArtDef link groups of a fitted source
        vg = new.vertex_groups.get(item.name)
        if vg is not None:
            new.vertex_groups.remove(vg)
    rig.remove_link_colours(mesh)
    rig.remove_residual(mesh)
    io.clear_scan(mesh)
    mesh.update()
    return dropped


class ARTDEF_OT_fields_from_animation(bpy.types.Operator):
    """Sample the active mesh's animation over a frame range (armature, shape keys, mesh caches and Alembic, baked simulations: whatever Blender evaluates) into a tracked scan on a new mesh object - a copy without the modifiers that move it, its shape keys and its animation - ready to fit. The source object is not changed"""
    bl_idname = "artdef.fields_from_animation"
    bl_label = "Fields from Animation"
    bl_options = {'REGISTER', 'UNDO'}

    frame_start: IntProperty(name="Start", default=1,
                             description="First frame sampled (default: the scene's start)")
    frame_end: IntProperty(name="End", default=250,
                           description="Last frame sampled (default: the scene's end)")
    frame_step: IntProperty(name="Step", default=1, min=1,
                            description="Sample every n-th frame (bake simulations first, "
                                        "or use step 1 from their start frame)")
    rest: EnumProperty(
        name="Rest", default='BASE',
        items=(('BASE', "Base Mesh", "The undeformed mesh: its own vertex positions"),
               ('FRAME', "Frame", "The evaluated mesh at Rest Frame")),
        description="Rest shape the fields are measured from (setting Rest Frame picks 'Frame')")
    rest_frame: IntProperty(name="Rest Frame", default=0,
                            description="Frame of the rest shape when Rest is 'Frame'")

    @classmethod
    def poll(cls, context):
        return mesh_in_object_mode(cls, context) is not None

    def invoke(self, context, event):
        props = self.properties
        scene = context.scene
        if not props.is_property_set("frame_start"):
            self.frame_start = scene.frame_start
        if not props.is_property_set("frame_end"):
            self.frame_end = scene.frame_end
        return context.window_manager.invoke_props_dialog(self)

    def execute(self, context):
        t0 = time.perf_counter()
        scene = context.scene
        obj = context.active_object
        props = self.properties
        start = self.frame_start if props.is_property_set("frame_start") else scene.frame_start
        end = self.frame_end if props.is_property_set("frame_end") else scene.frame_end
        self.frame_start, self.frame_end = start, end
        use_frame = self.rest == 'FRAME' or (props.is_property_set("rest_frame")
                                             and not props.is_property_set("rest"))
        self.rest = 'FRAME' if use_frame else 'BASE'
        if end < start:
            self.report({'ERROR'}, f"The frame range is empty: end {end} is before start {start}")
            return {'CANCELLED'}
        frames = list(range(start, end + 1, self.frame_step))
        sample = sorted(set(frames) | ({self.rest_frame} if use_frame else set()))
        mesh = obj.data
        n = len(mesh.vertices)
        if n < 3 or len(mesh.polygons) == 0:
            self.report({'ERROR'}, f"'{obj.name}' has no faces to fit")
            return {'CANCELLED'}
        try:
            positions = sample_positions(context, obj, sample)
        except _scan.ScanError as err:
            self.report({'ERROR'}, f"'{obj.name}': {err}")
            return {'CANCELLED'}
        at = {f: i for i, f in enumerate(sample)}
        if use_frame:
            rest = positions[at[self.rest_frame]].astype(np.float64)
        else:
            rest = np.empty(3 * n, dtype=np.float32)
            _read_positions(mesh, rest)
            rest = rest.reshape(n, 3).astype(np.float64)
        disp = positions[[at[f] for f in frames]].astype(np.float64) - rest[None]
        extent = float(np.ptp(rest, axis=0).max()) or 1.0
        reach = np.abs(disp).reshape(len(frames), -1).max(axis=1)
        if (reach > MAX_FRAME_REACH * extent).any():
            k = int(np.flatnonzero(reach > MAX_FRAME_REACH * extent)[0])
            self.report({'ERROR'}, f"'{obj.name}': frame {frames[k]} moves a vertex by {reach[k]:.3g}, over "
                                   f"{MAX_FRAME_REACH:.0e} times the mesh's size (the animation is damaged)")
            return {'CANCELLED'}
        moves = np.abs(disp).reshape(len(frames), -1).max(axis=1) > 1e-6 * extent
        kept = [f for f, m in zip(frames, moves) if m]
        if not kept:
            self.report({'ERROR'}, f"'{obj.name}' does not move over frames {start}-{end} "
                                   f"(relative to the {'rest frame' if use_frame else 'base mesh'})")
            return {'CANCELLED'}
        disp = disp[moves]
        faces = np.empty(3 * len(mesh.loop_triangles), dtype=np.int32)
        mesh.loop_triangles.foreach_get("vertices", faces)
        try:
            scan = _scan.validate_scan(_scan.Scan(rest, faces.reshape(-1, 3).astype(np.int64),
                                                  displacements=disp))
        except _scan.ScanError as err:
            self.report({'ERROR'}, f"'{obj.name}': {err}")
            return {'CANCELLED'}
        try:
            new, dropped = copy_without_motion(context, obj, rest, f"{obj.name}_scan")
        except Exception as err:
            self.report({'ERROR'}, f"Copying '{obj.name}' failed: {err}")
            return {'CANCELLED'}
        try:
            io.write_scan(new.data, scan)
        except Exception as err:
            data = new.data
            bpy.data.objects.remove(new)
            bpy.data.meshes.remove(data)
            self.report({'ERROR'}, f"Storing the scan failed: {err}")
            return {'CANCELLED'}
        new.data["artdef_source"] = obj.name
        new.data["artdef_frames"] = kept
        new.data["artdef_sampled_frames"] = frames  # with the frames equal to the rest (replay timing)
        new.data["artdef_rest_frame"] = self.rest_frame if use_frame else -1
        _select_only(context, new)
        skipped = len(frames) - len(kept)
        msg = (f"'{new.name}': {len(kept)} frames of '{obj.name}' ({start}-{end}, step "
               f"{self.frame_step}) stored as a tracked scan, rest: "
               + (f"frame {self.rest_frame}" if use_frame else "base mesh"))
        if skipped:
            msg += f"; {skipped} frames equal to the rest skipped"
        if dropped:
            msg += f"; left out modifiers {', '.join(dropped)}"
        msg += f" ({time.perf_counter() - t0:.2f} s)"
        self.report({'INFO'}, msg)
        if len(kept) > MANY_FIELDS:
            self.report({'WARNING'}, f"{len(kept)} fields make fitting slow: consider a larger Step")
        return {'FINISHED'}


# --------------------------------------------------------------------------
# mesh sequence
# --------------------------------------------------------------------------

class FrameRange:
    """Start, End and Step of the frames an import samples, each left to the file unless given
    (a sequence's file numbers are its frames): one declaration for Import Mesh Sequence and
    Import Animated File (``animfile``), which passes them on to the former."""
    frame_start: IntProperty(name="Start", default=0,
                             description="First frame sampled; a sequence's file number "
                                         "(unset: the file's first key, the first file)")
    frame_end: IntProperty(name="End", default=0,
                           description="Last frame sampled; a sequence's file number "
                                       "(unset: the file's last key, the last file)")
    frame_step: IntProperty(name="Step", default=1, min=1,
                            description="Sample every n-th frame from Start "
                                        "(unset: the file's key spacing, every file)")

    def given_frames(self) -> dict:
        """The frame settings given to this call: ``{"frame_start": ..., ...}``."""
        return {p: getattr(self, p) for p in ("frame_start", "frame_end", "frame_step")
                if self.properties.is_property_set(p)}


class ARTDEF_OT_import_mesh_sequence(bpy.types.Operator, ImportHelper, FrameRange):
    """Import numbered OBJ or PLY files with shared connectivity (pose_000.obj, pose_001.obj, ...) as one tracked scan: the rest pose (the first file unless Rest Number names another) becomes a mesh, every other file a displacement field"""
    bl_idname = "artdef.import_mesh_sequence"
    bl_label = "Import Mesh Sequence"
    bl_options = {'REGISTER', 'UNDO'}

    filename_ext = ".obj"
    filter_glob: StringProperty(default="*.obj;*.ply", options={'HIDDEN'})
    directory: StringProperty(subtype='DIR_PATH', options={'HIDDEN', 'SKIP_SAVE'},
                              description="Folder holding one numbered sequence")
    rest_number: IntProperty(
        name="Rest Number", default=-1, min=-1,
        description="Number in the file name of the rest pose (-1: the first file)")

    @classmethod
    def poll(cls, context):
        return in_object_mode(cls, context)

    def _path(self):
        path = bpy.path.abspath(self.filepath) if self.filepath else ""
        if path and not os.path.isdir(path) and os.path.basename(path):
            return path
        return bpy.path.abspath(self.directory) if self.directory else path

    def execute(self, context):
        t0 = time.perf_counter()
        path = self._path()
        if not path:
            self.report({'ERROR'}, "Choose the first file of a numbered sequence (or its folder)")
            return {'CANCELLED'}
        wm = context.window_manager
        try:
            paths = sequence.find_sequence(path)
            rest = 0
            if self.rest_number >= 0:
                numbers = [sequence.split_number(os.path.basename(p))[1] for p in paths]
                if self.rest_number not in numbers:
                    raise sequence.SequenceError(
                        f"no file numbered {self.rest_number} in the sequence "
                        f"({numbers[0]}..{numbers[-1]})")
                rest = numbers.index(self.rest_number)
            given = self.given_frames()
            if given:  # a file's number is its frame; the rest file stays
                paths, rest = sequence.select_frames(paths, rest, given.get("frame_start"),
                                                     given.get("frame_end"), given.get("frame_step"))
            wm.progress_begin(0, len(paths))
            try:
                seq = sequence.load_sequence(paths, rest, lambda i, n: wm.progress_update(i))
            finally:
                wm.progress_end()
            extent = float(np.ptp(seq.vertices, axis=0).max()) or 1.0
            moves = np.abs(seq.displacements).reshape(len(seq.displacements), -1).max(axis=1) \
                > 1e-9 * extent
            scan = _scan.validate_scan(_scan.Scan(seq.vertices, seq.triangles,
                                                  displacements=seq.displacements[moves]))
        except (sequence.SequenceError, _scan.ScanError) as err:
            self.report({'ERROR'}, f"Cannot import the mesh sequence: {err}")
            return {'CANCELLED'}
        prefix = _text(sequence.split_number(os.path.basename(paths[0]))[0]).rstrip("_-. ") or "sequence"
        try:
            mesh = io.new_mesh_from_polygons(prefix, seq.vertices, seq.sizes, seq.indices)
        except _scan.ScanError as err:
            self.report({'ERROR'}, f"Cannot import the mesh sequence: {err}")
            return {'CANCELLED'}
        try:
            io.write_scan(mesh, scan)
        except Exception as err:
            bpy.data.meshes.remove(mesh)
            self.report({'ERROR'}, f"Cannot import the mesh sequence: {err}")
            return {'CANCELLED'}
        # faces that repeat a vertex or another face: Mesh.validate left them out (said, not silent)
        dropped = len(seq.sizes) - len(mesh.polygons)
        if dropped:
            mesh["artdef_dropped_faces"] = dropped
        mesh["artdef_source"] = _text(os.path.basename(paths[0]))
        mesh["artdef_rest_file"] = _text(os.path.basename(paths[rest]))
        # replay timing: a file's number is its frame (the rest file and files equal to it: rest)
        numbers = [sequence.split_number(os.path.basename(p))[1] for p in paths]
        moved = [n for i, n in enumerate(numbers) if i != rest]
        mesh["artdef_frames"] = [int(n) for n, m in zip(moved, moves) if m]
        mesh["artdef_sampled_frames"] = [int(n) for n in numbers]
        obj = bpy.data.objects.new(mesh.name, mesh)
        context.collection.objects.link(obj)
        _select_only(context, obj)
        skipped = int(np.count_nonzero(~moves))
        self.report({'INFO'}, f"Imported '{obj.name}': {len(paths)} files, {len(seq.vertices)} "
                              f"vertices, {scan.n_fields} fields, rest "
                              f"{_text(os.path.basename(paths[rest]))}"
                              + (f"; {skipped} files equal to the rest skipped" if skipped else "")
                              + (f"; {dropped} of the files' {len(seq.sizes)} faces left out "
                                 f"({wording.DROPPED_FACES})" if dropped else "")
                              + f" ({time.perf_counter() - t0:.2f} s)")
        return {'FINISHED'}


def _text(name):
    """A file name as Blender can hold it (UTF-8): bytes that are not UTF-8 (a POSIX name may hold
    them; Python keeps them as surrogates, which Blender's strings refuse) become U+FFFD."""
    return os.fsencode(name).decode("utf-8", "replace")


def menu_import(self, context):
    self.layout.operator(ARTDEF_OT_import_mesh_sequence.bl_idname,
                         text="ArtDef Mesh Sequence (.obj/.ply)")


classes = (ARTDEF_OT_fields_from_animation, ARTDEF_OT_import_mesh_sequence)


register, unregister = menus.registration(classes, "TOPBAR_MT_file_import", menu_import)
