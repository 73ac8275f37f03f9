"""Routes on the road graph and the vehicle's path along them.

A route is a walk on the world's directed edges (no U-turns). Its path is the
node polyline shifted to the right lane and with rounded corners, parametrised
by arc length. Headings are radians clockwise from North of the world frame
(the GNSS heading's convention, in radians).

>>> from fleetsim.world import straight_road
>>> w = straight_road()
>>> p = Path.along(w, [0, 1])
>>> xy, psi = p.at(np.array([0.0, 10.0]))
>>> xy.round(3).tolist(), psi.round(6).tolist()
([[1.75, -150.0], [1.75, -140.0]], [0.0, 0.0])
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from fleetsim.world import World

Array = NDArray[np.float64]

HEADING_RAMP_M = 1.0
"""Path length over which the heading turns at a vertex between two longer segments."""

CURVATURE_WINDOW_M = 10.0
"""Path length over which a driver reads the road's curvature (a few degrees at one
vertex is no corner)."""


@dataclass(frozen=True)
class SpeedProfile:
    """Arc length ``s`` (m) against time ``t`` (s from the start), both increasing."""

    s: Array
    t: Array

    @property
    def duration(self) -> float:
        return float(self.t[-1])

    def s_at(self, t: Array) -> Array:
        """Arc length at times ``t`` (s from the start; clamped to the ends)."""
        return np.interp(np.asarray(t, float), self.t, self.s)


def offset_right(points: Array, offset: float) -> Array:
    """A polyline shifted ``offset`` metres to the right of travel (mitred corners)."""
    p = np.asarray(points, float)
    t = np.diff(p, axis=0)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    r = np.column_stack([t[:, 1], -t[:, 0]])
    r_in = np.vstack([r[:1], r])  # normal of the segment arriving at each vertex
    r_out = np.vstack([r, r[-1:]])  # ... and of the one leaving it
    miter = (r_in + r_out) / (1.0 + np.sum(r_in * r_out, axis=1, keepdims=True))
    return p + offset * miter


def round_corners(points: Array, radius: float, step_deg: float = 10.0) -> Array:
    """Replace each interior vertex by a circular arc of ``radius`` (clipped to fit)."""
    p = np.asarray(points, float)
    out = [p[0]]
    for k in range(1, len(p) - 1):
        a, b, c = p[k - 1], p[k], p[k + 1]
        u, v = b - a, c - b
        lu, lv = np.linalg.norm(u), np.linalg.norm(v)
        u, v = u / lu, v / lv
        turn = np.arctan2(u[0] * v[1] - u[1] * v[0], float(u @ v))
        if abs(turn) < 1e-6:
            out.append(b)
            continue
        d = min(radius * np.tan(abs(turn) / 2.0), 0.45 * lu, 0.45 * lv)
        r = d / np.tan(abs(turn) / 2.0)
        start = b - u * d
        n = np.array([-u[1], u[0]]) * np.sign(turn)  # toward the arc centre
        centre = start + n * r
        m = max(int(np.ceil(np.degrees(abs(turn)) / step_deg)), 1)
        ang = np.linspace(0.0, turn, m + 1)
        s0 = start - centre
        cs, sn = np.cos(ang), np.sin(ang)
        arc = centre + np.column_stack([cs * s0[0] - sn * s0[1], sn * s0[0] + cs * s0[1]])
        out.extend(arc)
    out.append(p[-1])
    return np.asarray(out)


@dataclass(frozen=True)
class Path:
    """A vehicle path: polyline ``points`` (K, 2) ENU m with cumulative arc length."""

    points: Array
    s: Array

    @staticmethod
    def from_points(points: Array) -> Path:
        p = np.asarray(points, float)
        seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
        keep = np.concatenate([[True], seg > 1e-9])
        p = p[keep]
        seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
        if len(p) < 2:
            raise ValueError("a path needs two distinct points")
        return Path(p, np.concatenate([[0.0], np.cumsum(seg)]))

    @staticmethod
    def along(world: World, route: Sequence[int], corner_radius_m: float = 7.0) -> Path:
        """The right-lane path along a walk of node indices."""
        pts = world.nodes[np.asarray(route, np.int64)]
        lane = offset_right(pts, world.lane_offset_m)
        return Path.from_points(round_corners(lane, corner_radius_m))

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def at(self, s: Array) -> tuple[Array, Array]:
        """Positions (N, 2) and headings (N,) rad clockwise from North at arc lengths ``s``."""
        s = np.clip(np.asarray(s, float), 0.0, self.length)
        xy = np.column_stack(
            [np.interp(s, self.s, self.points[:, 0]), np.interp(s, self.s, self.points[:, 1])]
        )
        knots, ang = self.heading_knots()
        psi = np.interp(s, knots, ang) if knots.size > 1 else np.full(s.shape, ang[0])
        return xy, psi

    def heading_knots(self, ramp_m: float = HEADING_RAMP_M) -> tuple[Array, Array]:
        """Arc lengths and headings (unwrapped) that :meth:`at` interpolates between.

        Invariant: the heading is the direction the position moves in, except within
        ``ramp_m`` of a vertex, where it turns from one segment's direction to the next
        one's. A segment shorter than ``2 ramp_m`` (a rounded corner's 10-degree chords)
        has one knot at its middle, so that on a corner the heading turns smoothly; a
        longer one has a knot ``ramp_m`` inside each end and keeps its direction in
        between. (Interpolating between every segment's middle turned the heading over
        the whole last half of a straight before a corner, up to 5 degrees away from the
        direction of travel: a receiver's course over ground, which follows the track,
        then disagreed with the camera by 1.9 degrees RMS, the same at a place on every
        pass. docs/experiments/2026-12-gsdc-course-over-ground.md.)
        """
        d = np.diff(self.points, axis=0)
        ang = np.unwrap(np.arctan2(d[:, 0], d[:, 1]))
        a, b = self.s[:-1], self.s[1:]
        short = (b - a) <= 2.0 * ramp_m
        mid = (a + b) / 2.0
        first = np.where(short, mid, a + ramp_m)
        last = np.where(short, mid, b - ramp_m)
        knots = np.column_stack([first, last]).ravel()
        angles = np.repeat(ang, 2)
        keep = np.concatenate([[True], np.diff(knots) > 0])  # one knot per short segment
        return knots[keep], angles[keep]


def speed_profile(
    path: Path,
    v_max: float,
    lateral_accel: float | None,
    long_accel: float = 2.0,
    step_m: float = 0.5,
) -> SpeedProfile:
    """How a driver goes along ``path``: at most ``v_max``, slow enough in a curve that
    ``v^2 kappa <= lateral_accel`` (``kappa``: the heading's change over
    :data:`CURVATURE_WINDOW_M` around a point, over that length), speeding up and braking
    at ``long_accel``; entering and leaving the path at the speed its ends allow.
    ``lateral_accel`` None: ``v_max`` throughout (the constant-speed drive).

    >>> from fleetsim.world import straight_road
    >>> p = speed_profile(Path.along(straight_road(), [0, 1]), 10.0, 3.0)
    >>> round(p.duration, 6) == round(Path.along(straight_road(), [0, 1]).length / 10.0, 6)
    True
    """
    length = path.length
    n = max(int(np.ceil(length / step_m)), 1)
    s = np.linspace(0.0, length, n + 1)
    if lateral_accel is None:
        return SpeedProfile(s, s / v_max)
    knots, ang = path.heading_knots()
    psi = np.interp(s, knots, ang) if knots.size > 1 else np.full(s.shape, ang[0])
    half = CURVATURE_WINDOW_M / 2.0
    lo = np.interp(np.clip(s - half, 0.0, length), s, psi)
    hi = np.interp(np.clip(s + half, 0.0, length), s, psi)
    span = np.clip(s + half, 0.0, length) - np.clip(s - half, 0.0, length)
    kappa = np.abs(hi - lo) / np.maximum(span, 1e-9)
    # in v^2 the limits are linear in s: speeding up from any earlier point j bounds
    # v_i^2 by cap_j + 2 a (s_i - s_j), braking for any later one by cap_j + 2 a (s_j - s_i)
    cap = np.minimum(v_max, np.sqrt(lateral_accel / np.maximum(kappa, 1e-12))) ** 2
    two_a = 2.0 * long_accel
    cap = np.minimum(cap, two_a * s + np.minimum.accumulate(cap - two_a * s))
    cap = np.minimum(cap, np.minimum.accumulate((cap + two_a * s)[::-1])[::-1] - two_a * s)
    v = np.sqrt(cap)
    ds = np.diff(s)
    t = np.concatenate([[0.0], np.cumsum(2.0 * ds / (v[:-1] + v[1:]))])
    return SpeedProfile(s, t)


def random_route(
    world: World, rng: np.random.Generator, min_length_m: float, max_edges: int = 64
) -> list[int]:
    """A random walk on the directed edges, without U-turns, of at least ``min_length_m``.

    Stops early at a dead end (e.g. the end of a straight road).
    """
    e = world.edges
    first = e[rng.integers(len(e))]
    route = [int(first[0]), int(first[1])]
    length = float(np.linalg.norm(world.nodes[first[1]] - world.nodes[first[0]]))
    while length < min_length_m and len(route) <= max_edges:
        here, prev = route[-1], route[-2]
        nxt = e[(e[:, 0] == here) & (e[:, 1] != prev), 1]
        if nxt.size == 0:
            break
        n = int(nxt[rng.integers(nxt.size)])
        length += float(np.linalg.norm(world.nodes[n] - world.nodes[here]))
        route.append(n)
    return route
