"""The fit and the segmentation in a worker process (artdef_addon.jobs): the same results as in
this process, cancelling, a memory limit, the kept segmentation."""
import os

import numpy as np
import pytest

from artdef_addon import FitCancelled, FitOptions, api, jobs, procs, samples

pytestmark = pytest.mark.core


@pytest.fixture
def session():
    s = jobs.Session()
    yield s
    s.close()


def test_the_fit_in_a_worker_is_the_fit_in_this_process(session):
    scan = samples.make("branching", seed=4)
    options = FitOptions(skin="refined")
    stages = []
    got = session.fit(scan, 11, options, lambda stage, fraction: stages.append(stage))
    ref = api.fit(scan, 11, options)
    assert session.pid is not None and session.pid != os.getpid()
    assert np.array_equal(got.face_labels, ref.face_labels)
    assert np.array_equal(got.parents, ref.parents)
    np.testing.assert_allclose(got.joints, ref.joints, rtol=0, atol=1e-12)   # NaN where ref's is
    np.testing.assert_allclose(got.weights, ref.weights, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got.residual, ref.residual, rtol=0, atol=1e-12)
    assert got.rms_articulation == pytest.approx(ref.rms_articulation, rel=1e-12)
    assert got.options == options and got.estimate == ref.estimate and got.groups == ref.groups
    assert got.reduced == ref.reduced and got.notes == ref.notes
    assert stages[0] == "features" and stages[-1] == "done" and "skin" in stages


def test_links_auto_in_a_worker_keeps_its_reason_and_curve(session):
    scan = samples.make("rod", n_fields=4, seed=3)
    got = session.fit(scan, "auto", FitOptions(max_links=6))
    ref = api.fit(scan, "auto", FitOptions(max_links=6))
    assert got.n_links == ref.n_links == 3
    assert got.link_reason == ref.link_reason and got.link_errors == pytest.approx(ref.link_errors)


def test_a_progress_callback_that_cancels_ends_the_worker(session):
    scan = samples.make("branching")
    with pytest.raises(FitCancelled):
        session.fit(scan, 11, None, lambda stage, fraction: stage == "cluster")
    assert session.worker is None
    # the next call starts a fresh worker
    assert session.fit(samples.make("rod"), 3).n_links == 3


def test_a_fit_over_the_memory_limit_is_one_line_and_ends_the_worker():
    s = jobs.Session(memory_limit=4 * 2**20)
    with pytest.raises(procs.WorkerError) as info:
        s.fit(samples.make("branching"), 11)
    assert info.value.kind == "memory" and "ran out of memory (its limit is 4 MB)" in str(info.value)
    assert s.worker is None


def test_the_worker_keeps_the_segmentation_between_calls(session):
    scan = samples.make("branching", seed=2)
    assert session.cached(scan) is None                  # no worker yet
    labels, reduced, _ = session.segment(scan, 11)
    ref = api.segment(scan, 11)[0]
    assert np.array_equal(labels, ref) and not reduced
    token = session.cached(scan)
    assert token is not None
    assert len(np.unique(session.segment(scan, 5)[0])) == 5
    assert session.cached(scan) == token                 # the same segmentation served
    assert session.fit(scan, 11).n_links == 11
    assert session.cached(scan) == token
    assert session.cached(scan, FitOptions(strategy="paper")) is None   # other settings: another
    session.kill()
    assert session.cached(scan) is None
