"""``min_cost_assignment`` gives the pairs ``scipy.optimize.linear_sum_assignment`` gives,
ties included, on random small matrices (the detections of one image), so the onboard
tracker without scipy and the matcher assign alike."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

from hdmap.mapping.assignment import min_cost_assignment


@pytest.mark.parametrize("kind", ["uniform", "small_integers", "gated", "mostly_gated"])
def test_same_pairs_as_scipy(kind):
    rng = np.random.default_rng(["uniform", "small_integers", "gated", "mostly_gated"].index(kind))
    for _ in range(2000):
        n, m = rng.integers(1, 8, 2)
        if kind == "uniform":
            c = rng.random((n, m))
        elif kind == "small_integers":  # many ties
            c = rng.integers(0, 3, (n, m)).astype(float)
        elif kind == "gated":  # as assign_per_image builds them: 1e9 = not allowed
            c = np.where(rng.random((n, m)) < 0.5, 1e9, rng.random((n, m)))
        else:
            c = np.where(rng.random((n, m)) < 0.3, 1.0, 1e9)
        rows, cols = min_cost_assignment(c)
        ref_rows, ref_cols = linear_sum_assignment(c)
        assert rows.tolist() == ref_rows.tolist() and cols.tolist() == ref_cols.tolist(), c


def test_refuses_what_it_cannot_assign():
    with pytest.raises(ValueError, match="finite"):
        min_cost_assignment(np.array([[np.inf, 1.0]]))
    with pytest.raises(ValueError, match="2-d"):
        min_cost_assignment(np.zeros(3))
    rows, cols = min_cost_assignment(np.zeros((0, 4)))
    assert rows.size == cols.size == 0
