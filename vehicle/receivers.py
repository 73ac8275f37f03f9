"""What GNSS receivers report, turned into the sigmas of :class:`vehicle.geoloc.GnssFixes`.

``GnssFixes`` wants one standard deviation (1 sigma) per fix: ``sigma_h_m`` per
horizontal axis (east and north alike), ``sigma_v_m`` on the height and
``sigma_heading_deg`` on the course over ground. Receivers report other things:

Android ``android.location.Location`` (API 26+):

- ``getAccuracy()``: metres, the radius of the horizontal circle around the fix that
  holds the true position with 68 % probability. For a circular Gaussian of sigma ``s``
  per axis the radius ``r`` holds ``1 - exp(-r^2 / (2 s^2))`` of it, so the 68 % radius
  is ``sqrt(-2 ln 0.32) s = 1.5096 s``: :data:`ANDROID_R68_PER_SIGMA`.
- ``getVerticalAccuracyMeters()``: metres, half-width of the 68 % interval of the
  altitude: 0.9945 sigma for a Gaussian (:data:`GAUSS_68_PER_SIGMA`).
- ``getBearingAccuracyDegrees()``: degrees, half-width of the 68 % interval of the
  bearing (course over ground): 0.9945 sigma.

NMEA 0183 ``$--GST,time,rms,major,minor,orient,lat,lon,alt`` (pseudorange error
statistics): ``lat``, ``lon`` and ``alt`` (fields 6-8) are the 1-sigma errors of
latitude, longitude and altitude in metres, already sigmas; ``rms`` (field 2) is the RMS
of the range residuals, not a position error. The horizontal sigma per axis is the RMS
of the latitude and longitude sigmas (the error ellipse, fields 3-5, is not kept:
``GnssFixes`` has one horizontal sigma). GST has no course accuracy: take it from the
receiver's documentation or its proprietary messages.

These sigmas are what a receiver claims: usually its total error, shared parts (biases
that last minutes) included. Report them as they are; telling the shared part from the
white part is the vehicle's and the estimator's work, not the caller's: the poses claim
of each sigma only the share the pass's own fixes show changing within a view of a sign
(:func:`vehicle.pose.view_shares`), and the solver adds what passes share
(``SolverConfig.shared_floor_m2``). Measured: claiming the simulated receiver's totals
maps within 10 % of claiming its exact split on four seeds (docs/estimator.md section 12).

>>> s = from_android(accuracy_m=np.array([3.0]), vertical_accuracy_m=np.array([5.0]),
...                  bearing_accuracy_deg=np.array([2.0]))
>>> [round(float(x[0]), 3) for x in s]
[1.987, 5.028, 2.011]
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

ANDROID_R68_PER_SIGMA = math.sqrt(-2.0 * math.log(1.0 - 0.68))
"""The 68 % radius of a circular 2D Gaussian, in sigmas per axis (1.5096)."""

GAUSS_68_PER_SIGMA = 0.994457883209753
"""The half-width of the central 68 % interval of a 1D Gaussian, in sigmas
(``scipy.stats.norm.ppf(0.84)``; the onboard side does not import scipy)."""


class Sigmas(NamedTuple):
    """Per fix: sigma per horizontal axis (m), vertical (m), course (deg)."""

    h_m: Array
    v_m: Array
    heading_deg: Array


def _positive(name: str, value: ArrayLike) -> Array:
    a = np.asarray(value, float)
    if not np.all(np.isfinite(a)) or np.any(a <= 0):
        raise ValueError(f"{name}: every value must be finite and > 0 (a receiver's claim)")
    return a


def from_android(
    accuracy_m: ArrayLike, vertical_accuracy_m: ArrayLike, bearing_accuracy_deg: ArrayLike
) -> Sigmas:
    """Android ``Location`` accuracies (68 %; module docstring) -> 1-sigma values."""
    return Sigmas(
        _positive("accuracy_m", accuracy_m) / ANDROID_R68_PER_SIGMA,
        _positive("vertical_accuracy_m", vertical_accuracy_m) / GAUSS_68_PER_SIGMA,
        _positive("bearing_accuracy_deg", bearing_accuracy_deg) / GAUSS_68_PER_SIGMA,
    )


def from_nmea_gst(
    sigma_lat_m: ArrayLike,
    sigma_lon_m: ArrayLike,
    sigma_alt_m: ArrayLike,
    sigma_heading_deg: ArrayLike,
) -> Sigmas:
    """NMEA ``GST`` 1-sigma latitude, longitude and altitude errors (fields 6-8, m), and a
    course sigma from elsewhere (GST has none) -> 1-sigma values."""
    lat = _positive("sigma_lat_m", sigma_lat_m)
    lon = _positive("sigma_lon_m", sigma_lon_m)
    return Sigmas(
        np.sqrt((lat**2 + lon**2) / 2.0),
        _positive("sigma_alt_m", sigma_alt_m),
        _positive("sigma_heading_deg", sigma_heading_deg),
    )
