# SPDX-License-Identifier: GPL-3.0-or-later
"""3D View sidebar tab "ArtDef": active scan, fit settings, actions, last fit."""

import textwrap

import bpy

from ..artdef_addon import wording
from ..artdef_addon.cost import format_seconds
from ..artdef_addon.options import GB, FitOptions
from ..operators import io, ops, rig
from ..operators.props import SETTING_NAMES, auto_name


def _subpanel(layout, idname, title):
    """A collapsible section (closed by default): its body layout, or None while
    closed.  Blender 4.1+ ``layout.panel``; older ones draw it open."""
    if hasattr(layout, "panel"):
        header, body = layout.panel(idname, default_closed=True)
        header.label(text=title)
        return body
    layout.label(text=title)
    return layout.column()


class ARTDEF_UL_file_meshes(bpy.types.UIList):
    """The meshes of the animated file a scan came from: a Fit tickbox, the name, the vertex count,
    and why a mesh cannot be fitted."""

    def draw_item(self, context, layout, data, item, icon, active_data, active_propname, index):
        row = layout.row(align=True)
        tick = row.row(align=True)
        tick.enabled = not item.reason
        tick.prop(item, "fit", text="")
        row.label(text=item.name, icon='MESH_DATA')
        row.label(text=f"{item.vertices:,}")
        if item.reason:
            row.label(text=item.reason)


class ARTDEF_PT_main(bpy.types.Panel):
    bl_label = "ArtDef"
    bl_idname = "ARTDEF_PT_main"
    bl_space_type = 'VIEW_3D'
    bl_region_type = 'UI'
    bl_category = "ArtDef"

    def draw(self, context):
        layout = self.layout
        col = layout.column(align=True)
        col.operator("artdef.import_scan", icon='IMPORT')
        col.operator("artdef.import_mesh_sequence", icon='FILE_FOLDER')
        col.operator("artdef.fields_from_file", icon='FILE_MOVIE')
        obj = ops._active_mesh(context)      # a source mesh's rigged object: the joined mesh
        if obj is None:
            layout.label(text="Select a mesh to fit", icon='INFO')
            return
        mesh = obj.data

        box = layout.box()
        box.label(text=f"Scan: {obj.name}", icon='MESH_DATA')
        if io.has_scan(mesh):
            info = io.scan_info(mesh)
            col = box.column(align=True)
            col.label(text=f"Vertices: {len(mesh.vertices):,}")
            col.label(text=f"Triangles: {len(mesh.loop_triangles):,}")
            kind = "Green's matrix" if info["kind"] == "greens" else "Tracked poses"
            col.label(text=f"Kind: {kind}")
            col.label(text=f"Fields: {info['fields']}")
            if info["kind"] == "greens":
                col.label(text=f"Load points: {info['loads']}  (probe {info['probe_load']:g})")
            if info["support"]:
                col.label(text=f"Support vertices: {info['support']}")
        else:
            box.label(text="No scan on this mesh", icon='ERROR')
        if len(obj.artdef.file_meshes):
            box.label(text=f"Meshes of {mesh.get('artdef_source_file', 'the file')}:")
            box.template_list("ARTDEF_UL_file_meshes", "", obj.artdef, "file_meshes", obj.artdef,
                              "file_meshes_index", rows=min(4, len(obj.artdef.file_meshes)))
            box.operator("artdef.resample_meshes", icon='FILE_REFRESH')
        keys = mesh.shape_keys
        if keys is not None and len(keys.key_blocks) > 1:
            box.operator("artdef.fields_from_shape_keys", icon='SHAPEKEY_DATA')
        box.operator("artdef.fields_from_animation", icon='ANIM')

        st = obj.artdef
        box = layout.box()
        box.label(text="Fit", icon='ARMATURE_DATA')
        col = box.column()
        col.use_property_split = True
        col.use_property_decorate = False
        col.prop(st, "auto_links")
        col.prop(st, "max_links" if st.auto_links else "links")
        greens = io.has_scan(mesh) and io.scan_info(mesh)["kind"] == "greens"
        # the fit options in their declared order (artdef_addon/options.py): Green's-only ones
        # only for a Green's scan (or a pseudo mode already set), the advanced ones in a section
        decl = FitOptions.declaration()
        for name, (_, opt) in decl.items():
            if name == "max_links" or opt.advanced:
                continue
            if opt.greens_only and not greens and not (name == "mode" and st.mode == 'PSEUDO'):
                continue
            if opt.tracked_only and greens:
                continue
            if opt.auto:        # its Auto switch, and the count when that is off
                col.prop(st, auto_name(name))
                if getattr(st, auto_name(name)):
                    continue
            col.prop(st, name)
            if name == "mode" and st.mode == 'PSEUDO':
                col.prop(st, "load_index")
        adv = _subpanel(box, "ARTDEF_fit_advanced", "Advanced")
        if adv is not None:
            adv.use_property_split = True
            adv.use_property_decorate = False
            for name, (_, opt) in decl.items():
                if opt.advanced:
                    adv.prop(st, name)
            if io.has_scan(mesh):
                adv.prop(st, "frames_per_field")
        if io.has_scan(mesh):
            _draw_estimate(box, mesh, st)
        row = box.row(align=True)
        row.scale_y = 1.3
        op = row.operator("artdef.fit", icon='PLAY')
        for name in SETTING_NAMES:
            setattr(op, name, getattr(st, name))
        row = box.row(align=True)
        row.operator("artdef.preview_links", icon='COLOR').links = st.links
        row.operator("artdef.clear_rig", icon='TRASH')
        if rig.has_rig(obj):  # hand-off: engines (Export Rig), animators (Finalize)
            row = box.row(align=True)
            row.operator("artdef.export_rig", icon='EXPORT')
            row.operator("artdef.finalize", icon='CHECKMARK')
            row = box.row(align=True)
            row.operator("artdef.name_bones", icon='SORTALPHA')
            row.operator("artdef.rotation_only", icon='CON_ROTLIKE')

        if st.has_fit:
            box = layout.box()
            box.label(text="Last fit", icon='INFO')
            col = box.column(align=True)
            mode = st.fit_mode.title()
            if st.fit_load_index >= 0:
                mode += f" (load {st.fit_load_index})"
            col.label(text=f"Links: {st.fit_links}   {mode}, {st.fit_motion.lower()}"
                           + (f", {st.fit_skin} skin" if st.fit_skin else ""))
            if st.fit_link_reason:
                errors = list(obj.get("artdef_link_errors", []))
                plain = wording.plain_link_reason(st.fit_links, errors, st.fit_articulation_percent) or st.fit_link_reason
                for line in textwrap.wrap(plain, 44):
                    col.label(text=line)
                curve = _subpanel(box, "ARTDEF_link_curve", "Quick error by link count")
                if curve is not None:
                    for line in wording.error_curve_lines(errors, st.fit_links) or \
                            textwrap.wrap(st.fit_link_reason, 44):
                        curve.label(text=line)
            if st.fit_p_max > 0:
                col.label(text=f"Hardening p_max: {st.fit_p_max:g}")
            e = st.fit_articulation_percent
            col.label(text=f"Articulation error (Karni–Gotsman): {e:.3g}%" if e >= 0
                      else "Articulation error (Karni–Gotsman): n/a")
            if st.fit_e_rms == st.fit_e_rms:   # not NaN
                col.label(text=f"E_RMS: {st.fit_e_rms:.4g}")
            if st.fit_rigid_percent == st.fit_rigid_percent:
                col.label(text=f"One rigid motion: {st.fit_rigid_percent:.3g}%, "
                               f"rank-{st.fit_linear_rank} linear: {st.fit_linear_percent:.3g}%")
            if not st.fit_articulated:
                col.label(text="The data do not look articulated (see note)", icon='ERROR')
            col.label(text=f"RMS articulation: {st.fit_rms_articulation:.4g}")
            col.label(text=f"RMS total: {st.fit_rms_total:.4g}")
            if st.fit_diagonal > 0:
                col.label(text=f"Vertex residual: mean {_rel(st.fit_residual_mean, st)}, "
                               f"max {_rel(st.fit_residual_max, st)}")
            if st.fit_notes:
                for note in st.fit_notes.splitlines():
                    for i, line in enumerate(textwrap.wrap(note, 44)):
                        col.label(text=line, icon='INFO' if i == 0 else 'BLANK1')
            col.label(text=f"Time: {st.fit_seconds:.2f} s")
            if st.fit_timings:
                for part in st.fit_timings.split(", "):
                    col.label(text=f"  {part}")
            if st.fit_replay:
                col.label(text=st.fit_replay.capitalize(), icon='ACTION')
            if st.rig is not None:
                col.label(text=f"Rig: {st.rig.name}", icon='OUTLINER_OB_ARMATURE')
                if rig.stale_greens_rig(obj):
                    col.label(text="Built by an earlier version: refit to pose small loads exactly", icon='ERROR')
            _draw_colours(box, mesh, st)
            if len(st.fit_link_stats):
                _draw_link_stats(box, st)
            if st.fit_summary:
                sub = box.column(align=True)
                sub.scale_y = 0.8
                # its "note: ..." lines are shown above, with the figures
                lines = [l for l in st.fit_summary.splitlines() if not l.startswith("note: ")]
                for line in lines[:8]:
                    sub.label(text=line)
        elif rig.has_rig(obj):
            layout.label(text="Rig present (no summary)", icon='INFO')
            if rig.stale_greens_rig(obj):
                layout.label(text="Built by an earlier version: refit to pose small loads exactly", icon='ERROR')


def _gb(nbytes):
    gb = nbytes / GB
    if gb < 0.095:
        return f"{gb:.2f}"
    if gb < 9.5:
        return f"{gb:.1f}"
    return f"{gb:,.0f}"


def _draw_estimate(layout, mesh, st):
    """What a fit with these settings costs, from the counts only (no fit):
    memory, time and the method (full, or reduced on about N patches)."""
    try:
        info = io.scan_info(mesh)
        auto = bool(st.auto_links)
        est, _ = ops.method_plan(len(mesh.loop_triangles), info["fields"], len(mesh.vertices),
                                 info["kind"], st.reduce, st.memory_budget, links=st.links, auto=auto,
                                 max_links=st.max_links)
    except (ValueError, TypeError) as err:     # OptionsError, a damaged scan property: a line, not a raise
        row = layout.row()
        row.alert = True
        row.label(text=f"No estimate: {err}", icon='ERROR')
        return
    col = layout.column(align=True)
    col.scale_y = 0.8
    col.label(text=f"Estimate: about {_gb(est.memory_bytes)} GB, "
                   f"{format_seconds(est.seconds)}", icon='TIME')
    if est.reduced:
        col.label(text=f"reduced method on about {est.units:,} patches", icon='BLANK1')
    else:
        col.label(text=f"full method on {est.triangles:,} triangles", icon='BLANK1')
    if est.memory_bytes > st.memory_budget * GB:
        row = col.row()
        row.alert = True
        row.label(text="over the memory budget", icon='ERROR')


def _rel(value, st):
    """An error in scene units and as a percentage of the scan's bounding-box diagonal."""
    if st.fit_diagonal > 0:
        return f"{value:.3g} ({100.0 * value / st.fit_diagonal:.2f}%)"
    return f"{value:.3g}"


def _draw_colours(layout, mesh, st):
    """Buttons: show the link colours or the residual colours (and their scale)."""
    attrs = mesh.color_attributes
    if rig.RESIDUAL_COLOR_ATTR not in attrs:
        return
    active = attrs.active_color.name if attrs.active_color is not None else ""
    row = layout.row(align=True)
    row.label(text="Show:")
    for which, name, text in (('LINKS', rig.COLOR_ATTR, "Links"),
                              ('RESIDUAL', rig.RESIDUAL_COLOR_ATTR, "Residual")):
        sub = row.row(align=True)
        sub.enabled = name in attrs
        sub.operator("artdef.show_colours", text=text,
                     depress=active == name).which = which
    if active == rig.RESIDUAL_COLOR_ATTR:
        layout.label(text=f"Blue 0, red {_rel(st.fit_residual_max, st)}", icon='INFO')


def _draw_link_stats(layout, st):
    """Per link: parent, joint error, rigid residual, triangles."""
    box = layout.box()
    box.prop(st, "show_link_stats", icon='TRIA_DOWN' if st.show_link_stats else 'TRIA_RIGHT',
             emboss=False)
    if not st.show_link_stats:
        return
    col = box.column(align=True)
    col.scale_y = 0.85
    col.label(text="link  parent  joint err  rigid res  tris")
    for item in st.fit_link_stats:
        parent = ("world" if item.grounded else "-") if item.parent < 0 else f"{item.parent:02d}"
        joint = _rel(item.joint_error, st) if item.has_joint else "-"
        col.label(text=f"{item.link:02d}  {parent}  {joint}  "
                       f"{_rel(item.rigid_residual, st)}  {item.triangles}")


classes = (ARTDEF_UL_file_meshes, ARTDEF_PT_main)


# Blender's own helper: registers in order, unregisters in reverse
register, unregister = bpy.utils.register_classes_factory(classes)
