"""The rig's driver expressions as text (``artdef_addon.drivers``), checked without Blender: each one
evaluates, with the load empties' locations as its variables, to the core's model of the loads
(:mod:`artdef_addon.model`)."""
import math
from types import SimpleNamespace

import numpy as np
import pytest

from artdef_addon import drivers, model


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
    """The first-order keys' expressions are the hardening map over its slope at zero, the bump
    keys' the probe-exactness weight: :func:`model.greens_key_values`, for loads below, at and
    beyond the probe load and for no load."""
    rng = np.random.default_rng(7)
    M, probe = 3, 0.37
    fake = SimpleNamespace(probe_load=probe, p_max=p_max)
    axis = np.zeros((M, 3))
    axis[:, 0] = probe                                  # at the probe load: every bump weight is 1
    for loads in (0.1 * rng.normal(size=(M, 3)), rng.normal(size=(M, 3)), 5.0 * rng.normal(size=(M, 3)),
                  axis, np.zeros((M, 3))):
        want = model.greens_key_values(fake, loads)
        first = [_eval(drivers.shape_value_expression(k, d, probe, p_max), loads) for k in range(M) for d in range(3)]
        bump = [_eval(drivers.bump_value_expression(k, d, probe), loads) for k in range(M) for d in range(3)]
        np.testing.assert_allclose(first + bump, want, rtol=1e-7, atol=1e-12)
    np.testing.assert_allclose(model.greens_key_values(fake, axis)[3 * M::3], 1.0)


def test_felt_load_expressions_are_the_models_rotation_and_the_turn_solves_a_spring():
    """Each felt-load expression is component d of the load turned back by w (model.rotate_vectors of −w),
    for turns from none to large; and a rigid link on a rotational spring under a load across it turns
    to θ of k θ = F L cos θ within 2 % (model.dead_loads), where the linear spring's F L / k is 0.5–60 % off."""
    rng = np.random.default_rng(3)
    for scale in (0.0, 1e-9, 0.3, 2.5):
        w = scale * rng.normal(size=3)
        loads = rng.normal(size=(2, 3))
        names = {f"{a}{k}": float(loads[k, d]) for k in range(2) for d, a in enumerate("xyz")}
        names.update(dict(zip(drivers.TURN_VARS, map(float, w))), sqrt=math.sqrt, cos=math.cos, sin=math.sin,
                     max=max)
        got = [eval(drivers.felt_expression(1, d), {"__builtins__": {}}, names) for d in range(3)]
        np.testing.assert_allclose(got, model.rotate_vectors(-w, loads[1]), rtol=1e-12, atol=1e-14)
    L, k = 2.0, 5.0
    kappa = np.zeros((1, 6, 3))
    kappa[0, 0, 2] = L / k
    rod = SimpleNamespace(kappa=kappa, load_vertices=np.array([0]), weights=np.ones((1, 1)),
                          frames=np.eye(3)[None], parents=np.array([-1]))
    for theta in (0.1, 0.3, 0.6, 0.9):
        F = k * theta / (L * math.cos(theta))
        g = model.dead_loads(rod, np.array([[0.0, 0.0, F]]))
        got = model.pose_params_for_loads(rod, g)[0, 0]
        assert abs(got - theta) <= 0.02 * theta and abs(F * L / k - theta) >= 0.004 * theta
        assert np.linalg.norm(g) == pytest.approx(F)         # a dead load turns, it does not shrink
