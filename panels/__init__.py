# SPDX-License-Identifier: GPL-3.0-or-later
"""3D View sidebar tab "ArtDef": active scan, fit settings, actions, last fit."""

import bpy

from ..operators import io, rig


class ARTDEF_PT_main(bpy.types.Panel):
    bl_label = "ArtDef"
    bl_idname = "ARTDEF_PT_main"
    bl_space_type = 'VIEW_3D'
    bl_region_type = 'UI'
    bl_category = "ArtDef"

    def draw(self, context):
        layout = self.layout
        layout.operator("artdef.import_scan", icon='IMPORT')
        obj = context.active_object
        if obj is None or obj.type != 'MESH':
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
        keys = mesh.shape_keys
        if keys is not None and len(keys.key_blocks) > 1:
            box.operator("artdef.fields_from_shape_keys", icon='SHAPEKEY_DATA')

        st = obj.artdef
        box = layout.box()
        box.label(text="Fit", icon='ARMATURE_DATA')
        col = box.column()
        col.use_property_split = True
        col.use_property_decorate = False
        col.prop(st, "links")
        col.prop(st, "mode")
        if st.mode == 'PSEUDO':
            col.prop(st, "load_index")
        col.prop(st, "motion")
        col.prop(st, "p_max")
        row = box.row(align=True)
        row.scale_y = 1.3
        op = row.operator("artdef.fit", icon='PLAY')
        op.links, op.mode, op.motion = st.links, st.mode, st.motion
        op.p_max, op.load_index = st.p_max, st.load_index
        row = box.row(align=True)
        row.operator("artdef.preview_links", icon='COLOR').links = st.links
        row.operator("artdef.clear_rig", icon='TRASH')

        if st.has_fit:
            box = layout.box()
            box.label(text="Last fit", icon='INFO')
            col = box.column(align=True)
            mode = st.fit_mode.title()
            if st.fit_load_index >= 0:
                mode += f" (load {st.fit_load_index})"
            col.label(text=f"Links: {st.fit_links}   {mode}, {st.fit_motion.lower()}")
            if st.fit_p_max > 0:
                col.label(text=f"Hardening p_max: {st.fit_p_max:g}")
            col.label(text=f"RMS articulation: {st.fit_rms_articulation:.4g}")
            col.label(text=f"RMS total: {st.fit_rms_total:.4g}")
            col.label(text=f"Time: {st.fit_seconds:.2f} s")
            if st.fit_timings:
                for part in st.fit_timings.split(", "):
                    col.label(text=f"  {part}")
            if st.rig is not None:
                col.label(text=f"Rig: {st.rig.name}", icon='OUTLINER_OB_ARMATURE')
            if st.fit_summary:
                sub = box.column(align=True)
                sub.scale_y = 0.8
                for line in st.fit_summary.splitlines()[:8]:
                    sub.label(text=line)
        elif rig.has_rig(obj):
            layout.label(text="Rig present (no summary)", icon='INFO')


classes = (ARTDEF_PT_main,)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)


def unregister():
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
