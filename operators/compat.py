# SPDX-License-Identifier: GPL-3.0-or-later
"""Version-dependent Blender API used by the hand-off code (reading actions,
exporter options).  The ``blender`` branch (#14) owns this module; these are
the functions the export / animated-file code needs, each with the difference
it hides.  The merge unifies them with that branch's functions.
"""

import bpy


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
