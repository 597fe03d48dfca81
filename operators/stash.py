# SPDX-License-Identifier: GPL-3.0-or-later
"""A re-fit's transaction: the previous rig set aside while the new one is built, then put back
(a failed build) or removed (a finished one); and the datablock snapshot that lets a failed
build remove everything it made.
"""

import bpy
from mathutils import Matrix

from .attributes import set_active_colour
from .names import COLOR_ATTR, MODIFIER_NAME, RESIDUAL_ATTR, RESIDUAL_COLOR_ATTR, STASH_PREFIX
from .rig import _remove_object, _restore_frame_range, owns_rig


_RECORD = ("made_basis", "key_action", "key_action_previous", "old_parent", "old_parent_type",
           "old_parent_bone", "old_parent_inverse", "set_frame_range", "replay_frame_range",
           "old_frame_range", "has_fit")
_TRANSFORM = ("location", "rotation_mode", "rotation_euler", "rotation_quaternion",
              "rotation_axis_angle", "scale")


def _copy(value):
    if isinstance(value, (str, bpy.types.ID)) or value is None:
        return value
    return tuple(value) if hasattr(value, "__len__") else value


def _stash_name(name):
    return STASH_PREFIX + name


class RigStash:
    """What :func:`stash_rig` set aside: the previous rig (or Preview Links' colours), renamed
    out of the new build's way; :func:`restore_rig` puts it back, :func:`drop_stash` removes it."""

    def __init__(self, obj):
        self.obj = obj
        self.record = {}
        self.rig = None
        self.owned = False
        self.ids = []              # (ID, its name): the previous rig's datablocks, renamed
        self.groups = []           # (temporary name, name) of vertex groups
        self.keys = []             # (temporary name, name) of shape keys
        self.tracks = []           # (temporary name, name) of the shape keys' clip tracks
        self.attrs = []            # (temporary name, name) of colour / residual attributes
        self.modifier = None       # (temporary name, index)
        self.parent = None         # (parent, type, bone, parent inverse, transform)
        self.frames = None         # the scene and its (start, end)
        self.key_action = None     # (action, slot) the shape keys played
        self.key_animdata = False  # the shape keys had animation data
        self.active = None         # (active group, active shape key, active attribute,
                                   #  active colour, render colour index)


def _rig_ids(arm):
    """The datablocks of ArtDef armature ``arm``: itself, its data, its load empties and the
    actions they play (their own, as the Clear Rig removes them)."""
    out = [arm]
    if arm.data is not None:
        out.append(arm.data)
    for ob in [arm] + [c for c in arm.children if c.get("artdef_load") is not None]:
        if ob is not arm:
            out.append(ob)
        ad = ob.animation_data
        if ad is None:
            continue
        for action in [ad.action] + [s.action for t in ad.nla_tracks for s in t.strips]:
            if action is not None and action.get("artdef_made") and action not in out:
                out.append(action)    # once: the active action is also a clip's strip
    return out


def stash_rig(obj, scene):
    """Set aside what a fit of ``obj`` would replace — the previous rig, or the link colours of
    Preview Links — so that a failed build can put it back (:func:`restore_rig`) and a finished
    one removes it (:func:`drop_stash`). Afterwards ``obj`` looks unfitted to :func:`build_rig`:
    the previous rig's pieces are renamed out of the way (``STASH_PREFIX``), the mesh is parented
    as before the previous fit and the scene has its frame range back; nothing is deleted."""
    st, mesh = obj.artdef, obj.data
    stash = RigStash(obj)
    stash.record = {name: _copy(getattr(st, name)) for name in _RECORD}
    stash.record["groups"] = [item.name for item in st.groups]
    stash.record["shape_keys"] = [item.name for item in st.shape_keys]
    colours = mesh.color_attributes
    stash.active = (obj.vertex_groups.active_index, obj.active_shape_key_index,
                    mesh.attributes.active.name if mesh.attributes.active is not None else None,
                    colours.active_color.name if colours.active_color is not None else None,
                    colours.render_color_index)
    if scene is not None:
        stash.frames = (scene, scene.frame_start, scene.frame_end)
        _restore_frame_range(st, scene)
    # parent: as clear_rig leaves it (the new armature copies the mesh's parent and transform)
    arm = st.rig
    stash.rig = arm
    if arm is not None and obj.parent == arm:
        stash.parent = (obj.parent, obj.parent_type, obj.parent_bone, obj.matrix_parent_inverse.copy(),
                        {name: _copy(getattr(obj, name)) for name in _TRANSFORM})
        world = obj.matrix_world.copy()
        obj.parent = st.old_parent
        if st.old_parent is not None:
            obj.parent_type = st.old_parent_type or 'OBJECT'
            if st.old_parent_bone:
                obj.parent_bone = st.old_parent_bone
            obj.matrix_parent_inverse = Matrix([st.old_parent_inverse[i * 4:i * 4 + 4] for i in range(4)])
        else:
            obj.matrix_parent_inverse = Matrix.Identity(4)
        obj.matrix_world = world
    mod = obj.modifiers.get(MODIFIER_NAME)
    if mod is not None:
        index = list(obj.modifiers).index(mod)
        mod.name = _stash_name(MODIFIER_NAME)
        stash.modifier = (mod.name, index)
    stash.owned = owns_rig(obj, arm)
    if stash.owned:   # a duplicate's rig is the original's: it stays as it is
        for db in _rig_ids(arm):
            stash.ids.append((db, db.name))
            db.name = _stash_name(db.name)
    for name in stash.record["groups"]:
        vg = obj.vertex_groups.get(name)
        if vg is not None:
            vg.name = _stash_name(name)
            stash.groups.append((vg.name, name))
    keys = mesh.shape_keys
    if keys is not None:
        ad = keys.animation_data
        stash.key_animdata = ad is not None
        if ad is not None:
            stash.key_action = (ad.action, getattr(ad, "action_slot", None))
            if st.key_action is not None and ad.action == st.key_action:
                ad.action = st.key_action_previous   # the action the new replay will record
            made = [st.key_action] if st.key_action is not None else []
            for track in ad.nla_tracks:
                actions = [s.action for s in track.strips]
                if actions and all(a is not None and a.get("artdef_made") for a in actions):
                    name = track.name
                    track.name = _stash_name(name)
                    stash.tracks.append((track.name, name))
                    made += [a for a in actions if a not in made]
            for action in made:      # the replay's shape-key actions: out of the new ones' names
                if action.get("artdef_made") and all(action is not db for db, _ in stash.ids):
                    stash.ids.append((action, action.name))
                    action.name = _stash_name(action.name)
        for name in stash.record["shape_keys"]:
            kb = keys.key_blocks.get(name)
            if kb is not None:
                kb.name = _stash_name(name)     # Blender renames the drivers' and actions' paths too
                stash.keys.append((kb.name, name))
    for name in (COLOR_ATTR, RESIDUAL_COLOR_ATTR, RESIDUAL_ATTR):
        attr = mesh.attributes.get(name)
        if attr is not None:
            attr.name = _stash_name(name)
            stash.attrs.append((attr.name, name))
    st.rig = None
    st.old_parent = None
    st.old_parent_bone = ""
    st.groups.clear()
    st.shape_keys.clear()
    st.key_action = None
    st.key_action_previous = None
    st.made_basis = False
    st.has_fit = False
    return stash


def _names_back(collection, renamed):
    """Give the items of a Blender ``collection`` their names back: ``renamed`` holds (temporary
    name, name) pairs of :func:`stash_rig` (an item since removed is passed over)."""
    for tmp, name in renamed:
        item = collection.get(tmp)
        if item is not None:
            item.name = name


def restore_rig(stash):
    """Put back what :func:`stash_rig` set aside, after the new build's pieces were removed
    (:func:`clear_rig` and :func:`remove_new_datablocks`)."""
    obj = stash.obj
    st, mesh = obj.artdef, obj.data
    for db, name in stash.ids:
        db.name = name
    _names_back(obj.vertex_groups, stash.groups)
    keys = mesh.shape_keys
    if keys is not None:
        _names_back(keys.key_blocks, stash.keys)
        ad = keys.animation_data
        if ad is not None:
            _names_back(ad.nla_tracks, stash.tracks)
            if stash.key_action is not None:
                action, slot = stash.key_action
                ad.action = action
                if slot is not None and getattr(ad, "action_slot", None) != slot:
                    ad.action_slot = slot
            elif (not stash.key_animdata and ad.action is None and not len(ad.drivers)
                  and not len(ad.nla_tracks)):
                keys.animation_data_clear()
    _names_back(mesh.attributes, stash.attrs)
    if stash.modifier is not None:
        mod = obj.modifiers.get(stash.modifier[0])
        if mod is not None:
            mod.name = MODIFIER_NAME
            index = list(obj.modifiers).index(mod)
            target = min(stash.modifier[1], len(obj.modifiers) - 1)
            if index != target:
                obj.modifiers.move(index, target)
    if stash.parent is not None:
        parent, parent_type, bone, inverse, transform = stash.parent
        obj.parent = parent
        obj.parent_type = parent_type
        if bone:
            obj.parent_bone = bone
        obj.matrix_parent_inverse = inverse
        for name, value in transform.items():
            setattr(obj, name, value)
    st.rig = stash.rig
    for name in _RECORD:
        setattr(st, name, stash.record[name])
    st.groups.clear()
    for name in stash.record["groups"]:
        st.groups.add().name = name
    st.shape_keys.clear()
    for name in stash.record["shape_keys"]:
        st.shape_keys.add().name = name
    group, key, attribute, colour, render = stash.active
    obj.vertex_groups.active_index = group
    obj.active_shape_key_index = key
    if attribute is not None and mesh.attributes.get(attribute) is not None:
        mesh.attributes.active = mesh.attributes[attribute]
    if colour is not None:
        set_active_colour(mesh, colour)
    if render < len(mesh.color_attributes):
        mesh.color_attributes.render_color_index = render
    if stash.frames is not None:
        scene, start, end = stash.frames
        if start > scene.frame_end:
            scene.frame_end = end
            scene.frame_start = start
        else:
            scene.frame_start = start
            scene.frame_end = end


def drop_stash(stash):
    """Remove what :func:`stash_rig` set aside, once the new rig is built."""
    obj = stash.obj
    st, mesh = obj.artdef, obj.data
    if stash.modifier is not None:
        mod = obj.modifiers.get(stash.modifier[0])
        if mod is not None:
            obj.modifiers.remove(mod)
    if stash.owned and stash.rig is not None:
        arm = stash.rig
        for child in list(arm.children):
            if child.get("artdef_load") is not None:
                _remove_object(child)
        _remove_object(arm)
    for tmp, _ in stash.groups:
        vg = obj.vertex_groups.get(tmp)
        if vg is not None:
            obj.vertex_groups.remove(vg)
    keys = mesh.shape_keys
    actions = [stash.record["key_action"]] if stash.record.get("key_action") is not None else []
    if keys is not None:
        ad = keys.animation_data
        if ad is not None:
            for tmp, _ in stash.tracks:
                track = ad.nla_tracks.get(tmp)
                if track is not None:
                    actions += [s.action for s in track.strips if s.action is not None]
                    ad.nla_tracks.remove(track)
            paths = {f'key_blocks["{tmp}"].value' for tmp, _ in stash.keys}
            for fc in list(ad.drivers):
                if fc.data_path in paths:
                    ad.drivers.remove(fc)
        for tmp, _ in stash.keys:
            kb = keys.key_blocks.get(tmp)
            if kb is not None:
                obj.shape_key_remove(kb)
    if stash.record.get("made_basis"):
        st.made_basis = True      # the previous fit's Basis is the new rig's now
    for action in {a.session_uid: a for a in actions}.values():   # the previous replay's
        if action.users == 0 and action.get("artdef_made"):
            bpy.data.actions.remove(action)
    for tmp, _ in stash.attrs:
        attr = mesh.attributes.get(tmp)
        if attr is not None:
            mesh.attributes.remove(attr)


# --------------------------------------------------------------------------
# datablocks: a failed build leaves none behind
# --------------------------------------------------------------------------

#: ID collections of ``bpy.data`` that a rig build could never create and that
#: must not be touched (the UI's own).
_UI_COLLECTIONS = {"window_managers", "screens", "workspaces", "libraries"}


def id_collections():
    """Names of every ``bpy.data`` collection of datablocks (objects, meshes,
    armatures, actions, images, texts, shape_keys, ...), read from RNA so that
    a collection added by a later Blender is counted too."""
    names = []
    for prop in bpy.data.bl_rna.properties:
        if prop.type != 'COLLECTION':
            continue
        rna = prop.fixed_type
        while rna is not None and rna.identifier != "ID":
            rna = rna.base
        if rna is not None:
            names.append(prop.identifier)
    return names


def datablock_snapshot():
    """``{collection: set of session_uid}`` of every datablock now in ``bpy.data``."""
    return {name: {db.session_uid for db in getattr(bpy.data, name)}
            for name in id_collections() if name not in _UI_COLLECTIONS}


def remove_new_datablocks(before):
    """Remove every datablock not in snapshot ``before``; return their names."""
    new = []
    for name, uids in before.items():
        new += [db for db in getattr(bpy.data, name) if db.session_uid not in uids]
    names = [f"{db.__class__.__name__} '{db.name}'" for db in new]
    if new:
        bpy.data.batch_remove(new)
    return names

