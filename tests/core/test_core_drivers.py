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
