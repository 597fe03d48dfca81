"""Helpers of the hand-off tests (tests/blender/test_handoff_*.py): the keyed character, running the
command line, reading back."""
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from conftest import ADDON_MODULE, REPO_ROOT

bpy = pytest.importorskip("bpy")

from morph_assets import world_positions  # noqa: E402,F401  (evaluated world positions)
from test_headless_gltf import _validate, accessor, read_glb  # noqa: E402  (GLB reader, validator)


KEY_STEP = 5
LAST_FRAME = 41                 # keys at 1, 6, ..., 41
KEYED = list(range(1, LAST_FRAME + 1, KEY_STEP))
MAX_TOL = 0.01                  # of the bounding-box diagonal, at the worst vertex
RMS_TOL = 0.002


def _run(args, cwd, timeout=900):
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        [str(REPO_ROOT)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    proc = subprocess.run([sys.executable, *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=timeout)
    return proc


def _ok(proc):
    assert proc.returncode == 0, (
        f"exit {proc.returncode}\n--- stdout\n{proc.stdout[-4000:]}\n--- stderr\n{proc.stderr[-4000:]}")
    return proc


def _edit_bones(arm, fn):
    view_layer = bpy.context.view_layer
    view_layer.objects.active = arm
    with bpy.context.temp_override(active_object=arm, object=arm, selected_objects=[arm],
                                   selected_editable_objects=[arm]):
        bpy.ops.object.mode_set(mode='EDIT')
        fn(arm.data.edit_bones)
        bpy.ops.object.mode_set(mode='OBJECT')


BONES = ("hip", "knee", "ankle")


def build_character(last_frame=LAST_FRAME, step=KEY_STEP, name="Leg"):
    """A tube (12 sides, 19 rings, 3 units tall) skinned with blended weights to
    a chain hip > knee > ankle, rotations keyed at 1, 1+step, ..., last_frame."""
    sides, rings, height = 12, 19, 3.0
    z = np.linspace(0.0, height, rings)
    ang = np.arange(sides) * 2 * math.pi / sides
    verts = np.array([(0.2 * math.cos(a), 0.2 * math.sin(a), zz) for zz in z for a in ang])
    polys = [(r * sides + s, r * sides + (s + 1) % sides, (r + 1) * sides + (s + 1) % sides,
              (r + 1) * sides + s) for r in range(rings - 1) for s in range(sides)]
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(verts.tolist(), [], polys)
    obj = bpy.data.objects.new(name, mesh)
    arm = bpy.data.objects.new(f"{name}Rig", bpy.data.armatures.new(f"{name}Rig"))
    for o in (arm, obj):
        bpy.context.scene.collection.objects.link(o)

    def bones(eb):
        parent = None
        for i, n in enumerate(BONES):
            b = eb.new(n)
            b.head, b.tail = (0, 0, float(i)), (0, 0, float(i + 1))
            b.parent, b.use_connect = parent, parent is not None
            parent = b
    _edit_bones(arm, bones)
    for i, n in enumerate(BONES):
        w = np.clip(1.0 - np.abs(verts[:, 2] - (i + 0.5)), 0.0, 1.0)
        if i == 0:
            w[verts[:, 2] < 0.5] = 1.0
        if i == len(BONES) - 1:
            w[verts[:, 2] > 2.5] = 1.0
        vg = obj.vertex_groups.new(name=n)
        for v in np.flatnonzero(w > 0):
            vg.add([int(v)], float(w[v]), 'REPLACE')
    obj.parent = arm
    obj.modifiers.new("Armature", 'ARMATURE').object = arm
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, last_frame
    for f in range(1, last_frame + 1, step):
        t = (f - 1) / max(last_frame - 1, 1)
        for i, n in enumerate(BONES):
            pb = arm.pose.bones[n]
            pb.rotation_mode = 'XYZ'
            pb.rotation_euler = (0.7 * math.sin(2 * math.pi * t + i),
                                 0.4 * math.sin(4 * math.pi * t) * (i > 0), 0.0)
            pb.keyframe_insert("rotation_euler", frame=f)
    bpy.context.view_layer.objects.active = obj
    return obj, arm


def _import(path):
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    if str(path).endswith(".fbx"):
        # Blender's FBX importer shifts animation by +1 frame by default
        # (anim_offset=1): the file's times are the source's, read them as such.
        assert bpy.ops.import_scene.fbx(filepath=str(path), anim_offset=0.0) == {'FINISHED'}
    else:
        assert bpy.ops.import_scene.gltf(filepath=str(path)) == {'FINISHED'}
    return [o for o in bpy.data.objects]


def _skinned(objects):
    meshes = [o for o in objects if o.type == 'MESH' and o.find_armature() is not None]
    assert len(meshes) == 1, [(o.name, o.type) for o in objects]
    return meshes[0]


def compare(reference, ref_rest, moved, rest):
    """(max, rms) distance between ``moved`` and ``reference`` as fractions of the
    diagonal, vertices matched by nearest rest position."""
    from scipy.spatial import cKDTree
    dist, index = cKDTree(ref_rest).query(rest)
    diag = float(np.linalg.norm(np.ptp(ref_rest, axis=0)))
    assert dist.max() < 1e-4 * diag, "the output's rest mesh is not the source's"
    err = np.linalg.norm(moved - reference[:, index], axis=-1)
    return err.max() / diag, math.sqrt(float(np.mean(err ** 2))) / diag


def glb_times(gltf, binary):
    return sorted({round(float(t), 5) for a in gltf.get("animations", [])
                   for s in a["samplers"] for t in accessor(gltf, binary, s["input"]).ravel()})


def _menu_functions(menu):
    """Names of the functions appended to a menu (File > Export ...)."""
    return [f.__name__ for f in menu._dyn_ui_initialize()
            if f.__module__.endswith(".operators.export")]


def _evaluated(obj, frames):
    return world_positions(obj, frames)[0]


def _draw(closed=True):
    from ophelpers import _Layout

    class Layout(_Layout):
        def _sub(self, *args, **kw):
            return Layout(self.log)
        box = row = column = split = _sub

        def panel(self, idname, default_closed=True):
            self.log.append(("panel", idname))
            return Layout(self.log), (None if closed else Layout(self.log))

    log = []
    bpy.types.ARTDEF_PT_main.draw(type("P", (), {"layout": Layout(log)})(), bpy.context)
    return log


def _write_obj(path, verts, polys):
    with open(path, "w") as f:
        f.write("".join(f"v {x:.7f} {y:.7f} {z:.7f}\n" for x, y, z in verts))
        f.write("".join("f " + " ".join(str(i + 1) for i in p) + "\n" for p in polys))


def _play_clip(clip):
    """Make clip ``clip`` (an NLA track name, as Blender's glTF importer stores a
    file's animations) the active action of every object and shape-key set."""
    for o in bpy.data.objects:
        for id_data in (o, getattr(o.data, "shape_keys", None)):
            ad = getattr(id_data, "animation_data", None) if id_data is not None else None
            if ad is None:
                continue
            strips = [s for t in ad.nla_tracks if t.name == clip for s in t.strips]
            if strips:
                ad.use_nla = False
                ad.action = strips[0].action
                if hasattr(ad, "action_slot") and ad.action_slot is None and ad.action.slots:
                    ad.action_slot = ad.action.slots[0]


def _two_clip_character():
    """The test character with two clips: Walk (its action, frames 1-21) and Wave (keys at 1, 6, 11,
    on an NLA track named Wave). Returns (mesh, armature, walk, wave)."""
    obj, arm = build_character(last_frame=21)
    walk = arm.animation_data.action
    walk.name = "Walk"
    wave = bpy.data.actions.new("Wave")
    arm.animation_data.action = wave
    for f in (1, 6, 11):
        for i, n in enumerate(BONES):
            arm.pose.bones[n].rotation_euler = (0.0, 0.0, 0.5 * math.sin(f / 3 + i))
            arm.pose.bones[n].keyframe_insert("rotation_euler", frame=f)
    arm.animation_data.action = walk
    track = arm.animation_data.nla_tracks.new()
    track.name = "Wave"
    track.strips.new("Wave", 1, wave)
    return obj, arm, walk, wave
