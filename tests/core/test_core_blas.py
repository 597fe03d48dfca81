"""One BLAS thread for the link-count search's many small products (artdef_addon.blas)."""
import numpy as np
import pytest

from artdef_addon import blas, metric, samples
from artdef_addon import segmenter as SG


def test_single_threaded_sets_and_restores_openblas_threads_and_changes_no_bit():
    fns = blas._openblas()
    if fns is None:
        pytest.skip("numpy does not use OpenBLAS here: single_threaded does nothing")
    set_, get_ = fns
    before = get_()
    seg = SG.Segmenter(samples.make("branching"))
    f = seg.features[0]
    rows, cols = np.arange(0, seg.features[0].n, 2), np.arange(seg.features[0].n)
    many = metric.distance_block(f, rows, cols)
    with blas.single_threaded():
        assert get_() == 1
        with blas.single_threaded():
            assert get_() == 1
        assert get_() == 1
        one = metric.distance_block(f, rows, cols)
    assert get_() == before
    assert np.array_equal(one, many)
