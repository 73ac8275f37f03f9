"""Receiver accuracies -> 1-sigma values (vehicle.receivers), checked against samples of
the distributions the receivers describe, with binomial bounds for the stated seed."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vehicle.receivers import (
    ANDROID_R68_PER_SIGMA,
    GAUSS_68_PER_SIGMA,
    from_android,
    from_nmea_gst,
)

N = 200_000
Z = 4.0
"""Half-width of the accepted band in binomial standard deviations (two-sided p ~ 6e-5)."""


def within_68(fraction: float) -> bool:
    half = Z * math.sqrt(0.68 * 0.32 / N)
    return abs(fraction - 0.68) <= half


def test_android_accuracy_is_the_68_percent_radius():
    sigma = 2.0
    rng = np.random.default_rng(0)  # the stated seed
    xy = rng.normal(0.0, sigma, (N, 2))
    r68 = sigma * ANDROID_R68_PER_SIGMA  # what a receiver of this sigma reports
    assert within_68(float(np.mean(np.hypot(*xy.T) <= r68)))
    got = from_android(np.array([r68]), np.array([1.0]), np.array([1.0]))
    assert got.h_m[0] == pytest.approx(sigma)


def test_vertical_and_bearing_accuracies_are_68_percent_half_widths():
    sigma = 3.0
    rng = np.random.default_rng(1)
    z = rng.normal(0.0, sigma, N)
    half = sigma * GAUSS_68_PER_SIGMA
    assert within_68(float(np.mean(np.abs(z) <= half)))
    got = from_android(np.array([1.0]), np.array([half]), np.array([half]))
    assert got.v_m[0] == pytest.approx(sigma) and got.heading_deg[0] == pytest.approx(sigma)


def test_gst_sigmas_are_kept_and_the_horizontal_one_is_their_rms():
    got = from_nmea_gst([3.0, 1.0], [4.0, 1.0], [5.0, 2.0], [1.5, 0.5])
    np.testing.assert_allclose(got.h_m, [math.sqrt(12.5), 1.0])
    np.testing.assert_allclose(got.v_m, [5.0, 2.0])
    np.testing.assert_allclose(got.heading_deg, [1.5, 0.5])


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf")])
def test_a_claim_that_is_not_positive_and_finite_is_refused_naming_it(bad):
    with pytest.raises(ValueError, match="vertical_accuracy_m"):
        from_android([3.0], [bad], [2.0])
    with pytest.raises(ValueError, match="sigma_lon_m"):
        from_nmea_gst([1.0], [bad], [1.0], [1.0])
