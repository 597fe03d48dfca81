# SPDX-License-Identifier: GPL-3.0-or-later
"""Every difference of Blender's Python API between the supported versions.

Supported: 4.5 LTS (Python 3.11) through 5.3 (Python 3.13); the manifest's
``blender_version_min`` is 4.5.0.  The rest of the add-on calls these functions
and never tests ``bpy.app.version`` itself.  Each difference has a comment
saying which versions behave how (measured with the bpy wheels 4.5.15, 5.0.1,
5.2.3 and 5.3.0, ``benchmarks/blender_matrix.py``).  A few functions keep a
4.2/4.3 fallback (legacy actions) although 4.5 is the minimum: harmless, and
an installed copy never reaches it.
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

# --------------------------------------------------------------------------
# Reading the F-Curves of an action
# --------------------------------------------------------------------------
# 4.2/4.3: legacy actions, ``Action.fcurves``.  4.4+: layered actions (slots,
# layers, keyframe strips, channel bags) with ``Action.fcurves`` still there
# as a proxy of the first slot; 5.0 removed ``Action.fcurves``.  Reading every
# channel bag of every keyframe strip works from 4.4 on; older actions fall
# back to ``Action.fcurves``.

def action_fcurves(action):
    """Every F-Curve of ``action`` (all slots, all layers)."""
    layers = getattr(action, "layers", None)
    if layers is not None and len(layers):
        out = []
        for layer in layers:
            for strip in layer.strips:
                for bag in getattr(strip, "channelbags", ()):
                    out.extend(bag.fcurves)
        return out
    legacy = getattr(action, "fcurves", None)
    return list(legacy) if legacy is not None else []


def slot_fcurves(action, slot):
    """F-Curves of ``action`` that animate ``slot`` (all F-Curves on 4.2/4.3,
    whose actions have no slots)."""
    layers = getattr(action, "layers", None)
    if slot is None or layers is None or not len(layers):
        return action_fcurves(action)
    out = []
    for layer in layers:
        for strip in layer.strips:
            bag = strip.channelbag(slot) if hasattr(strip, "channelbag") else None
            if bag is not None:
                out.extend(bag.fcurves)
    return out


def keyed_frames(action, slot=None):
    """Sorted frames (float) at which ``action`` (``slot``'s channels if given) has keys."""
    frames = set()
    for fc in (action_fcurves(action) if slot is None else slot_fcurves(action, slot)):
        n = len(fc.keyframe_points)
        if n:
            co = [0.0] * (2 * n)
            fc.keyframe_points.foreach_get("co", co)
            frames.update(co[0::2])
    return sorted(frames)


def assign_action(id_data, action):
    """Make ``action`` the active action of ``id_data`` (4.4+: also its slot for
    this ID: the first slot of the right ID type, or the one Blender picks)."""
    ad = id_data.animation_data or id_data.animation_data_create()
    ad.action = action
    if action is not None and hasattr(ad, "action_slot") and ad.action_slot is None:
        slots = [s for s in getattr(action, "slots", ()) if s.target_id_type == id_data.id_type]
        if slots:
            ad.action_slot = slots[0]


# --------------------------------------------------------------------------
# Exporter options
# --------------------------------------------------------------------------
# Blender's glTF exporter: ``export_vertex_color`` (enum, 4.2+ adds 'NONE';
# older releases had ``export_colors``); FBX: ``colors_type`` (3.x+).  Only the
# options the running exporter knows are passed.

def supported_options(op, options):
    """``options`` without the keys the operator ``op`` (e.g.
    ``bpy.ops.export_scene.gltf``) does not have in this Blender."""
    names = {p.identifier for p in op.get_rna_type().properties}
    return {k: v for k, v in options.items() if k in names}


def gltf_tracks_drop_armature_node():
    """Whether the glTF exporter's NLA Tracks mode (one animation per clip) works
    with ``export_armature_object_remove`` (no armature node, so the validator has
    no NODE_SKINNED_MESH_NON_ROOT warning).  4.5.15 and 5.0.1 fail there
    (``UnboundLocalError: 'animation'`` in ``anim_utils.bake_animation``: they
    read the NLA tracks of armatures they do not export, e.g. the hidden
    source's); 5.1.2, 5.2.3 and 5.3.0 export it."""
    return bpy.app.version >= (5, 1, 0)


def remove_fcurve(action, fcurve):
    """Remove ``fcurve`` from ``action``.  4.4+: from the channel bag holding it
    (5.0 has no ``Action.fcurves``); 4.2/4.3: ``Action.fcurves.remove``."""
    layers = getattr(action, "layers", None)
    if layers is not None and len(layers):
        for layer in layers:
            for strip in layer.strips:
                for bag in getattr(strip, "channelbags", ()):
                    for fc in bag.fcurves:
                        if fc == fcurve:
                            bag.fcurves.remove(fc)
                            return
        return
    action.fcurves.remove(fcurve)


# --------------------------------------------------------------------------
# NLA
# --------------------------------------------------------------------------
# 4.4+: an NLA strip plays one slot of its action (``NlaStrip.action_slot``);
# it is picked automatically only when the slot's name matches the ID.  4.2:
# no slots.

def nla_clip_track(id_data, name, action, start):
    """A muted NLA track ``name`` on ``id_data`` holding ``action`` from frame
    ``start`` (how Blender's glTF importer stores a file's animations; the glTF
    exporter's NLA Tracks mode writes one animation per track name)."""
    ad = id_data.animation_data or id_data.animation_data_create()
    track = ad.nla_tracks.new()
    track.name = name
    strip = track.strips.new(name, int(start), action)
    if hasattr(strip, "action_slot") and strip.action_slot is None:
        slots = [s for s in getattr(action, "slots", ()) if s.target_id_type == id_data.id_type]
        if slots:
            strip.action_slot = slots[0]
    track.mute = True
    return track


# --------------------------------------------------------------------------
# Process exit
# --------------------------------------------------------------------------
# The bpy 4.5 module (pip ``bpy==4.5.15``) can deadlock at interpreter exit,
# in C++ static destructors, after a glTF import or export (the command line's
# outputs were all written, then the process waited forever).  5.0 and later
# exit normally.  ``python -m artdef_addon`` therefore ends with
# ``os._exit`` after the Python exit handlers when the bpy module was loaded
# (artdef_addon/cli.exit_process, used by artdef_addon/__main__.py and
# scripts/artdef_fit.py: the core cannot import this module).


# --------------------------------------------------------------------------
# File paths relative to the .blend
# --------------------------------------------------------------------------
# Every supported version (4.5.15, 5.0.1, 5.1.2, 5.2.3, 5.3.0) warns
# (``RuntimeWarning: ...filepath: does not support blend relative "//" prefix``)
# when a script sets a FILE_PATH property to ``//...`` and the property does not
# declare ``'PATH_SUPPORTS_BLEND_RELATIVE'``, as bpy_extras' ImportHelper/
# ExportHelper ``filepath`` does not; all of them accept the option.  ArtDef's
# file operators resolve ``//`` themselves (``bpy.path.abspath``), so they
# declare it.

def blend_relative_filepath(description, options=frozenset()):
    """The ``filepath`` property of a file operator that takes ``//`` paths
    (next to the .blend): ImportHelper's/ExportHelper's declaration plus
    ``'PATH_SUPPORTS_BLEND_RELATIVE'`` and ``options``."""
    return bpy.props.StringProperty(name="File Path", description=description, maxlen=1024,
                                    subtype='FILE_PATH',
                                    options={'PATH_SUPPORTS_BLEND_RELATIVE', *options})


# --------------------------------------------------------------------------
# Custom properties
# --------------------------------------------------------------------------
# 5.0 keeps the properties registered with bpy.props (our ``Object.artdef``
# group) apart from user custom properties; in 4.5 ``ID.keys()`` lists them
# too (``'artdef'``).  ``custom_keys`` gives the user's custom properties only.

def custom_keys(id_data):
    """Names of ``id_data``'s custom properties, without add-on-registered ones."""
    registered = id_data.bl_rna.properties
    return [k for k in id_data.keys() if k not in registered]
