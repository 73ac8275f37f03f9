"""Estimator scenes: exact angles, random batches, passes of one sign with a bias."""

from __future__ import annotations

import numpy as np

from hdmap.mapping.estimator import (
    Rays,
)

SIGN = np.array([5.0, 0.0, 2.5])


def passes(rng: np.random.Generator, n_pass: int, first: int, bias_m: float = 0.0) -> tuple:
    """Rays of ``n_pass`` passes (8-14 rays each) at SIGN; per pass a 2.5 m GNSS offset,
    plus ``bias_m`` east (a shifted vehicle)."""
    meas, true, clusters = [], [], []
    for p in range(n_pass):
        k = int(rng.integers(8, 15))
        off = rng.normal(0.0, 2.5, 3) * [1.0, 1.0, 0.3] + [bias_m, 0.0, 0.0]
        a = SIGN + np.stack([rng.uniform(-6, -4, k), np.linspace(-40, -10, k), np.full(k, -1.1)], 1)
        true.append(a)
        meas.append(a + off)
        clusters.append(np.full(k, first + p))
    meas, true = np.concatenate(meas), np.concatenate(true)
    az, el = true_angles(np.broadcast_to(SIGN, true.shape), true)
    n = meas.shape[0]
    r = Rays.from_angles(
        meas, az + rng.normal(0, 0.01, n), el + rng.normal(0, 0.005, n), 0.01, 0.005, 1.0, 1.5
    )
    return np.concatenate(clusters), r


def true_angles(x: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    v = x - a
    return np.arctan2(v[..., 0], v[..., 1]), np.arctan2(v[..., 2], np.hypot(v[..., 0], v[..., 1]))


# ---------------------------------------------------------------- sums and passes
def random_batch(rng, n_rows=7, n=300, x=None):
    x = np.array([5.0, 0.0, 2.5]) if x is None else x
    rows = rng.integers(0, n_rows, n)
    clusters = rng.integers(0, 12, n)
    xs = x + 10.0 * rows[:, None] * np.array([1.0, 0.5, 0.0])
    a = xs + np.stack([rng.uniform(-3, 3, n), rng.uniform(-40, -8, n), np.full(n, -1.0)], 1)
    az, el = true_angles(xs, a)
    r = Rays.from_angles(
        a + rng.normal(0, 1.0, (n, 3)),
        az + rng.normal(0, 0.05, n),
        el + rng.normal(0, 0.01, n),
        0.05,
        0.01,
        1.0,
        1.5,
    )
    return rows, clusters, r, xs
