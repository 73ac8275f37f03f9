"""Synthetic plumbing observations: valid, random, for tests and benchmarks of the bus."""

from __future__ import annotations

import time

import numpy as np

from schemas import Observations


def make_observations(
    n: int, seed: int = 0, t: float | None = None, lat: float = 60.17, lon: float = 24.94
) -> Observations:
    """Valid observations (random horizontal directions) for plumbing tests."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d[:, 2] = 0.0
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return Observations(
        obs_id=np.arange(1, n + 1, dtype=np.uint64),
        t=np.full(n, time.time() if t is None else t),
        image=(np.arange(n) // 2).astype(np.uint32),
        sign_class=np.full(n, 4, np.uint16),
        lat=np.full(n, lat) + rng.normal(0, 1e-4, n),
        lon=np.full(n, lon) + rng.normal(0, 1e-4, n),
        h=np.full(n, 20.0),
        direction=d,
        sigma_az=np.full(n, 0.01),
        sigma_el=np.full(n, 0.01),
        sigma_pos_h=np.full(n, 2.5),
        sigma_pos_v=np.full(n, 4.0),
        range_m=np.full(n, 20.0),
        sigma_range_m=np.full(n, 2.0),
        score=np.full(n, 0.9, np.float32),
    )
