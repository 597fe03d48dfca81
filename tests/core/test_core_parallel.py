"""The fit's work over several processes (FitOptions.jobs, artdef_addon.parallel): the same rig as
the serial path (jobs 1), links, joints and weights equal to 1e-9."""
import numpy as np
import pytest

from artdef_addon import FitOptions, api, parallel, procs, samples, skinning

pytestmark = pytest.mark.core


def test_jobs_1_and_the_pool_give_the_same_rig(monkeypatch):
    # the pooled stages start at the sizes of large scans: lowered so a small scan takes them
    monkeypatch.setattr(parallel, "POOL_TRIANGLES", 0)
    monkeypatch.setattr(skinning, "POOL_ROWS", 0)
    monkeypatch.setattr(skinning, "SOLVE_BLOCK", 128)
    used = []
    real = procs.Pool.imap

    def imap(self, function, tasks, arrays=None):
        used.append(function.rpartition(":")[2])
        return real(self, function, tasks, arrays)

    monkeypatch.setattr(procs.Pool, "imap", imap)
    scan = samples.make("branching", seed=6, n_fields=10)
    one = api.fit(scan, 11, FitOptions(reduce="on", jobs=1))
    assert used == []
    api.clear_cache()                   # the segmentation is computed again, on the pool
    two = api.fit(scan, 11, FitOptions(reduce="on", jobs=2))
    assert {"neighbour_task", "weight_task"} <= set(used)
    assert np.array_equal(one.face_labels, two.face_labels)
    assert np.array_equal(one.parents, two.parents)
    np.testing.assert_allclose(two.joints, one.joints, rtol=0, atol=1e-9)
    np.testing.assert_allclose(two.weights, one.weights, rtol=0, atol=1e-9)
    assert two.rms_articulation == pytest.approx(one.rms_articulation, rel=1e-9)


def test_the_default_is_one_process_per_core():
    assert FitOptions().jobs == 0 and FitOptions().processes == procs.cores() >= 1
    assert FitOptions(jobs=3).processes == 3
