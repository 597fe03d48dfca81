"""Morph-target animated .glb files made with Blender, the kind engines ship (three.js' Horse,
Flamingo, Parrot): one mesh whose every keyed frame is a shape key (glTF morph target) played by
its weights, with UV seams, hard edges, vertex colours and a material, written by Blender's own
glTF exporter.

Frames come from a posed rig (the shared data's ``vertices``/``faces``/``displacements``, poses of
a true skeleton) or from a generated vertex animation (:func:`wave_tube`: a bending tube that also
breathes, so part of its motion is no articulation at all). The hand-off tests and
``benchmarks/handoff.py`` use these files.

Works with the ``bpy`` module (4.5 LTS, 5.2 LTS); numpy only otherwise.
"""
from __future__ import annotations

import math

import numpy as np

#: frames between two keys of the morph animation (three.js' Horse: one key per frame of a 30 fps clip)
KEY_STEP = 1


def rig_cycle(vertices, joints, parents, weights, n_frames=30, amplitude=0.45, seed=0):
    """A looping clip of a true skeleton: ``displacements (P, N, 3)`` of ``vertices (N, 3)``
    skinned (linear blend, ``weights (N, J)``) to bones with heads ``joints (J, 3)`` and
    ``parents (J,)`` (−1: root), each bone turning about its head by up to ``amplitude`` radians
    about its own random axis, on a sine of the cycle with its own phase (a walk or a wing beat:
    every frame a mix of a few smooth motions), the root also bobbing by 2 % of the size."""
    from scipy.spatial.transform import Rotation
    rng = np.random.default_rng(seed)
    x0 = np.asarray(vertices, dtype=np.float64)
    joints = np.asarray(joints, dtype=np.float64)
    J = len(joints)
    axes = rng.normal(size=(J, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    phase = rng.uniform(0, 2 * math.pi, J)
    harmonic = rng.integers(1, 3, J)
    size = float(np.linalg.norm(np.ptp(x0, axis=0)))
    order = _root_first(parents)
    out = []
    for p in range(n_frames):
        t = 2 * math.pi * p / n_frames
        ang = amplitude * np.sin(harmonic * t + phase)
        Rl = Rotation.from_rotvec(axes * ang[:, None]).as_matrix()
        R = np.zeros((J, 3, 3))
        T = np.zeros((J, 3))
        for j in order:             # bones, not vertices
            tl = joints[j] - Rl[j] @ joints[j]
            if parents[j] < 0:
                R[j], T[j] = Rl[j], tl + np.array([0.0, 0.0, 0.02 * size * math.sin(2 * t)])
            else:
                q = parents[j]
                R[j], T[j] = R[q] @ Rl[j], R[q] @ tl + T[q]
        moved = np.einsum("nj,jab,nb->na", weights, R, x0) + weights @ T
        out.append(moved - x0)
    return np.array(out)


def _root_first(parents):
    order, todo = [], list(np.flatnonzero(np.asarray(parents) < 0))
    while todo:
        j = int(todo.pop(0))
        order.append(j)
        todo.extend(np.flatnonzero(np.asarray(parents) == j))
    return order


def wave_tube(n_frames=24, sides=16, rings=33, seed=0, swell=0.15):
    """A generated vertex animation: ``(vertices (N, 3), faces (T, 3), displacements (P, N, 3))``.

    A closed tube 4 units tall bends along a smooth curve that travels up it (a tail or a neck:
    every ring turns a little, so it is a chain of many small joints) and flexes, its
    cross-section squashed into an oval by up to ``swell`` where a second wave passes (no rigid
    motion of a ring explains that part)."""
    rng = np.random.default_rng(seed)
    z = np.linspace(0.0, 4.0, rings)
    ang = np.arange(sides) * 2 * math.pi / sides
    ring = np.stack([0.3 * np.cos(ang), 0.3 * np.sin(ang)], axis=1)
    verts = np.concatenate([np.column_stack([ring, np.full(sides, zz)]) for zz in z]
                           + [np.array([[0, 0, 0.0], [0, 0, 4.0]])])
    r, s = np.meshgrid(np.arange(rings - 1), np.arange(sides), indexing="ij")
    a, b = r * sides + s, r * sides + (s + 1) % sides
    c, d = (r + 1) * sides + (s + 1) % sides, (r + 1) * sides + s
    quads = np.stack([a, b, c, d], axis=-1).reshape(-1, 4)
    tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    bottom, top = len(verts) - 2, len(verts) - 1
    cap0 = np.column_stack([np.full(sides, bottom), (np.arange(sides) + 1) % sides, np.arange(sides)])
    last = (rings - 1) * sides
    cap1 = np.column_stack([np.full(sides, top), last + np.arange(sides), last + (np.arange(sides) + 1) % sides])
    faces = np.concatenate([tris, cap0, cap1]).astype(np.int64)
    phase = rng.uniform(0, 2 * math.pi)
    poses = []
    for p in range(n_frames):
        t = 2 * math.pi * p / n_frames
        # bend: curvature along the height, a travelling wave; integrate the angle up the tube
        zz = verts[:, 2]
        h = np.linspace(0.0, 4.0, 200)
        kappa = 0.35 * np.sin(1.3 * h - t + phase)
        theta = np.concatenate([[0.0], np.cumsum(0.5 * (kappa[1:] + kappa[:-1]) * np.diff(h))])
        cx = np.concatenate([[0.0], np.cumsum(np.sin(0.5 * (theta[1:] + theta[:-1])) * np.diff(h))])
        cz = np.concatenate([[0.0], np.cumsum(np.cos(0.5 * (theta[1:] + theta[:-1])) * np.diff(h))])
        th, x0, z0 = (np.interp(zz, h, v) for v in (theta, cx, cz))
        phi = np.arctan2(verts[:, 1], verts[:, 0])
        grow = 1.0 + swell * np.sin(2.0 * zz + 2 * t) * np.cos(2 * phi)
        lx, ly = verts[:, 0] * grow, verts[:, 1] * grow
        pos = np.column_stack([x0 + lx * np.cos(th), ly, z0 - lx * np.sin(th)])
        poses.append(pos - verts)
    return verts, faces, np.array(poses)


def write_morph_glb(path, vertices, faces, displacements, name="Creature", key_step=KEY_STEP,
                    sharp_angle=45.0, normals=True):
    """Write ``path``: a morph-target animation of the mesh ``vertices (N, 3)``, ``faces (T, 3)``
    whose frame ``p`` (at frame 1 + p·key_step) is the rest plus ``displacements[p]``.

    The mesh is smooth shaded with edges sharper than ``sharp_angle`` degrees marked sharp (hard
    edges: the exporter splits normals there), UV islands from Smart UV Project (seams), a vertex
    colour per vertex and one material; each frame one shape key, its value keyed 1 at its frame
    and 0 at the frames next to it. ``normals=False`` writes no normals (as three.js' Horse: glTF
    viewers then shade every face flat). Returns (vertices in the file, keyed frames)."""
    import bpy
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    v = np.asarray(vertices, dtype=np.float64)
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(v.tolist(), [], np.asarray(faces).tolist())
    mesh.validate()
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(obj)
    bpy.context.view_layer.objects.active = obj
    obj.select_set(True)
    # hard edges and UV seams
    with bpy.context.temp_override(active_object=obj, object=obj, selected_objects=[obj],
                                   selected_editable_objects=[obj]):
        bpy.ops.object.shade_smooth()
        bpy.ops.object.mode_set(mode='EDIT')
        bpy.ops.mesh.select_all(action='SELECT')
        bpy.ops.uv.smart_project(angle_limit=math.radians(66.0), island_margin=0.01)
        bpy.ops.mesh.select_all(action='DESELECT')
        bpy.ops.mesh.edges_select_sharp(sharpness=math.radians(sharp_angle))
        bpy.ops.mesh.mark_sharp()
        bpy.ops.object.mode_set(mode='OBJECT')
    # a colour per vertex (by height) and a material that shows it
    lo, hi = v.min(axis=0), v.max(axis=0)
    u = (v - lo) / np.maximum(hi - lo, 1e-12)
    col = mesh.color_attributes.new("Col", 'FLOAT_COLOR', 'POINT')
    rgba = np.column_stack([0.3 + 0.7 * u[:, 2], 0.5 * u[:, 0] + 0.2, 1.0 - 0.8 * u[:, 2], np.ones(len(v))])
    col.data.foreach_set("color", rgba.astype(np.float32).ravel())
    mat = bpy.data.materials.new(f"{name}Skin")
    mat.use_nodes = True
    nodes = mat.node_tree.nodes
    bsdf = next(n for n in nodes if n.type == 'BSDF_PRINCIPLED')
    attr = nodes.new("ShaderNodeVertexColor")
    attr.layer_name = col.name
    mat.node_tree.links.new(attr.outputs["Color"], bsdf.inputs["Base Color"])
    mesh.materials.append(mat)
    # one shape key a frame, played one after the other
    obj.shape_key_add(name="Basis", from_mix=False)
    n = len(v)
    frames = []
    for p, d in enumerate(np.asarray(displacements, dtype=np.float64)):
        kb = obj.shape_key_add(name=f"frame_{p:03d}", from_mix=False)
        kb.data.foreach_set("co", (v + d).astype(np.float32).ravel())
        frames.append(1 + p * key_step)
    keys = mesh.shape_keys.key_blocks
    for p, f in enumerate(frames):
        kb = keys[p + 1]
        for g, val in ((f - key_step, 0.0), (f, 1.0), (f + key_step, 0.0)):
            if frames[0] <= g <= frames[-1]:
                kb.value = val
                kb.keyframe_insert("value", frame=g)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = frames[0], frames[-1]
    assert n == len(mesh.vertices)
    result = bpy.ops.export_scene.gltf(filepath=str(path), export_format='GLB',
                                       export_normals=normals, export_morph_normal=False)
    assert result == {'FINISHED'}, result
    return n, frames


def read_back(path):
    """The one mesh of glTF file ``path`` imported by Blender's importer into an empty scene (the
    importer's bone display shape aside)."""
    import bpy
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    assert bpy.ops.import_scene.gltf(filepath=str(path)) == {'FINISHED'}
    shapes = {pb.custom_shape for o in bpy.data.objects if o.type == 'ARMATURE' for pb in o.pose.bones}
    meshes = [o for o in bpy.data.objects if o.type == 'MESH' and o not in shapes]   # not a bone's look
    assert len(meshes) == 1, [o.name for o in bpy.data.objects]
    return meshes[0]


def world_positions(obj, frames):
    """(F, N, 3) evaluated world positions of ``obj`` at ``frames`` and (N, 3) at rest."""
    import bpy
    scene = bpy.context.scene
    out = []
    for f in frames:
        scene.frame_set(f)
        ev = obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
        me = ev.to_mesh()
        co = np.empty(3 * len(me.vertices), dtype=np.float32)
        me.vertices.foreach_get("co", co)
        mw = np.array(ev.matrix_world)
        ev.to_mesh_clear()
        out.append(co.reshape(-1, 3).astype(np.float64) @ mw[:3, :3].T + mw[:3, 3])
    rest = np.empty(3 * len(obj.data.vertices), dtype=np.float32)
    obj.data.vertices.foreach_get("co", rest)
    mw = np.array(obj.matrix_world)
    return np.array(out), rest.reshape(-1, 3) @ mw[:3, :3].T + mw[:3, 3]


def replay_error(source, out, frames):
    """(max, RMS) distance, as fractions of the bounding-box diagonal, between the rig ``out`` and
    the morph animation ``source``, both read back by Blender's glTF importer, at ``frames``;
    vertices matched by rest position (a seam's copies move together)."""
    from scipy.spatial import cKDTree
    ref, ref_rest = world_positions(read_back(source), frames)
    moved, rest = world_positions(read_back(out), frames)
    dist, index = cKDTree(ref_rest).query(rest)
    diag = float(np.linalg.norm(np.ptp(ref_rest, axis=0)))
    assert dist.max() < 1e-4 * diag, "the rig's rest mesh is not the source's"
    err = np.linalg.norm(moved - ref[:, index], axis=-1)
    return float(err.max()) / diag, math.sqrt(float(np.mean(err ** 2))) / diag


def glb_mesh_counts(path):
    """``(meshes, skins, vertices of the first mesh's primitives, morph targets)`` of a .glb,
    read from its JSON chunk."""
    import json
    import struct
    with open(path, "rb") as fh:
        data = fh.read()
    length = struct.unpack_from("<I", data, 12)[0]
    gltf = json.loads(data[20:20 + length])
    meshes = gltf.get("meshes", [])
    prims = meshes[0]["primitives"] if meshes else []
    verts = sum(gltf["accessors"][p["attributes"]["POSITION"]]["count"] for p in prims)
    targets = max((len(p.get("targets", [])) for p in prims), default=0)
    return len(meshes), len(gltf.get("skins", [])), verts, targets
