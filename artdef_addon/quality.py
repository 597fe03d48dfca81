"""Agreement and error measures used by the tests, benchmarks and the fit summary."""
from __future__ import annotations

import numpy as np
from scipy.special import comb


def adjusted_rand_index(a, b) -> float:
    """Adjusted Rand index of two labellings (Hubert & Arabie 1985); 1 = identical partitions."""
    a = np.unique(np.asarray(a), return_inverse=True)[1]
    b = np.unique(np.asarray(b), return_inverse=True)[1]
    n = a.size
    table = np.zeros((a.max() + 1, b.max() + 1))
    np.add.at(table, (a, b), 1)
    sum_ij = comb(table, 2).sum()
    sum_a = comb(table.sum(axis=1), 2).sum()
    sum_b = comb(table.sum(axis=0), 2).sum()
    expected = sum_a * sum_b / comb(n, 2) if n > 1 else 0.0
    top = 0.5 * (sum_a + sum_b)
    if top == expected:
        return 1.0
    return float((sum_ij - expected) / (top - expected))


def match_links(pred, truth) -> np.ndarray:
    """For every predicted link, the true link it overlaps most (by triangle count)."""
    pred = np.asarray(pred)
    truth = np.asarray(truth)
    table = np.zeros((pred.max() + 1, truth.max() + 1))
    np.add.at(table, (pred, truth), 1)
    return table.argmax(axis=1)
