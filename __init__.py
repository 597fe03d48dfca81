# SPDX-License-Identifier: GPL-3.0-or-later
"""ArtDef: fit an articulated rig to measured deformation of a mesh.

Blender extension entry point.  This module must stay importable without
``bpy`` (pytest imports it because the repository root is the package), so
the Blender-facing sub-packages are imported only inside ``register()``.
"""

# Sub-modules whose register() succeeded, in order; unregister() walks it
# backwards so a failure half-way through register() can be undone cleanly.
_registered = []


def _ui_modules():
    from . import operators, panels  # lazy: keeps this file bpy-free
    return (operators, panels)


def register():
    if _registered:  # register() twice without unregister(): start clean
        unregister()
    try:
        for mod in _ui_modules():
            mod.register()
            _registered.append(mod)
    except Exception:
        unregister()
        raise


def unregister():
    while _registered:
        _registered.pop().unregister()
