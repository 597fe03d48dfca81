# SPDX-License-Identifier: GPL-3.0-or-later
"""Headless Blender outputs for ``python -m artdef_addon fit ... --blend/--glb/--png``.

The command line fits once (the core's ``artdef_addon.fit``) and hands the result here: a fresh
scene gets the scan's mesh and the rig built from that result by ``ops.apply_result`` (what the
Fit operator does after its job), then any of the .blend, a glTF binary made by Blender's own
exporter (skinned mesh, morph targets, animation) and a Workbench render are written.

This module belongs to the Blender layer. The Blender side's entry point of the command line,
``scripts/artdef_fit.py``, passes it to ``artdef_addon.cli.main`` (``python -m artdef_addon``
hands a command that needs Blender to that script); the script loads it from its file when it
runs from a checkout, so it must work loaded on its own: no relative imports; the registered
extension's modules are reached through :func:`ensure_registered`'s package name. Works with the
``bpy`` module (``pip install bpy``) and inside Blender (``blender -b -P scripts/artdef_fit.py --
fit ...``).
"""
from __future__ import annotations

import atexit
import os
import shutil
import signal
import sys
import tempfile

NEED_BPY = ("this needs Blender: run inside "
            "`blender -b -P scripts/artdef_fit.py -- ...` or install the bpy module")

EXT_ID = "artdef"
_HEADLESS_REPO = "artdef_headless"  # module name of the temporary extension repository

# Render-only helper objects (bone sticks) carry this custom property, so they
# can be found and removed again.
_RENDER_TAG = "artdef_render_helper"


def _bpy():
    try:
        import bpy  # noqa: PLC0415 (lazy on purpose)
    except ImportError as ex:
        raise RuntimeError(NEED_BPY) from ex
    return bpy


def require_bpy() -> None:
    """Raise RuntimeError(NEED_BPY) unless ``bpy`` can be imported.  Cheap
    enough to call before a long fit, so a missing Blender is reported before
    any work is done or any file is written."""
    import importlib.util  # noqa: PLC0415

    loaded = sys.modules.get("bpy", False)  # None: import blocked on purpose
    if loaded:
        return
    if loaded is None or importlib.util.find_spec("bpy") is None:
        raise RuntimeError(NEED_BPY)


# --------------------------------------------------------------------------
# Registration
# --------------------------------------------------------------------------

def _operators_registered(bpy) -> bool:
    # hasattr() is always True on bpy.ops sub-modules; dir() lists only
    # the operators that are registered.
    names = dir(bpy.ops.artdef)
    return "import_scan" in names and "fit" in names


def _source_root() -> str | None:
    """The extension's root (directory holding blender_manifest.toml), i.e.
    the repository root or an installed copy of the extension."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    if os.path.isfile(os.path.join(root, "blender_manifest.toml")) and \
            os.path.isfile(os.path.join(root, "__init__.py")):
        return root
    return None


def _enable(module_name: str) -> None:
    import addon_utils  # noqa: PLC0415

    errors = []
    addon_utils.enable(module_name, default_set=True, handle_error=errors.append)
    if errors:
        raise RuntimeError(f"enabling {module_name} failed: {errors[0]}") from errors[0]


def _scipy_importable() -> bool:
    try:
        import scipy  # noqa: F401, PLC0415
    except ImportError:
        return False
    return True


def ensure_registered() -> str:
    """Make sure ``bpy.ops.artdef.*`` exist; return the add-on module name.

    1. Already registered (add-on enabled in Blender's preferences): nothing to do.
    2. We are running from an installed copy of the extension
       (``bl_ext.<repo>.artdef.artdef_addon``): enable that copy.
    3. Otherwise register this source tree as an extension: symlink it as
       ``<tmp>/artdef`` into a temporary user repository and enable
       ``bl_ext.artdef_headless.artdef``.  The operators, the manifest and the
       wheels are then exactly those of the checkout being run.
    """
    bpy = _bpy()
    import addon_utils  # noqa: PLC0415

    if _operators_registered(bpy):
        for name in bpy.context.preferences.addons.keys():
            if name == EXT_ID or name.endswith("." + EXT_ID):
                return name
        return EXT_ID

    pkg = __package__ or ""
    if pkg.startswith("bl_ext.") and pkg.count(".") >= 3:
        module_name = pkg.rsplit(".", 1)[0]  # bl_ext.<repo>.artdef
        _enable(module_name)
        if _operators_registered(bpy):
            return module_name

    root = _source_root()
    if root is None:
        raise RuntimeError("cannot find the artdef extension: bpy.ops.artdef is not registered "
                           "and no blender_manifest.toml is next to artdef_addon/")
    module_name = f"bl_ext.{_HEADLESS_REPO}.{EXT_ID}"
    repos = bpy.context.preferences.extensions.repos
    repo = next((r for r in repos if r.module == _HEADLESS_REPO), None)
    if repo is None:
        try:    # inside the installed extension, or loaded from a checkout next to artdef_addon/
            from ..artdef_addon.files import remove_stale  # noqa: PLC0415
        except ImportError:
            from artdef_addon.files import remove_stale  # noqa: PLC0415
        remove_stale(tempfile.gettempdir(), "artdef-headless-repo-")   # of a killed earlier run
        repo_dir = tempfile.mkdtemp(prefix=f"artdef-headless-repo-{os.getpid()}-")
        link = os.path.join(repo_dir, EXT_ID)
        os.symlink(root, link, target_is_directory=True)

        def _cleanup(repo_dir=repo_dir, link=link):
            try:
                os.unlink(link)
            except OSError:
                pass
            shutil.rmtree(repo_dir, ignore_errors=True)
        atexit.register(_cleanup)
        repos.new(name="ArtDef (headless)", module=_HEADLESS_REPO,
                  custom_directory=repo_dir, source='USER')
    # Install the bundled wheels only when this Python has no scipy of its own
    # (plain Blender); the bpy module's venv normally has it already, and the
    # wheels/ folder may not even be downloaded in a fresh checkout.
    errors = []
    addon_utils.extensions_refresh(ensure_wheels=not _scipy_importable(),
                                   addon_modules_pending=[module_name],
                                   handle_error=errors.append)
    _enable(module_name)
    if not _operators_registered(bpy):
        detail = f" ({errors[0]})" if errors else ""
        raise RuntimeError(f"{module_name} is enabled but bpy.ops.artdef.import_scan/fit "
                           f"are not registered{detail}")
    return module_name


# --------------------------------------------------------------------------
# Scene helpers
# --------------------------------------------------------------------------

def _find_armature(mesh):
    arm = mesh.find_armature()
    if arm is not None:
        return arm
    if mesh.parent is not None and mesh.parent.type == 'ARMATURE':
        return mesh.parent
    for mod in mesh.modifiers:
        if mod.type == 'ARMATURE' and mod.object is not None:
            return mod.object
    return None


def _parent_keep_transform(child, parent):
    """Parent ``child`` to ``parent`` (object parenting), keeping its world
    transform.  Blender's glTF exporter bakes driven shape keys into morph
    weight animation only for a mesh parented to its armature."""
    if child.parent == parent:
        return
    world = child.matrix_world.copy()
    child.parent = parent
    child.parent_type = 'OBJECT'
    child.matrix_parent_inverse = parent.matrix_world.inverted()
    child.matrix_world = world


def _abs(path: str) -> str:
    # the directory must exist: the command line checks every output path before any work
    # (files.check_outputs) and writes into temporaries there (files.Outputs)
    return os.path.abspath(path)


class _Interrupts:
    """Ctrl-C during the Blender stage, handled without raising inside ``bpy``.

    A KeyboardInterrupt raised while Blender runs Python (its start-up, add-on registration, an
    operator, the exporter) left bpy half-initialised and crashed the process at exit (SIGSEGV,
    or assorted exit codes). Here SIGINT only sets a flag: the fit operator's progress callback
    cancels on it (``operators.ops.PROGRESS_HOOKS``) and :meth:`check`, called between the
    stages, raises KeyboardInterrupt in plain Python, where the caller removes its temporaries.
    """

    #: SIGTERM (``kill``, ``timeout``) too: raised inside an operator it would be swallowed by
    #: Blender's report and the command would go on to write its outputs
    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self):
        self._old = None
        self._got = []

    def __enter__(self):
        def caught(signum, frame):
            self._got.append(signum)
        self._old = {}
        try:
            for sig in self.SIGNALS:
                self._old[sig] = signal.signal(sig, caught)
        except ValueError:      # not the main thread: leave signals alone
            self._old = None
        return self

    def hook(self, stage, fraction) -> bool:
        return bool(self._got)

    def check(self):
        if self._got:
            term = self._old and self._old.get(signal.SIGTERM)
            if signal.SIGTERM in self._got and callable(term):
                term(signal.SIGTERM, None)      # the caller's own handling (the command line: exit 143)
            raise KeyboardInterrupt

    def __exit__(self, *exc):
        if self._old is not None:
            for sig, handler in self._old.items():
                signal.signal(sig, handler)
        return False


def save_blend(path: str) -> str:
    bpy = _bpy()
    path = _abs(path)
    bpy.ops.wm.save_as_mainfile(filepath=path, check_existing=False)
    return path


def export_rig(path: str, mesh, fmt: str | None = None) -> str:
    """Write the rig of ``mesh`` with ``bpy.ops.artdef.export_rig`` (the Export
    Rig operator of the UI: only the fitted mesh and its armature, one clip at
    the replay's frames, no debug colours, at most 4 influences, a Green's rig
    baked); ``fmt`` 'GLB' | 'GLTF_SEPARATE' | 'FBX' (default: from the name)."""
    bpy = _bpy()
    ensure_registered()
    path = _abs(path)
    kwargs = {"filepath": path}
    if fmt is not None:
        kwargs["export_format"] = fmt
    with bpy.context.temp_override(active_object=mesh, object=mesh, selected_objects=[mesh]):
        result = bpy.ops.artdef.export_rig(**kwargs)
    if 'FINISHED' not in result or not os.path.isfile(path):
        raise RuntimeError(f"artdef.export_rig could not write {path}")
    return path


def export_glb(path: str, mesh, armature=None) -> str:
    """The rig of ``mesh`` as .glb (see :func:`export_rig`)."""
    return export_rig(path, mesh, "GLB")


# --------------------------------------------------------------------------
# Render
# --------------------------------------------------------------------------

def _octahedral_bone_mesh(bpy, name, head, tail, width, color, attr_name):
    """A Blender-style octahedral bone from head to tail (world space)."""
    from mathutils import Vector  # noqa: PLC0415

    head, tail = Vector(head), Vector(tail)
    axis = tail - head
    length = axis.length
    if length < 1e-9:
        return None
    d = axis / length
    helper = Vector((0, 0, 1)) if abs(d.z) < 0.9 else Vector((1, 0, 0))
    u = d.cross(helper).normalized()
    v = d.cross(u).normalized()
    r = width
    mid = head + d * (0.15 * length)
    verts = [head, mid + u * r, mid + v * r, mid - u * r, mid - v * r, tail]
    faces = [(0, 2, 1), (0, 3, 2), (0, 4, 3), (0, 1, 4),
             (5, 1, 2), (5, 2, 3), (5, 3, 4), (5, 4, 1)]
    me = bpy.data.meshes.new(name)
    me.from_pydata([tuple(p) for p in verts], [], faces)
    me.update()
    _fill_color_attribute(me, attr_name, color)
    ob = bpy.data.objects.new(name, me)
    ob[_RENDER_TAG] = True
    ob.show_in_front = True
    return ob


def _joint_ball(bpy, name, center, radius, color, attr_name):
    import bmesh  # noqa: PLC0415

    me = bpy.data.meshes.new(name)
    bm = bmesh.new()
    bmesh.ops.create_uvsphere(bm, u_segments=16, v_segments=8, radius=radius)
    bm.to_mesh(me)
    bm.free()
    _fill_color_attribute(me, attr_name, color)
    ob = bpy.data.objects.new(name, me)
    ob.location = center
    ob[_RENDER_TAG] = True
    ob.show_in_front = True
    return ob


def _fill_color_attribute(me, attr_name, color):
    attr = me.color_attributes.new(attr_name or "Color", 'FLOAT_COLOR', 'POINT')
    if attr is None:  # name too long (see BLENDER_FACTS): fall back
        attr = me.color_attributes.new("Color", 'FLOAT_COLOR', 'POINT')
    attr.data.foreach_set("color", list(color) * len(me.vertices))
    me.color_attributes.active_color = attr
    me.color_attributes.render_color_index = me.color_attributes.active_color_index


def _bounds_world(obj, depsgraph):
    from mathutils import Vector  # noqa: PLC0415

    ev = obj.evaluated_get(depsgraph)
    me = ev.to_mesh()
    try:
        mw = ev.matrix_world
        pts = [mw @ v.co for v in me.vertices]
    finally:
        ev.to_mesh_clear()
    if not pts:
        return Vector((0, 0, 0)), Vector((0, 0, 0)), []
    lo = Vector((min(p.x for p in pts), min(p.y for p in pts), min(p.z for p in pts)))
    hi = Vector((max(p.x for p in pts), max(p.y for p in pts), max(p.z for p in pts)))
    return lo, hi, pts


def render_png(path: str, mesh, armature, resolution=(960, 640)) -> str:
    """Workbench render of the first fitted pose (frame_start + 10: with the default 10 frames per
    field, a tracked scan's replay keys field 0 there and a Green's scan's load sweep has load 0
    at the probe load along x; the rest pose is frame 0): the mesh coloured by its
    active colour attribute (the fit's link colours), the deforming bones, as
    posed, drawn as octahedral sticks in front of it (armatures are overlays,
    which renders never show)."""
    bpy = _bpy()
    from mathutils import Vector  # noqa: PLC0415

    path = _abs(path)
    scene = bpy.context.scene
    depsgraph = bpy.context.evaluated_depsgraph_get()
    frame_before = scene.frame_current
    scene.frame_set(min(scene.frame_end, scene.frame_start + 10))

    mesh_colors = mesh.data.color_attributes
    if mesh_colors.active_color is None and len(mesh_colors):
        mesh_colors.active_color_index = 0
    attr_name = mesh_colors.active_color.name if mesh_colors.active_color else None

    helpers = []
    depsgraph = bpy.context.evaluated_depsgraph_get()
    lo, hi, pts = _bounds_world(mesh, depsgraph)
    size = max((hi - lo).length, 1e-6)
    if armature is not None:
        mw = armature.matrix_world
        bone_pts = []
        for pbone in armature.pose.bones:  # posed, like the deformed mesh
            if not pbone.bone.use_deform:
                continue
            head, tail = mw @ pbone.head, mw @ pbone.tail
            bone_pts += [head, tail]
            ob = _octahedral_bone_mesh(bpy, f"_artdef_bone_{pbone.name}", head, tail,
                                       width=0.06 * (tail - head).length,
                                       color=(0.05, 0.05, 0.05, 1.0), attr_name=attr_name)
            if ob is not None:
                helpers.append(ob)
            helpers.append(_joint_ball(bpy, f"_artdef_joint_{pbone.name}", head, 0.015 * size,
                                       (0.95, 0.95, 0.95, 1.0), attr_name))
        pts = pts + bone_pts

    cam_data = bpy.data.cameras.new("_artdef_render_camera")
    cam_data.type = 'ORTHO'
    cam = bpy.data.objects.new("_artdef_render_camera", cam_data)
    cam[_RENDER_TAG] = True
    helpers.append(cam)
    for ob in helpers:
        scene.collection.objects.link(ob)

    world_before = scene.world
    world = bpy.data.worlds.new("_artdef_render_world")
    world.color = (0.92, 0.92, 0.92)
    scene.world = world

    render = scene.render
    saved = (render.engine, render.resolution_x, render.resolution_y,
             render.resolution_percentage, render.filepath, scene.camera,
             render.image_settings.file_format, render.film_transparent)
    shading = scene.display.shading
    saved_shading = (shading.light, shading.color_type, shading.show_shadows,
                     shading.show_cavity, shading.show_object_outline)
    try:
        render.engine = 'BLENDER_WORKBENCH'
        render.resolution_x, render.resolution_y = resolution
        render.resolution_percentage = 100
        render.image_settings.file_format = 'PNG'
        render.film_transparent = False
        shading.light = 'STUDIO'
        shading.color_type = 'VERTEX' if attr_name else 'MATERIAL'
        shading.show_shadows = False
        shading.show_cavity = True
        shading.show_object_outline = True

        # Orthographic three-quarter view from the front-right, slightly
        # above, framing the mesh and the bones with a margin.
        view_dir = Vector((0.55, -1.0, 0.45)).normalized()
        rot = (-view_dir).to_track_quat('-Z', 'Y')
        right, up = rot @ Vector((1, 0, 0)), rot @ Vector((0, 1, 0))
        xs = [p.dot(right) for p in pts] or [0.0]
        ys = [p.dot(up) for p in pts] or [0.0]
        ds = [p.dot(view_dir) for p in pts] or [0.0]
        width, height = max(xs) - min(xs), max(ys) - min(ys)
        aspect = resolution[0] / resolution[1]
        cam_data.ortho_scale = max(width, height * aspect, 1e-3) * 1.15
        cam_data.sensor_fit = 'HORIZONTAL'
        center_2d = right * (max(xs) + min(xs)) / 2 + up * (max(ys) + min(ys)) / 2
        cam.rotation_euler = rot.to_euler()
        cam.location = center_2d + view_dir * (max(ds) + size + 1.0)
        cam_data.clip_start = 0.01
        cam_data.clip_end = (max(ds) - min(ds)) + 2 * size + 10.0
        scene.camera = cam

        render.filepath = path
        bpy.ops.render.render(write_still=True)
    finally:
        (render.engine, render.resolution_x, render.resolution_y,
         render.resolution_percentage, render.filepath, scene.camera,
         render.image_settings.file_format, render.film_transparent) = saved
        (shading.light, shading.color_type, shading.show_shadows,
         shading.show_cavity, shading.show_object_outline) = saved_shading
        scene.world = world_before
        bpy.data.worlds.remove(world)
        for ob in helpers:
            data = ob.data
            bpy.data.objects.remove(ob)
            if isinstance(data, bpy.types.Mesh):
                bpy.data.meshes.remove(data)
            elif isinstance(data, bpy.types.Camera):
                bpy.data.cameras.remove(data)
        scene.frame_set(frame_before)
    if not os.path.isfile(path):
        raise RuntimeError(f"render wrote nothing to {path}")
    return path


# --------------------------------------------------------------------------
# Entry point used by artdef_addon.cli
# --------------------------------------------------------------------------

def scan_from_file(path: str, frames=None, clips=(), meshes=()):
    """See :func:`_scan_from_file`; Ctrl-C is a flag here too (:class:`_Interrupts`), raised as
    KeyboardInterrupt once Blender's import and sampling have returned."""
    with _Interrupts() as intr:
        out = _scan_from_file(path, frames, clips, meshes)
        intr.check()
        return out


def _scan_from_file(path: str, frames=None, clips=(), meshes=()):
    """Import an animated file or an OBJ/PLY sequence in a fresh scene and
    sample it into a tracked scan with ``bpy.ops.artdef.fields_from_file`` (the
    Fields from Animation code, over the file's own frames unless ``frames`` =
    (start, end, step), which applies to every input; a sequence's file numbers
    are its frames).  ``clips``: more files or sequences of the same mesh,
    each one clip: the scans are merged, so the fit makes one rig with one
    action per clip (named after the files).  ``meshes``: the names of the file's meshes to
    fit (default: every animated one, as one scan).  Returns ``(mesh object holding
    the scan, Scan)``; RuntimeError with a one-line reason on failure."""
    bpy = _bpy()
    import importlib  # noqa: PLC0415

    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    module_name = ensure_registered()
    given = {} if frames is None else dict(frame_start=frames[0], frame_end=frames[1], frame_step=frames[2])
    animfile = importlib.import_module(module_name + ".operators.animfile")
    objects = []
    for p in [path, *clips]:          # --frames: every input alike
        messages = []
        try:
            result = bpy.ops.artdef.fields_from_file(filepath=os.path.abspath(p), meshes=",".join(meshes), **given)
        except RuntimeError as ex:  # the operator's ERROR report
            messages.append(animfile.operator_error(ex))
            result = {'CANCELLED'}
        if 'FINISHED' not in result:
            raise RuntimeError(messages[0] if messages else f"cannot sample {p}")
        objects.append(bpy.context.view_layer.objects.active)
    if clips:
        names = [animfile.clip_name(p) for p in [path, *clips]]
        try:
            animfile.merge_clip_scans(objects, names)
        except ValueError as ex:
            raise RuntimeError(str(ex)) from None
    mesh = objects[0]
    bpy.context.view_layer.objects.active = mesh
    io = importlib.import_module(module_name + ".operators.io")
    return mesh, io.read_scan(mesh).scan


def labels_of_kept_faces(kept, faces, labels):
    """The face labels ``labels (T,)`` of the scan's ``faces (T, 3)`` for the triangles ``kept
    (K, 3)`` of the mesh Blender built from it (Blender drops triangles with a repeated vertex),
    matched by their vertex sets, whatever the corner order. RuntimeError when a kept triangle is
    not a face of the scan."""
    import numpy as np  # noqa: PLC0415
    both = np.sort(np.concatenate([np.asarray(faces), np.asarray(kept)]).astype(np.int64), axis=1)
    _, inverse = np.unique(both, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    T = len(faces)
    first = np.full(int(inverse.max()) + 1 if inverse.size else 0, -1, dtype=np.int64)
    first[inverse[:T][::-1]] = np.arange(T)[::-1]           # the first scan face of each vertex set
    index = first[inverse[T:]]
    if np.any(index < 0):
        raise RuntimeError("the mesh Blender built from the scan has a triangle the scan does not")
    return np.asarray(labels)[index]


def build_outputs(scan_path: str, scan, result, blend: str | None, glb: str | None,
                  png: str | None, *, fbx: str | None = None, mesh=None, rotation_only: bool = False,
                  load_index: int = 0, frames_per_field: int = 10) -> dict:
    """Build the rig of ``result`` — the fit the command line already made of ``scan`` (read from
    ``scan_path``) — with :func:`operators.ops.apply_result`, the function the Fit operator calls
    after its job, and write the requested outputs. ``mesh``: the object holding the scan when it
    was sampled from an animated file (:func:`scan_from_file`); else a fresh scene gets the scan
    file's mesh. Nothing is fitted here: the .npz, the .blend and the exports hold the same
    numbers. Returns ``{"blend"|"glb"|"fbx"|"png": path}`` for those written (and
    ``"rotation_only_error"``: (max, rms) % of the diagonal, with ``rotation_only``).

    Ctrl-C (SIGINT) is caught as a flag for the whole Blender stage and raised as
    KeyboardInterrupt between its steps (see :class:`_Interrupts`); the caller writes to
    temporary paths and removes them then (``files.Outputs``)."""
    with _Interrupts() as intr:
        return _build_outputs(intr, scan_path, scan, result, blend, glb, png, fbx, mesh, rotation_only,
                              load_index, frames_per_field)


def _build_outputs(intr, scan_path, scan, result, blend, glb, png, fbx, mesh, rotation_only,
                   load_index, frames_per_field):
    bpy = _bpy()
    import importlib  # noqa: PLC0415

    intr.check()
    if mesh is None:  # a scan file: a fresh scene
        bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
        intr.check()
    module_name = ensure_registered()
    intr.check()
    ops = importlib.import_module(module_name + ".operators.ops")
    io = importlib.import_module(module_name + ".operators.io")
    if mesh is None:
        mesh, _ = io.import_scan_file(bpy.context, os.path.abspath(scan_path))
        intr.check()
    stored = io.read_scan(mesh)
    if len(stored.scan.faces) != len(result.face_labels):
        # Blender's mesh has no triangle with a repeated vertex (the scan may, and the fit kept it)
        import dataclasses  # noqa: PLC0415
        result = dataclasses.replace(result, face_labels=labels_of_kept_faces(
            stored.scan.faces, scan.faces, result.face_labels))
    with bpy.context.temp_override(active_object=mesh, object=mesh,
                                   selected_objects=[mesh], selected_editable_objects=[mesh]):
        ops.apply_result(bpy.context, mesh, result, scan, stored.tri_polygons, load_index=load_index,
                         frames_per_field=frames_per_field,
                         auto_links=bool(getattr(result, "link_reason", "")),
                         seconds=float(result.timings.get("total", 0.0)))
    intr.check()
    armature = _find_armature(mesh)
    if armature is not None:  # bones an animator can read: source joint names, else root-first
        with bpy.context.temp_override(active_object=mesh, object=mesh, selected_objects=[mesh]):
            bpy.ops.artdef.name_bones(scheme='AUTO')
            if rotation_only:
                if 'FINISHED' not in bpy.ops.artdef.rotation_only():
                    raise RuntimeError("--rotation-only: the rig has no action (Green's rigs "
                                       "are driven by their loads)")

    written = {}
    if rotation_only and mesh.data.get("artdef_rotation_only_error") is not None:
        worst, rms = mesh.data["artdef_rotation_only_error"]
        written["rotation_only_error"] = (float(worst), float(rms))
    if blend is not None:
        written["blend"] = save_blend(blend)
        intr.check()
    if glb is not None:
        written["glb"] = export_rig(glb, mesh, "GLB")
        intr.check()
    if fbx is not None:
        written["fbx"] = export_rig(fbx, mesh, "FBX")
        intr.check()
    if png is not None:
        written["png"] = render_png(png, mesh, armature)
        intr.check()
    return written


__all__ = ["build_outputs", "scan_from_file", "export_rig", "require_bpy",
           "ensure_registered",
           "save_blend", "export_glb", "render_png", "NEED_BPY"]
