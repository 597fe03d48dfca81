# SPDX-License-Identifier: GPL-3.0-or-later
"""ArtDef operators (public scripting API: ``bpy.ops.artdef.*``)."""

import os
import time
import traceback

import bpy
import numpy as np
from bpy.props import EnumProperty, IntProperty, StringProperty
from bpy_extras.io_utils import ImportHelper

from ..artdef_addon import api as _api
from ..artdef_addon import scan as _scan
from ..artdef_addon.options import FitOptions, OptionsError
from . import compat, io, menus, parts, rig, worker
from .apply import apply_result, store_summary  # noqa: F401
from .jobs import _STAGES, _FitJob, _PreviewJob, _preview_job, model_of, stage_text  # noqa: F401
from .modal import _WorkerModal
from .props import SETTING_NAMES, FitSettings, options_from
from .state import LAST_RESULTS, PROGRESS_HOOKS, _forget, last_result  # noqa: F401


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
    """The worker's kept segmentation of ``obj``'s scan for its settings (``jobs.Kept``: equal
    while the same one serves), or None (tests, scripts)."""
    return worker.cached(io.read_scan(obj).scan, options_from(obj.artdef))


def _active_mesh(context):
    """The active mesh object; for a source mesh's rigged object (:mod:`.parts`), the joined mesh
    it was cut from: that one holds the scan, and its fit and rig are the one over all its meshes."""
    obj = parts.owner_of(context.active_object)
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
        obj = _active_mesh(context)
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
            job.start().wait(lambda: wm.progress_update(int(1000 * min(max(job.fraction, 0.0), 1.0))))
        finally:
            wm.progress_end()
        return self._finish(context, job)

    # -- interactive path: worker process + modal timer, Esc cancels ---------
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
            return _preview_job(_active_mesh(context), self.links)
        except (_scan.ScanError, ValueError) as err:
            self.report({'ERROR'}, str(err))
            return None

    def execute(self, context):
        job = self._prepare(context)
        if job is None:
            return {'CANCELLED'}
        job.start().wait()
        return self._finish(context, job)

    # -- interactive path: the first clustering of a big scan runs in the worker process,
    #    with progress in the status bar and Esc to cancel (a cached one is instant)
    def invoke(self, context, event):
        if not self.properties.is_property_set("links"):
            self.links = _active_mesh(context).artdef.links
        if bpy.app.background or context.window is None:
            return self.execute(context)
        job = self._prepare(context)
        if job is None:
            return {'CANCELLED'}
        if job.cached:
            job.start().wait()
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
        obj = _active_mesh(context)
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

register, unregister = menus.registration(classes, "TOPBAR_MT_file_import", menu_import, after_unregister=_forget)
