# SPDX-License-Identifier: GPL-3.0-or-later
"""Bones an animator can read.

The fit names its bones ``artdef_link_NN`` in clustering order.  ``artdef.name_bones``
renames them:

* ``TREE``: ``bone_00`` is the root, then the tree depth first (bigger
  branches first), so the numbers read root-first along the skeleton;
* ``SOURCE``: when the scan was sampled from a mesh an armature moved (Fields
  from Animation, an animated file), every bone takes the name of the nearest
  bone of that source armature (fitted bone midpoint to source bone segment,
  one name each by an optimal assignment; a fit with more bones than the source
  adds ``_2``, ``_3``, ... to the nearest name);
* ``AUTO``: ``SOURCE`` when there is a source armature, else ``TREE``;
* ``ONE``: rename one bone (``bone`` -> ``new_name``).

Blender renames the vertex groups of the meshes the armature deforms, the
animation paths and the constraint targets with the bone; the fit's records
(its vertex-group list and per-link figures) and the Green's helper bones
follow here.
"""

import bpy
import numpy as np
from bpy.props import EnumProperty, StringProperty


def tree_order(parents, sizes=None):
    """Link indices root-first, depth first, bigger subtrees first.

    parents: (L,) parent link or -1; sizes: (L,) tie-break weight (e.g. triangles).
    """
    parents = [int(p) for p in parents]
    n = len(parents)
    sizes = np.ones(n) if sizes is None else np.asarray(sizes, dtype=np.float64)
    children = {i: [] for i in range(-1, n)}
    for i, p in enumerate(parents):
        children[p if 0 <= p < n else -1].append(i)
    subtree = np.zeros(n)

    def weight(i):
        if subtree[i] == 0:
            subtree[i] = sizes[i] + sum(weight(c) for c in children[i])
        return subtree[i]
    order, stack = [], sorted(children[-1], key=lambda i: (-weight(i), i))[::-1]
    while stack:
        i = stack.pop()
        order.append(i)
        stack.extend(sorted(children[i], key=lambda c: (-weight(c), c))[::-1])
    return order


def _deform_bones(arm):
    return [b for b in arm.data.bones if b.use_deform]


def _bone_tree(arm):
    """(names, parents) of the deforming bones."""
    bones = _deform_bones(arm)
    names = [b.name for b in bones]
    index = {n: i for i, n in enumerate(names)}
    parents = [index.get(b.parent.name, -1) if b.parent is not None else -1 for b in bones]
    return names, parents


def source_armature(mesh_obj):
    """The armature that moved the object the scan was sampled from, or None."""
    src = bpy.data.objects.get(str(mesh_obj.data.get("artdef_source", "")))
    if src is None or src.type != 'MESH':
        return None
    for mod in src.modifiers:
        if mod.type == 'ARMATURE' and mod.object is not None:
            return mod.object
    return None


def tree_names(arm):
    """New names for the deforming bones: ``bone_NN`` root-first."""
    names, parents = _bone_tree(arm)
    order = tree_order(parents)
    width = max(2, len(str(len(names) - 1)))
    return {names[i]: f"bone_{rank:0{width}d}" for rank, i in enumerate(order)}


def _segment_distance(points, heads, tails):
    """(P, S) distance from each point to each segment head-tail."""
    d = tails - heads                                            # (S, 3)
    t = np.einsum("psk,sk->ps", points[:, None] - heads[None], d) / np.maximum(
        np.einsum("sk,sk->s", d, d), 1e-30)
    closest = heads[None] + np.clip(t, 0.0, 1.0)[..., None] * d[None]
    return np.linalg.norm(points[:, None] - closest, axis=-1)


def source_names(arm, source):
    """New names for the deforming bones after the nearest bone of ``source``
    (world space: each fitted bone's midpoint to each source bone's segment),
    one source name per bone where possible (an optimal assignment); bones
    beyond the source's count take their nearest name with ``_2``, ``_3``, ..."""
    from scipy.optimize import linear_sum_assignment
    names, parents = _bone_tree(arm)
    src = [b for b in source.data.bones if b.use_deform] or list(source.data.bones)

    def world(ob, bones):
        mw = np.array(ob.matrix_world)
        h = np.array([b.head_local for b in bones]) @ mw[:3, :3].T + mw[:3, 3]
        t = np.array([b.tail_local for b in bones]) @ mw[:3, :3].T + mw[:3, 3]
        return h, t
    sh, stl = world(source, src)
    fh, ft = world(arm, [arm.data.bones[n] for n in names])
    dist = _segment_distance(0.5 * (fh + ft), sh, stl)           # (L, S)
    rows, cols = linear_sum_assignment(dist)
    pick = {int(r): int(c) for r, c in zip(rows, cols)}
    out, used = {}, set()
    for i in tree_order(parents):
        base = src[pick[i] if i in pick else int(np.argmin(dist[i]))].name
        name, k = base, 2
        while name in used:
            name, k = f"{base}_{k}", k + 1
        used.add(name)
        out[names[i]] = name
    return out


def rename_bones(mesh_obj, arm, mapping):
    """Rename bones ``old -> new`` (vertex groups, animation, constraints and the
    fit's records follow).  Two passes, so names may swap."""
    # Blender keeps at most 63 bytes of a name (UTF-8): cut there, on a character boundary, so the
    # fit's records hold the names Blender shows
    mapping = {o: n.encode("utf-8")[:63].decode("utf-8", errors="ignore") for o, n in mapping.items()}
    mapping = {o: n for o, n in mapping.items() if o != n and o in arm.data.bones}
    if not mapping:
        return {}
    # a Green's rig: the helper bone of a link keeps following its link's name
    helpers = {}
    for old in mapping:
        h = arm.data.bones.get(old + "_load")
        if h is not None and not h.use_deform:
            helpers[h.name] = mapping[old] + "_load"
    full = {**mapping, **helpers}
    taken = {b.name for b in arm.data.bones} - set(full)
    clash = [n for n in full.values() if n in taken]
    if clash:
        raise ValueError(f"bone name {clash[0]!r} is already used")
    # a bone deforms through the mesh's vertex group of its name: one of the user's own groups
    # must not be taken over (nor removed with the rig later)
    ours = {item.name for item in mesh_obj.artdef.groups}
    users = [n for n in mapping.values() if n in mesh_obj.vertex_groups and n not in ours]
    if users:
        raise ValueError(f"{users[0]!r} is a vertex group of the mesh that the fit did not make; "
                         "choose another name")
    temp = {}
    for i, old in enumerate(full):
        arm.data.bones[old].name = f"__artdef_tmp_{i}"
        temp[f"__artdef_tmp_{i}"] = full[old]
    for t, new in temp.items():
        arm.data.bones[t].name = new
    # records of the fit
    st = mesh_obj.artdef
    for item in st.groups:
        item.name = mapping.get(item.name, item.name)
    for item in st.fit_link_stats:
        item.name = mapping.get(item.name, item.name)
    return mapping


def name_bones(mesh_obj, arm, scheme='AUTO'):
    """Apply a naming scheme ('TREE', 'SOURCE', 'AUTO'); returns the mapping used."""
    source = source_armature(mesh_obj) if scheme in ('SOURCE', 'AUTO') else None
    if scheme == 'SOURCE' and source is None:
        raise ValueError("the scan was not sampled from an armature-driven mesh")
    mapping = source_names(arm, source) if source is not None else tree_names(arm)
    return rename_bones(mesh_obj, arm, mapping)


class ARTDEF_OT_name_bones(bpy.types.Operator):
    """Rename the fitted bones so an animator can read them: numbered root-first along the tree, or after the nearest joint of the source armature; or rename one bone. Vertex groups, animation and the fit's records follow"""
    bl_idname = "artdef.name_bones"
    bl_label = "Name Bones"
    bl_options = {'REGISTER', 'UNDO'}

    scheme: EnumProperty(
        name="Names", default='AUTO',
        items=(('AUTO', "Auto", "After the source armature's joints when there is one, "
                                "else numbered root-first"),
               ('TREE', "Root First", "bone_00 is the root, then along the tree"),
               ('SOURCE', "Source Joints", "The name of the nearest joint of the armature "
                                           "that moved the source"),
               ('ONE', "One Bone", "Rename the bone named in Bone to New Name")),
        description="How the bones are named")
    bone: StringProperty(name="Bone", description="One Bone: its current name")
    new_name: StringProperty(name="New Name", description="One Bone: its new name")

    @classmethod
    def poll(cls, context):
        from .export import poll_rig
        return poll_rig(cls, context) is not None

    def execute(self, context):
        from .export import rig_parts
        mesh_obj, arm = rig_parts(context.active_object)
        try:
            if self.scheme == 'ONE':
                if self.bone not in arm.data.bones:
                    raise ValueError(f"'{arm.name}' has no bone {self.bone!r}")
                if not self.new_name.strip():
                    raise ValueError("New Name is empty")
                mapping = rename_bones(mesh_obj, arm, {self.bone: self.new_name.strip()[:63]})
            else:
                mapping = name_bones(mesh_obj, arm, self.scheme)
        except ValueError as err:
            self.report({'ERROR'}, str(err))
            return {'CANCELLED'}
        shown = ", ".join(f"{o} -> {n}" for o, n in list(mapping.items())[:4])
        self.report({'INFO'}, f"'{arm.name}': {len(mapping)} bones renamed"
                              + (f" ({shown}{', ...' if len(mapping) > 4 else ''})" if shown else ""))
        return {'FINISHED'}


classes = (ARTDEF_OT_name_bones,)


# Blender's own helper: registers in order, unregisters in reverse
register, unregister = bpy.utils.register_classes_factory(classes)


__all__ = ["tree_order", "name_bones", "rename_bones", "source_names", "tree_names"]
