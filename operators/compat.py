# SPDX-License-Identifier: GPL-3.0-or-later
"""Every difference of Blender's Python API between the supported versions.

Supported: 4.5 LTS (Python 3.11) through 5.3 (Python 3.13); the manifest's
``blender_version_min`` is 4.5.0.  The rest of the add-on calls these functions
and never tests ``bpy.app.version`` itself.  Each difference has a comment
saying which versions behave how (measured with the bpy wheels 4.5.15, 5.0.1,
5.2.3 and 5.3.0, ``benchmarks/blender_matrix.py``).
"""

import bpy

# --------------------------------------------------------------------------
# Actions: slots and channel bags
# --------------------------------------------------------------------------
# 4.4 introduced layered actions (slots, layers, keyframe strips, channel bags);
# 5.0 removed the legacy ``Action.fcurves``/``Action.groups``.  The convenience
# helper ``bpy_extras.anim_utils.action_ensure_channelbag_for_slot`` exists only
# from 5.0 on, and ``ActionChannelbagFCurves.new()`` takes ``group_name=`` only
# from 5.0 on.  What works in 4.5 *and* 5.x: make the layer and keyframe strip
# ourselves, ``strip.channelbag(slot, ensure=True)``, ``bag.fcurves.new(path,
# index=)``, then put the F-Curve into a group made by ``bag.groups.new()``
# (``FCurve.group`` is writable in every supported version).


def _channelbag(action, slot):
    """The channel bag of ``slot`` in ``action``'s first keyframe strip (made if missing)."""
    layer = action.layers[0] if len(action.layers) else action.layers.new("Layer")
    strip = layer.strips[0] if len(layer.strips) else layer.strips.new(type='KEYFRAME')
    return strip.channelbag(slot, ensure=True)


def new_action(id_data, name):
    """Assign a new action named ``name`` to ``id_data``; return ``(action, new_fcurve)``.

    ``new_fcurve(data_path, index, group_name)`` adds an F-Curve in the action's
    slot for ``id_data``, inside the F-Curve group ``group_name``.
    """
    ad = id_data.animation_data or id_data.animation_data_create()
    action = bpy.data.actions.new(name)
    try:
        ad.action = action
        # A fresh action has no slot; assigning one names what it animates.
        slot = ad.action_slot
        if slot is None:
            slot = action.slots.new(id_type=id_data.id_type, name=id_data.name)
            ad.action_slot = slot
        bag = _channelbag(action, slot)
    except BaseException:
        ad.action = None
        bpy.data.actions.remove(action)
        raise
    groups = {}

    def new_fcurve(data_path, index, group_name):
        fc = bag.fcurves.new(data_path, index=index)
        group = groups.get(group_name)
        if group is None:
            group = groups[group_name] = bag.groups.new(group_name)
        fc.group = group
        return fc

    return action, new_fcurve


# --------------------------------------------------------------------------
# Extension wheels
# --------------------------------------------------------------------------
# 4.5/5.0 embed Python 3.11, 5.1+ Python 3.13.  The zip carries a scipy wheel
# for each; Blender installs the one whose tag matches into
# ``<user>/extensions/.local/lib/python3.X/site-packages``.

def python_tag():
    """``python3.11`` / ``python3.13``: the site-packages directory name of Blender's Python."""
    import sys
    return f"python{sys.version_info[0]}.{sys.version_info[1]}"
