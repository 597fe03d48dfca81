# SPDX-License-Identifier: GPL-3.0-or-later
"""Blender-facing operators of ArtDef.

* ``io``    — scans stored on meshes (import, read back, shape keys -> scan);
* ``rig``   — builds/removes the armature, groups, shape keys, drivers, actions;
* ``props`` — ``Object.artdef`` settings, the fit's record and summary;
* ``ops``   — the operators ``artdef.import_scan``, ``artdef.fields_from_shape_keys``,
  ``artdef.fit``, ``artdef.preview_links``, ``artdef.clear_rig``;
* ``sources`` — ``artdef.fields_from_animation``, ``artdef.import_mesh_sequence``;
* ``animfile`` — ``artdef.fields_from_file`` (an animated glTF/FBX/Alembic/USD file or
  a mesh sequence, sampled through Fields from Animation);
* ``export`` — ``artdef.export_rig`` (glTF/FBX of the rig only, engine settings);
* ``finalize`` — ``artdef.finalize`` (bake drivers, drop helpers and records);
* ``naming`` — ``artdef.name_bones`` (root-first numbers, source joint names, one bone);
* ``engine`` — ``artdef.rotation_only`` (rotation-only joints, fixed bone lengths);
* ``sequence`` — numbered OBJ/PLY files (pure numpy, no bpy);
* ``fitquality`` — residual and per-link figures of a fit (pure numpy);
* ``menus`` — registration of a module's classes with its File menu entry.
"""

from . import props, ops, sources, animfile, export, finalize, naming, engine

_modules = (props, ops, sources, animfile, export, finalize, naming, engine)


def register():
    for mod in _modules:
        mod.register()


def unregister():
    for mod in reversed(_modules):
        mod.unregister()
