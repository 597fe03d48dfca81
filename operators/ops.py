# SPDX-License-Identifier: GPL-3.0-or-later
"""ArtDef operators (public scripting API: ``bpy.ops.artdef.*``)."""

import inspect
import threading
import time
import traceback

import bpy
import numpy as np
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, StringProperty
from bpy_extras.io_utils import ImportHelper

from ..artdef_addon import cost as _cost
from ..artdef_addon import fit as _fit
from ..artdef_addon import scan as _scan
from ..artdef_addon.files import MAX_AUTO_LINKS
from . import fitquality, io, rig
from .props import (BUDGET_MIN, BUDGET_SOFT_MIN, MEMORY_BUDGET_DESCRIPTION, MODE_ITEMS,
                    MOTION_ITEMS, REDUCE_ITEMS, SKIN_ITEMS)

try:  # automatic link count (issue 5), in cores that have it
    from ..artdef_addon import linkcount as _linkcount
except ImportError:
    _linkcount = None

#: The core's ``fit()`` takes ``skin='seam'|'refined'`` (refined skin weights, issue 5).
HAS_SKIN = "skin" in inspect.signature(_fit.fit).parameters
#: The core can choose the link count (``linkcount.choose_links``).
HAS_AUTO_LINKS = _linkcount is not None and hasattr(_linkcount, "choose_links")

#: Extra cancel checks consulted by every fit's progress callback:
#: ``hook(stage, fraction) -> bool`` (True cancels).  For scripts and tests;
#: the interactive path cancels with Esc.
PROGRESS_HOOKS = []

#: Last FitResult per mesh object name (the model behind the rig; for
#: scripting and tests — not saved in the .blend).
LAST_RESULTS = {}

#: Segmenter cache shared by Preview Links and Fit: object name ->
#: (key, Segmenter), the key being the scan fingerprint and the method settings
#: that shape the segmenter (see :func:`segmenter_key`).  The segmenter holds the
#: expensive pairwise distances/trees, so changing the link count does not
#: recompute them; changing Reduced Method or Memory Budget does.
_SEGMENTERS = {}
_SEGMENTER_CACHE_SIZE = 2


#: Fit jobs started in a worker thread (interactive path); a cancelled one may
#: still be winding down when the next fit or preview starts.
_THREAD_JOBS = []


# --------------------------------------------------------------------------
# method settings: reduced method and memory budget (issue 6)
# --------------------------------------------------------------------------

GB = 2 ** 30  # the core's budgets are bytes; DEFAULT_BUDGET is 2 * 2**30


def strategy_for(kind):
    """The strategy the core's Segmenter picks by default ("auto")."""
    return "paper" if kind == "greens" else "summed"


def method_plan(triangles, fields, vertices, kind, reduce='AUTO', budget_gb=2.0, links=None,
                auto=False):
    """What a fit with these settings will do, from counts only (no fit).

    Returns ``(estimate, reduce_arg)``: the core's :class:`cost.Estimate` for the
    method that will run (``estimate.reduced``) and the ``reduce`` argument for the
    Segmenter (None: the core decides by the budget, and notes why). ``links``: the link
    count the fit will use (its skin decompositions grow with it; None: the core's default),
    ``auto``: Auto Links (the link-count search, priced as the core prices it).
    """
    budget = float(budget_gb) * GB
    strategy = strategy_for(kind)
    kw = dict(links=None if auto or links is None else int(links), auto=bool(auto))
    if reduce == 'OFF':
        return _cost.estimate(triangles, fields, vertices, strategy, float("inf"), **kw), False
    if reduce == 'ON':
        # the estimate of the reduced branch, with the patch count this budget gives
        units = min(triangles, _cost.reduced_units(budget, fields))
        return _cost.estimate(triangles, fields, vertices, strategy, 0.0, units=units, **kw), True
    return _cost.estimate(triangles, fields, vertices, strategy, budget, **kw), None


def segmenter_key(fingerprint, reduced, reduce='AUTO', budget_gb=2.0):
    """Cache key of a Segmenter: what its result depends on.

    The full method does not depend on the budget (any budget, Auto or Off give the
    same segmenter); the reduced one depends on it through the patch count, and under
    Auto its note quotes the budget.
    """
    if not reduced:
        return (fingerprint, False)
    if reduce == 'AUTO':
        return (fingerprint, True, 'AUTO', round(float(budget_gb), 6))
    return (fingerprint, True, reduce, _cost.reduced_units(float(budget_gb) * GB))


def valid_triangles(scan):
    """Triangles the core segments (degenerate ones take their neighbours' link)."""
    return scan.n_faces - len(scan.degenerate_faces)


def planned_key(stored, reduce, budget_gb):
    """``(key, reduce_arg)`` of the Segmenter these settings make for ``stored``."""
    scan = stored.scan
    est, reduce_arg = method_plan(valid_triangles(scan), scan.n_fields, scan.n_vertices,
                                  scan.kind, reduce, budget_gb)
    return segmenter_key(stored.fingerprint, est.reduced, reduce, budget_gb), reduce_arg


def _cached_segmenter(name, key):
    """The cached Segmenter for this key, unless a worker thread still uses it."""
    cached = _SEGMENTERS.get(name)
    if cached is None or cached[0] != key:
        return None
    _THREAD_JOBS[:] = [j for j in _THREAD_JOBS if j.thread.is_alive()]
    if any(j.segmenter is cached[1] for j in _THREAD_JOBS):
        return None  # never share one Segmenter between two threads
    return cached[1]


def _cache_segmenter(name, key, seg):
    _SEGMENTERS.pop(name, None)
    _SEGMENTERS[name] = (key, seg)
    while len(_SEGMENTERS) > _SEGMENTER_CACHE_SIZE:
        _SEGMENTERS.pop(next(iter(_SEGMENTERS)))


def last_result(obj):
    return LAST_RESULTS.get(obj.name)


def _active_mesh(context):
    obj = context.active_object
    return obj if obj is not None and obj.type == 'MESH' else None


def mesh_in_object_mode(cls, context):
    """The active mesh object if the operator can run on it (Object Mode), else None with the
    reason set as the poll message."""
    obj = _active_mesh(context)
    if obj is None:
        cls.poll_message_set("Select a mesh object")
        return None
    if context.mode != 'OBJECT':
        cls.poll_message_set("Switch to Object Mode")
        return None
    return obj


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

    @classmethod
    def poll(cls, context):
        if context.mode != 'OBJECT':
            cls.poll_message_set("Switch to Object Mode")
            return False
        return True

    def invoke(self, context, event):
        if self.properties.is_property_set("filepath"):  # dropped on the 3D View
            return self.execute(context)
        return ImportHelper.invoke(self, context, event)

    def execute(self, context):
        t0 = time.perf_counter()
        try:
            obj, scan = io.import_scan_file(context, self.filepath)
        except _scan.ScanError as err:
            self.report({'ERROR'}, f"Not a valid ArtDef scan: {err}")
            return {'CANCELLED'}
        except (OSError, ValueError) as err:
            self.report({'ERROR'}, f"Could not read '{self.filepath}': {err}")
            return {'CANCELLED'}
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
    "joints": ("joints, bones and skin weights", False),
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
    """One fit: the core runs here (possibly in a worker thread); no bpy access."""

    def __init__(self, scan, links, mode, motion, p_max, segmenter=None, load_index=0,
                 skin=None, max_links=None, reduce=None, budget=_cost.DEFAULT_BUDGET):
        self.scan, self.links, self.mode, self.motion, self.p_max = scan, links, mode, motion, p_max
        self.reduce = reduce            # Segmenter's reduce: None (by budget), True, False
        self.budget = budget            # bytes
        self.load_index = load_index
        self.skin = skin                # 'seam' | 'refined' | None: the core's default
        self.max_links = max_links      # not None: choose the link count, up to this
        self.link_reason = ""
        self.segmenter = segmenter  # cached one (same scan), or None: made in run()
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
            self.links_fraction = float(fraction)
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
            if self.segmenter is None:
                self.segmenter = _fit.Segmenter(self.scan, callback, reduce=self.reduce,
                                                budget=self.budget)
            if self.max_links is not None:
                self.segmenter.progress = callback
                self.links_fraction = 0.0
                try:
                    choice = _linkcount.choose_links(self.segmenter, self.max_links,
                                                     progress=callback)
                finally:
                    self.links_fraction = None
                self.links, self.link_reason = int(choice.links), str(choice.reason)
                errors = getattr(choice, "errors", None)
                self.link_errors = [] if errors is None else [float(e) for e in errors]
            extra = {} if self.skin is None else {"skin": self.skin}
            reuse = getattr(choice, "reusable", None) if self.max_links is not None else None
            self.result = reuse(self.mode, self.motion, self.skin) if reuse is not None else None
            if self.result is not None:     # the chooser fitted this count already
                self.result.p_max = self.p_max
            else:
                self.result = _fit.fit(self.scan, self.links, mode=self.mode, motion=self.motion,
                                       p_max=self.p_max, progress=callback, segmenter=self.segmenter,
                                       **extra)
            self._quality()
        except BaseException as err:  # reported on the main thread
            self.error = err
        finally:
            if self.segmenter is not None:
                self.segmenter.progress = None  # don't keep this job's callback in the cache
        self.seconds = time.perf_counter() - t0

    @property
    def notes(self):
        """The core's notes on this fit (e.g. that and why the reduced method ran)."""
        return [str(n) for n in (getattr(self.result, "notes", None) or [])]

    @property
    def reduced(self):
        return bool(getattr(self.segmenter, "reduced", False))

    def status_text(self):
        """What the status bar shows while the job runs."""
        text = stage_text(self.stage, self.fraction)
        if self.links_fraction is not None and self.stage != "links":
            # Auto Links segments every count up to Max Links: say where it is overall
            text = f"{stage_text('links', self.links_fraction)} ({text})"
        return text

    def _quality(self):
        """The model to build and its per-vertex articulation residual."""
        model, fields = self.result, None
        if self.mode == "pseudo":
            pseudo = self.result.pseudo or []
            if self.load_index >= len(pseudo):
                return  # reported by the operator
            model = pseudo[self.load_index]
            fields = self.segmenter.groups[self.load_index]
        self.model = model
        self.vertex_residual = fitquality.vertex_residual(model, self.scan, fields)

    def start_thread(self):
        self.thread = threading.Thread(target=self.run, name="artdef-fit", daemon=True)
        _THREAD_JOBS.append(self)
        self.thread.start()


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


class ARTDEF_OT_fit(_WorkerModal, bpy.types.Operator):
    """Fit an articulated rig to the active mesh's scan: vertex groups, an armature, residual shape keys, and load controls (Green's scans) or a replay action (tracked scans). Pseudo mode fits each load point separately and builds the rig of the load point chosen by Load Index. Esc cancels without changing the scene"""
    bl_idname = "artdef.fit"
    bl_label = "Fit Articulation"
    bl_options = {'REGISTER', 'UNDO'}

    links: IntProperty(name="Links", default=3, min=1, soft_max=64,
                       description="Number of rigid links (bones) to fit")
    mode: EnumProperty(name="Mode", items=MODE_ITEMS, default='GLOBAL',
                       description="Global fit (default), or the pseudo-articulation of one "
                                   "load point (Load Index)")
    motion: EnumProperty(name="Motion", items=MOTION_ITEMS, default='ROBUST',
                         description="How each link's rigid motion is estimated")
    p_max: FloatProperty(name="Max Hardening", default=0.0, min=0.0, soft_max=20.0,
                         description="Strain hardening limit in units of the probe load "
                                     "(> 1); 0 = off (linear)")
    load_index: IntProperty(name="Load Index", default=0, min=0,
                            description="Pseudo mode: the load point whose model becomes the rig")
    frames_per_field: IntProperty(name="Frames per Field", default=10, min=1, soft_max=100,
                                  description="Tracked scans: the replay action keys field p at "
                                              "frame (p+1) x this and the rest pose at frame 0. "
                                              "Green's scans: the load sweep takes 2 x this frames "
                                              "per load point and axis (0, probe load, 0). The "
                                              "scene's frame range is set to cover it")
    auto_links: BoolProperty(name="Auto Links", default=False,
                             description="Choose the number of links from the data (where the "
                                         "articulation error stops dropping), up to Max Links; "
                                         "the reason is reported. Turn off to set Links yourself")
    max_links: IntProperty(name="Max Links", default=30, min=1, max=MAX_AUTO_LINKS, soft_max=64,
                           description="Auto Links: the largest link count tried")
    skin: EnumProperty(name="Skin", items=SKIN_ITEMS, default='AUTO',
                       description="Skin weights: seam-blended, or refined per vertex by least "
                                   "squares over all fields (Auto: refined for tracked scans, "
                                   "seam for Green's scans)")
    reduce: EnumProperty(name="Reduced Method", items=REDUCE_ITEMS, default='AUTO',
                         description="Segment small patches of triangles instead of every "
                                     "triangle (large scans); Auto: when the full method would "
                                     "exceed the Memory Budget")
    memory_budget: FloatProperty(name="Memory Budget", default=2.0, min=BUDGET_MIN,
                                 soft_min=BUDGET_SOFT_MIN, soft_max=64.0, precision=2,
                                 description=MEMORY_BUDGET_DESCRIPTION)

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
        for name in ("links", "mode", "motion", "p_max", "load_index", "frames_per_field",
                     "auto_links", "max_links", "skin", "reduce", "memory_budget"):
            if not props.is_property_set(name):
                setattr(self, name, getattr(st, name))

    def _prepare(self, context):
        """Read the scan and check the settings; returns a job or None (reported)."""
        obj = context.active_object
        self._settings(obj)
        if self.p_max != 0.0 and self.p_max <= 1.0:
            self.report({'ERROR'}, f"Max Hardening must be 0 (off) or > 1, got {self.p_max:g}")
            return None
        try:
            stored = io.read_scan(obj)
        except (_scan.ScanError, ValueError) as err:
            self.report({'ERROR'}, str(err))
            return None
        scan = stored.scan
        if self.mode == 'PSEUDO':
            if scan.kind != "greens":
                self.report({'ERROR'}, "Pseudo mode needs a Green's scan (with load points)")
                return None
            if self.load_index >= len(scan.load_vertices):
                self.report({'ERROR'}, f"Load Index {self.load_index} is out of range: the scan has "
                                       f"{len(scan.load_vertices)} load points")
                return None
        if self.skin != 'AUTO' and not HAS_SKIN:
            self.report({'ERROR'}, "This ArtDef core has no skin option: use Skin 'Auto'")
            return None
        if self.auto_links and not HAS_AUTO_LINKS:
            self.report({'ERROR'}, "This ArtDef core cannot choose the link count: "
                                   "turn Auto Links off")
            return None
        key, reduce_arg = planned_key(stored, self.reduce, self.memory_budget)
        job = _FitJob(scan, self.links, self.mode.lower(), self.motion.lower(),
                      None if self.p_max == 0.0 else float(self.p_max),
                      _cached_segmenter(obj.name, key), self.load_index,
                      skin=None if self.skin == 'AUTO' else self.skin.lower(),
                      max_links=self.max_links if self.auto_links else None,
                      reduce=reduce_arg, budget=self.memory_budget * GB)
        job.obj_name = obj.name
        job.tri_polygons = stored.tri_polygons
        job.fingerprint = stored.fingerprint
        return job

    def _finish(self, context, job):
        """Report the job's outcome; on success write the rig.  Main thread only."""
        if self._failed(job):
            return {'CANCELLED'}
        obj = bpy.data.objects.get(job.obj_name)
        if obj is None or obj.type != 'MESH' or len(obj.data.vertices) != len(job.scan.vertices):
            self.report({'ERROR'}, "The mesh changed while fitting; nothing was created")
            return {'CANCELLED'}
        # keyed on what the core actually built (the plan predicts it; never trust a guess)
        _cache_segmenter(job.obj_name, segmenter_key(job.fingerprint, job.reduced, self.reduce,
                                                     self.memory_budget), job.segmenter)
        self.links = job.links  # chosen by Auto Links, or as given
        if job.link_reason:
            self.report({'INFO'}, job.link_reason)
        model = job.model
        load_names = None
        if self.mode == 'PSEUDO':
            if model is None:
                self.report({'ERROR'}, "The fit returned no pseudo-articulation for that load point")
                return {'CANCELLED'}
            load_names = [self.load_index]
        try:
            rig.build_rig(context, obj, model, job.tri_polygons, job.scan.kind, load_names,
                          self.frames_per_field)
            scale = float(job.vertex_residual.max()) if len(job.vertex_residual) else 0.0
            rig.write_residual(obj.data, job.vertex_residual, scale)
        except Exception as err:
            traceback.print_exc()
            rig.clear_rig(obj, context.scene)
            self.report({'ERROR'}, f"Building the rig failed: {err}")
            return {'CANCELLED'}
        LAST_RESULTS[obj.name] = model
        self._store_summary(obj, model, job)
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

    def _store_summary(self, obj, model, job):
        st = obj.artdef
        st.has_fit = True
        st.fit_links = int(model.n_links)
        st.fit_mode = self.mode
        st.fit_motion = self.motion
        st.fit_kind = job.scan.kind
        st.fit_load_index = self.load_index if self.mode == 'PSEUDO' else -1
        st.fit_p_max = self.p_max
        st.fit_rms_articulation = float(model.rms_articulation)
        st.fit_rms_total = float(model.rms_total)
        st.fit_seconds = job.seconds
        timings = getattr(model, "timings", None) or getattr(job.result, "timings", None) or {}
        st.fit_timings = ", ".join(f"{k} {v:.2f}s" for k, v in timings.items())
        e = float(model.articulation_error_percent)
        st.fit_articulation_percent = e if e == e else -1.0   # −1: undefined (one field), shown "n/a"
        res = job.vertex_residual
        st.fit_residual_max = float(res.max()) if len(res) else 0.0
        st.fit_residual_mean = float(res.mean()) if len(res) else 0.0
        st.fit_diagonal = float(np.linalg.norm(np.ptp(job.scan.vertices, axis=0)))
        st.fit_link_stats.clear()
        for item in fitquality.link_stats(model):
            rec = st.fit_link_stats.add()
            rec.name = rig.GROUP_FMT.format(item["link"])
            for key, value in item.items():
                setattr(rec, key, value)
        if st.set_frame_range:
            start, end = st.replay_frame_range
            if job.scan.kind == "greens":
                st.fit_replay = (f"load sweep: load k along axis d at the probe load at frame "
                                 f"(2(3k+d)+1)x{self.frames_per_field}, scene frames set to "
                                 f"{start}-{end}")
            else:
                st.fit_replay = (f"replay: field p at frame (p+1)x{self.frames_per_field}, "
                                 f"scene frames set to {start}-{end}")
        else:
            st.fit_replay = ""
        try:
            st.fit_summary = str(model.summary())
        except Exception:  # the summary is informative only
            st.fit_summary = ""
        if st.fit_replay:
            st.fit_summary += ("\n" if st.fit_summary else "") + st.fit_replay
        st.fit_link_reason = job.link_reason
        obj["artdef_link_errors"] = list(getattr(job, "link_errors", None) or [])  # panel's curve
        st.fit_skin = str(getattr(model, "skin", "") or "")
        st.fit_notes = "\n".join(job.notes)
        st.fit_reduced = job.reduced
        # Remember the settings that made this rig (Links: the count used, also when chosen).
        st.links, st.mode, st.motion = self.links, self.mode, self.motion
        st.p_max, st.load_index = self.p_max, self.load_index
        st.frames_per_field = self.frames_per_field
        st.auto_links, st.max_links, st.skin = self.auto_links, self.max_links, self.skin
        st.reduce, st.memory_budget = self.reduce, self.memory_budget

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

    Builds the Segmenter unless a cached one fits, then cuts it to ``links``; the progress
    callback reports the stage and cancels on Esc, like the fit's.
    """

    def __init__(self, obj_name, stored, reduce_arg, budget, links, segmenter=None):
        self.obj_name, self.stored, self.reduce_arg, self.budget = obj_name, stored, reduce_arg, budget
        self.links = links
        self.segmenter = segmenter
        self.cached = segmenter is not None
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
            if self.segmenter is None:
                self.segmenter = _fit.Segmenter(self.stored.scan, self.progress, reduce=self.reduce_arg,
                                                budget=self.budget)
            self.segmenter.progress = self.progress
            self.labels = self.segmenter.labels(self.links)
        except BaseException as err:  # reported on the main thread
            self.error = err
        finally:
            if self.segmenter is not None:
                self.segmenter.progress = None

    def status_text(self):
        return stage_text(self.stage, self.fraction)

    def start_thread(self):
        self.thread = threading.Thread(target=self.run, name="artdef-preview", daemon=True)
        _THREAD_JOBS.append(self)
        self.thread.start()


def _preview_job(obj, links):
    """A :class:`_PreviewJob` for ``obj``'s scan and its Reduced Method / Memory Budget settings."""
    stored = io.read_scan(obj)
    st = obj.artdef
    key, reduce_arg = planned_key(stored, st.reduce, st.memory_budget)
    seg = _cached_segmenter(obj.name, key)
    return _PreviewJob(obj.name, stored, reduce_arg, st.memory_budget * GB, links, seg)


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
        seg, stored = job.segmenter, job.stored
        obj = bpy.data.objects.get(job.obj_name)
        if obj is None or obj.type != 'MESH' or len(obj.data.vertices) != len(stored.scan.vertices):
            self.report({'ERROR'}, f"'{job.obj_name}' changed while it was being segmented; nothing done")
            return {'CANCELLED'}
        st = obj.artdef
        _cache_segmenter(obj.name, segmenter_key(stored.fingerprint, seg.reduced, st.reduce,
                                                 st.memory_budget), seg)
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


def register():
    for cls in classes:
        bpy.utils.register_class(cls)
    bpy.types.TOPBAR_MT_file_import.append(menu_import)


def unregister():
    bpy.types.TOPBAR_MT_file_import.remove(menu_import)
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
    _SEGMENTERS.clear()
    LAST_RESULTS.clear()
