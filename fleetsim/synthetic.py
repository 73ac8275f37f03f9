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


def ray_observations(
    lat: np.ndarray,
    lon: np.ndarray,
    h: np.ndarray,
    direction: np.ndarray,
    image: np.ndarray,
    obs_id: np.ndarray,
    sign_class: int,
    sigma_ang: float = 0.005,
    t: float | None = None,
) -> Observations:
    """Rays without a range from given origins and ENU directions: 1 m / 1.5 m reported
    position sigmas (horizontal / vertical), ``sigma_ang`` rad on both angles, score 0.9."""
    n = len(obs_id)
    return Observations(
        obs_id=np.asarray(obs_id).astype(np.uint64),
        t=np.full(n, time.time() if t is None else t),
        image=np.asarray(image).astype(np.uint32),
        sign_class=np.full(n, sign_class, np.uint16),
        lat=np.atleast_1d(lat),
        lon=np.atleast_1d(lon),
        h=np.atleast_1d(h),
        direction=direction,
        sigma_az=np.full(n, sigma_ang),
        sigma_el=np.full(n, sigma_ang),
        sigma_pos_h=np.full(n, 1.0),
        sigma_pos_v=np.full(n, 1.5),
        range_m=np.zeros(n),
        sigma_range_m=np.zeros(n),
        score=np.full(n, 0.9, np.float32),
    )
