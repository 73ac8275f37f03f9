"""Confidence ellipses of horizontal positions: pure, vectorised.

A landmark's horizontal uncertainty is the 2x2 east/north block of its ENU covariance
(``Landmarks.cov`` = ee en eu nn nu uu, m^2; :func:`horizontal_cov`). Its ``level`` ellipse
has semi-axes ``sqrt(k^2 lambda_i)`` along the block's eigenvectors, ``k^2`` the
chi-square(2) quantile at ``level``, which for 2 degrees of freedom has the closed form
``-2 ln(1 - level)`` (:func:`chi2_2dof`; 5.991 at 95 %, :data:`CHI2_2DOF_95`).

>>> a, b, az = ellipse_axes(np.array([[4.0, 0.0, 1.0]]))  # sigma_E 2 m, sigma_N 1 m
>>> round(float(a[0]), 3), round(float(b[0]), 3), round(float(az[0]), 1)
(4.895, 2.448, 90.0)
>>> a, b, az = ellipse_axes([[1.0, 0.9, 1.0]])  # correlated: along north-east
>>> round(float(a[0]), 3), round(float(b[0]), 3), round(float(az[0]), 1)
(3.374, 0.774, 45.0)
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]


def chi2_2dof(level: float) -> float:
    """chi-square(2) quantile at ``level``: ``-2 ln(1 - level)``.

    >>> round(chi2_2dof(0.95), 4), round(chi2_2dof(0.3934693), 4)
    (5.9915, 1.0)
    """
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")
    return -2.0 * math.log1p(-level)


CHI2_2DOF_95 = chi2_2dof(0.95)
"""chi-square(2) 0.95 quantile (5.9915): the 95 % region of a 2-D normal."""


def horizontal_cov(cov6: ArrayLike) -> Array:
    """(N, 3) east-east, east-north, north-north of (N, 6) ENU covariances (ee en eu nn nu
    uu).

    >>> horizontal_cov([[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]]).tolist()
    [[1.0, 2.0, 4.0]]
    """
    c = np.asarray(cov6, float).reshape(-1, 6)
    return np.stack([c[:, 0], c[:, 1], c[:, 3]], axis=1)


def ellipse_axes(cov_en: ArrayLike, level: float = 0.95) -> tuple[Array, Array, Array]:
    """(semi-major m, semi-minor m, azimuth of the major axis in degrees clockwise from North
    in [0, 180)) of the ``level`` ellipses of (N, 3) covariances (ee, en, nn) in m^2.

    Non-finite entries count as 0; a negative eigenvalue (rounding) as 0."""
    c = np.nan_to_num(np.asarray(cov_en, float).reshape(-1, 3), nan=0.0, posinf=0.0, neginf=0.0)
    ee, en, nn = c[:, 0], c[:, 1], c[:, 2]
    mean = 0.5 * (ee + nn)
    half = np.hypot(0.5 * (ee - nn), en)
    k2 = chi2_2dof(level)
    major = np.sqrt(k2 * np.maximum(mean + half, 0.0))
    minor = np.sqrt(k2 * np.maximum(mean - half, 0.0))
    theta = 0.5 * np.arctan2(2.0 * en, ee - nn)  # major axis, radians from East toward North
    azimuth = np.mod(90.0 - np.degrees(theta), 180.0)
    return major, minor, azimuth
