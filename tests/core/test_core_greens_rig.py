"""A Green's rig poses G f to first order (paper §7.1; model.greens_keys): for every mode, with and
without hardening, on solids it never saw, any load on any points in any direction; the probe fields
stay exact and the rest pose is the rest."""
import numpy as np
import pytest

from artdef_addon import model
import artdef_addon
from benchmarks import solids as S

pytestmark = pytest.mark.core


def _gf(scan, loads):
    return (scan.greens @ loads.ravel()).reshape(-1, 3)


@pytest.mark.parametrize("name,seed,mode,p_max", [("finger", 31, "global", None), ("T", 32, "pseudo", None),
                                                  ("fork", 33, "global", 3.0), ("finger", 34, "pseudo", 2.0)])
def test_rig_is_G_to_first_order_and_exact_at_the_probe(name, seed, mode, p_max):
    solid = S.make_solid(name, seed)
    scan = S.greens_scan(solid)
    r = artdef_addon.fit(scan, len(solid.joints) + 1, mode=mode, p_max=p_max)
    x0, M, ph = scan.vertices, scan.n_loads, scan.probe_load
    assert np.abs(model.evaluate_loads(r, x0, np.zeros((M, 3))) - x0).max() <= 1e-12 * np.abs(x0).max()
    rng = np.random.default_rng(seed)
    # the difference from G f shrinks in proportion to the load: rig(f) = G f + O(|f|^2)
    f = rng.normal(size=(M, 3)) * ph
    rel = [np.linalg.norm(model.evaluate_loads(r, x0, e * f) - x0 - _gf(scan, e * f)) / np.linalg.norm(_gf(scan, e * f))
           for e in (1e-2, 1e-3)]
    assert rel[1] <= 2e-4 and rel[1] <= 0.12 * rel[0], rel
    # small loads on 2-3 points in random directions: within 1 % of G f
    for _ in range(6):
        f = np.zeros((M, 3))
        pts = rng.choice(M, int(rng.integers(2, 4)), replace=False)
        d = rng.normal(size=(len(pts), 3))
        f[pts] = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0.05, 0.2, (len(pts), 1)) * ph
        u = model.evaluate_loads(r, x0, f) - x0
        assert np.linalg.norm(u - _gf(scan, f)) <= 0.01 * np.linalg.norm(_gf(scan, f))
    # each probe field is reproduced
    fields = scan.fields()
    for c in range(3 * M):
        loads = np.zeros((M, 3))
        loads[c // 3, c % 3] = ph
        assert np.abs(model.evaluate_loads(r, x0, loads) - x0 - fields[c]).max() <= 1e-9 * np.abs(fields).max()


def test_linear_displacement_is_the_derivative_of_the_skin():
    solid = S.make_solid("T", 35)
    scan = S.greens_scan(solid)
    r = artdef_addon.fit(scan, 3)
    params = np.random.default_rng(0).normal(size=(r.n_links, 6))
    x0 = scan.vertices
    lin = model.linear_displacement(r.parents, r.heads, r.frames, r.weights, params, x0)
    h = 1e-6

    def skinned(e):
        R, t = model.forward_kinematics(r.parents, r.heads, r.frames, e * params)
        return model.skin(r.weights, R, t, x0)
    np.testing.assert_allclose((skinned(h) - skinned(-h)) / (2 * h), lin, atol=1e-6 * np.abs(lin).max())
