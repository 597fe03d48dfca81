"""Helpers of the operator tests (tests/blender/test_op_*.py): scene reading, reference rigs, geometry."""

import dataclasses

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

REL_TOL = 1e-4      # evaluated rig vs the core's model, relative to the displacement
HEAD_TOL = 1e-5     # bone heads vs the core's heads
FPF = 10            # default frames per field of the tracked replay


def import_scan(path):
    assert bpy.ops.artdef.import_scan(filepath=path) == {'FINISHED'}
    obj = bpy.context.view_layer.objects.active
    assert obj is not None and obj.type == 'MESH'
    return obj


def rest_positions(obj):
    co = np.empty(3 * len(obj.data.vertices), dtype=np.float32)
    obj.data.vertices.foreach_get("co", co)
    return co.reshape(-1, 3).astype(np.float64)


def evaluated_positions(obj):
    dg = bpy.context.evaluated_depsgraph_get()
    dg.update()
    ev = obj.evaluated_get(dg)
    mesh = ev.to_mesh()
    try:
        co = np.empty(3 * len(mesh.vertices), dtype=np.float32)
        mesh.vertices.foreach_get("co", co)
    finally:
        ev.to_mesh_clear()
    return co.reshape(-1, 3).astype(np.float64)


def weight_matrix(obj, names):
    w = np.zeros((len(obj.data.vertices), len(names)))
    index = {obj.vertex_groups[n].index: j for j, n in enumerate(names)}
    for v in obj.data.vertices:
        for g in v.groups:
            j = index.get(g.group)
            if j is not None:
                w[v.index, j] = g.weight
    return w


def scene_snapshot():
    """Everything a fit could touch, as comparable plain data."""
    snap = {
        "objects": sorted((o.name, o.type, o.parent.name if o.parent else None,
                           tuple(round(x, 6) for row in o.matrix_world for x in row))
                          for o in bpy.data.objects),
        "armatures": sorted(a.name for a in bpy.data.armatures),
        "actions": sorted(a.name for a in bpy.data.actions),
        "meshes": {},
    }
    for o in bpy.data.objects:
        if o.type == 'MESH':
            keys = o.data.shape_keys
            snap["meshes"][o.name] = {
                "groups": [g.name for g in o.vertex_groups],
                "modifiers": [m.name for m in o.modifiers],
                "keys": [k.name for k in keys.key_blocks] if keys else [],
                "attributes": sorted(a.name for a in o.data.attributes),
                "rest": rest_positions(o).round(6).tobytes(),
                "has_fit": o.artdef.has_fit,
            }
    return snap


def field_model(pkg, result, rest, p):
    """The core's model of tracked field ``p``: the pose ``result.params[p]`` with the residual
    shapes the rig keys (``residuals.rig_shapes``: the principal shapes and their weights in
    field p, or field p's own residual) at their values in that field."""
    shapes, values = pkg.residuals.rig_shapes(result)
    w = np.eye(shapes.shape[0])[p] if values is None else values[p]
    keyed = dataclasses.replace(result, residual=shapes)
    return pkg.model.deform(keyed, rest, result.params[p], w)


def check_rig(pkg, obj, links, n_fields):
    st = obj.artdef
    arm = st.rig
    assert arm is not None and arm.type == 'ARMATURE'
    assert arm.name == f"{obj.name}_artdef_rig"
    result = pkg.ops.last_result(obj)
    assert result is not None and result.n_links == links
    names = [pkg.rig.GROUP_FMT.format(l) for l in range(links)]
    assert sorted(g.name for g in obj.vertex_groups if g.name.startswith("artdef_link_")) == names
    assert [b.name for b in arm.data.bones if b.use_deform] == names
    check_load_helpers(pkg, arm, names, greens=result.kappa is not None)
    keys = obj.data.shape_keys.key_blocks
    # a Green's rig: a first-order key per field (model.greens_keys); a tracked rig: the
    # principal residual shapes the fit kept (residuals.low_rank_basis)
    basis = result.residual_basis
    wanted = n_fields if result.kappa is not None else basis.keys if basis is not None else n_fields
    assert len(keys) == wanted + 1 and keys[0].name == "Basis"
    assert all(k.name.startswith("artdef_field_") for k in keys[1:])
    # bones: heads, tree, rotation mode; world = armature space (identity object transforms)
    for l, name in enumerate(names):
        bone = arm.data.bones[name]
        np.testing.assert_allclose(np.array(arm.matrix_world @ bone.head_local), result.heads[l],
                                   atol=HEAD_TOL)
        # Blender recomputes the frame from head, tail and roll in float32; bones
        # near -Y (a singular direction of its roll formula) differ by ~4e-5.
        np.testing.assert_allclose(np.array(bone.matrix_local.to_3x3()), result.frames[l], atol=1e-4)
        parent = result.parents[l]
        assert (bone.parent.name if bone.parent else None) == (names[parent] if parent >= 0 else None)
        assert not bone.use_connect and bone.use_deform
        assert arm.pose.bones[name].rotation_mode == 'XYZ'
    # weights
    w = weight_matrix(obj, names)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(w, result.weights, atol=1e-6)
    # parenting + modifier
    assert obj.parent == arm
    mod = obj.modifiers[0]
    assert mod.name == "ArtDef Armature" and mod.type == 'ARMATURE' and mod.object == arm
    assert obj.data.color_attributes.active_color.name == "artdef_links"
    return arm, result


def check_load_helpers(pkg, arm, names, greens):
    """Green's rigs: one hidden non-deforming helper bone per link bone (same rest
    frame and parent) that the link bone's Copy Transforms constraint puts before
    its own transform.  Tracked rigs: no helpers, no constraints."""
    helpers = [pkg.rig.HELPER_FMT.format(l) for l in range(len(names))]
    assert sorted(b.name for b in arm.data.bones if not b.use_deform) == (helpers if greens else [])
    for name, helper in zip(names, helpers):
        cons = arm.pose.bones[name].constraints
        if not greens:
            assert len(cons) == 0, name
            continue
        bone, hbone = arm.data.bones[name], arm.data.bones[helper]
        assert [c.name for c in hbone.collections] == [pkg.rig.HELPER_COLLECTION]
        assert not hbone.collections[0].is_visible
        assert hbone.parent == bone.parent
        np.testing.assert_allclose(np.array(hbone.matrix_local), np.array(bone.matrix_local), atol=1e-6)
        assert arm.pose.bones[helper].rotation_mode == 'QUATERNION'
        assert [c.type for c in cons] == ['COPY_TRANSFORMS']
        con = cons[0]
        assert (con.target, con.subtarget) == (arm, helper)
        assert (con.target_space, con.owner_space, con.mix_mode) == ('LOCAL', 'LOCAL', 'BEFORE_FULL')


LOADS = np.array([[0.3, -0.2, 0.5], [0.0, 0.0, 0.0], [1.0, 0.5, -0.2], [0.1, 0.1, 2.1]])


def set_loads(obj, loads, names=None):
    names = range(len(loads)) if names is None else names
    for k, p in zip(names, loads):
        bpy.data.objects[f"artdef_load_{k}"].location = p


def assert_drivers_simple(obj):
    drivers = list(obj.artdef.rig.animation_data.drivers) + list(obj.data.shape_keys.animation_data.drivers)
    assert drivers
    for fc in drivers:
        d = fc.driver
        assert d.is_valid, fc.data_path
        # no (0,0),(1,1) keys: with them Blender snaps values near 0 or 1 to the key
        assert len(fc.keyframe_points) == 0, fc.data_path
        if d.type == 'SCRIPTED':
            assert d.is_simple_expression, (fc.data_path, d.expression)


def evaluated_pose(arm):
    """The armature's evaluated pose bones (drivers and constraints applied)."""
    dg = bpy.context.evaluated_depsgraph_get()
    dg.update()
    return arm.evaluated_get(dg).pose.bones


def fit_greens_rod(pkg, sample_files):
    """The Green's rod fitted with 3 links: (mesh object, armature, result, rest positions)."""
    obj = import_scan(sample_files["greens_rod"])
    rest = rest_positions(obj)
    assert bpy.ops.artdef.fit(links=3) == {'FINISHED'}
    ref = pkg.files.read_scan(sample_files["greens_rod"])
    arm, result = check_rig(pkg, obj, 3, ref.n_fields)
    return obj, arm, result, rest


class _Layout:
    """Stand-in for UILayout that records what a panel draws and checks names."""

    def __init__(self, log):
        self.__dict__["log"] = log

    def _sub(self, *args, **kw):
        return _Layout(self.log)

    box = row = column = split = _sub

    def label(self, text="", **kw):
        self.log.append(("label", text))

    def separator(self, **kw):
        pass

    def prop(self, data, name, **kw):
        assert name in data.bl_rna.properties, name
        self.log.append(("prop", name))

    def operator(self, idname, **kw):
        mod, name = idname.split(".")
        op = getattr(getattr(bpy.ops, mod), name)
        props = op.get_rna_type().properties
        self.log.append(("operator", idname, op.poll()))

        class Props:
            def __setattr__(self, key, value):
                assert key in props, (idname, key)
        return Props()

    def template_list(self, listtype, list_id, data, propname, active_data, active_propname, **kw):
        """A UIList: recorded, and each of its items drawn by the list's own ``draw_item``."""
        assert propname in data.bl_rna.properties and active_propname in active_data.bl_rna.properties
        self.log.append(("list", listtype, propname))
        for i, item in enumerate(getattr(data, propname)):
            getattr(bpy.types, listtype).draw_item(None, bpy.context, _Layout(self.log), data, item, 0,
                                                   active_data, active_propname, i)

    def __setattr__(self, key, value):
        assert key in ("scale_y", "use_property_split", "use_property_decorate", "enabled", "alert")
        self.log.append(("set", key, value))


def draw_panel():
    log = []
    panel = type("P", (), {"layout": _Layout(log)})()
    bpy.types.ARTDEF_PT_main.draw(panel, bpy.context)
    return log


SEGMENTS = 3
JOINTS = np.array([[0.0, 0.0, float(z)] for z in range(SEGMENTS)])  # heads of the chain's bones


def tube_geometry(rings_per_segment=6, sides=12, radius=0.15):
    """Quads along z in [0, SEGMENTS] with n-gon caps; the segment of every vertex."""
    n_rings = SEGMENTS * rings_per_segment + 1
    z = np.linspace(0.0, SEGMENTS, n_rings)
    a = 2 * np.pi * np.arange(sides) / sides
    verts = np.stack([np.tile(radius * np.cos(a), n_rings), np.tile(radius * np.sin(a), n_rings),
                      np.repeat(z, sides)], axis=1)
    polys = []
    for r in range(n_rings - 1):
        for s in range(sides):
            i, j = r * sides + s, r * sides + (s + 1) % sides
            polys.append([i, j, j + sides, i + sides])
    polys.append(list(range(sides))[::-1])
    polys.append(list(range((n_rings - 1) * sides, n_rings * sides)))
    segment = np.minimum((np.repeat(np.arange(n_rings), sides)) // rings_per_segment, SEGMENTS - 1)
    # the joint rings belong to the segment above them, except the top ring
    return verts, polys, segment


def random_rotations(rng, n_poses, max_angle=0.7):
    return rng.uniform(-max_angle, max_angle, size=(n_poses, SEGMENTS, 3))


def tube_weights(verts, blend=0.0):
    """(N, SEGMENTS) skin weights: hard by segment, or blended linearly over
    ``blend`` on either side of each joint (like a painted character)."""
    z = verts[:, 2]
    w = np.zeros((len(verts), SEGMENTS))
    lower = np.ones(len(verts))
    for b in range(1, SEGMENTS):
        zj = JOINTS[b, 2]
        t = (np.clip((z - zj + blend) / (2 * blend), 0.0, 1.0) if blend > 0
             else (z >= zj).astype(float))
        w[:, b - 1] = lower * (1 - t)
        lower = lower * t
    w[:, -1] = lower
    return w


def chain_pose(verts, weights, eulers, basis=np.eye(3)):
    """Linear blend skinning of a chain: bone b rotates by euler[b] (XYZ, in the
    bone frame ``basis``) about JOINTS[b], children follow."""
    from mathutils import Euler
    out = np.zeros_like(verts)
    R_acc, t_acc = np.eye(3), np.zeros(3)
    for b in range(SEGMENTS):
        R = basis @ np.array(Euler(eulers[b], 'XYZ').to_matrix()) @ basis.T
        # G_b = G_{b-1} o (rotate about joint b)
        t_local = JOINTS[b] - R @ JOINTS[b]
        R_acc, t_acc = R_acc @ R, R_acc @ t_local + t_acc
        out += weights[:, b:b + 1] * (verts @ R_acc.T + t_acc)
    return out


def check_joints(pkg, obj, tol_fraction=0.01):
    """The fitted rig's joints (heads of links with a parent) match JOINTS[1:]."""
    result = pkg.ops.last_result(obj)
    assert result.n_links == SEGMENTS
    arm = obj.artdef.rig
    heads = {b.name: np.array(b.head_local) for b in arm.data.bones}
    fitted = np.array([heads[pkg.rig.GROUP_FMT.format(l)] for l in range(SEGMENTS)
                       if result.parents[l] >= 0])
    assert len(fitted) == SEGMENTS - 1
    rest = rest_positions(obj)
    diag = np.linalg.norm(np.ptp(rest, axis=0))
    dist = np.linalg.norm(fitted[:, None] - JOINTS[None, 1:], axis=2)
    # every true joint has a fitted one nearby, one to one
    assert sorted(dist.argmin(axis=1).tolist()) == list(range(SEGMENTS - 1)), dist
    err = dist.min(axis=1).max() / diag
    assert err < tol_fraction, (err, fitted)
    return err


def _edit_bones(arm, fn):
    view_layer = bpy.context.view_layer
    view_layer.objects.active = arm
    with bpy.context.temp_override(active_object=arm, object=arm, selected_objects=[arm],
                                   selected_editable_objects=[arm]):
        bpy.ops.object.mode_set(mode='EDIT')
        fn(arm.data.edit_bones)
        bpy.ops.object.mode_set(mode='OBJECT')


def build_animated_tube(rng, n_poses=8, blend=0.0):
    """The user's rig: a tube skinned to a 3-bone chain, keyed at frames 1..n."""
    verts, polys, segment = tube_geometry()
    weights = tube_weights(verts, blend)
    mesh = bpy.data.meshes.new("tube")
    mesh.from_pydata(verts.tolist(), [], polys)
    mesh.shade_smooth()
    tube = bpy.data.objects.new("tube", mesh)
    skel = bpy.data.objects.new("skel", bpy.data.armatures.new("skel"))
    for ob in (skel, tube):
        bpy.context.scene.collection.objects.link(ob)
    skel.location = (2.0, -1.0, 0.5)  # object space is what is sampled

    def bones(eb):
        parent = None
        for b in range(SEGMENTS):
            bone = eb.new(f"b{b}")
            bone.head, bone.tail = JOINTS[b], JOINTS[b] + (0, 0, 1)
            bone.parent, bone.use_connect = parent, parent is not None
            parent = bone
    _edit_bones(skel, bones)
    for b in range(SEGMENTS):
        vg = tube.vertex_groups.new(name=f"b{b}")
        for i in np.flatnonzero(weights[:, b] > 0):
            vg.add([int(i)], float(weights[i, b]), 'REPLACE')
    tube.parent = skel
    mod = tube.modifiers.new("Armature", 'ARMATURE')
    mod.object = skel
    tube.modifiers.new("Subdivision", 'SUBSURF')  # changes topology: off while sampling
    eulers = random_rotations(rng, n_poses)
    for f in range(n_poses):
        for b in range(SEGMENTS):
            pb = skel.pose.bones[f"b{b}"]
            pb.rotation_mode = 'XYZ'
            pb.rotation_euler = eulers[f, b]
            pb.keyframe_insert("rotation_euler", frame=f + 1)
    bpy.context.view_layer.objects.active = tube
    return tube, skel, verts, weights, eulers


def shape_key_blob():
    """A mesh whose shape keys are animated: frames 1-4 (3 and 4 equal)."""
    verts, polys, segment = tube_geometry(rings_per_segment=2, sides=6)
    mesh = bpy.data.meshes.new("blob")
    mesh.from_pydata(verts.tolist(), [], polys)
    obj = bpy.data.objects.new("blob", mesh)
    bpy.context.scene.collection.objects.link(obj)
    bpy.context.view_layer.objects.active = obj
    obj.shape_key_add(name="Basis")
    offsets = [np.outer(segment == s, [0.1 * (s + 1), 0.0, 0.05]) for s in range(2)]
    for s, off in enumerate(offsets):
        kb = obj.shape_key_add(name=f"k{s}")
        kb.data.foreach_set("co", (verts + off).astype(np.float32).ravel())
    values = {1: (1.0, 0.0), 2: (0.0, 1.0), 3: (0.5, 0.5), 4: (0.5, 0.5)}
    keys = mesh.shape_keys.key_blocks
    for f, vals in values.items():
        for s, v in enumerate(vals):
            keys[f"k{s}"].value = v
            keys[f"k{s}"].keyframe_insert("value", frame=f)
    return obj, verts, offsets, values


def _vertex_cutting_nodes():
    """Geometry nodes that delete the vertices with index < current frame."""
    ng = bpy.data.node_groups.new("cut", 'GeometryNodeTree')
    ng.interface.new_socket("Geometry", in_out='INPUT', socket_type='NodeSocketGeometry')
    ng.interface.new_socket("Geometry", in_out='OUTPUT', socket_type='NodeSocketGeometry')
    n = ng.nodes
    gin, gout = n.new('NodeGroupInput'), n.new('NodeGroupOutput')
    delete, index = n.new('GeometryNodeDeleteGeometry'), n.new('GeometryNodeInputIndex')
    time_, compare = n.new('GeometryNodeInputSceneTime'), n.new('FunctionNodeCompare')
    compare.data_type, compare.operation = 'FLOAT', 'LESS_THAN'
    ng.links.new(index.outputs[0], compare.inputs[0])
    ng.links.new(time_.outputs["Frame"], compare.inputs[1])
    ng.links.new(gin.outputs[0], delete.inputs["Geometry"])
    ng.links.new(compare.outputs[0], delete.inputs["Selection"])
    ng.links.new(delete.outputs[0], gout.inputs[0])
    return ng


def write_obj(path, verts, polys):
    with open(path, "w") as f:
        f.write("# ArtDef test\no tube\n")
        f.writelines(f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in verts)
        f.write("vn 0 0 1\n")
        f.writelines("f " + " ".join(f"{i + 1}//1" for i in poly) + "\n" for poly in polys)


def write_ply(path, verts, polys, fmt):
    head = (f"ply\nformat {fmt} 1.0\ncomment ArtDef test\nelement vertex {len(verts)}\n"
            "property float x\nproperty float y\nproperty float z\nproperty uchar flag\n"
            f"element face {len(polys)}\nproperty list uchar int vertex_indices\nend_header\n")
    with open(path, "wb") as f:
        f.write(head.encode())
        if fmt == "ascii":
            f.writelines(f"{x:.9g} {y:.9g} {z:.9g} 1\n".encode() for x, y, z in verts)
            f.writelines((f"{len(p)} " + " ".join(map(str, p)) + "\n").encode() for p in polys)
        else:
            vt = np.zeros(len(verts), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("f", "u1")])
            vt["x"], vt["y"], vt["z"] = np.asarray(verts).T
            f.write(vt.tobytes())
            for p in polys:
                f.write(bytes([len(p)]) + np.asarray(p, dtype="<i4").tobytes())


def write_sequence(directory, poses, polys, name="pose_{:03d}.obj", fmt=None):
    directory.mkdir(exist_ok=True)
    paths = []
    for i, x in enumerate(poses):
        path = directory / name.format(i)
        write_obj(path, x, polys) if fmt is None else write_ply(path, x, polys, fmt)
        paths.append(str(path))
    return paths
