"""Ground-truth helpers for evaluators: rays and landmarks against the true signs.

- :func:`lines_in_world` puts projection lines (geodetic origin, direction in
  ENU at the origin) into the world's ENU frame;
- :func:`ray_errors` measures each ray against the sign it truly saw
  (``DriveTruth.sign_id``): perpendicular miss distance, range error;
- :func:`match_landmarks` pairs estimated landmarks with true signs (same class,
  within a gate, optimal one-to-one assignment) to count found, missed and
  spurious landmarks and to measure position errors.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import linear_sum_assignment

from fleetsim.world import World
from schemas import STATUS_CONFIRMED, Landmarks
from vehicle.geoloc import ProjectionLines

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


def lines_in_world(lines: ProjectionLines, world: World) -> tuple[Array, Array]:
    """Ray origins (N, 3) and unit directions (N, 3) in the world's ENU frame."""
    if len(lines) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    origin = world.frame.from_geodetic(lines.lat, lines.lon, lines.h).reshape(-1, 3)
    d = world.frame.vectors_from_enu_at(lines.direction, lines.lat, lines.lon).reshape(-1, 3)
    return origin, d / np.linalg.norm(d, axis=1, keepdims=True)


def ray_point_distance(origin: ArrayLike, direction: ArrayLike, point: ArrayLike) -> Array:
    """Perpendicular distance of points to rays (rows broadcast), m."""
    o, d, p = (np.asarray(a, float) for a in (origin, direction, point))
    v = p - o
    along = np.sum(v * d, axis=-1, keepdims=True)
    return np.linalg.norm(v - along * d, axis=-1)


@dataclass(frozen=True)
class RayErrors:
    """Per ray that saw a real sign (false positives are left out)."""

    rows: IntArray
    """Rows of the ProjectionLines these errors belong to."""
    sign_id: IntArray
    miss_m: Array
    """Perpendicular distance from the true panel centre to the ray, m."""
    true_range_m: Array
    """Distance from the ray origin to the true panel centre, m."""
    range_error_m: Array
    """range_m - true_range_m; NaN where the ray has no range estimate."""


def ray_errors(lines: ProjectionLines, sign_id: ArrayLike, world: World) -> RayErrors:
    """Errors of rays against the signs they truly saw (``sign_id`` -1 = false positive)."""
    ids = np.asarray(sign_id, np.int64)
    row_sign = world.signs.index_of(ids)
    rows = np.flatnonzero(row_sign >= 0)
    origin, d = lines_in_world(lines, world)
    target = world.signs.position[row_sign[rows]]
    o, dd = origin[rows], d[rows]
    true_range = np.linalg.norm(target - o, axis=1)
    rng = np.asarray(lines.range_m, float)[rows]
    return RayErrors(
        rows=rows,
        sign_id=ids[rows],
        miss_m=ray_point_distance(o, dd, target),
        true_range_m=true_range,
        range_error_m=np.where(rng > 0, rng - true_range, np.nan),
    )


@dataclass(frozen=True)
class LandmarkMatch:
    """One-to-one pairing of estimated landmarks with true signs."""

    landmark: IntArray
    """Rows of the matched estimates."""
    sign_row: IntArray
    """Rows of world.signs they matched."""
    error_enu: Array
    """(K, 3) estimate minus truth, world ENU m."""
    spurious: IntArray
    """Estimate rows without a true sign."""
    missed: IntArray
    """Sign rows without an estimate."""

    @property
    def horizontal_error_m(self) -> Array:
        return np.hypot(self.error_enu[:, 0], self.error_enu[:, 1])


def match_landmarks(
    world: World,
    lat: ArrayLike,
    lon: ArrayLike,
    h: ArrayLike,
    sign_class: ArrayLike,
    gate_m: float = 10.0,
    preferred: ArrayLike | None = None,
) -> LandmarkMatch:
    """Pair estimates with true signs of the same class within ``gate_m`` (horizontal).

    Minimises the total horizontal distance (scipy's linear_sum_assignment). With
    ``preferred`` (per estimate, bool), as many pairs as possible first, then as few of them
    with an estimate that is not preferred, then the distance: a sign is paired with the
    landmark a map user takes for it (a confirmed one) rather than with a provisional
    candidate that happens to stand nearer (:func:`match_map`).
    """
    cls = np.asarray(sign_class, np.int64).reshape(-1)
    n_est, n_sign = cls.size, len(world.signs)
    if n_est:
        est = world.frame.from_geodetic(lat, lon, h).reshape(-1, 3)
    else:
        est = np.zeros((0, 3))
    truth = world.signs.position
    dist = np.linalg.norm(est[:, None, :2] - truth[None, :, :2], axis=-1)
    allowed = (cls[:, None] == world.signs.sign_class[None, :]) & (dist <= gate_m)
    penalty = 0.0
    if preferred is not None:  # any pair with a preferred estimate costs less than any without
        penalty = (2.0 * gate_m + 1.0) * ~np.asarray(preferred, bool).reshape(-1, 1)
    cost = np.where(allowed, dist + penalty, 1e9)
    if n_est and n_sign:
        r, c = linear_sum_assignment(cost)
        good = allowed[r, c]
        r, c = r[good], c[good]
    else:
        r = c = np.zeros(0, np.int64)
    return LandmarkMatch(
        landmark=r.astype(np.int64),
        sign_row=c.astype(np.int64),
        error_enu=est[r] - truth[c],
        spurious=np.setdiff1d(np.arange(n_est), r).astype(np.int64),
        missed=np.setdiff1d(np.arange(n_sign), c).astype(np.int64),
    )


def match_map(world: World, lm: Landmarks, gate_m: float = 10.0) -> LandmarkMatch:
    """:func:`match_landmarks` for a published map: confirmed landmarks are preferred.

    Pitfall: by distance alone a sign was paired with a two-pass candidate 0.5 m from it
    (and 11 m below) instead of its confirmed 75-pass landmark 1.0 m from it, which then
    counted as a duplicate, and the sign's error and coverage were the candidate's.
    """
    return match_landmarks(
        world, lm.lat, lm.lon, lm.h, lm.sign_class, gate_m, lm.status == STATUS_CONFIRMED
    )
