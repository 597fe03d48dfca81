"""Residual shapes of a tracked rig as a low-rank basis (``artdef_addon.residuals``): known answers."""
import numpy as np
import pytest

import artdef_addon
from artdef_addon import residuals, samples
from artdef_addon.options import (FitOptions, OptionsError, RESIDUAL_TARGET_MAX, RESIDUAL_TARGET_RMS)


def _low_rank(P, N, K, seed):
    rng = np.random.default_rng(seed)
    S = rng.normal(size=(K, N, 3))
    C = rng.normal(size=(P, K))
    return np.einsum("pk,knd->pnd", C, S)


@pytest.mark.parametrize("P,N,K", [(12, 40, 3), (30, 5, 4)])      # both sides of the Gram matrix
def test_principal_shapes_recover_a_residual_of_known_rank(P, N, K):
    seed = np.random.SeedSequence().entropy % 2 ** 32
    res = _low_rank(P, N, K, seed)
    U, s, V = residuals.principal_shapes(res, 10)
    assert U.shape[1] == K, "numerical zeros make no shape"
    assert np.allclose(U.T @ U, np.eye(K), atol=1e-8)
    back = (U * s) @ V
    assert np.allclose(back, res.reshape(P, -1), atol=1e-8 * np.abs(res).max())
    # the singular values are numpy's
    assert np.allclose(s, np.linalg.svd(res.reshape(P, -1), compute_uv=False)[:K], rtol=1e-8)
    err = residuals.truncation_errors(res, U, diag=1.0)
    assert err.shape == (K + 1, 2)
    assert np.all(np.diff(err[:, 1]) <= 1e-12), "RMS error falls with every shape"
    assert err[K, 0] < 1e-8 * 100 * np.abs(res).max()
    assert err[0, 0] == pytest.approx(100 * np.linalg.norm(res, axis=2).max())


def test_choose_rank_takes_the_fewest_that_reach_both_targets():
    errors = np.array([[5.0, 1.0], [2.0, 0.1], [0.9, 0.19], [0.5, 0.1]])
    assert residuals.choose_rank(errors, 3) == (2, True)
    assert residuals.choose_rank(errors, 1) == (1, False)          # the cap: the most allowed
    assert residuals.choose_rank(np.array([[0.5, 0.1]]), 4) == (0, True)   # the skin is enough


@pytest.fixture(scope="module")
def one_bone_short():
    """The branching object (11 bones) fitted with 10 links: what the missing bone moves, the skin
    misses."""
    sc = samples.make("branching", n_fields=24, seed=7)
    return sc, artdef_addon.fit(sc, 10, residuals=0)


def test_auto_rank_reaches_the_target_in_replay(one_bone_short):
    sc, res = one_bone_short
    x0, fields = sc.vertices, sc.fields()
    assert res.residual_basis.rank == 0                             # residuals=0: the skin alone
    b = residuals.low_rank_basis(res, x0, fields, None)
    assert b.skin_error[0] > RESIDUAL_TARGET_MAX, "the skin misses: the test is not empty"
    assert 0 < b.rank <= residuals.frame_cap(sc.n_fields)
    assert b.reached and b.replay_error[0] <= RESIDUAL_TARGET_MAX and b.replay_error[1] <= RESIDUAL_TARGET_RMS
    assert b.values.min() >= 0 and b.values.max() == pytest.approx(1.0)   # a weight slider's range
    assert b.keys in (b.rank, b.rank + 1)                           # and the offset of that shift
    # the replay with every field's own residual is exact (what the rank truncates)
    full = residuals.replay_error(res, x0, fields, res.residual, np.eye(sc.n_fields), b.skin_error[0] or 1.0)
    assert full[0] < 1e-6
    # the replay error of the fewer shapes is worse: the rank is the smallest that reaches the target
    fewer = residuals.low_rank_basis(res, x0, fields, b.rank - 1)
    assert fewer.rank == b.rank - 1
    assert fewer.replay_error[1] > b.replay_error[1]


def test_asked_count_and_the_rig_shapes(one_bone_short):
    sc, res = one_bone_short
    b = residuals.low_rank_basis(res, sc.vertices, sc.fields(), 3)
    assert b.rank == 3 and b.values.shape == (sc.n_fields, b.keys) and b.shapes.shape == (b.keys, sc.n_vertices, 3)
    assert b.keys == 4 and np.all(b.values[:, 3] == 1.0)            # signed weights: the offset key
    # the shapes at their weights are the best rank-3 residual (Eckart-Young: the SVD's truncation)
    approx = np.einsum("pk,knd->pnd", b.values, b.shapes).reshape(sc.n_fields, -1)
    U, s, Vt = np.linalg.svd(res.residual.reshape(sc.n_fields, -1), full_matrices=False)
    assert np.allclose(approx, (U[:, :3] * s[:3]) @ Vt[:3], atol=1e-9 * np.abs(res.residual).max())
    # more than the frames: as many as there are
    assert residuals.low_rank_basis(res, sc.vertices, sc.fields(), 64).rank <= sc.n_fields
    res.residual_basis = b
    shapes, values = residuals.rig_shapes(res)
    assert shapes.shape[0] == 4 and values.shape == (sc.n_fields, 4)


def test_greens_fits_keep_one_shape_per_field():
    sc = samples.make("greens_rod")
    res = artdef_addon.fit(sc, 3)
    assert res.residual_basis is None
    shapes, values = residuals.rig_shapes(res)
    assert values is None and shapes.shape[0] == sc.n_fields


def test_residuals_setting_is_checked_once():
    assert FitOptions().residuals is None                           # auto
    assert FitOptions(residuals=0).residuals == 0
    for bad in (-1, 65, 2.5, "three"):
        with pytest.raises(OptionsError):
            FitOptions(residuals=bad)


def test_the_basis_survives_the_result_file(one_bone_short, tmp_path):
    """The result file (and the worker's hand-over, the same arrays) keeps the rig's residual shapes."""
    sc, res = one_bone_short
    res.residual_basis = residuals.low_rank_basis(res, sc.vertices, sc.fields(), None)
    res.save(tmp_path / "r.npz")
    back = artdef_addon.FitResult.load(tmp_path / "r.npz").residual_basis
    b = res.residual_basis
    assert back.rank == b.rank and back.asked is None and back.cap == b.cap and back.reached == b.reached
    assert np.array_equal(back.shapes, b.shapes) and np.array_equal(back.values, b.values)
    assert back.replay_error == b.replay_error and back.describe() == b.describe()
