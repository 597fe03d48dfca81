# SPDX-License-Identifier: GPL-3.0-or-later
"""Green's scans: the load empties, their load-sweep actions and the drivers they feed.

Load empties ``artdef_load_K`` (children of the armature) hold the load vector in ``location``;
a load-sweep action per empty raises load k along axis d (field c = 3k+d) from 0 to the probe
load p̂ and back, rest at frame 2c·frames_per_field, +p̂ at (2c+1)·frames_per_field. The loads
drive the shape keys and, per link, a hidden non-deforming helper bone ``artdef_link_XX_load``;
the link bone's Copy Transforms constraint ``ArtDef Load`` puts the helper's local transform
before its own. The expressions are :mod:`artdef_addon.drivers`'.
"""

import bpy
import numpy as np
from mathutils import Matrix

from ..artdef_addon import drivers as _drivers
from ..artdef_addon import model as _model
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
    location, or (``empties`` a :class:`FeltLoads`) the load as its link feels it."""
    for k, d in which:
        var = driver.variables.new()
        var.name = f"{_AXES[d]}{k}"
        var.type = 'SINGLE_PROP'
        if isinstance(empties, FeltLoads):
            var.targets[0].id = empties.arm
            var.targets[0].data_path = f'["{FELT_FMT.format(empties.step, k, _AXES[d])}"]'
        else:
            var.targets[0].id = empties[k]
            var.targets[0].data_path = f"location[{d}]"


#: custom properties of the armature: load k's component d as its link feels it after dead-load step
#: s (:func:`artdef_addon.model.dead_loads`), the link's turn that step and its half-step W g
FELT_FMT = "artdef_felt_{}_{}_{}"
TURN_FMT = "artdef_turn_{}_{}_{}"
HALF_FMT = "artdef_half_{}_{}_{}"


class FeltLoads:
    """The loads after dead-load step ``step`` (custom properties of ``arm``), as a source of driver
    variables for :func:`_add_load_vars`."""

    def __init__(self, arm, step):
        self.arm, self.step = arm, step


def _prop_var(driver, name, arm, prop):
    var = driver.variables.new()
    var.name = name
    var.type = 'SINGLE_PROP'
    var.targets[0].id = arm
    var.targets[0].data_path = f'["{prop}"]'


def _scripted_prop(arm, prop):
    """A SCRIPTED driver on the armature's custom property ``prop`` (made, at 0)."""
    arm[prop] = 0.0
    drv = _driver_fcurve(arm.driver_add(f'["{prop}"]')).driver
    drv.type = 'SCRIPTED'
    return drv


def _build_felt_loads(arm, empties, result):
    """Drivers of the loads the links feel (:func:`artdef_addon.model.dead_loads`): per step s and
    load k the half-step ½ W g (linear in the previous step's loads g, the empties' at the first), the
    link's turn w_s = ½ w_(s−1) + ½ W g, and the load turned back by it (Rodrigues,
    :func:`artdef_addon.drivers.felt_expression`). Returns the last step's :class:`FeltLoads`."""
    W = _model.load_turn_maps(result)
    m = W.shape[0]
    source = empties
    for s in range(1, _model.DEAD_LOAD_STEPS + 1):
        for k in range(m):
            for a in range(3):
                half = HALF_FMT.format(s, k, _AXES[a])
                arm[half] = 0.0
                _drive_linear(arm, f'["{half}"]', None, 0.5 * W[k, a], source, arm, f"h{s}_{k}_{a}")
                drv = _scripted_prop(arm, TURN_FMT.format(s, k, _AXES[a]))
                _prop_var(drv, "h", arm, half)
                if s > 1:
                    _prop_var(drv, "p", arm, TURN_FMT.format(s - 1, k, _AXES[a]))
                drv.expression = "h+0.5*p" if s > 1 else "h"
        for k in range(m):
            for d in range(3):
                drv = _scripted_prop(arm, FELT_FMT.format(s, k, _AXES[d]))
                _add_load_vars(drv, empties, [(k, 0), (k, 1), (k, 2)])
                for a, name in enumerate(_drivers.TURN_VARS):
                    _prop_var(drv, name, arm, TURN_FMT.format(s, k, _AXES[a]))
                drv.expression = _drivers.felt_expression(k, d)
        source = FeltLoads(arm, s)
    return source


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
    """Load empties driving, through the loads their links feel (:func:`_build_felt_loads`), the
    helper bones (linearly through κ) and the shape keys (through the strain-hardening map); the
    link bones follow their helpers. Returns the empties."""
    kappa = np.asarray(result.kappa, dtype=np.float64)
    m = len(result.load_vertices)
    if load_names is None:
        load_names = list(range(m))
    co = np.empty(3 * len(obj.data.vertices), dtype=np.float32)
    obj.data.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3)
    extent = float(np.linalg.norm(co.max(0) - co.min(0))) or 1.0
    empties = _make_load_empties(obj, arm, result, load_names, 0.02 * extent)
    felt = _build_felt_loads(arm, empties, result)
    for l, bname in enumerate(bone_names):
        pb = arm.pose.bones[HELPER_FMT.format(l)]
        _add_load_constraint(arm, arm.pose.bones[bname], pb.name)
        for j in range(6):
            coeffs = kappa[l, j]
            if not np.any(coeffs):
                continue
            path = "rotation_euler" if j < 3 else "location"
            _drive_linear(pb, path, j % 3, coeffs, felt, arm, f"{l:02d}_{'rl'[j // 3]}{j % 3}")
    keys = obj.data.shape_keys
    probe = float(result.probe_load)
    p_max = None if result.p_max is None else float(result.p_max)
    first = len(key_names) // 2
    for c, kname in enumerate(key_names):
        k, d = divmod(c % first, 3)
        fc = _driver_fcurve(keys.driver_add(f'key_blocks["{kname}"].value'))
        drv = fc.driver
        drv.type = 'SCRIPTED'
        _add_load_vars(drv, felt, [(k, 0), (k, 1), (k, 2)])
        drv.expression = (_drivers.shape_value_expression(k, d, probe, p_max) if c < first
                          else _drivers.bump_value_expression(k, d, probe))
    arm[RIG_VERSION_PROP] = RIG_VERSION
    return empties

