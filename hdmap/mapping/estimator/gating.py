"""Gating statistic, a vectorised initialiser and a calibration of unreported angular noise.

Gating: ray j (origin ``a``, measured azimuth/elevation) against a landmark estimate ``x``
with covariance ``C``: with ``v = x - a``, predicted angles ``az(v), el(v)`` and their
Jacobian ``J`` (2x3),

    chi2 = r^T S^-1 r,   r = (wrap(az(v) - az_j), el(v) - el_j),
    S = diag(s_az^2, s_el^2) + J (C + Sigma_a) J^T,   Sigma_a = diag(s_h^2, s_h^2, s_v^2),

about chi-square with 2 dof when the ray belongs to the landmark (first order in the
position terms; the angular noise enters directly in angle space).

>>> import numpy as np
>>> r = Rays.from_angles([[0.0, 0, 0]], [0.0], [0.0], 0.1, 0.1, 0.0, 0.0)
>>> ray_chi2(np.array([[0.0, 10.0, 0.0]]), np.zeros((1, 3, 3)), r).round(9).tolist()
[0.0]
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hdmap.mapping.estimator.model import (
    EstimatorConfig,
    Rays,
    effective_sigmas,
    ray_angles,
    sym_to_mat,
)
from hdmap.mapping.estimator.terms import ray_terms

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


def wrap(a: ArrayLike) -> Array:
    """Angles to [-pi, pi)."""
    return (np.asarray(a, float) + np.pi) % (2.0 * np.pi) - np.pi


def angle_jacobian(v: Array) -> Array:
    """``d(az, el)/dx`` at ``x = a + v``, shape (..., 2, 3)."""
    e, n, u = v[..., 0], v[..., 1], v[..., 2]
    rho2 = np.maximum(e * e + n * n, 1e-12)
    rho = np.sqrt(rho2)
    r2 = rho2 + u * u
    j = np.zeros((*v.shape[:-1], 2, 3))
    j[..., 0, 0] = n / rho2
    j[..., 0, 1] = -e / rho2
    j[..., 1, 0] = -u * e / (r2 * rho)
    j[..., 1, 1] = -u * n / (r2 * rho)
    j[..., 1, 2] = rho / r2
    return j


def ray_chi2(x: ArrayLike, cov: ArrayLike, rays: Rays, cfg: EstimatorConfig | None = None) -> Array:
    """Mahalanobis residual (n,) of ray j against landmark estimate ``x[j]``, ``cov[j]``.

    Angular residuals against the (effective) ``sigma_az``/``sigma_el``, plus the landmark
    covariance and the origin's position noise projected through the angle Jacobian.
    """
    cfg = cfg or EstimatorConfig()
    x = np.asarray(x, float).reshape(-1, 3)
    c = np.asarray(cov, float).reshape(-1, 3, 3)
    v = x - np.asarray(rays.origin, float)
    az, el = ray_angles(v)
    az_m, el_m = ray_angles(rays.direction)
    res = np.stack([wrap(az - az_m), el - el_m], axis=-1)
    j = angle_jacobian(v)
    sa = np.zeros_like(c)
    sa[:, 0, 0] = sa[:, 1, 1] = np.asarray(rays.sigma_pos_h, float) ** 2
    sa[:, 2, 2] = np.asarray(rays.sigma_pos_v, float) ** 2
    s = j @ (c + sa) @ np.swapaxes(j, -1, -2)
    s_az, s_el = effective_sigmas(rays, cfg)
    s[:, 0, 0] += s_az**2
    s[:, 1, 1] += s_el**2
    det = s[:, 0, 0] * s[:, 1, 1] - s[:, 0, 1] * s[:, 1, 0]
    det = np.where(det > 0, det, 1e-300)
    return (
        res[:, 0] ** 2 * s[:, 1, 1]
        - 2 * res[:, 0] * res[:, 1] * s[:, 0, 1]
        + res[:, 1] ** 2 * s[:, 0, 0]
    ) / det


def triangulate(
    rays: Rays,
    groups: ArrayLike | None = None,
    range_prior_m: float | None = 30.0,
    sigma_range_prior_m: float = 30.0,
    cfg: EstimatorConfig | None = None,
) -> tuple[Array, Array]:
    """Initial points of groups of rays (e.g. one pass each): textbook (uncompensated)
    weighted orthogonal-distance least squares, plus, with ``range_prior_m``, a weak prior
    that the point lies that far along each ray (keeps near-parallel rays finite).

    Returns ``x`` (k, 3) and the model covariance ``A^-1`` (k, 3, 3) for groups 0..k-1
    (NaN where singular). Weights use ``range_prior_m`` (or 30 m) as the range.

    >>> r = Rays.from_angles([[-10.0, 0, 0], [0, -10.0, 0]], [np.pi / 2, 0.0], [0.0, 0.0],
    ...                      0.01, 0.01, 1.0, 1.0)
    >>> triangulate(r, range_prior_m=None)[0].round(6).tolist()
    [[0.0, 0.0, 0.0]]
    """
    base = cfg or EstimatorConfig()
    tb = EstimatorConfig(
        compensate=False,
        weighting=base.weighting,
        extra_sigma_az=base.extra_sigma_az,
        extra_sigma_el=base.extra_sigma_el,
        min_range_m=base.min_range_m,
        min_sigma_pos_m=base.min_sigma_pos_m,
    )
    n = len(rays)
    g = np.zeros(n, np.int64) if groups is None else np.asarray(groups, np.int64).reshape(-1)
    k = int(g.max()) + 1 if n else 0
    origin = np.asarray(rays.origin, float)
    d = np.asarray(rays.direction, float)
    r0 = 30.0 if range_prior_m is None else float(range_prior_m)
    alpha, beta = ray_terms(rays, origin, origin + r0 * d, tb)
    a = np.zeros((k, 3, 3))
    b = np.zeros((k, 3))
    np.add.at(a, g, sym_to_mat(alpha))
    np.add.at(b, g, beta)
    if range_prior_m is not None:
        v = 1.0 / sigma_range_prior_m**2
        np.add.at(a, g, v * d[:, :, None] * d[:, None, :])
        np.add.at(b, g, v * d * (np.einsum("ni,ni->n", d, origin) + r0)[:, None])
    lam = np.linalg.eigvalsh(a)
    good = lam[:, 0] > 1e-12 * np.maximum(lam[:, -1], 1e-300)
    safe = np.where(good[:, None, None], a, np.eye(3))
    cov = np.linalg.inv(safe)
    x = np.einsum("kij,kj->ki", cov, b)
    nan = np.where(good, 0.0, np.nan)
    return x + nan[:, None], cov + nan[:, None, None]


def _gauss_hermite_2d(k: int = 24) -> tuple[Array, Array, Array]:
    t, w = np.polynomial.hermite_e.hermegauss(k)
    w = w / w.sum()
    return np.repeat(t, k), np.tile(t, k), np.outer(w, w).ravel()


_GH = _gauss_hermite_2d()


def _position_azimuth_variance_exact(q: Array) -> Array:
    qq = np.asarray(q, float)[..., None]
    u, v, w = _GH
    return (np.arctan2(qq * u, 1.0 - qq * v) ** 2 * w).sum(axis=-1)


_Q_GRID = np.linspace(0.0, 2.0, 2001)
_F_GRID = _position_azimuth_variance_exact(_Q_GRID)


def position_azimuth_variance(q: ArrayLike) -> Array:
    """``E[atan2(u, 1 - v)^2]`` for ``(u, v) ~ N(0, q^2 I)``: the azimuth variance an
    isotropic horizontal origin error of std ``q * rho`` causes at horizontal range ``rho``
    (``~ q^2`` for small ``q``; Gauss-Hermite quadrature, tabulated for ``q <= 2``).

    >>> position_azimuth_variance(np.array([0.01, 0.2])).round(6).tolist()
    [0.0001, 0.041815]
    """
    qq = np.asarray(q, float)
    return np.interp(np.minimum(qq, _Q_GRID[-1]), _Q_GRID, _F_GRID)


def excess_angular_variance(
    rays: Rays, x: ArrayLike, passes: ArrayLike, min_rays: int = 6, min_range_sigmas: float = 4.0
) -> tuple[float, int]:
    """Calibrate unreported azimuth noise shared by a pass (a heading bias) against
    landmarks of known position (surveyed reference signs, or well-converged ones).

    ``x[j]`` is ray j's landmark position, ``passes[j]`` its pass. Per pass, the weighted
    mean ``beta^_p`` of the azimuth residuals ``wrap(az_j - az(x_j - a_j))`` (weights
    ``1 / (s_az^2 + f(s_h / rho))``, ``f`` = :func:`position_azimuth_variance`, ``rho`` the
    horizontal range; rays nearer than ``min_range_sigmas * s_h`` left out, there the
    azimuth error from the origin noise is far from Gaussian) estimates the pass's heading
    offset with model variance ``V_p = 1 / sum w``; so ``s_x^2 = mean(beta^_p^2 - V_p)``.

    Assumes the rays' white errors are independent and as reported, and that the origins
    carry no unreported pass-level *position* offset (correct them first with the pass
    offset the matcher estimates): seen from a narrow corridor, a lateral offset ``o`` of
    the whole pass turns every bearing by about ``o / rho`` and is counted as heading bias.

    Returns ``(s_x, passes used)``; use ``s_x`` as :attr:`EstimatorConfig.extra_sigma_az`.

    >>> rng = np.random.default_rng(0)
    >>> p = np.repeat(np.arange(400), 20)                 # 400 passes of 20 rays
    >>> a = np.stack([np.zeros(8000), rng.uniform(-60, -25, 8000), np.zeros(8000)], 1)
    >>> az = np.arctan2(-a[:, 0], -a[:, 1]) + rng.normal(0, 0.05, 8000) + rng.normal(
    ...     0, 0.1, 400)[p]                                # white 0.05 + pass bias 0.1
    >>> r = Rays.from_angles(a, az, np.zeros(8000), 0.05, 0.01, 0.0, 0.0)
    >>> s_x, n = excess_angular_variance(r, np.zeros((8000, 3)), p)
    >>> round(s_x, 1), n
    (0.1, 400)
    """
    x = np.asarray(x, float).reshape(-1, 3)
    v = x - np.asarray(rays.origin, float)
    rho = np.maximum(np.hypot(v[:, 0], v[:, 1]), 1e-6)
    az, _ = ray_angles(v)
    az_m, _ = ray_angles(rays.direction)
    r = wrap(az_m - az)
    s_h = np.asarray(rays.sigma_pos_h, float)
    w = 1.0 / (np.asarray(rays.sigma_az, float) ** 2 + position_azimuth_variance(s_h / rho))
    keep = rho >= min_range_sigmas * s_h
    _, p = np.unique(np.asarray(passes, np.int64).reshape(-1)[keep], return_inverse=True)
    sw = np.bincount(p, w[keep])
    swr = np.bincount(p, w[keep] * r[keep])
    cnt = np.bincount(p)
    use = cnt >= min_rays
    if not use.any():
        return 0.0, 0
    beta = swr[use] / sw[use]
    est = float(np.mean(beta**2 - 1.0 / sw[use]))
    return float(np.sqrt(max(est, 0.0))), int(use.sum())
