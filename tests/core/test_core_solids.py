"""The nonlinear truth the Green's rig is judged against (benchmarks/solids.py): its stiffness at zero
load is the linear stiffness that made G, a small load's solution is G f, and it is frame-indifferent."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from artdef_addon.scan import validate_scan
from benchmarks import solids as S

pytestmark = pytest.mark.core


@pytest.mark.parametrize("name,seed", [("finger", 11), ("T", 12), ("fork", 13)])
def test_tangent_at_zero_is_the_linear_stiffness_and_small_loads_give_G_f(name, seed):
    solid = S.make_solid(name, seed)
    K = S.linear_stiffness(solid)
    Kt = S.tangent_stiffness(solid, np.zeros((len(solid.nodes), 3)))
    assert abs(K - Kt).max() <= 1e-12 * abs(K).max()
    scan = validate_scan(S.greens_scan(solid))
    rng = np.random.default_rng(seed)
    f = rng.normal(size=(len(solid.loads), 3)) * scan.probe_load
    rel = []
    for scale in (1e-3, 1e-2):
        u = S.surface_truth(solid, scale * f)
        lin = (scan.greens @ (scale * f).ravel()).reshape(-1, 3)
        rel.append(np.linalg.norm(u - lin) / np.linalg.norm(lin))
    # u = G f + O(|f|²): the relative difference is small and shrinks in proportion to the load
    assert rel[1] <= 3e-3 and rel[0] <= 0.2 * rel[1]
    # a large load is not linear: the truth moves off G f
    u = S.surface_truth(solid, 5 * f)
    lin = (scan.greens @ (5 * f).ravel()).reshape(-1, 3)
    assert np.linalg.norm(u - lin) >= 0.02 * np.linalg.norm(lin)


def test_rigid_motion_has_no_internal_force_and_large_loads_keep_equilibrium():
    solid = S.make_solid("finger", 5)
    R = Rotation.from_rotvec([0.3, -0.7, 0.4]).as_matrix()
    u = solid.nodes @ R.T + [1.0, 2.0, -3.0] - solid.nodes
    f = S.internal_forces(solid, u)
    assert np.abs(f).max() <= 1e-9 * solid.mu.max()
    scan = S.greens_scan(solid)
    loads = np.zeros((len(solid.loads), 3))
    loads[-1, 2] = 10 * scan.probe_load
    u = S.nonlinear_solve(solid, loads)
    r = S.internal_forces(solid, u) - S._load_vector(solid, loads)
    free = np.setdiff1d(np.arange(len(solid.nodes)), solid.fixed)
    assert np.linalg.norm(r[free]) <= 1e-8 * np.linalg.norm(loads)
    assert np.all(u[solid.fixed] == 0)
    # the stiff links stay rigid: their nodes keep their distances to 1e-3
    link = solid.nodes[solid.link == 2]
    moved = link + u[solid.link == 2]
    d0 = np.linalg.norm(link[:, None] - link[None], axis=-1)
    d1 = np.linalg.norm(moved[:, None] - moved[None], axis=-1)
    assert np.abs(d1 - d0).max() <= 1e-3 * d0.max()
