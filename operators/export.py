# SPDX-License-Identifier: GPL-3.0-or-later
"""Export Rig: the fitted mesh and its armature, the way engines expect.

``export_rig`` (behind the ``artdef.export_rig`` operator, File > Export, the
panel's Export button and the command line's ``--glb``/``--fbx``) writes
glTF (.glb/.gltf, Blender's glTF exporter) or FBX (Blender's FBX exporter):

* only the fitted mesh and its armature: a temporary copy of the mesh is
  exported, selected together with the armature (the exporters' selection
  option), so the source character, load empties, helpers and everything
  else in the scene stay out;
* what the copy drops: the debug colour attributes (links, residual) unless
  ``debug_attributes`` (the source's own colours, UVs, materials and vertices stay); shape keys and vertex groups that the fit did not make
  (the source's), so input data never rides along silently;
* one clip per input clip: the armature's replay and the shape-key replay are
  merged into one animation, keyed at the replay's own frames (the source's
  frames for a scan sampled from an animation), the timing untouched;
* at most 4 influences per vertex (the exporters keep the 4 largest weights
  and renormalise);
* a Green's rig (load empties driving helper bones and shape keys) is baked:
  the driven pose into a temporary action on the armature, sampled every
  frame of the scene; the exporters then write plain joint and morph-weight
  animation.

The user's objects, actions, selection and frame range are restored.
"""

import os

import bpy
import numpy as np
from bpy.props import BoolProperty, EnumProperty, StringProperty
from bpy_extras.io_utils import ExportHelper

from . import compat, menus, parts, rig
from .ops import in_object_mode
from ..artdef_addon import gltfinfo
from ..artdef_addon.files import Outputs, same_file

FORMATS = (('GLB', "glTF Binary (.glb)", "One .glb file"),
           ('GLTF_SEPARATE', "glTF Separate (.gltf + .bin)", "A .gltf with its .bin next to it"),
           ('FBX', "FBX (.fbx)", "Autodesk FBX through Blender's FBX exporter"))
EXTENSIONS = {'GLB': ".glb", 'GLTF_SEPARATE': ".gltf", 'FBX': ".fbx"}
#: the colour attributes a fit adds to show links and residuals (left out unless debug_attributes)
DEBUG_COLOUR_ATTRS = frozenset((rig.COLOR_ATTR, rig.RESIDUAL_COLOR_ATTR))


def format_for_path(path):
    """'GLB' / 'GLTF_SEPARATE' / 'FBX' from a file name's extension (None if none fits)."""
    ext = os.path.splitext(path)[1].lower()
    return {".glb": 'GLB', ".gltf": 'GLTF_SEPARATE', ".fbx": 'FBX'}.get(ext)


def rig_parts(obj):
    """(mesh, armature) of the ArtDef rig ``obj`` belongs to (either of them), or (None, None)."""
    if obj is None:
        return None, None
    obj = parts.owner_of(obj)       # a source mesh's rigged object: the rig of the joined mesh
    if obj.type == 'MESH':
        arm = obj.artdef.rig
        return (obj, arm) if arm is not None else (None, None)
    if obj.type == 'ARMATURE':
        for o in bpy.data.objects:
            if o.type == 'MESH' and o.artdef.rig == obj and o.get(parts.PART_OF) is None:
                return o, obj
    return None, None


def poll_rig(cls, context):
    """The shared ``poll`` of the operators that work on a fitted rig: Object Mode and an
    active object that is an ArtDef rig's mesh or armature. Returns ``(mesh, armature)``, or
    ``None`` after setting the poll message."""
    if not in_object_mode(cls, context):
        return None
    mesh, arm = rig_parts(context.active_object)
    if mesh is None:
        cls.poll_message_set("Select a fitted mesh or its ArtDef armature")
        return None
    return mesh, arm


def _artdef_shape_keys(mesh_obj):
    return {item.name for item in mesh_obj.artdef.shape_keys}


def _clean_copy(context, obj, arm, debug_attributes):
    """A temporary copy of mesh object ``obj`` holding only what the fit made.
    Returns (copy, list of what was left out)."""
    new = obj.copy()
    new.data = obj.data.copy()
    context.scene.collection.objects.link(new)
    new.parent = arm
    new.matrix_parent_inverse = obj.matrix_parent_inverse.copy()
    new.matrix_basis = obj.matrix_basis.copy()
    left_out = []
    mesh = new.data
    if not debug_attributes:
        for attr in [a for a in mesh.color_attributes if a.name in DEBUG_COLOUR_ATTRS]:
            left_out.append(f"colour attribute '{attr.name}'")
            mesh.color_attributes.remove(attr)
        res = mesh.attributes.get(rig.RESIDUAL_ATTR)
        if res is not None:
            mesh.attributes.remove(res)
        if len(mesh.color_attributes):       # the source's own colours: the one it showed
            rig.set_active_colour(mesh, source_colour(mesh).name)
    ours = _artdef_shape_keys(obj)
    keys = mesh.shape_keys
    if keys is not None:
        for kb in list(keys.key_blocks)[1:]:
            if kb.name not in ours:
                left_out.append(f"shape key '{kb.name}'")
                new.shape_key_remove(kb)
    bones = {b.name for b in arm.data.bones if b.use_deform}
    for vg in list(new.vertex_groups):
        if vg.name not in bones:
            left_out.append(f"vertex group '{vg.name}'")
            new.vertex_groups.remove(vg)
    return new, left_out


def source_colour(mesh):
    """The colour attribute the mesh shows that is not one of ArtDef's debug colours (the
    rendered one, else the first), or None."""
    own = [a for a in mesh.color_attributes if a.name not in DEBUG_COLOUR_ATTRS]
    if not own:
        return None
    index = mesh.color_attributes.render_color_index
    shown = mesh.color_attributes[index] if 0 <= index < len(mesh.color_attributes) else None
    return shown if shown is not None and shown.name not in DEBUG_COLOUR_ATTRS else own[0]


def flat_shaded(mesh):
    """Every face is flat shaded and no custom normals are set: what Blender's glTF importer
    makes of a file that has no normals (glTF: a viewer then shades every face flat). Written
    with normals, each face would need vertices of its own."""
    if getattr(mesh, "has_custom_normals", False) or not len(mesh.polygons):
        return False
    sharp = mesh.attributes.get("sharp_face")
    if sharp is None or sharp.domain != 'FACE' or sharp.data_type != 'BOOLEAN':
        return False
    values = np.empty(len(mesh.polygons), dtype=bool)
    sharp.data.foreach_get("value", values)
    return bool(values.all())


def _driven_bone_channels(arm):
    ad = arm.animation_data
    if ad is None:
        return []
    return [(fc.data_path, fc.array_index) for fc in ad.drivers if fc.data_path.startswith("pose.bones[")]


def _bake_driven_pose(context, arm):
    """Key the driven pose-bone channels (Green's rig: the load helper bones)
    at every frame of the scene into a temporary action on the armature (a copy
    of its action if it has one, so an animator's keys come along).  Returns
    the previous action and the temporary one."""
    scene = context.scene
    ad = arm.animation_data
    old = ad.action
    action = old.copy() if old is not None else bpy.data.actions.new(f"{arm.name}_bake")
    action.name = f"{arm.name}_bake"
    compat.assign_action(arm, action)
    channels = _driven_bone_channels(arm)
    for frame in range(scene.frame_start, scene.frame_end + 1):
        scene.frame_set(frame)
        for path, index in channels:
            arm.keyframe_insert(path, index=index, frame=frame)
    return old, action


def _action_range(obj, arm):
    """(start, end) frames of the rig's animation (its actions' frame ranges)."""
    ranges = []
    for id_data in (arm, obj.data.shape_keys):
        ad = getattr(id_data, "animation_data", None) if id_data is not None else None
        if ad is not None and ad.action is not None:
            ranges.append(tuple(ad.action.frame_range))
    if not ranges:
        return None
    return int(min(r[0] for r in ranges)), int(max(r[1] for r in ranges))


def _key_step(obj, arm):
    """The frame step of the rig's keys when they are evenly spaced (the
    exporters then sample exactly at the keys: at the source's frames), else 1."""
    frames = set()
    for id_data in (arm, obj.data.shape_keys):
        ad = getattr(id_data, "animation_data", None) if id_data is not None else None
        if ad is not None and ad.action is not None:
            frames.update(round(f) for f in compat.keyed_frames(ad.action))
    frames = sorted(frames)
    steps = {b - a for a, b in zip(frames, frames[1:])}
    return steps.pop() if len(steps) == 1 and next(iter(steps)) >= 1 else 1


def _clip_count(obj):
    names = obj.data.get("artdef_clip_names")
    return len(names) if names is not None else 1


def _gltf(path, fmt, clip_name, debug_attributes, step=1, clips=1, mesh=None):
    """Blender's glTF exporter on the selection. The mesh keeps the source file's vertices: no
    normals where it is flat shaded throughout (:func:`flat_shaded`), no morph-target normals (a
    shape key's own corner normals split the vertices where its faces are flat; the residual
    shapes are small corrections whose normals the base mesh's stand for), its own colours."""
    own_colour = mesh is not None and source_colour(mesh) is not None
    options = dict(
        filepath=path, check_existing=False, export_format=fmt,
        use_selection=True, use_visible=False, use_active_collection=False,
        export_yup=True, export_apply=False,
        export_skins=True, export_def_bones=True, export_rest_position_armature=True,
        # validator: no NODE_SKINNED_MESH_NON_ROOT.  With several clips only where
        # the NLA Tracks mode allows it (5.1 on; compat.gltf_tracks_drop_armature_node)
        export_armature_object_remove=clips == 1 or compat.gltf_tracks_drop_armature_node(),
        export_influence_nb=4, export_all_influences=False,
        export_normals=mesh is None or not flat_shaded(mesh),
        export_morph=True, export_morph_normal=False, export_morph_animation=True,
        export_animations=True, export_force_sampling=True, export_frame_range=False,
        export_frame_step=int(step),
        export_anim_slide_to_zero=False, export_negative_frame='SLIDE',
        # the armature's and the shape keys' actions as ONE animation; several
        # clips: one animation per NLA track name (armature + shape keys merged)
        export_animation_mode='NLA_TRACKS' if clips > 1 else 'ACTIVE_ACTIONS',
        export_nla_strips_merged_animation_name=clip_name,
        export_vertex_color='ACTIVE' if debug_attributes or own_colour else 'NONE',
        export_all_vertex_colors=bool(debug_attributes),
        export_attributes=False,
        export_cameras=False, export_lights=False, export_extras=False,
    )
    bpy.ops.export_scene.gltf(**compat.supported_options(bpy.ops.export_scene.gltf, options))


def _fbx(path, debug_attributes, step=1, clips=1, mesh=None):
    own_colour = mesh is not None and source_colour(mesh) is not None
    options = dict(
        filepath=path, check_existing=False, use_selection=True,
        object_types={'ARMATURE', 'MESH'},
        use_mesh_modifiers=False,                 # keep the skin, do not apply the Armature
        mesh_smooth_type='FACE',
        use_armature_deform_only=True,            # joints = deforming bones
        add_leaf_bones=False,
        primary_bone_axis='Y', secondary_bone_axis='X',
        bake_anim=True, bake_anim_use_all_bones=True, bake_anim_use_nla_strips=clips > 1,
        bake_anim_use_all_actions=False,          # the active actions, one take
        bake_anim_force_startend_keying=True, bake_anim_step=float(step),
        bake_anim_simplify_factor=0.0,            # every frame, no key reduction
        colors_type='SRGB' if debug_attributes or own_colour else 'NONE',
        use_custom_props=False,
        axis_forward='-Z', axis_up='Y',
    )
    bpy.ops.export_scene.fbx(**compat.supported_options(bpy.ops.export_scene.fbx, options))


def export_rig(context, obj, path, fmt=None, debug_attributes=False, clip_name=None):
    """Write the rig of mesh (or armature) ``obj`` to ``path``; return
    ``(path, left_out)``: the written file and what of the mesh was left out
    (debug attributes, the source's shape keys and vertex groups).

    ``fmt``: 'GLB', 'GLTF_SEPARATE' or 'FBX' (default: from the extension).
    RuntimeError when ``obj`` has no rig or the exporter wrote nothing.
    """
    mesh_obj, arm = rig_parts(obj)
    if mesh_obj is None:
        raise RuntimeError(f"'{getattr(obj, 'name', obj)}' has no ArtDef rig to export")
    fmt = fmt or format_for_path(path) or 'GLB'
    path = os.path.abspath(bpy.path.abspath(path))
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    scene, view_layer = context.scene, context.view_layer
    clip_name = clip_name or mesh_obj.data.get("artdef_clip") or "ArtDef"

    # written all or nothing (files.Outputs): the exporter writes into a hidden folder beside the
    # file, and the file (with a glTF Separate's .bin) replaces the user's only once complete
    with Outputs() as out:
        target = out.path(path)
        saved_selection = [o for o in view_layer.objects if o.select_get()]
        saved_active = view_layer.objects.active
        saved_range = (scene.frame_start, scene.frame_end)
        saved_frame = scene.frame_current
        saved_name = mesh_obj.name
        arm_hidden = arm.hide_get(view_layer=view_layer)
        copy, baked, others = None, None, []
        try:
            arm.hide_set(False)
            step = 1
            if _driven_bone_channels(arm):           # a Green's rig: bake its load sweep
                baked = _bake_driven_pose(context, arm)
            elif _clip_count(mesh_obj) == 1:
                step = _key_step(mesh_obj, arm)
                span = _action_range(mesh_obj, arm)
                if span is not None:                 # FBX bakes over the scene's range
                    for _ in range(2):
                        scene.frame_start, scene.frame_end = span
            copy, left_out = _clean_copy(context, mesh_obj, arm, debug_attributes)
            mesh_obj.name = saved_name + "_artdef_export_source"
            copy.name = saved_name                   # the exported node keeps the mesh's name
            others = parts.split_parts(context, copy)    # a file's several meshes: each its own
            clips = _clip_count(mesh_obj)
            export_scene, export_layer = scene, view_layer
            for o in export_layer.objects:
                o.select_set(False, view_layer=export_layer)
            for o in (copy, *others, arm):
                o.select_set(True, view_layer=export_layer)
            export_layer.objects.active = copy
            with context.temp_override(scene=export_scene, view_layer=export_layer, active_object=copy,
                                       object=copy, selected_objects=[copy, *others, arm]):
                if fmt == 'FBX':
                    muted = []
                    if clips > 1:  # the FBX exporter writes one take per NOT muted NLA strip
                        for id_data in (arm, copy.data.shape_keys):
                            ad = getattr(id_data, "animation_data", None) if id_data else None
                            for track in (ad.nla_tracks if ad is not None else ()):
                                if track.mute:
                                    track.mute = False
                                    muted.append(track)
                    try:
                        _fbx(target, debug_attributes, step, clips, copy.data)
                    finally:
                        for track in muted:
                            track.mute = True
                else:
                    _gltf(target, fmt, clip_name, debug_attributes, step, clips, copy.data)
        finally:
            for o in others:
                data = o.data
                bpy.data.objects.remove(o, do_unlink=True)
                if data.users == 0:
                    bpy.data.meshes.remove(data)
            if copy is not None:
                data = copy.data
                bpy.data.objects.remove(copy, do_unlink=True)
                if data.users == 0:
                    bpy.data.meshes.remove(data)
            mesh_obj.name = saved_name
            if baked is not None:
                old, action = baked
                compat.assign_action(arm, old)
                bpy.data.actions.remove(action)
            for _ in range(2):
                scene.frame_start, scene.frame_end = saved_range
            scene.frame_set(saved_frame)
            for o in view_layer.objects:
                o.select_set(o in saved_selection)
            view_layer.objects.active = saved_active
            arm.hide_set(arm_hidden)

        if not os.path.isfile(target):
            raise RuntimeError(f"the exporter wrote nothing to {path}")
        folder = os.path.dirname(target)
        final_dir = os.path.dirname(os.path.realpath(path) if os.path.islink(path) else path)
        for name in sorted(os.listdir(folder)):   # a glTF Separate's .bin, written beside the .gltf
            if name != os.path.basename(target):
                os.replace(os.path.join(folder, name), out.path(os.path.join(final_dir, name)))
        out.commit()
    return path, left_out


class ARTDEF_OT_export_rig(bpy.types.Operator, ExportHelper):
    """Export the fitted mesh and its armature for a game engine or another application (glTF or FBX): only the rig, one animation clip keyed at the source's frames, at most 4 bone influences per vertex, no debug colours; a Green's rig is baked into plain bone and shape-key animation"""
    bl_idname = "artdef.export_rig"
    bl_label = "Export Rig"
    bl_options = {'REGISTER', 'UNDO'}

    filename_ext = ".glb"
    filter_glob: StringProperty(default="*.glb;*.gltf;*.fbx", options={'HIDDEN'})
    filepath: compat.blend_relative_filepath("File to export to ('//' for next to the .blend)")
    export_format: EnumProperty(name="Format", items=FORMATS, default='GLB',
                                description="File format (the extension follows it)")
    debug_attributes: BoolProperty(
        name="Debug Colours", default=False,
        description="Also export the link and residual colour attributes "
                    "(viewers tint the mesh with them)")

    @classmethod
    def poll(cls, context):
        return poll_rig(cls, context) is not None

    def check(self, context):
        self.filename_ext = EXTENSIONS[self.export_format]
        return ExportHelper.check(self, context)

    def execute(self, context):
        path = bpy.path.abspath(self.filepath)
        if not os.path.basename(path) or os.path.isdir(path):
            self.report({'ERROR'}, f"Export Rig: give a file name, not a folder ('{self.filepath}')")
            return {'CANCELLED'}
        fmt = format_for_path(path)     # the file name's extension wins
        if fmt is None:
            fmt = self.export_format
            path += EXTENSIONS[fmt]
        folder = os.path.dirname(path) or "."
        if os.path.exists(folder) and not os.path.isdir(folder):
            self.report({'ERROR'}, f"Export Rig: {folder} is a file, not a folder")
            return {'CANCELLED'}
        mesh_obj, _ = rig_parts(context.active_object)   # the armature may be the active object
        source = mesh_obj.data.get("artdef_source_path") if mesh_obj is not None else None
        if source and os.path.exists(path) and same_file(path, source):
            self.report({'ERROR'}, f"Export Rig: {os.path.basename(path)} is the file the scan was imported "
                                   "from; choose another name")
            return {'CANCELLED'}
        try:
            written, left_out = export_rig(context, context.active_object, path, fmt,
                                           self.debug_attributes)
        except (RuntimeError, OSError) as err:
            self.report({'ERROR'}, f"Export failed: {err}")
            return {'CANCELLED'}
        msg = f"Exported the rig to {written}"
        msg += ": " + gltfinfo.report(written, source)
        if left_out:
            msg += f"; left out {', '.join(left_out[:4])}{', ...' if len(left_out) > 4 else ''}"
        self.report({'INFO'}, msg)
        return {'FINISHED'}


def menu_export(self, context):
    self.layout.operator(ARTDEF_OT_export_rig.bl_idname, text="ArtDef Rig (.glb/.gltf/.fbx)")


classes = (ARTDEF_OT_export_rig,)


register, unregister = menus.registration(classes, "TOPBAR_MT_file_export", menu_export)
