# SPDX-License-Identifier: GPL-3.0-or-later
"""Green's scans: the load empties, their load-sweep actions and the drivers they feed.

Load empties ``artdef_load_K`` (children of the armature) hold the load vector in ``location``;
a load-sweep action per empty raises load k along axis d (field c = 3k+d) from 0 to the probe
load p̂ and back, rest at frame 2c·frames_per_field, +p̂ at (2c+1)·frames_per_field. The loads
drive the shape keys and, per link, a hidden non-deforming helper bone ``artdef_link_XX_load``;
the link bone's Copy Transforms constraint ``ArtDef Load`` puts the helper's local transform
before its own. The helper turns by its joint's spring turn (:mod:`artdef_addon.springs`), solved in
chained custom properties of the armature; the expressions are :mod:`artdef_addon.drivers`'.
"""

import bpy
import numpy as np
from mathutils import Matrix

from ..artdef_addon import drivers as _drivers
from ..artdef_addon import model as _model
from ..artdef_addon import springs as _model_springs
from .replay import _key_curve, _new_action

from .names import HELPER_FMT, LOAD_CONSTRAINT, LOAD_FMT, RIG_VERSION, RIG_VERSION_PROP

_AXES = _drivers.AXES


def _driver_fcurve(fcurve):
    """``fcurve`` with no keyframes, so its value is the driver's value itself.

    ``driver_add()`` gives the F-Curve two keyframes (0, 0) and (1, 1); with
    them Blender snaps a driver value within about 1e-4 of a key to the key
    (measured: 8.3e-5 became 0 and 1e-4 became 0), which zeroes small bone
    angles and shape key values at small loads.
    """
    points = fcurve.keyframe_points
    while len(points):
        points.remove(points[len(points) - 1], fast=True)
    return fcurve


def _add_load_vars(driver, empties, which):
    """Driver variables ``x<k>``, ``y<k>``, ``z<k>`` reading load k's component d: the load empty's
    location, or (``empties`` a :class:`CarriedLoads`) the load as the link carrying it feels it."""
    for k, d in which:
        var = driver.variables.new()
        var.name = f"{_AXES[d]}{k}"
        var.type = 'SINGLE_PROP'
        if isinstance(empties, CarriedLoads):
            var.targets[0].id = empties.arm
            var.targets[0].data_path = f'["{empties.prop(k, d)}"]'
        else:
            var.targets[0].id = empties[k]
            var.targets[0].data_path = f"location[{d}]"


#: custom properties of the armature holding the spring solve (:mod:`artdef_addon.springs`), per step s:
#: joint j's turn after s steps (s = 0: the linear turn Ω f), the linear remainder E f, load k as link j
#: feels it at turns s, the lever arm from j's head to load k, their cross product, j's torque in its
#: own frame and in its parent's
TURN_FMT = "artdef_w_{}_{}_{}"
LINEAR_FMT = "artdef_e_{}_{}"
FELT_FMT = "artdef_g_{}_{}_{}_{}"
LEVER_FMT = "artdef_l_{}_{}_{}_{}"
CROSS_FMT = "artdef_q_{}_{}_{}_{}"
TORQUE_FMT = "artdef_t_{}_{}_{}"
PARENT_TORQUE_FMT = "artdef_tp_{}_{}_{}"


class CarriedLoads:
    """The loads as the links carrying them feel them at the final turns (custom properties of
    ``arm``), as a source of driver variables for :func:`_add_load_vars`."""

    def __init__(self, arm, springs):
        self.arm, self.sp = arm, springs

    def prop(self, k, d):
        return FELT_FMT.format(_model_springs.SPRING_STEPS, int(self.sp.carrier[k]), k, _AXES[d])


def _prop_var(driver, name, arm, prop):
    var = driver.variables.new()
    var.name = name
    var.type = 'SINGLE_PROP'
    var.targets[0].id = arm
    var.targets[0].data_path = f'["{prop}"]'


def _scripted_prop(arm, prop, kind='SCRIPTED'):
    """A driver on the armature's custom property ``prop`` (made, at 0)."""
    arm[prop] = 0.0
    drv = _driver_fcurve(arm.driver_add(f'["{prop}"]')).driver
    drv.type = kind
    return drv


def _vector_drivers(arm, fmt_out, expr, inputs):
    """Three drivers ``fmt_out(d)`` = ``expr(d)`` over the named 3-vectors ``inputs``: (variable
    names, property format of component a, or constants)."""
    for d in range(3):
        drv = _scripted_prop(arm, fmt_out(d))
        for names, src in inputs:
            for a in range(3):
                _prop_var(drv, names[a], arm, src(a))
        drv.expression = expr(d)


def _build_springs(arm, empties, result, rest):
    """Drivers of the joints' spring turns (:func:`artdef_addon.springs.spring_turns`): the linear
    turn Ω f and remainder E f, then per step the felt loads down the tree (the empties' at the
    roots), the lever arms up it, their cross products, the torques (SUM), turned into the parent's
    frame, and the damped step. Returns (the springs, the :class:`CarriedLoads` at the final turns)."""
    sp = _model_springs.joint_springs(result, rest)
    L, m = sp.down.shape
    W, V = _drivers.TURN_VARS, _drivers.VECTOR_VARS
    for j in range(L):
        for a in range(3):
            for fmt, coeffs, tag in ((TURN_FMT.format(0, j, _AXES[a]), sp.turns[j, a], "w"),
                                     (LINEAR_FMT.format(j, _AXES[a]), sp.linear[j, a], "e")):
                arm[fmt] = 0.0
                _drive_linear(arm, f'["{fmt}"]', None, coeffs, empties, arm, f"{tag}{j}_{a}")
    turn = lambda s, j: (lambda a: TURN_FMT.format(s, j, _AXES[a]))          # noqa: E731
    felt = lambda s, j, k: (lambda a: FELT_FMT.format(s, j, k, _AXES[a]))    # noqa: E731
    lever = lambda s, j, k: (lambda a: LEVER_FMT.format(s, j, k, _AXES[a]))  # noqa: E731
    steps = _model_springs.SPRING_STEPS
    for s in range(steps + 1):
        for j in sp.order:                                   # felt loads, down the tree
            p = int(sp.parents[j])
            for k in np.flatnonzero(sp.down[j]):
                for d in range(3):
                    drv = _scripted_prop(arm, felt(s, j, k)(d))
                    for a in range(3):
                        _prop_var(drv, W[a], arm, turn(s, j)(a))
                        if p < 0:
                            var = drv.variables.new()
                            var.name, var.type = V[a], 'SINGLE_PROP'
                            var.targets[0].id = empties[k]
                            var.targets[0].data_path = f"location[{a}]"
                        else:
                            _prop_var(drv, V[a], arm, felt(s, p, k)(a))
                    drv.expression = _drivers.rotate_expression(d, sign=-1)
        if s == steps:
            break
        for j in reversed(sp.order):                         # lever arms, up the tree
            for k in np.flatnonzero(sp.down[j]):
                n = int(sp.next[j, k])
                for d in range(3):
                    prop = lever(s, j, k)(d)
                    if n < 0:
                        arm[prop] = float(sp.segment[j, k, d])
                        continue
                    drv = _scripted_prop(arm, prop)
                    for a in range(3):
                        _prop_var(drv, W[a], arm, turn(s, n)(a))
                        _prop_var(drv, V[a], arm, lever(s, n, k)(a))
                    drv.expression = _drivers.rotate_expression(d, sign=1, offset=float(sp.segment[j, k, d]))
        for j in range(L):
            ks = np.flatnonzero(sp.down[j])
            for k in ks:                                     # λ × g
                _vector_drivers(arm, lambda d: CROSS_FMT.format(s, j, k, _AXES[d]), _drivers.cross_expression,
                                [(V, lever(s, j, k)), (W, felt(s, j, k))])
            for d in range(3):
                if ks.size:
                    drv = _scripted_prop(arm, TORQUE_FMT.format(s, j, _AXES[d]), 'SUM')
                    for k in ks:
                        _prop_var(drv, f"q{k}", arm, CROSS_FMT.format(s, j, k, _AXES[d]))
            if ks.size:
                _vector_drivers(arm, lambda d: PARENT_TORQUE_FMT.format(s, j, _AXES[d]),
                                lambda d: _drivers.rotate_expression(d, sign=1),
                                [(W, turn(s, j)), (V, lambda a: TORQUE_FMT.format(s, j, _AXES[a]))])
            for d in range(3):
                drv = _scripted_prop(arm, turn(s + 1, j)(d))
                _prop_var(drv, "p", arm, turn(s, j)(d))
                _prop_var(drv, "e", arm, LINEAR_FMT.format(j, _AXES[d]))
                row = sp.compliance[j, d] if ks.size else np.zeros(3)
                if ks.size:
                    for a in range(3):
                        _prop_var(drv, f"t{a}", arm, PARENT_TORQUE_FMT.format(s, j, _AXES[a]))
                drv.expression = _drivers.spring_step_expression(_model_springs.SPRING_DAMPING, row)
    return sp, CarriedLoads(arm, sp)


def _drive_linear(owner, path, index, coeffs, empties, arm_obj, tag):
    """Drive ``owner.path[index]`` = sum_c coeffs[c] * load_flat[c].

    One simple expression when it fits Blender's 255 characters, otherwise
    partial sums in custom properties of ``arm_obj`` added by a SUM driver.
    """
    chunks = _drivers.linear_chunks(coeffs)

    def fill(driver, cs):
        driver.type = 'SCRIPTED'
        _add_load_vars(driver, empties, [(c // 3, c % 3) for c in cs])
        driver.expression = _drivers.linear_expression(coeffs, cs)

    fcurve = _driver_fcurve(owner.driver_add(path, index) if index is not None
                            else owner.driver_add(path))
    if len(chunks) == 1:
        fill(fcurve.driver, chunks[0])
        return [fcurve.driver]
    made = []
    fcurve.driver.type = 'SUM'
    for i, cs in enumerate(chunks):
        prop = f"artdef_sum_{tag}_{i}"
        arm_obj[prop] = 0.0
        sub = _driver_fcurve(arm_obj.driver_add(f'["{prop}"]'))
        fill(sub.driver, cs)
        made.append(sub.driver)
        var = fcurve.driver.variables.new()
        var.name = f"s{i}"
        var.type = 'SINGLE_PROP'
        var.targets[0].id = arm_obj
        var.targets[0].data_path = f'["{prop}"]'
    made.append(fcurve.driver)
    return made


def _make_load_empties(obj, arm, result, load_names, size):
    mesh = obj.data
    empties = []
    for k, vert in enumerate(np.asarray(result.load_vertices)):
        name = LOAD_FMT.format(load_names[k])
        emp = bpy.data.objects.new(name, None)
        for coll in arm.users_collection:
            coll.objects.link(emp)
        emp["artdef_load"] = int(load_names[k])
        emp.parent = arm
        emp.matrix_parent_inverse = Matrix.Identity(4)
        emp.delta_location = mesh.vertices[int(vert)].co  # rest position: location = load
        emp.location = (0.0, 0.0, 0.0)
        emp.empty_display_type = 'SPHERE'
        emp.empty_display_size = size
        emp.show_in_front = True
        emp.hide_render = True
        emp.lock_rotation = (True, True, True)
        emp.lock_scale = (True, True, True)
        empties.append(emp)
    return empties


def sweep_frame(c, frames_per_field=10):
    """Frame at which the load sweep holds field c = 3k+d: load k = p̂ along axis d."""
    return (2 * int(c) + 1) * max(int(frames_per_field), 1)


def _build_load_sweep(empties, probe_load, frames_per_field=10):
    """One action per load empty sweeping its load along x, y, z in turn.

    Field c = 3k+d (empty k, axis d): location[d] is 0 at frame 2c·F, the probe
    load p̂ at (2c+1)·F and 0 again at (2c+2)·F (F = frames_per_field), so
    playing the scene shows every scanned load case once, one after the other,
    and any frame in between is a smaller load of the same case.  Returns the
    last frame.
    """
    step = max(int(frames_per_field), 1)
    n = 3 * len(empties)
    end = 2 * n * step
    for k, emp in enumerate(empties):
        action, new_fcurve = _new_action(emp, f"{emp.name}_sweep")
        action["artdef_made"] = True
        action.use_frame_range = True
        action.frame_start, action.frame_end = 0, end
        for d in range(3):
            c = 3 * k + d
            frames = [0.0, 2 * c * step, (2 * c + 1) * step, (2 * c + 2) * step, end]
            values = [0.0, 0.0, probe_load, 0.0, 0.0]
            # drop repeated frames (first and last case), keep the order
            keep = [i for i in range(len(frames)) if i == 0 or frames[i] != frames[i - 1]]
            _key_curve(new_fcurve("location", d, "Load Sweep"),
                       [frames[i] for i in keep], [values[i] for i in keep])
    return end


def _add_load_constraint(arm, pb, helper):
    """Copy Transforms ``ArtDef Load`` on link bone ``pb``: its local transform
    becomes helper's local transform (the load-driven one) followed by its own
    (the animator's keys), as if the helper were its parent."""
    con = pb.constraints.new('COPY_TRANSFORMS')
    con.name = LOAD_CONSTRAINT
    con.target = arm
    con.subtarget = helper
    con.target_space = 'LOCAL'
    con.owner_space = 'LOCAL'
    con.mix_mode = 'BEFORE_FULL'


def _build_load_controls(obj, arm, result, bone_names, key_names, load_names):
    """Load empties driving the joints' spring turns (:func:`_build_springs`), the helper bones from
    them (rotation as a quaternion of the turn, location through κ's translation rows of the carried
    loads) and the shape keys (through the strain-hardening map); the link bones follow their helpers.
    Returns the empties."""
    kappa = np.asarray(result.kappa, dtype=np.float64)
    m = len(result.load_vertices)
    if load_names is None:
        load_names = list(range(m))
    co = np.empty(3 * len(obj.data.vertices), dtype=np.float32)
    obj.data.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3)
    extent = float(np.linalg.norm(co.max(0) - co.min(0))) or 1.0
    empties = _make_load_empties(obj, arm, result, load_names, 0.02 * extent)
    sp, carried = _build_springs(arm, empties, result, co.astype(np.float64))
    final = _model_springs.SPRING_STEPS
    for l, bname in enumerate(bone_names):
        pb = arm.pose.bones[HELPER_FMT.format(l)]
        _add_load_constraint(arm, arm.pose.bones[bname], pb.name)
        for i in range(4):
            drv = _driver_fcurve(pb.driver_add("rotation_quaternion", i)).driver
            drv.type = 'SCRIPTED'
            for a, name in enumerate(_drivers.TURN_VARS):
                _prop_var(drv, name, arm, TURN_FMT.format(final, l, _AXES[a]))
            drv.expression = _drivers.quaternion_expression(i, np.asarray(result.frames[l]))
        for j in range(3, 6):
            coeffs = kappa[l, j]
            if not np.any(coeffs):
                continue
            _drive_linear(pb, "location", j % 3, coeffs, carried, arm, f"{l:02d}_l{j % 3}")
    keys = obj.data.shape_keys
    probe = float(result.probe_load)
    p_max = None if result.p_max is None else float(result.p_max)
    for c, kname in enumerate(key_names):
        k, d = divmod(c, 3)
        fc = _driver_fcurve(keys.driver_add(f'key_blocks["{kname}"].value'))
        drv = fc.driver
        drv.type = 'SCRIPTED'
        _add_load_vars(drv, carried, [(k, 0), (k, 1), (k, 2)])
        drv.expression = _drivers.shape_value_expression(k, d, probe, p_max)
    arm[RIG_VERSION_PROP] = RIG_VERSION
    return empties
