"""The white part of a pass's elevation error, measured from the pass's own tracks.

A ray's elevation errs by the detector's vertical pixel noise (known: the camera model
propagates it) and by the camera's pitch, which GNSS does not give. The vehicle model's
``pitch_sigma_rad`` is a bound on that pitch error, not a measurement, and the landmark
estimator's bias compensation needs the part that changes from ray to ray within a pass
(docs/estimator.md section 3): a claim above it over-corrects, and every landmark is
placed beyond its sign along the line of sight by an amount that more passes do not
average away (0.24 m at 1,200 passes of the fleet evaluation with 0.5 deg claimed and none
there; docs/experiments/2026-12-pass-weights-consistency.md).

Along one track (one sign, seen in consecutive frames) the true elevation is a smooth
function of time. For three consecutive rays ``(t_1, e_1), (t_2, e_2), (t_3, e_3)`` of a
track the residual of the middle one against the chord of the outer two,

    d = e_2 - (w e_1 + (1 - w) e_3),    w = (t_3 - t_2) / (t_3 - t_1),

has variance ``p_2 + w^2 p_1 + (1 - w)^2 p_3 + s^2 (1 + w^2 + (1 - w)^2)`` for white pixel
variances ``p_j`` and a white pitch error of std ``s``, plus the curvature of the true
elevation over the triple (``e'' (t_3 - t_2)(t_2 - t_1) / 2``, small beyond a few metres;
rays closer than ``min_range_m`` by their box range are left out). ``s^2`` is estimated
robustly from the normalised residuals ``z = d / sqrt(1 + w^2 + (1 - w)^2)``: the squared
scale ``(1.4826 MAD(z))^2`` less the median normalised pixel variance, at least 0.

Pitfall: pitch that drifts slowly (a loaded car, a sloped road) is shared by consecutive
rays and the residuals do not see it; that part is for the between-pass covariance, as a
pass's shared heading error is, and the compensation must not see it. A pass with fewer
than ``min_triples`` residuals keeps the vehicle model's bound (the conservative side).

>>> rng = np.random.default_rng(0)
>>> t = np.tile(np.arange(40) / 15.0, 10); track = np.repeat(np.arange(1, 11), 40)
>>> rho = 40.0 - 10.0 * (t % (40 / 15.0))
>>> el = np.arctan2(1.5, rho) + rng.normal(0.0, 0.005, t.size)
>>> s = white_pitch_sigma(t, el, track, np.full(t.size, 0.002), rho, cap_rad=0.0087)
>>> bool(0.0035 < s < 0.0055)
True
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

MAD_TO_SIGMA = 1.4826
"""``sigma = 1.4826 MAD`` for a normal distribution."""


def chord_residuals(
    t: ArrayLike, el: ArrayLike, track: ArrayLike, pixel_var: ArrayLike, keep: ArrayLike
) -> tuple[Array, Array]:
    """Per triple of consecutive kept rays of one track (by time): the normalised residual
    ``z`` of the module docstring and its normalised pixel variance."""
    t, el = np.asarray(t, float), np.asarray(el, float)
    tr, pv = np.asarray(track), np.asarray(pixel_var, float)
    k = np.flatnonzero(np.asarray(keep, bool))
    k = k[np.lexsort((t[k], tr[k]))]
    if k.size < 3:
        return np.zeros(0), np.zeros(0)
    i1, i2, i3 = k[:-2], k[1:-1], k[2:]
    span = t[i3] - t[i1]
    ok = (tr[i1] == tr[i2]) & (tr[i2] == tr[i3]) & (t[i2] > t[i1]) & (t[i3] > t[i2])
    i1, i2, i3, span = i1[ok], i2[ok], i3[ok], span[ok]
    w = (t[i3] - t[i2]) / span
    d = el[i2] - (w * el[i1] + (1.0 - w) * el[i3])
    f = 1.0 + w**2 + (1.0 - w) ** 2
    pix = pv[i2] + w**2 * pv[i1] + (1.0 - w) ** 2 * pv[i3]
    return d / np.sqrt(f), pix / f


def white_pitch_sigma(
    t: ArrayLike,
    el: ArrayLike,
    track: ArrayLike,
    sigma_pixel_el: ArrayLike,
    range_m: ArrayLike,
    cap_rad: float,
    min_range_m: float = 8.0,
    min_triples: int = 30,
) -> float:
    """The white pitch std of one pass (rad, at most ``cap_rad``) from its rays' times,
    elevations (rad), track ids (0 or less: untracked, left out), the pixel part of each
    elevation sigma (rad) and box ranges (m, 0: none; rays with a range under
    ``min_range_m`` are left out, those without one kept). ``cap_rad`` when the pass has
    fewer than ``min_triples`` residuals."""
    tr = np.asarray(track)
    r = np.asarray(range_m, float)
    keep = (tr > 0) & ((r <= 0) | (r >= min_range_m)) & np.isfinite(np.asarray(el, float))
    z, pix = chord_residuals(t, el, tr, np.square(np.asarray(sigma_pixel_el, float)), keep)
    if z.size < min_triples:
        return float(cap_rad)
    scale2 = (MAD_TO_SIGMA * np.median(np.abs(z - np.median(z)))) ** 2
    return float(min(np.sqrt(max(scale2 - np.median(pix), 0.0)), cap_rad))


def elevation(direction: ArrayLike) -> Array:
    """Elevation of ENU directions (n, 3), rad."""
    d = np.asarray(direction, float)
    return np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1]))


def measured_sigma_el(
    t: ArrayLike,
    direction: ArrayLike,
    sigma_el: ArrayLike,
    range_m: ArrayLike,
    track: ArrayLike,
    pitch_bound_rad: float,
) -> tuple[Array, float]:
    """Each ray's elevation sigma with the pitch bound replaced by the pass's measured white
    pitch (:func:`white_pitch_sigma`), and that pitch std. ``sigma_el`` as the camera model
    gives it: the pixel part and ``pitch_bound_rad`` in quadrature."""
    s = np.asarray(sigma_el, float)
    pixel = np.sqrt(np.maximum(s**2 - pitch_bound_rad**2, 0.0))
    pitch = white_pitch_sigma(t, elevation(direction), track, pixel, range_m, pitch_bound_rad)
    return np.sqrt(pixel**2 + pitch**2), pitch
