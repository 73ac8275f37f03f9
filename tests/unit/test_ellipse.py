"""hdmap.geo.ellipse: the 95 % ellipses of the dashboard and the export, against
independent references (scipy's chi-square quantile, numpy's eigen-decomposition)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chi2

from hdmap.geo.ellipse import CHI2_2DOF_95, chi2_2dof, ellipse_axes, horizontal_cov


def test_the_95_percent_level_is_the_chi_square_2_quantile():
    assert CHI2_2DOF_95 == pytest.approx(chi2.ppf(0.95, 2), rel=1e-12)
    assert CHI2_2DOF_95 == pytest.approx(5.991464547107979)
    for level in (0.5, 0.9, 0.99, 1e-9):
        assert chi2_2dof(level) == pytest.approx(chi2.ppf(level, 2), rel=1e-9)
    for level in (0.0, 1.0, -0.5, 1.5):
        with pytest.raises(ValueError, match="level"):
            chi2_2dof(level)


def test_the_horizontal_block_of_enu_covariances():
    cov6 = np.arange(12.0).reshape(2, 6)  # ee en eu nn nu uu
    assert horizontal_cov(cov6).tolist() == [[0.0, 1.0, 3.0], [6.0, 7.0, 9.0]]
    assert horizontal_cov(np.zeros((0, 6))).shape == (0, 3)


def test_axes_of_an_axis_aligned_covariance():
    # sigma_E 3 m, sigma_N 1 m: semi-axes 3 k and 1 k, the major one East (azimuth 90)
    major, minor, az = ellipse_axes(np.array([[9.0, 0.0, 1.0]]))
    k = math.sqrt(chi2.ppf(0.95, 2))
    assert major[0] == pytest.approx(3.0 * k, rel=1e-12)
    assert minor[0] == pytest.approx(1.0 * k, rel=1e-12)
    assert az[0] == pytest.approx(90.0)
    # sigma_N the larger one: the major axis points North (azimuth 0)
    _, _, az = ellipse_axes(np.array([[1.0, 0.0, 9.0]]))
    assert az[0] == pytest.approx(0.0)


def test_axes_of_rotated_covariances_match_their_eigen_decomposition():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(200, 2, 2)) * rng.uniform(0.1, 5.0, (200, 1, 1))
    c = a @ a.transpose(0, 2, 1)
    major, minor, az = ellipse_axes(np.stack([c[:, 0, 0], c[:, 0, 1], c[:, 1, 1]], axis=1))
    k2 = chi2.ppf(0.95, 2)
    for i in range(len(c)):
        w, v = np.linalg.eigh(c[i])
        assert major[i] == pytest.approx(math.sqrt(k2 * w[1]), rel=1e-9)
        assert minor[i] == pytest.approx(math.sqrt(k2 * max(w[0], 0.0)), rel=1e-6, abs=1e-9)
        assert 0.0 <= az[i] < 180.0
        # the major axis's direction (east, north) = (sin az, cos az) is the eigenvector
        d = np.array([math.sin(math.radians(az[i])), math.cos(math.radians(az[i]))])
        assert abs(float(d @ v[:, 1])) == pytest.approx(1.0, abs=1e-6)


def test_a_known_rotated_ellipse():
    # major axis along azimuth 30 (clockwise from North), sigmas 4 m and 1 m
    t = math.radians(30.0)
    u, v = np.array([math.sin(t), math.cos(t)]), np.array([-math.cos(t), math.sin(t)])
    c = 16.0 * np.outer(u, u) + 1.0 * np.outer(v, v)
    major, minor, az = ellipse_axes(np.array([[c[0, 0], c[0, 1], c[1, 1]]]))
    k = math.sqrt(chi2.ppf(0.95, 2))
    assert (major[0], minor[0], az[0]) == pytest.approx((4.0 * k, 1.0 * k, 30.0))


def test_other_levels_scale_the_axes():
    c = np.array([[9.0, 2.0, 4.0]])
    major95, minor95, az95 = ellipse_axes(c)
    major, minor, az = ellipse_axes(c, level=0.5)
    ratio = math.sqrt(chi2.ppf(0.5, 2) / chi2.ppf(0.95, 2))
    assert (major[0], minor[0], az[0]) == pytest.approx(
        (major95[0] * ratio, minor95[0] * ratio, az95[0])
    )


def test_degenerate_covariances_give_finite_axes():
    major, minor, _ = ellipse_axes(np.array([[0.0, 0.0, 0.0], [np.nan, 0.0, 4.0], [1.0, 1.0, 1.0]]))
    assert np.isfinite(major).all() and np.isfinite(minor).all()
    assert major[0] == 0.0 and minor[2] == pytest.approx(0.0, abs=1e-6)
