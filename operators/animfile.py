# SPDX-License-Identifier: GPL-3.0-or-later
"""Fit the file you have: an animated file Blender imports, as a tracked scan.

``artdef.fields_from_file`` imports a .glb/.gltf, .fbx, .abc or .usd/.usdc/
.usda/.usdz file with Blender's own importer (or a numbered OBJ/PLY sequence,
a folder or a pattern, with ``artdef.import_mesh_sequence``), picks the
animated meshes (every one, or those named in ``meshes``; :mod:`parts`) and samples them through ``artdef.fields_from_animation`` - the
same code as the Fields from Animation button - over the file's own frames:
the frames the file has keys at (an even step when they are evenly spaced,
else every frame of their range), or the scene range an Alembic/USD importer
set for a cache.  ``frame_start``/``frame_end``/``frame_step`` override it.

The command line (``python -m artdef_addon fit FILE``) runs this operator.
"""

import glob
import os

import bpy
import numpy as np
from bpy.props import BoolProperty, StringProperty
from bpy_extras.io_utils import ImportHelper

from . import compat, isolated, menus, ops, parts, rig
from .ops import in_object_mode
from .sources import FrameRange
from ..artdef_addon import cli as _cli
from ..artdef_addon import filecheck
from ..artdef_addon.cli import SEQUENCE_EXTENSIONS

#: extension -> (importer operator path, keyword arguments)
IMPORTERS = {
    ".glb": ("import_scene.gltf", {}),
    ".gltf": ("import_scene.gltf", {}),
    ".fbx": ("import_scene.fbx", {}),
    ".abc": ("wm.alembic_import", {}),
    ".usd": ("wm.usd_import", {}),
    ".usdc": ("wm.usd_import", {}),
    ".usda": ("wm.usd_import", {}),
    ".usdz": ("wm.usd_import", {}),
}
#: Modifiers whose evaluation replays a cache (no action to read keys from).
CACHE_MODIFIERS = frozenset(("MESH_SEQUENCE_CACHE", "MESH_CACHE"))


#: what the fit can read from a path: the command line's rule (one list of extensions for both)
file_kind = _cli.input_kind


def _operator(path):
    mod, name = path.split(".")
    return getattr(getattr(bpy.ops, mod), name)


def _sequence_path(path):
    """A folder or the first file of a numbered OBJ/PLY sequence (a pattern is
    resolved to its first match)."""
    if any(c in os.path.basename(path) for c in "*?["):
        matches = sorted(p for p in glob.glob(path) if p.lower().endswith(SEQUENCE_EXTENSIONS))
        if not matches:
            raise ValueError(f"no .obj/.ply file matches {path}")
        return matches[0]
    return path


def _actions_moving(obj):
    """(action, slot) pairs that move mesh object ``obj``: its own, its shape
    keys', its armatures' and its parents'."""
    ids = [obj, obj.data.shape_keys]
    for mod in obj.modifiers:
        if mod.type == 'ARMATURE' and mod.object is not None:
            ids.append(mod.object)
    parent = obj.parent
    while parent is not None:
        ids.append(parent)
        parent = parent.parent
    out = []
    for id_data in ids:
        ad = getattr(id_data, "animation_data", None) if id_data is not None else None
        if ad is not None and ad.action is not None:
            out.append((ad.action, getattr(ad, "action_slot", None)))
    return out


def check_keys(actions):
    """ValueError naming the first of ``actions`` with a keyframe whose time or value is NaN or
    infinite, or a rotation key whose quaternion is zero (a damaged file's keys: Blender clamps
    such values or rounds such times, and its USD importer keys NaN rotations as zero quaternions,
    so the frames sampled from them would look plausible and be wrong)."""
    for action in actions:
        quats = {}
        for fc in compat.action_fcurves(action):
            n = len(fc.keyframe_points)
            if not n:
                continue
            co = np.empty(2 * n, dtype=np.float64)
            fc.keyframe_points.foreach_get("co", co)
            co = co.reshape(n, 2)
            bad = ~np.isfinite(co)
            if bad.any():
                k = int(np.flatnonzero(bad.any(axis=1))[0])
                where = ("a keyframe time" if bad[k, 0] else f"the key at frame {co[k, 0]:g}")
                raise ValueError(f"its animation '{action.name}' ({fc.data_path}) holds NaN or infinite "
                                 f"numbers: {where} is not a number")
            if fc.data_path.endswith("rotation_quaternion"):
                quats.setdefault(fc.data_path, {})[fc.array_index] = co
        for path, channels in quats.items():
            if len(channels) != 4 or len({len(c) for c in channels.values()}) != 1:
                continue
            times = channels[0][:, 0]
            if any(not np.array_equal(c[:, 0], times) for c in channels.values()):
                continue
            norm = np.sqrt(sum(c[:, 1] ** 2 for c in channels.values()))
            if (norm < 1e-6).any():
                k = int(np.flatnonzero(norm < 1e-6)[0])
                raise ValueError(f"its animation '{action.name}' ({path}) holds a zero rotation (a quaternion "
                                 f"of length 0) in its key {k + 1} (frame {times[k]:g}): the file's keys are damaged")


def activate_own_animations(objects):
    """Give every armature among ``objects`` that has no active action the first action of its
    NLA tracks: Blender's glTF importer makes one animation active and puts the others in NLA
    tracks, so in a file of several characters, each with its own animation, all but one would
    stand still."""
    for obj in objects:
        ad = obj.animation_data if obj.type == 'ARMATURE' else None
        if ad is None or ad.action is not None:
            continue
        strips = [s for t in ad.nla_tracks for s in t.strips if s.action is not None]
        if strips:
            compat.assign_action(obj, strips[0].action)


def _moving(obj):
    """Whether something animates mesh object ``obj``: an action on it, its shape keys,
    armature or parents, or a cache modifier."""
    return bool(_actions_moving(obj)) or any(m.type in CACHE_MODIFIERS for m in obj.modifiers)


def animated_meshes(objects, chosen=()):
    """``(meshes to fit, [(name, why left out)])`` among ``objects``: every animated mesh
    (``chosen``: those named), largest first (:func:`parts.animated_meshes`)."""
    return parts.animated_meshes(objects, _moving, chosen)


def frames_of(objs, scene):
    """(start, end, step) over which the file animates ``objs`` (:func:`file_frames` of each:
    their whole range, their common step or 1)."""
    ranges = [file_frames(o, scene) for o in objs]
    steps = {r[2] for r in ranges}
    return min(r[0] for r in ranges), max(r[1] for r in ranges), (steps.pop() if len(steps) == 1 else 1)


def sample_meshes(context, objs, start, end, step):
    """Sample ``objs`` over ``start..end`` by ``step`` through ``artdef.fields_from_animation``;
    several meshes are joined into one scan (:func:`parts.join_scans`). Returns the scan object
    (active) or None (reported)."""
    copies, done = [], False
    try:
        for obj in objs:
            context.view_layer.objects.active = obj
            with context.temp_override(active_object=obj, object=obj, selected_objects=[obj]):
                result = bpy.ops.artdef.fields_from_animation(frame_start=start, frame_end=end,
                                                              frame_step=step)
            if 'FINISHED' not in result:
                return None
            copies.append(context.view_layer.objects.active)
        joined = copies[0] if len(copies) == 1 else parts.join_scans(context, copies, [o.name for o in objs])
        done = True
        return joined
    finally:
        if not done:  # failed half way: no copy stays
            for other in copies:
                data = other.data
                bpy.data.objects.remove(other, do_unlink=True)
                bpy.data.meshes.remove(data)


def file_frames(obj, scene):
    """(start, end, step) the file animates ``obj`` over: its keys' frames when
    it has actions (their even spacing as step, else 1), else the scene's range
    (caches: the importer sets it)."""
    keys = set()
    for action, slot in _actions_moving(obj):
        keys.update(round(f) for f in compat.keyed_frames(action, slot))
    if len(keys) >= 2:
        frames = sorted(keys)
        steps = {b - a for a, b in zip(frames, frames[1:])}
        step = steps.pop() if len(steps) == 1 else 1
        return frames[0], frames[-1], step
    return scene.frame_start, scene.frame_end, 1


def armature_clips(obj):
    """(armature, [actions]) when an armature moving ``obj`` has several clips:
    its active action and the actions of its NLA tracks (where Blender's glTF and
    FBX importers put a file's other animations); else (None, [])."""
    for mod in obj.modifiers:
        if mod.type == 'ARMATURE' and mod.object is not None:
            ad = mod.object.animation_data
            if ad is None:
                continue
            actions = [ad.action] if ad.action is not None else []
            for track in ad.nla_tracks:
                for strip in track.strips:
                    if strip.action is not None and strip.action not in actions:
                        actions.append(strip.action)
            if len(actions) > 1:
                return mod.object, actions
    return None, []


def _even_range(frames):
    frames = sorted(set(int(round(f)) for f in frames))
    steps = {b - a for a, b in zip(frames, frames[1:])}
    return frames[0], frames[-1], (steps.pop() if len(steps) == 1 else 1)


def sample_clips(context, objs, arm, actions):
    """Sample the meshes ``objs`` once per clip (each action made the armature's active one,
    NLA off meanwhile) through ``artdef.fields_from_animation``, and merge the
    scans into the first copy: its fields are every clip's, in clip order, with
    ``artdef_field_clips``/``artdef_clip_names``/``artdef_clip_sampled`` for the
    replay (one action per clip).  Returns the scan object or None (reported)."""
    ad = arm.animation_data
    saved = (ad.action, getattr(ad, "action_slot", None), ad.use_nla)
    copies, names = [], []
    try:
        ad.use_nla = False
        for action in actions:
            compat.assign_action(arm, action)
            start, end, step = _even_range(compat.keyed_frames(action))
            scan_obj = sample_meshes(context, objs, start, end, step)
            if scan_obj is None:
                return None
            copies.append(scan_obj)
            names.append(action.name)
        first = merge_clip_scans(copies, names)
        copies = copies[:1]
        return first
    finally:
        compat.assign_action(arm, saved[0])
        ad.use_nla = saved[2]
        if len(copies) > 1:  # failed half way: nothing of the sampling stays
            for other in copies:
                data = other.data
                bpy.data.objects.remove(other, do_unlink=True)
                bpy.data.meshes.remove(data)


def merge_clip_scans(objects, names):
    """Merge the tracked scans on ``objects`` (one clip each, same mesh and rest)
    into the first: its fields become every clip's, in order, with the replay's
    per-clip timing (``artdef_field_clips``, ``artdef_clip_names``,
    ``artdef_clip_sampled``).  The other objects are deleted.  ValueError (and
    nothing changed) if a clip's mesh or rest shape differs from the first's."""
    from ..artdef_addon import scan as _scan
    from . import io
    scans = [io.read_scan(o).scan for o in objects]
    first = scans[0]
    diag = float(np.linalg.norm(np.ptp(first.vertices, axis=0))) or 1.0
    for name, sc in zip(names[1:], scans[1:]):
        if sc.vertices.shape != first.vertices.shape or not np.array_equal(sc.faces, first.faces):
            raise ValueError(f"clip {name!r} is not the same mesh as {names[0]!r} "
                             f"({len(sc.vertices)} vertices, expected {len(first.vertices)})")
        if np.abs(sc.vertices - first.vertices).max() > 1e-5 * diag:
            raise ValueError(f"clip {name!r} has another rest shape than {names[0]!r}")
    for o in objects:
        if o.data.get("artdef_field_clips") is not None:
            raise ValueError(f"'{o.name}' holds several clips already")
    merged = _scan.validate_scan(_scan.Scan(
        first.vertices, first.faces, displacements=np.concatenate([s.displacements for s in scans])))
    frames, clips, sampled = [], [], {}
    for c, o in enumerate(objects):
        kept = [int(f) for f in o.data.get("artdef_frames", [])]
        if len(kept) != scans[c].n_fields:  # no source frames: the clip's fields 1, 2, ...
            kept = list(range(1, scans[c].n_fields + 1))
        frames += kept
        clips += [c] * len(kept)
        sampled[str(c)] = [int(f) for f in o.data.get("artdef_sampled_frames", kept)]
    target = objects[0]
    io.write_scan(target.data, merged)
    target.data["artdef_frames"] = frames
    target.data["artdef_field_clips"] = clips
    target.data["artdef_clip_names"] = list(names)
    target.data["artdef_clip_sampled"] = sampled
    target.data["artdef_clip"] = names[0]
    if "artdef_sampled_frames" in target.data:
        del target.data["artdef_sampled_frames"]
    for other in objects[1:]:
        data = other.data
        bpy.data.objects.remove(other, do_unlink=True)
        if data.users == 0:
            bpy.data.meshes.remove(data)
    return target


def clip_name(path):
    """A clip's name from its file, folder or pattern: ``walk/``, ``walk_*.obj``,
    ``walk.glb`` -> ``walk``."""
    base = os.path.basename(os.path.normpath(path))
    stem = os.path.splitext(base)[0] if not os.path.isdir(path) else base
    return stem.split("*")[0].rstrip("_-. ") or stem or "clip"


def import_animated(context, path):
    """Import ``path`` with Blender's importer; return the new objects. ValueError when the
    importer reads nothing, or when a new action's keys are not finite (:func:`check_keys`)."""
    ext = os.path.splitext(path)[1].lower()
    op_path, kwargs = IMPORTERS[ext]
    before = set(bpy.data.objects)
    actions = set(bpy.data.actions)
    result = _operator(op_path)(filepath=path, **kwargs)
    if 'FINISHED' not in result:
        raise ValueError("could not read the file")
    check_keys([a for a in bpy.data.actions if a not in actions])
    return [o for o in bpy.data.objects if o not in before]


def operator_error(err: RuntimeError) -> str:
    """The one line of a failed ``bpy.ops`` call: its last ERROR report (Blender raises them as
    ``Error: ...`` lines, a nested call's inside a traceback, then ``Location: ...``)."""
    lines = [ln.strip() for ln in str(err).splitlines()]
    errors = [ln.split("Error: ", 1)[1].replace("Error: ", "") for ln in lines
              if "Error: " in ln and not ln.startswith("Error: Python: Traceback")]
    raw = str(err).splitlines()
    # a traceback's own last line, its exception (``struct.error: ...``, which no "Error: " names)
    raised = [ln.strip() for ln in raw[1:] if ln.strip() and not ln[:1].isspace()
              and not ln.startswith("Location:")] if lines and lines[0].startswith("Error: Python: Traceback") else []
    line = errors[-1] if errors else raised[-1] if raised else (lines[0] if lines else "the operator failed")
    # the importers' pointer to their console output, which a headless run (and a user who has no
    # console window open) does not see: the line is the message
    for tail in (", see console for details", ", see console for detail", " (see console for details)",
                 " (see console for detail)", ", see the console for details"):
        if line.endswith(tail):
            line = line[:-len(tail)]
    return line


def sample_file(op, context, path, objs, left_out, given):
    """Sample the file's meshes ``objs`` (largest first; ``left_out``: (name, why) of its other
    meshes) into one scan object over the file's own frames (its clips, or its keys' range;
    ``given``: frame_start/end/step the user set), as Fields from File does; the scan records its
    source file and the given frames. Returns the scan object (active), or None after reporting on
    ``op`` why not (nothing of the sampling left)."""
    obj = objs[0]
    which = parts.describe([o.name for o in objs], left_out)
    name = os.path.basename(path)
    if len(objs) > 1 or left_out:
        op.report({'INFO'}, f"{name}: {which}")

    def mark(scan_obj):
        scan_obj.data["artdef_meshes"] = which
        scan_obj.data["artdef_source_file"] = name
        scan_obj.data["artdef_source_path"] = os.path.abspath(path)   # Export Rig must not replace it
        scan_obj.data["artdef_given_frames"] = dict(given)

    arm, clips = armature_clips(obj)
    if clips and not given:
        scan_obj = sample_clips(context, objs, arm, clips)
        if scan_obj is None:
            op.report({'ERROR'}, f"{name}: sampling '{obj.name}' failed (see the Info log)")
            return None
        mark(scan_obj)
        for o in context.view_layer.objects:
            o.select_set(o == scan_obj)
        context.view_layer.objects.active = scan_obj
        op.report({'INFO'}, f"'{scan_obj.name}': {', '.join(repr(o.name) for o in objs)} of {name}, "
                            f"{len(clips)} clips ({', '.join(a.name for a in clips)}) sampled at their own frames")
        return scan_obj
    first, last, step = frames_of(objs, context.scene)
    step = given.get("frame_step", step)
    start, end = given.get("frame_start", first), given.get("frame_end", last)
    if given:   # the given range, on its own grid, within the file's frames
        start += -(-max(first - start, 0) // step) * step
        end = min(end, last)
        if start > end:
            op.report({'ERROR'}, f"{name}: no frame within {given.get('frame_start', first)}.."
                                 f"{given.get('frame_end', last)} (its frames are {first}..{last})")
            return None
    scene = context.scene
    for _ in range(2):  # the file's own range (start may not pass end: set twice)
        scene.frame_start, scene.frame_end = start, max(end, start)
    for o in context.view_layer.objects:
        o.select_set(False)
    scan_obj = sample_meshes(context, objs, start, end, step)
    if scan_obj is None:
        op.report({'ERROR'}, f"{name}: sampling '{obj.name}' failed (see the Info log)")
        return None
    mark(scan_obj)
    clips = _actions_moving(obj)
    if clips:  # the exported clip keeps the source clip's name
        scan_obj.data["artdef_clip"] = clips[0][0].name
    op.report({'INFO'}, f"'{scan_obj.name}': {', '.join(repr(o.name) for o in objs)} of {name} "
                        f"sampled over frames {start}-{end} step {step}")
    return scan_obj


def record_file_meshes(scan_obj, fitted, left_out):
    """The file's meshes on ``scan_obj``'s list (the panel's Meshes of the File): each fitted mesh
    ticked, every other one unticked with the reason it cannot be fitted (none for a mesh that
    was only not chosen)."""
    items = scan_obj.artdef.file_meshes
    items.clear()
    for name, why in [(o.name, "") for o in fitted] + list(left_out):
        item = items.add()
        item.name = name
        ob = bpy.data.objects.get(name)
        item.vertices = len(ob.data.vertices) if ob is not None and ob.type == 'MESH' else 0
        item.reason = "" if why in ("", parts.NOT_CHOSEN) else why
        item.fit = not why


class ARTDEF_OT_fields_from_file(bpy.types.Operator, ImportHelper, FrameRange):
    """Import an animated file (glTF, FBX, Alembic, USD, or a numbered OBJ/PLY sequence) with Blender's importer and sample its animated mesh over the file's own frames into a tracked scan (Fields from Animation), ready to fit"""
    bl_idname = "artdef.fields_from_file"
    bl_label = "Import Animated File as Scan"
    bl_options = {'REGISTER', 'UNDO'}

    filter_glob: StringProperty(
        default="*.glb;*.gltf;*.fbx;*.abc;*.usd;*.usdc;*.usda;*.usdz;*.obj;*.ply",
        options={'HIDDEN'})
    filepath: compat.blend_relative_filepath("Animated file or first file of a numbered sequence to import "
                                             "('//' for next to the .blend)", {'SKIP_PRESET', 'HIDDEN'})
    filename_ext = ""
    meshes: StringProperty(name="Meshes", default="",
                           description="Names of the meshes to fit, separated by commas (empty: every "
                                       "animated mesh of the file, fitted together as one scan)")
    isolate: BoolProperty(name="Read in a Child Process First", default=True, options={'HIDDEN', 'SKIP_SAVE'},
                          description="Read and sample the file in a separate process before importing it "
                                      "here, so that an importer crash on a damaged file cannot close Blender")

    @classmethod
    def poll(cls, context):
        return in_object_mode(cls, context)

    def execute(self, context):
        path = bpy.path.abspath(self.filepath)
        kind = file_kind(path)
        if kind not in ("animated", "sequence") or (kind == "animated" and not os.path.isfile(path)):
            what = "not found" if kind == "animated" else "not an animated file Blender imports"
            self.report({'ERROR'}, f"{os.path.basename(path) or path}: {what}")
            return {'CANCELLED'}
        if kind == "sequence":
            try:
                first = _sequence_path(path)
            except ValueError as err:
                self.report({'ERROR'}, str(err))
                return {'CANCELLED'}
            try:
                return bpy.ops.artdef.import_mesh_sequence(filepath=first, **self.given_frames())
            except RuntimeError as err:  # its ERROR report, once more as this operator's
                self.report({'ERROR'}, operator_error(err))
                return {'CANCELLED'}
        if os.path.getsize(path) == 0:
            self.report({'ERROR'}, f"{os.path.basename(path)}: the file is empty")
            return {'CANCELLED'}
        bad = filecheck.gltf_not_finite(path) if path.lower().endswith((".glb", ".gltf")) else None
        if bad:
            self.report({'ERROR'}, f"{os.path.basename(path)}: {bad}")
            return {'CANCELLED'}
        if self.isolate:
            try:
                isolated.read_in_child(path, self.meshes, self.given_frames())
            except RuntimeError as err:
                self.report({'ERROR'}, str(err))
                return {'CANCELLED'}
        # a failure anywhere below leaves bpy.data and the scene's frames as they were: the
        # importer's meshes, materials and actions too, not only its objects
        before = rig.datablock_snapshot()
        frames = (context.scene.frame_start, context.scene.frame_end)
        try:
            result = self._import_animated(context, path)
        except RuntimeError as err:      # a nested operator's failure (its report) or the sampler's
            line = operator_error(err)
            name = os.path.basename(path)
            self.report({'ERROR'}, line if name in line else f"{name}: {line}")
            result = {'CANCELLED'}
        if 'CANCELLED' in result:
            rig.remove_new_datablocks(before)
            for _ in range(2):           # start may not pass end: set twice
                context.scene.frame_start, context.scene.frame_end = frames
        return result

    def _import_animated(self, context, path):
        try:
            new = import_animated(context, path)
        except (RuntimeError, ValueError) as err:
            if isinstance(err, ValueError) and str(err).startswith("its animation"):
                line = f"{os.path.basename(path)}: {err}"
            else:
                words = operator_error(err) if isinstance(err, RuntimeError) else str(err).strip()
                line = filecheck.importer_error(path, words)
            self.report({'ERROR'}, line)
            return {'CANCELLED'}
        activate_own_animations(new)
        try:
            objs, left_out = animated_meshes(new, [n.strip() for n in self.meshes.split(",") if n.strip()])
        except ValueError as err:
            self._remove(new)
            self.report({'ERROR'}, f"{os.path.basename(path)}: {err}")
            return {'CANCELLED'}
        if not objs:
            self._remove(new)
            self.report({'ERROR'}, f"{os.path.basename(path)}: no animated mesh in the file"
                                   + (f" ({parts.describe([], left_out).split('; ', 1)[1]})" if left_out else ""))
            return {'CANCELLED'}
        scan_obj = sample_file(self, context, path, objs, left_out, self.given_frames())
        if scan_obj is None:
            self._remove(new)
            return {'CANCELLED'}
        record_file_meshes(scan_obj, objs, left_out)
        # The source stays for comparison, bone names and Resample Meshes, but out of sight:
        # the scan copy sits exactly on it.
        for o in new:
            o.hide_set(True)
            o.hide_render = True
        return {'FINISHED'}

    @staticmethod
    def _remove(objects):
        for o in objects:
            bpy.data.objects.remove(o, do_unlink=True)


class ARTDEF_OT_resample_meshes(bpy.types.Operator):
    """Sample the ticked meshes of the animated file into this scan again, the others left out (the file's objects in the scene are read, not the file on disk)"""
    bl_idname = "artdef.resample_meshes"
    bl_label = "Resample Meshes"
    bl_options = {'REGISTER', 'UNDO'}

    @classmethod
    def poll(cls, context):
        obj = ops._active_mesh(context)
        if obj is None or not len(obj.artdef.file_meshes):
            cls.poll_message_set("The active object is not a scan sampled from an animated file")
            return False
        return in_object_mode(cls, context)

    def _refusal(self, obj, name):
        """Why the list cannot be sampled now (one line), or None."""
        items = obj.artdef.file_meshes
        if rig.has_rig(obj):
            return f"'{obj.name}' has a rig: clear it (Clear Rig) before choosing other meshes"
        ticked = [it for it in items if it.fit]
        if not ticked:
            return f"{name}: tick at least one mesh to fit"
        for it in ticked:
            if it.reason:
                return f"{name}: mesh '{it.name}' cannot be fitted: {it.reason}"
            ob = bpy.data.objects.get(it.name)
            if ob is None or ob.type != 'MESH':
                return f"{name}: mesh '{it.name}' is no longer in the scene"
        return None

    def execute(self, context):
        obj = ops._active_mesh(context)
        name = obj.data.get("artdef_source_file", "the file")
        why = self._refusal(obj, name)
        if why:
            self.report({'ERROR'}, why)
            return {'CANCELLED'}
        items = obj.artdef.file_meshes
        chosen = [it.name for it in items if it.fit]
        try:
            objs, _ = animated_meshes([bpy.data.objects[n] for n in chosen], chosen)
        except ValueError as err:
            self.report({'ERROR'}, f"{name}: {err}")
            return {'CANCELLED'}
        left_out = [(it.name, it.reason or parts.NOT_CHOSEN) for it in items if not it.fit]
        listed = [(it.name, it.fit, it.vertices, it.reason) for it in items]
        given = obj.data.get("artdef_given_frames")
        given = given.to_dict() if hasattr(given, "to_dict") else {}
        path = obj.data.get("artdef_source_path", name)
        before = rig.datablock_snapshot()
        frames = (context.scene.frame_start, context.scene.frame_end)
        try:
            scan_obj = sample_file(self, context, path, objs, left_out, given)
        except RuntimeError as err:
            self.report({'ERROR'}, f"{name}: {operator_error(err)}")
            scan_obj = None
        if scan_obj is None:           # the scene and the scan as they were
            rig.remove_new_datablocks(before)
            for _ in range(2):
                context.scene.frame_start, context.scene.frame_end = frames
            context.view_layer.objects.active = obj
            return {'CANCELLED'}
        for entry, fit, vertices, reason in listed:      # the same list, as ticked
            item = scan_obj.artdef.file_meshes.add()
            item.name, item.fit, item.vertices, item.reason = entry, fit, vertices, reason
        old_name, old_data = obj.name, obj.data
        bpy.data.objects.remove(obj, do_unlink=True)
        if old_data.users == 0:
            bpy.data.meshes.remove(old_data)
        scan_obj.name = old_name
        return {'FINISHED'}


def menu_import(self, context):
    self.layout.operator(ARTDEF_OT_fields_from_file.bl_idname,
                         text="ArtDef Animated File as Scan (.glb/.fbx/.abc/.usd)")


classes = (ARTDEF_OT_fields_from_file, ARTDEF_OT_resample_meshes)


register, unregister = menus.registration(classes, "TOPBAR_MT_file_import", menu_import)
