"""Estimates usable before the between-pass covariance can be trusted.

The cluster-robust covariance needs ``min_clusters`` passes (``EstimatorConfig``). Below
that, a landmark seen by at least ``min_passes`` passes whose information matrix is
well-conditioned still has a usable estimate; what its few passes cannot measure is the
error they share (each pass's GNSS bias), so its covariance gets that prior added,
``diag(sigma_bias^2) / G`` for ``G`` passes. Such estimates are published as candidates
and used for gating; ``Solution.ok`` ones are confirmed.

>>> import numpy as np
>>> prior_covariance((2.0, 2.0, 1.0), np.array([1, 4]))[:, 0, 0].tolist()
[4.0, 1.0]
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hdmap.mapping.estimator.model import EstimatorConfig
from hdmap.mapping.estimator.solve import Solution


def provisional(sol: Solution, cfg: EstimatorConfig, min_passes: int) -> NDArray[np.bool_]:
    """Landmarks not ``ok`` yet with a finite, well-conditioned estimate from
    ``min_passes`` passes and ``cfg.min_rays`` rays (``min_passes`` 0: none)."""
    n_clusters = np.asarray(sol.n_clusters)
    return (
        ~np.asarray(sol.ok, bool)
        & (min_passes > 0)
        & (n_clusters >= max(min_passes, 1))
        & (np.asarray(sol.n_obs) >= cfg.min_rays)
        & np.isfinite(sol.x).all(axis=1)
        & np.isfinite(sol.cov).all(axis=(1, 2))
        & (np.asarray(sol.cond) <= cfg.max_cond)
        & (np.asarray(sol.significance) >= cfg.min_realized_significance)
    )


def prior_covariance(bias_sigma: ArrayLike, n_passes: ArrayLike) -> NDArray[np.float64]:
    """(n, 3, 3) covariance of the mean of ``n_passes`` independent per-pass biases."""
    g = np.maximum(np.asarray(n_passes, float).reshape(-1), 1.0)
    d = np.diag(np.square(np.asarray(bias_sigma, float)))
    return d[None] / g[:, None, None]


def usable(
    sol: Solution, cfg: EstimatorConfig, min_passes: int, bias_sigma: ArrayLike
) -> tuple[NDArray[np.bool_], NDArray[np.bool_], NDArray[np.float64]]:
    """(usable, provisional, covariance): ``ok`` or provisional landmarks within
    ``cfg.max_offset_m`` of their frame's origin, and their covariance (the solution's,
    plus the bias prior for the provisional ones)."""
    with np.errstate(invalid="ignore"):
        near = np.linalg.norm(np.asarray(sol.x, float), axis=1) <= cfg.max_offset_m
    prov = provisional(sol, cfg, min_passes) & near
    cov = np.array(sol.cov, float, copy=True)
    if prov.any():
        cov[prov] += prior_covariance(bias_sigma, np.asarray(sol.n_clusters)[prov])
    return (np.asarray(sol.ok, bool) & near) | prov, prov, cov
