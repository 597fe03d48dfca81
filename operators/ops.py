# SPDX-License-Identifier: GPL-3.0-or-later
"""ArtDef operators (public scripting API: ``bpy.ops.artdef.*``)."""

import os
import threading
import time
import traceback

import bpy
import numpy as np
from bpy.props import EnumProperty, IntProperty, StringProperty
from bpy_extras.io_utils import ImportHelper

from ..artdef_addon import api as _api
from ..artdef_addon import fit as _fit
from ..artdef_addon import scan as _scan
from ..artdef_addon.options import FitOptions, OptionsError
from . import compat, fitquality, io, menus, rig
from .props import SETTING_NAMES, FitSettings, enum_id, options_from, store_options

#: Extra cancel checks consulted by every fit's progress callback:
#: ``hook(stage, fraction) -> bool`` (True cancels).  For scripts and tests;
#: the interactive path cancels with Esc.
PROGRESS_HOOKS = []

#: Last FitResult per mesh object name (the model behind the rig; for
#: scripting and tests — not saved in the .blend).
LAST_RESULTS = {}

def method_plan(triangles, fields, vertices, kind, reduce='AUTO', budget_gb=2.0, links=None,
                auto=False, max_links=None):
    """What a fit with these settings will do, from counts only (the core's :func:`api.plan`):
    ``(estimate, reduce_arg)``. ``links``: the link count the fit will use (its skin
    decompositions grow with it; None: the core's default), ``auto``: Auto Links (the
    link-count search up to ``max_links``, priced as the core prices it)."""
    options = FitOptions(reduce=reduce.lower(), memory_budget=float(budget_gb))
    if auto and max_links is not None:
        options = options.replace(max_links=int(max_links))
    return _api.plan(triangles, fields, vertices, kind, options,
                     links=None if auto or links is None else int(links), auto=bool(auto))


def cached_segmentation(obj):
    """The core's kept segmentation of ``obj``'s scan for its settings, or None (tests, scripts)."""
    return _api.cached(io.read_scan(obj).scan, options_from(obj.artdef))


def last_result(obj):
    return LAST_RESULTS.get(obj.name)


def _active_mesh(context):
    obj = context.active_object
    return obj if obj is not None and obj.type == 'MESH' else None


def in_object_mode(cls, context) -> bool:
    """Whether Blender is in Object Mode; if not, the reason is set as the poll message."""
    if context.mode != 'OBJECT':
        cls.poll_message_set("Switch to Object Mode")
        return False
    return True


def mesh_in_object_mode(cls, context):
    """The active mesh object if the operator can run on it (Object Mode), else None with the
    reason set as the poll message."""
    obj = _active_mesh(context)
    if obj is None:
        cls.poll_message_set("Select a mesh object")
        return None
    if not in_object_mode(cls, context):
        return None
    return obj


def shared_rig_message(obj):
    """One line when another object that uses ``obj``'s mesh data (a linked duplicate) has its
    ArtDef rig on that mesh — its vertex groups and shape keys are the mesh's, so fitting or
    clearing ``obj`` would replace or remove them; else None."""
    mesh = obj.data
    if mesh is None or mesh.users < 2:
        return None
    for other in bpy.data.objects:
        if other != obj and other.data == mesh and rig.owns_rig(other, other.artdef.rig):
            return (f"'{obj.name}' shares its mesh '{mesh.name}' with '{other.name}', whose ArtDef "
                    f"rig (vertex groups, shape keys) is on that mesh; make '{obj.name}' single-user "
                    f"first (Object > Relations > Make Single User > Object & Data)")
    return None


def _scan_mesh_poll(cls, context):
    obj = mesh_in_object_mode(cls, context)
    if obj is None:
        return False
    if not io.has_scan(obj.data):
        cls.poll_message_set("The active mesh carries no ArtDef scan")
        return False
    return True


# --------------------------------------------------------------------------
# import
# --------------------------------------------------------------------------

class ARTDEF_OT_import_scan(bpy.types.Operator, ImportHelper):
    """Import a measured deformation scan (.npz: vertices, faces and a Green's matrix or tracked displacements) as a mesh"""
    bl_idname = "artdef.import_scan"
    bl_label = "Import ArtDef Scan"
    bl_options = {'REGISTER', 'UNDO'}

    filename_ext = ".npz"
    filter_glob: StringProperty(default="*.npz", options={'HIDDEN'})
    filepath: compat.blend_relative_filepath("Scan file to import ('//' for next to the .blend)",
                                             {'SKIP_PRESET', 'HIDDEN'})

    @classmethod
    def poll(cls, context):
        return in_object_mode(cls, context)

    def invoke(self, context, event):
        if self.properties.is_property_set("filepath"):  # dropped on the 3D View
            return self.execute(context)
        return ImportHelper.invoke(self, context, event)

    def execute(self, context):
        t0 = time.perf_counter()
        path = os.path.abspath(bpy.path.abspath(self.filepath))    # '//scan.npz': next to the .blend
        try:
            obj, scan = io.import_scan_file(context, path)
        except _scan.ScanError as err:
            self.report({'ERROR'}, f"Not a valid ArtDef scan: {err}")
            return {'CANCELLED'}
        except (OSError, ValueError) as err:
            self.report({'ERROR'}, f"Could not read '{self.filepath}': {err}")
            return {'CANCELLED'}
        obj.data["artdef_source_path"] = path      # Export Rig never writes over it
        loads = 0 if scan.load_vertices is None else len(scan.load_vertices)
        repeated = int(np.count_nonzero(io.repeated_vertex_faces(scan.faces)))
        if repeated:
            self.report({'WARNING'}, f"{repeated} triangle(s) use a vertex twice (zero area): left out "
                                     f"of the mesh; the fit gives them no weight")
        self.report({'INFO'}, f"Imported '{obj.name}': {len(scan.vertices)} vertices, "
                              f"{scan.n_fields} {scan.kind} fields, {loads} load points "
                              f"({time.perf_counter() - t0:.2f} s)")
        return {'FINISHED'}


if hasattr(bpy.types, "FileHandler"):  # Blender 4.1+: drag and drop of .npz files
    class ARTDEF_FH_scan(bpy.types.FileHandler):
        bl_idname = "ARTDEF_FH_scan"
        bl_label = "ArtDef scan"
        bl_import_operator = "artdef.import_scan"
        bl_file_extensions = ".npz"

        @classmethod
        def poll_drop(cls, context):
            return context.area is not None and context.area.type == 'VIEW_3D'
else:
    ARTDEF_FH_scan = None


def menu_import(self, context):
    self.layout.operator(ARTDEF_OT_import_scan.bl_idname,
                         text="Articulated Deformation Scan (.npz)")


# --------------------------------------------------------------------------
# fields from shape keys
# --------------------------------------------------------------------------

class ARTDEF_OT_fields_from_shape_keys(bpy.types.Operator):
    """Turn the active mesh's shape keys into a tracked scan: each pose key minus the basis becomes a displacement field (the motion-capture use)"""
    bl_idname = "artdef.fields_from_shape_keys"
    bl_label = "Fields from Shape Keys"
    bl_options = {'REGISTER', 'UNDO'}

    @classmethod
    def poll(cls, context):
        obj = mesh_in_object_mode(cls, context)
        if obj is None:
            return False
        keys = obj.data.shape_keys
        if keys is None or len(keys.key_blocks) < 2:
            cls.poll_message_set("The mesh needs a basis and at least one pose shape key")
            return False
        return True

    def execute(self, context):
        obj = context.active_object
        skip = {item.name for item in obj.artdef.shape_keys}
        try:
            scan, names = io.scan_from_shape_keys(obj, skip)
            io.write_scan(obj.data, scan)
        except (_scan.ScanError, ValueError) as err:
            self.report({'ERROR'}, str(err))
            return {'CANCELLED'}
        self.report({'INFO'}, f"'{obj.name}': {len(names)} shape keys stored as a tracked scan "
                              f"(fields {', '.join(names[:4])}{', ...' if len(names) > 4 else ''})")
        return {'FINISHED'}


# --------------------------------------------------------------------------
# fit
# --------------------------------------------------------------------------

#: Status-bar wording of the progress stages the core reports; ``True``: the
#: stage reports fractions (show a percentage), ``False``: one report at its start.
_STAGES = {
    "start": ("starting", False),
    "features": ("motions per triangle and field", True),
    "distances": ("pairwise distances", True),
    "cluster": ("clustering", True),
    "merge": ("merging pieces into links", True),
    "links": ("choosing the link count", True),
    "segment": ("segmenting into links", False),
    "motions": ("link motions", False),
    "relabel": ("relabelling faces by their skin", False),
    "skin": ("skin weights", False),
    "split": ("splitting links that hold two bones", False),
    "joints": ("joints and tree", False),
    "bones": ("bone frames", False),
    "pose": ("pose parameters", False),
    "residuals": ("residual and errors", False),
    "pseudo": ("one model per load point", True),
    "done": ("finishing", False),
}


def stage_text(stage, fraction):
    """A stage report as the status bar shows it: ``merge column 2`` -> readable words."""
    label, fractional = _STAGES.get(stage, (None, True))
    if label is None and stage.startswith("merge column "):
        label = f"merging pieces into links (load point {stage[len('merge column '):]})"
    if label is None:
        label = stage
    if not fractional:
        return label
    return f"{label} {100 * min(max(fraction, 0.0), 1.0):.0f}%"


class _FitJob:
    """One fit: the core's public :func:`artdef_addon.fit` runs here (possibly in a worker
    thread); no bpy access."""

    def __init__(self, scan, links, options=None, load_index=0):
        self.scan, self.links = scan, links            # links: int or "auto"
        self.options = options if options is not None else FitOptions()
        self.load_index = load_index
        self.link_reason = ""
        self.model = None            # the result whose rig is built (pseudo: one load point's)
        self.vertex_residual = None  # (N,) articulation residual of ``model``
        self.stage, self.fraction = "start", 0.0
        self.links_fraction = None   # while Auto Links tries link counts: how far it is
        self.cancel = threading.Event()
        self.result = None
        self.error = None
        self.seconds = 0.0
        self.thread = None

    def progress(self, stage, fraction):
        self.stage, self.fraction = stage, float(fraction)
        if stage == "links":
            # the search reports 1 when it has chosen; a fit of that count may follow
            self.links_fraction = float(fraction) if fraction < 1.0 else None
        if self.cancel.is_set():
            return True
        return any(hook(stage, fraction) for hook in list(PROGRESS_HOOKS))

    def run(self, on_progress=None):
        def callback(stage, fraction):
            stop = self.progress(stage, fraction)
            if on_progress is not None:
                on_progress(stage, fraction)
            return stop
        t0 = time.perf_counter()
        try:
            self.result = _api.fit(self.scan, self.links, self.options, callback)
            self.links_fraction = None
            self.links, self.link_reason = self.result.n_links, self.result.link_reason
            self.model, self.vertex_residual = model_of(self.result, self.scan, self.load_index)
        except BaseException as err:  # reported on the main thread
            self.error = err
        self.seconds = time.perf_counter() - t0

    @property
    def notes(self):
        """The core's notes on this fit (e.g. that and why the reduced method ran)."""
        return [str(n) for n in (getattr(self.result, "notes", None) or [])]

    @property
    def reduced(self):
        return bool(getattr(self.result, "reduced", False))

    def status_text(self):
        """What the status bar shows while the job runs."""
        text = stage_text(self.stage, self.fraction)
        if self.links_fraction is not None and self.stage != "links":
            # Auto Links segments every count up to Max Links: say where it is overall
            text = f"{stage_text('links', self.links_fraction)} ({text})"
        return text

    def start_thread(self):
        self.thread = threading.Thread(target=self.run, name="artdef-fit", daemon=True)
        self.thread.start()


def model_of(result, scan, load_index=0):
    """``(model, vertex residual (N,))``: the result whose rig is built — the result, or in pseudo
    mode load point ``load_index``'s model (None if there is none) — and its per-vertex
    articulation residual. Numpy only (runs in the fit's thread)."""
    model, fields = result, None
    if result.mode == "pseudo":
        pseudo = result.pseudo or []
        if load_index >= len(pseudo):
            return None, None
        model = pseudo[load_index]
        fields = result.groups[load_index] if result.groups else [3 * load_index + d for d in range(3)]
    return model, fitquality.vertex_residual(model, scan, fields)


def apply_result(context, obj, result, scan, tri_polygons, *, load_index=0, frames_per_field=10,
                 auto_links=None, seconds=0.0, model=None, vertex_residual=None):
    """Build the rig of ``result`` (a fit of ``scan``) on mesh ``obj`` and record it: vertex
    groups, armature, residual shape keys, load controls or replay, residual colours, the
    object's settings and summary. The one way a rig is made from a fit — the Fit operator after
    its job and the command line (``operators/headless.py``) both call it. Main thread only;
    on failure what the build made is removed, the previous rig (or the link colours of Preview
    Links) is put back as it was, and the error raised."""
    if model is None:
        model, vertex_residual = model_of(result, scan, load_index)
    if model is None:
        raise ValueError("The fit returned no pseudo-articulation for that load point")
    pseudo = result.mode == "pseudo"
    before = rig.datablock_snapshot()
    # the previous rig (or Preview Links' colours) is set aside, not removed, until the new rig
    # is built: a build that fails puts it back as it was
    stash = rig.stash_rig(obj, context.scene)
    try:
        rig.build_rig(context, obj, model, tri_polygons, scan.kind, [load_index] if pseudo else None,
                      frames_per_field)
        scale = float(vertex_residual.max()) if len(vertex_residual) else 0.0
        rig.write_residual(obj.data, vertex_residual, scale)
    except Exception:
        try:
            rig.clear_rig(obj, context.scene)
        finally:
            try:
                # whatever the build made and clear_rig did not know of yet
                # (an action, armature or empty made just before the failure)
                rig.remove_new_datablocks(before)
            finally:
                rig.restore_rig(stash)
        raise
    rig.drop_stash(stash)
    LAST_RESULTS[obj.name] = model
    store_summary(obj, result, model, scan, vertex_residual, load_index=load_index,
                  frames_per_field=frames_per_field, seconds=seconds, auto_links=auto_links)
    return model


def store_summary(obj, result, model, scan, vertex_residual, *, load_index=0, frames_per_field=10,
                  seconds=0.0, auto_links=None):
    """The object's record of the fit (panel) and the settings that made it."""
    st = obj.artdef
    o = result.options
    pseudo = result.mode == "pseudo"
    st.has_fit = True
    st.fit_links = int(model.n_links)
    st.fit_mode = enum_id(result.mode)
    st.fit_motion = enum_id(result.motion)
    st.fit_kind = scan.kind
    st.fit_load_index = load_index if pseudo else -1
    st.fit_p_max = result.p_max or 0.0
    st.fit_rms_articulation = float(model.rms_articulation)
    st.fit_rms_total = float(model.rms_total)
    st.fit_seconds = seconds
    timings = getattr(model, "timings", None) or getattr(result, "timings", None) or {}
    st.fit_timings = ", ".join(f"{k} {v:.2f}s" for k, v in timings.items())
    e = float(model.articulation_error_percent)
    st.fit_articulation_percent = e if e == e else -1.0   # −1: undefined (degenerate frames), shown "n/a"
    # issue 19's figures (NaN/absent on a pseudo model or an old result: shown as unknown)
    st.fit_e_rms = float(getattr(model, "e_rms", float("nan")))
    st.fit_rigid_percent = float(getattr(model, "rigid_error_percent", float("nan")))
    st.fit_linear_percent = float(getattr(model, "linear_error_percent", float("nan")))
    st.fit_linear_rank = int(getattr(model, "linear_rank", 0))
    st.fit_articulated = bool(getattr(model, "articulated", True))
    res = vertex_residual
    st.fit_residual_max = float(res.max()) if len(res) else 0.0
    st.fit_residual_mean = float(res.mean()) if len(res) else 0.0
    st.fit_diagonal = float(np.linalg.norm(np.ptp(scan.vertices, axis=0)))
    st.fit_link_stats.clear()
    for item in fitquality.link_stats(model):
        rec = st.fit_link_stats.add()
        rec.name = rig.GROUP_FMT.format(item["link"])
        for key, value in item.items():
            setattr(rec, key, value)
    if st.set_frame_range:
        start, end = st.replay_frame_range
        if scan.kind == "greens":
            st.fit_replay = (f"load sweep: load k along axis d at the probe load at frame "
                             f"(2(3k+d)+1)x{frames_per_field}, scene frames set to {start}-{end}")
        else:
            st.fit_replay = (f"replay: field p at frame (p+1)x{frames_per_field}, "
                             f"scene frames set to {start}-{end}")
    else:
        st.fit_replay = ""
    st.fit_summary = str(model.summary())
    if st.fit_replay:
        st.fit_summary += ("\n" if st.fit_summary else "") + st.fit_replay
    st.fit_link_reason = result.link_reason
    obj["artdef_link_errors"] = [float(e) for e in (result.link_errors or [])]  # panel's curve
    st.fit_skin = str(getattr(model, "skin", "") or "")
    st.fit_notes = "\n".join(str(n) for n in (result.notes or []))
    st.fit_reduced = bool(result.reduced)
    # Remember the settings that made this rig (Links: the count used, also when chosen)
    if o is not None:
        store_options(st, o)
    st.links = int(model.n_links)
    st.load_index = load_index
    st.frames_per_field = frames_per_field
    if auto_links is not None:
        st.auto_links = auto_links


class _WorkerModal:
    """The interactive path shared by Fit and Preview Links: the job runs in a worker thread,
    a modal timer shows its stage and progress, Esc cancels, the view can still be navigated.

    The operator sets ``_what`` (status-bar word) and implements ``_finish(context, job)``.
    """
    _what = "job"
    _job = None
    _timer = None

    def _start_modal(self, context, job):
        self._job = job
        wm = context.window_manager
        wm.progress_begin(0, 1000)
        self._timer = wm.event_timer_add(0.1, window=context.window)
        wm.modal_handler_add(self)
        job.start_thread()
        self._status(context, job.status_text())
        return {'RUNNING_MODAL'}

    def _status(self, context, text):
        if context.workspace is not None:
            context.workspace.status_text_set(
                None if text is None else f"ArtDef {self._what}: {text} — Esc to cancel")

    def _end(self, context):
        wm = context.window_manager
        if self._timer is not None:
            wm.event_timer_remove(self._timer)
            self._timer = None
        wm.progress_end()
        self._status(context, None)

    def modal(self, context, event):
        job = self._job
        if event.type == 'ESC':
            job.cancel.set()
            self._end(context)
            self.report({'WARNING'}, f"{self._what.capitalize()} cancelled; the scene is unchanged")
            return {'CANCELLED'}
        if event.type == 'TIMER':
            context.window_manager.progress_update(int(1000 * min(max(job.fraction, 0.0), 1.0)))
            self._status(context, job.status_text())
            if not job.thread.is_alive():
                self._end(context)
                return self._finish(context, job)
            return {'RUNNING_MODAL'}
        if event.type in {'MIDDLEMOUSE', 'WHEELUPMOUSE', 'WHEELDOWNMOUSE', 'TRACKPADPAN',
                          'TRACKPADZOOM', 'MOUSEMOVE', 'INBETWEEN_MOUSEMOVE'}:
            return {'PASS_THROUGH'}  # let the user navigate the view while it runs
        return {'RUNNING_MODAL'}  # block editing: the job works on a snapshot

    def _failed(self, job):
        """Report a cancelled or failed job (True), or nothing (False).  Main thread only."""
        err = job.error
        what = self._what.capitalize()
        if err is None:
            return False
        if isinstance(err, _fit.FitCancelled):
            self.report({'WARNING'}, f"{what} cancelled; the scene is unchanged")
        elif isinstance(err, (_scan.ScanError, ValueError)):
            self.report({'ERROR'}, f"{what} failed: {err}")
        else:
            traceback.print_exception(type(err), err, err.__traceback__)
            self.report({'ERROR'}, f"{what} failed ({type(err).__name__}): {err}")
        return True

    def cancel(self, context):  # window closed / file loaded while running
        if self._job is not None:
            self._job.cancel.set()
        self._end(context)


#: Blender's last scene frame (MAXFRAME)
MAX_FRAME = 1048574


class ARTDEF_OT_fit(FitSettings, _WorkerModal, bpy.types.Operator):
    """Fit an articulated rig to the active mesh's scan: vertex groups, an armature, residual shape keys, and load controls (Green's scans) or a replay action (tracked scans). Pseudo mode fits each load point separately and builds the rig of the load point chosen by Load Index. Esc cancels without changing the scene"""
    bl_idname = "artdef.fit"
    bl_label = "Fit Articulation"
    bl_options = {'REGISTER', 'UNDO'}

    # the properties: every fit setting, from props.FitSettings (the core's FitOptions declaration)

    _what = "fit"

    @classmethod
    def poll(cls, context):
        return _scan_mesh_poll(cls, context)

    # -- settings: explicit operator arguments win, else the object's settings
    def _settings(self, obj):
        st = obj.artdef
        props = self.properties
        if props.is_property_set("links") and not props.is_property_set("auto_links"):
            self.auto_links = False  # fit(links=L) means L links
        for name in SETTING_NAMES:
            if not props.is_property_set(name):
                setattr(self, name, getattr(st, name))

    def _prepare(self, context):
        """Read the scan and check the settings; returns a job or None (reported)."""
        obj = context.active_object
        shared = shared_rig_message(obj)
        if shared is not None:
            self.report({'ERROR'}, shared)
            return None
        self._settings(obj)
        try:
            options = options_from(self)
        except OptionsError as err:
            decl = FitOptions.declaration().get(err.option)
            self.report({'ERROR'}, f"{decl[1].label}: {err}" if decl else str(err))
            return None
        try:
            stored = io.read_scan(obj)
        except (_scan.ScanError, ValueError) as err:
            self.report({'ERROR'}, str(err))
            return None
        scan = stored.scan
        # the replay (a field every Frames per Field) or the load sweep (two steps a load component)
        # must end within Blender's frames: checked before the job, so the old rig stays
        last = self.frames_per_field * (2 * scan.n_fields if scan.kind == "greens" else scan.n_fields + 1)
        if last > MAX_FRAME:
            self.report({'ERROR'}, f"Frames per Field {self.frames_per_field}: the rig's animation would end at "
                                   f"frame {last:,}, past Blender's last frame {MAX_FRAME:,}")
            return None
        if options.mode == "pseudo":
            if scan.kind != "greens":
                self.report({'ERROR'}, "Pseudo mode needs a Green's scan (with load points)")
                return None
            if self.load_index >= len(scan.load_vertices):
                self.report({'ERROR'}, f"Load Index {self.load_index} is out of range: the scan has "
                                       f"{len(scan.load_vertices)} load points")
                return None
        job = _FitJob(scan, "auto" if self.auto_links else self.links, options, self.load_index)
        job.obj_name = obj.name
        job.tri_polygons = stored.tri_polygons
        return job

    def _finish(self, context, job):
        """Report the job's outcome; on success write the rig.  Main thread only."""
        if self._failed(job):
            return {'CANCELLED'}
        obj = bpy.data.objects.get(job.obj_name)
        if obj is None or obj.type != 'MESH' or len(obj.data.vertices) != len(job.scan.vertices):
            self.report({'ERROR'}, "The mesh changed while fitting; nothing was created")
            return {'CANCELLED'}
        self.links = job.links  # chosen by Auto Links, or as given
        if job.link_reason:
            self.report({'INFO'}, job.link_reason)
        if job.model is None:
            self.report({'ERROR'}, "The fit returned no pseudo-articulation for that load point")
            return {'CANCELLED'}
        try:
            model = apply_result(context, obj, job.result, job.scan, job.tri_polygons,
                                 load_index=self.load_index, frames_per_field=self.frames_per_field,
                                 auto_links=self.auto_links, seconds=job.seconds, model=job.model,
                                 vertex_residual=job.vertex_residual)
        except Exception as err:    # apply_result removed what it made and kept the previous rig
            traceback.print_exc()
            self.report({'ERROR'}, f"Building the rig failed: {err}")
            return {'CANCELLED'}
        # The core's notes (why and how the reduced method ran) go to the Info log; the
        # summary, reported last, is what the status bar keeps, so it names the method too.
        for note in job.notes:
            self.report({'INFO'}, f"ArtDef: {note}")
        self.report({'INFO'}, f"'{obj.name}': {model.n_links} links, rms articulation "
                              f"{model.rms_articulation:.4g} "
                              f"({model.error_percent_text()}), rms total "
                              f"{model.rms_total:.4g} ({job.seconds:.2f} s)"
                              + ("; reduced method on patches" if job.reduced else "")
                              + (f"; {obj.artdef.fit_replay}" if obj.artdef.fit_replay else ""))
        return {'FINISHED'}

    # -- synchronous path (scripts, background mode) -------------------------
    def execute(self, context):
        job = self._prepare(context)
        if job is None:
            return {'CANCELLED'}
        wm = context.window_manager
        wm.progress_begin(0, 1000)
        try:
            job.run(on_progress=lambda s, f: wm.progress_update(int(1000 * min(max(f, 0.0), 1.0))))
        finally:
            wm.progress_end()
        return self._finish(context, job)

    # -- interactive path: worker thread + modal timer, Esc cancels ----------
    def invoke(self, context, event):
        if bpy.app.background or context.window is None:
            return self.execute(context)
        job = self._prepare(context)
        if job is None:
            return {'CANCELLED'}
        return self._start_modal(context, job)


# --------------------------------------------------------------------------
# preview links
# --------------------------------------------------------------------------

class _PreviewJob:
    """Segment one scan for Preview Links (possibly in a worker thread); no bpy access.

    The core's :func:`artdef_addon.segment` keeps the segmentation, which the next preview or fit
    of the same scan and method settings reuses; the progress callback reports the stage and
    cancels on Esc, like the fit's.
    """

    def __init__(self, obj_name, stored, options, links):
        self.obj_name, self.stored, self.options = obj_name, stored, options
        self.links = links
        self.cached = _api.cached(stored.scan, options) is not None
        self.labels = None
        self.error = None
        self.stage, self.fraction = "start", 0.0
        self.cancel = threading.Event()
        self.thread = None

    def progress(self, stage, fraction):
        self.stage, self.fraction = stage, float(fraction)
        if self.cancel.is_set():
            return True
        return any(hook(stage, fraction) for hook in list(PROGRESS_HOOKS))

    def run(self):
        try:
            self.labels, _, _ = _api.segment(self.stored.scan, self.links, self.options, self.progress)
        except BaseException as err:  # reported on the main thread
            self.error = err

    def status_text(self):
        return stage_text(self.stage, self.fraction)

    def start_thread(self):
        self.thread = threading.Thread(target=self.run, name="artdef-preview", daemon=True)
        self.thread.start()


def _preview_job(obj, links):
    """A :class:`_PreviewJob` for ``obj``'s scan and its Reduced Method / Memory Budget settings."""
    return _PreviewJob(obj.name, io.read_scan(obj), options_from(obj.artdef), links)


class ARTDEF_OT_preview_links(_WorkerModal, bpy.types.Operator):
    """Colour the faces of the active scan by link for a given link count (colour attribute 'artdef_links'); the clustering is cached, so changing the count is fast"""
    bl_idname = "artdef.preview_links"
    bl_label = "Preview Links"
    bl_options = {'REGISTER', 'UNDO'}

    links: IntProperty(name="Links", default=3, min=1, soft_max=64,
                       description="Number of links to show")

    _what = "preview"

    @classmethod
    def poll(cls, context):
        return _scan_mesh_poll(cls, context)

    def _prepare(self, context):
        try:
            return _preview_job(context.active_object, self.links)
        except (_scan.ScanError, ValueError) as err:
            self.report({'ERROR'}, str(err))
            return None

    def execute(self, context):
        job = self._prepare(context)
        if job is None:
            return {'CANCELLED'}
        job.run()
        return self._finish(context, job)

    # -- interactive path: the first clustering of a big scan runs in a worker thread,
    #    with progress in the status bar and Esc to cancel (a cached one is instant)
    def invoke(self, context, event):
        if not self.properties.is_property_set("links"):
            self.links = context.active_object.artdef.links
        if bpy.app.background or context.window is None:
            return self.execute(context)
        job = self._prepare(context)
        if job is None:
            return {'CANCELLED'}
        if job.cached:
            job.run()
            return self._finish(context, job)
        return self._start_modal(context, job)

    def _finish(self, context, job):
        """Report the job's outcome; on success colour the faces.  Main thread only."""
        if self._failed(job):
            return {'CANCELLED'}
        stored = job.stored
        obj = bpy.data.objects.get(job.obj_name)
        if obj is None or obj.type != 'MESH' or len(obj.data.vertices) != len(stored.scan.vertices):
            self.report({'ERROR'}, f"'{job.obj_name}' changed while it was being segmented; nothing done")
            return {'CANCELLED'}
        labels = job.labels
        rig.write_link_colours(obj.data, labels, stored.tri_polygons)
        obj.data.update()
        space = context.space_data
        if space is not None and space.type == 'VIEW_3D' and space.shading.type == 'SOLID':
            space.shading.color_type = 'VERTEX'  # show the colour attribute
        self.report({'INFO'}, f"'{obj.name}': {int(labels.max()) + 1} links"
                              f"{' (cached clustering)' if job.cached else ''}")
        return {'FINISHED'}


# --------------------------------------------------------------------------
# which fit colours the viewport shows
# --------------------------------------------------------------------------

class ARTDEF_OT_show_colours(bpy.types.Operator):
    """Show the fit's link colours or its per-vertex articulation residual (blue = 0, red = largest) on the active mesh (sets the active colour attribute and the viewport's solid shading to attribute colours)"""
    bl_idname = "artdef.show_colours"
    bl_label = "Show Fit Colours"
    bl_options = {'REGISTER', 'UNDO'}

    which: EnumProperty(
        name="Show", default='LINKS',
        items=(('LINKS', "Links", "Faces coloured by link ('artdef_links')"),
               ('RESIDUAL', "Residual", "Vertices coloured by articulation residual "
                                        "('artdef_residual_color')")),
        description="Which colour attribute to show")

    @classmethod
    def poll(cls, context):
        obj = _active_mesh(context)
        if obj is None:
            cls.poll_message_set("Select a mesh object")
            return False
        attrs = obj.data.color_attributes
        if rig.COLOR_ATTR not in attrs and rig.RESIDUAL_COLOR_ATTR not in attrs:
            cls.poll_message_set("Fit or preview links first")
            return False
        return True

    def execute(self, context):
        mesh = context.active_object.data
        name = rig.COLOR_ATTR if self.which == 'LINKS' else rig.RESIDUAL_COLOR_ATTR
        if name not in mesh.color_attributes:
            self.report({'ERROR'}, f"'{mesh.name}' has no colour attribute '{name}'")
            return {'CANCELLED'}
        rig.set_active_colour(mesh, name)
        space = context.space_data
        if space is not None and space.type == 'VIEW_3D' and space.shading.type == 'SOLID':
            space.shading.color_type = 'VERTEX'
        return {'FINISHED'}


# --------------------------------------------------------------------------
# clear
# --------------------------------------------------------------------------

class ARTDEF_OT_clear_rig(bpy.types.Operator):
    """Remove everything the last fit created on the active mesh (armature, load empties, drivers, actions, ArtDef vertex groups and shape keys, link colours); the scan and the user's data stay"""
    bl_idname = "artdef.clear_rig"
    bl_label = "Clear Rig"
    bl_options = {'REGISTER', 'UNDO'}

    @classmethod
    def poll(cls, context):
        obj = mesh_in_object_mode(cls, context)
        if obj is None:
            return False
        if not rig.has_rig(obj):
            cls.poll_message_set("The active mesh has no ArtDef rig")
            return False
        return True

    def execute(self, context):
        obj = context.active_object
        shared = shared_rig_message(obj)
        if shared is not None:
            self.report({'ERROR'}, shared)
            return {'CANCELLED'}
        rig.clear_rig(obj, context.scene)
        LAST_RESULTS.pop(obj.name, None)
        self.report({'INFO'}, f"'{obj.name}': ArtDef rig removed")
        return {'FINISHED'}


classes = (
    ARTDEF_OT_import_scan,
    ARTDEF_OT_fields_from_shape_keys,
    ARTDEF_OT_fit,
    ARTDEF_OT_preview_links,
    ARTDEF_OT_show_colours,
    ARTDEF_OT_clear_rig,
)
if ARTDEF_FH_scan is not None:
    classes += (ARTDEF_FH_scan,)


def _forget():
    """What the add-on keeps between fits: the core's cached segmenters and the last results."""
    _api.clear_cache()
    LAST_RESULTS.clear()


register, unregister = menus.registration(classes, "TOPBAR_MT_file_import", menu_import, after_unregister=_forget)
