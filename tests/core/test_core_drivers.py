"""The rig's driver expressions as text (``artdef_addon.drivers``), checked without Blender: each one
evaluates, with the load empties' locations as its variables, to the core's model of the loads
(:mod:`artdef_addon.model`)."""
import math
from types import SimpleNamespace

import numpy as np
import pytest

from scipy.spatial.transform import Rotation

from artdef_addon import drivers, model, springs


def _eval(expression, loads):
    """``expression`` evaluated as Blender's simple expressions are, variables x<k>, y<k>, z<k>."""
    names = {f"{a}{k}": float(loads[k, d]) for k in range(loads.shape[0]) for d, a in enumerate("xyz")}
    names.update(sqrt=math.sqrt, exp=math.exp, max=max)
    return eval(expression, {"__builtins__": {}}, names)


@pytest.mark.parametrize("n_loads,limit", [(1, None), (4, None), (40, None), (40, 40), (7, 12)])
def test_linear_chunks_fit_and_sum_to_the_linear_model(n_loads, limit):
    rng = np.random.default_rng(n_loads * 100 + (limit or 0))
    coeffs = rng.normal(size=3 * n_loads) * 10.0 ** rng.integers(-6, 4, size=3 * n_loads)
    coeffs[rng.random(coeffs.size) < 0.3] = 0.0
    loads = rng.normal(size=(n_loads, 3))
    chunks = drivers.linear_chunks(coeffs, limit)
    used = [c for cs in chunks for c in cs]
    assert used == [c for c in range(coeffs.size) if coeffs[c] != 0.0]   # each non-zero term once, in order
    cap = drivers.MAX_EXPRESSION if limit is None else limit
    total = 0.0
    for cs in chunks:
        text = drivers.linear_expression(coeffs, cs)
        # a chunk holds one term more only while it fits (a single term may be longer than a tiny cap)
        assert len(cs) <= 1 or len(text) <= cap, (len(text), cap)
        total += _eval(text, loads)
    assert total == pytest.approx(float(coeffs @ loads.reshape(-1)), rel=1e-7, abs=1e-9)


def test_a_short_sum_is_one_expression_and_no_terms_is_zero():
    assert drivers.linear_chunks([0.5, 0.0, -2.0]) == [[0, 2]]
    assert drivers.linear_expression([0.5, 0.0, -2.0], [0, 2]) == "0.5*x0-2*z0"
    assert drivers.linear_chunks([0.0, 0.0, 0.0]) == [[]]
    assert drivers.linear_expression([0.0, 0.0, 0.0], []) == "0"


@pytest.mark.parametrize("p_max", [None, 1.5, 3.0, 20.0])
def test_shape_key_expressions_are_the_models_key_values(p_max):
    """The keys' expressions are the hardening map over its slope at zero, saturating:
    :func:`model.greens_key_values`, for loads below, at and beyond the probe load and for no load."""
    rng = np.random.default_rng(7)
    M, probe = 3, 0.37
    fake = SimpleNamespace(probe_load=probe, p_max=p_max)
    axis = np.zeros((M, 3))
    axis[:, 0] = probe
    for loads in (0.1 * rng.normal(size=(M, 3)), rng.normal(size=(M, 3)), 5.0 * rng.normal(size=(M, 3)),
                  axis, np.zeros((M, 3))):
        want = model.greens_key_values(fake, loads)
        got = [_eval(drivers.shape_value_expression(k, d, probe, p_max), loads) for k in range(M) for d in range(3)]
        np.testing.assert_allclose(got, want, rtol=1e-7, atol=1e-12)
    # at zero the value's slope is 1 / p̂ whatever the hardening: the rig's tangent is G
    h = 1e-7 * probe
    one = np.zeros((M, 3))
    one[1, 2] = h
    assert model.greens_key_values(fake, one)[5] == pytest.approx(h / probe, rel=1e-6)


def _vars(**vectors):
    names = dict(sqrt=math.sqrt, cos=math.cos, sin=math.sin, max=max)
    for key, v in vectors.items():
        names.update(zip(key, map(float, v)))
    return names


def test_rotation_cross_and_quaternion_expressions_are_the_springs_rotation():
    """Each Rodrigues expression is component d of springs.rotate (either sign, with an offset), the
    cross expression the cross product, the quaternion the bone-local rotation Bᵀ Rot(ω) B; for turns
    from none to large."""
    rng = np.random.default_rng(3)
    for scale in (0.0, 1e-9, 0.3, 2.5):
        w, v = scale * rng.normal(size=3), rng.normal(size=3)
        off = np.array([float(drivers.number(o)) for o in rng.normal(size=3)])   # as written: 9 digits
        names = _vars(abc=w, xyz=v)
        for sign in (1, -1):
            got = [eval(drivers.rotate_expression(d, sign, off[d]), {"__builtins__": {}}, names) for d in range(3)]
            np.testing.assert_allclose(got, off + springs.rotate(sign * w, v), rtol=1e-12, atol=1e-14)
        got = [eval(drivers.cross_expression(d), {"__builtins__": {}}, names) for d in range(3)]
        np.testing.assert_allclose(got, np.cross(v, w), rtol=1e-12, atol=1e-14)
        B = Rotation.random(random_state=int(1000 * scale) + 1).as_matrix()
        q = [eval(drivers.quaternion_expression(i, B), {"__builtins__": {}}, names) for i in range(4)]
        want = B.T @ Rotation.from_rotvec(w).as_matrix() @ B
        np.testing.assert_allclose(Rotation.from_quat(q[1:] + q[:1]).as_matrix(), want, atol=1e-12)


def test_a_rigid_link_on_a_rotational_spring_turns_to_its_balance():
    """A rigid link of length L on a rotational spring of stiffness k under a dead load F across it turns
    to θ of k θ = F L cos θ within 1 % up to 0.9 rad (springs.spring_turns), where the linear spring's
    F L / k is 4–60 % off; the load it feels is the load turned back, not shrunk."""
    L, k = 2.0, 5.0
    kappa = np.zeros((1, 6, 3))
    kappa[0, 0, 2] = L / k                           # θ_x from a load along z: (r × F)_x = L F_z
    kappa[0, 2, 0] = -L / k
    rod = SimpleNamespace(kappa=kappa, load_vertices=np.array([0]), weights=np.ones((1, 1)),
                          frames=np.eye(3)[None], parents=np.array([-1]), heads=np.zeros((1, 3)))
    sp = springs.joint_springs(rod, np.array([[0.0, L, 0.0]]))
    for theta in (0.3, 0.6, 0.9):
        F = k * theta / (L * math.cos(theta))
        w, g = springs.spring_turns(sp, np.array([[0.0, 0.0, F]]))
        assert abs(w[0, 0] - theta) <= 0.01 * theta and abs(F * L / k - theta) >= 0.04 * theta, (theta, w)
        assert np.abs(w[0, 1:]).max() <= 1e-12
        assert np.linalg.norm(springs.carried_loads(sp, g)) == pytest.approx(F)


def test_spring_step_expression_is_the_damped_step():
    C = np.array([0.5, -2.0, 0.0])
    names = dict(p=0.3, e=-0.1, t0=1.0, t1=0.25, t2=7.0)
    got = eval(drivers.spring_step_expression(0.6, C), {"__builtins__": {}}, names)
    assert got == pytest.approx(0.4 * 0.3 + 0.6 * (0.5 * 1.0 - 2.0 * 0.25 - 0.1))
