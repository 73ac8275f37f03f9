"""The shared-error floor (hdmap/mapping/gnss_floor.py) against synthetic drives with known
biases and AR(1) errors (fixed seeds, stated noise).

Each drive: 3,600 epochs at 1 Hz, a constant bias ``b_d`` (what its passes share) plus an
AR(1) error of standard deviation 0.6 m and lag-1 correlation 0.97 (a 33 s correlation
time, like the GSDC phones' east error, fleetsim/data/README.md). The true floor is
``(1/D) sum_d b_d b_d^T``. Over ``SEEDS`` independent logs the mean estimate must lie
within the two-sided 99 % Student-t interval of its own spread around the truth (a bias
test whose bounds come from the draws, not from a typed-in figure), and the estimate
without the batch-means term must be biased upward by about the mean's variance
``sigma^2 (1 + rho) / (1 - rho) / n`` (0.024 m^2 here).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from hdmap.mapping.gnss_floor import batch_means, floor_enu, psd_part, shared_floor

SEEDS = 20
N = 3600
SIGMA, RHO = 0.6, 0.97


def ar1(rng: np.random.Generator, n: int, k: int) -> np.ndarray:
    """(n, k) stationary AR(1) errors of standard deviation SIGMA, lag-1 correlation RHO."""
    e = np.empty((n, k))
    e[0] = rng.normal(0.0, SIGMA, k)
    innov = rng.normal(0.0, SIGMA * np.sqrt(1.0 - RHO**2), (n, k))
    for i in range(1, n):
        e[i] = RHO * e[i - 1] + innov[i]
    return e


def logs(seed: int, biases: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
    rng = np.random.default_rng(seed)
    t = np.arange(N, dtype=float)
    return [t] * len(biases), [b + ar1(rng, N, biases.shape[1]) for b in biases]


def t_interval_holds(values: np.ndarray, truth: float, level: float = 0.99) -> bool:
    half = stats.t.ppf(0.5 + level / 2, len(values) - 1) * values.std(ddof=1) / np.sqrt(len(values))
    return bool(abs(values.mean() - truth) <= half)


def test_floor_is_the_second_moment_of_the_drives_biases():
    biases = np.array([[0.5, -1.2], [-0.3, 0.8], [0.0, 1.0]])
    truth = biases.T @ biases / len(biases)
    est = np.array([shared_floor(*logs(s, biases)).cov for s in range(SEEDS)])
    for i, j in ((0, 0), (0, 1), (1, 1)):
        assert t_interval_holds(est[:, i, j], truth[i, j]), (i, j, est[:, i, j].mean(), truth)


def test_independent_errors_give_no_floor_and_the_naive_moment_would():
    """No bias: the floor's mean is 0 within its interval (before the projection, which
    only raises it: the test uses the unprojected second moment), while the drives' mean
    squared error alone is biased up by the mean's variance."""
    zero = np.zeros((2, 2))
    long_run = SIGMA**2 * (1 + RHO) / (1 - RHO) / N
    raw, naive = [], []
    for s in range(SEEDS):
        f = shared_floor(*logs(s, zero))
        m, v = f.drive_means, f.mean_variances
        raw.append((np.einsum("di,dj->ij", m, m) / len(m) - v.mean(axis=0))[0, 0])
        naive.append(float((m[:, 0] ** 2).mean()))
    assert t_interval_holds(np.array(raw), 0.0)
    assert t_interval_holds(np.array(naive), long_run)
    assert np.mean(naive) > 0.5 * long_run


def test_batch_means_and_projection():
    t = np.array([0.0, 1.0, 300.0, 301.0, 900.0])
    e = np.array([[1.0], [3.0], [5.0], [7.0], [9.0]])
    assert batch_means(t, e, 300.0).ravel().tolist() == [2.0, 6.0, 9.0]  # the empty window out
    c = psd_part(np.array([[1.0, 2.0], [2.0, 1.0]]))  # eigenvalues 3 and -1
    assert np.allclose(c, [[1.5, 1.5], [1.5, 1.5]])
    f = shared_floor([np.arange(10.0)], [np.ones((10, 2))])
    assert floor_enu(f)[2].tolist() == [0.0, 0.0, 0.0] and floor_enu(f)[0, 0] == pytest.approx(1)


def test_refuses_what_it_cannot_measure():
    with pytest.raises(ValueError, match="one time array per drive"):
        shared_floor([], [])
    with pytest.raises(ValueError, match="finite"):
        shared_floor([np.arange(3.0)], [np.array([[0.0, np.nan]] * 3)])
