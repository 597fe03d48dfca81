# SPDX-License-Identifier: GPL-3.0-or-later
"""Register a module's classes together with its File menu entry (import or export)."""

import bpy


def registration(classes, menu: str, entry, after_unregister=None):
    """``(register, unregister)`` for ``classes`` and the draw function ``entry`` appended to the menu
    type named ``menu`` (e.g. ``"TOPBAR_MT_file_import"``); ``after_unregister`` runs last."""
    register_classes, unregister_classes = bpy.utils.register_classes_factory(classes)

    def register():
        register_classes()
        getattr(bpy.types, menu).append(entry)

    def unregister():
        getattr(bpy.types, menu).remove(entry)
        unregister_classes()
        if after_unregister is not None:
            after_unregister()

    return register, unregister
