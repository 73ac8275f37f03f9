"""Real GNSS errors, replayed: what two phones' fixes got wrong, second by second.

The data (``fleetsim/data/gsdc2020_mtv1_phone_gnss_errors.csv``, see
``fleetsim/data/README.md``) is the Google Smartphone Decimeter Challenge 2020 drive
``2020-05-14-US-MTV-1``: a Pixel 4 and a Pixel 4 XL in one car for about 29 minutes,
each chipset fix minus the RTK/INS truth at the same second (east, north, m). Its errors
do not average out within a drive: they are biases that last minutes, not white noise.

:class:`ReplayedGnss` has the interface of :class:`fleetsim.noise.GnssNoise` (``sample``,
``reported_sigmas``). Per pass it draws one trace (uniformly) and a start second
(uniformly over the seconds that leave room for the pass; a pass longer than the trace
wraps around) and takes that trace's east and north errors at the pass's fix times,
linearly interpolated between the 1 Hz samples. What the data does not have:

- vertical: the vertical terms of :data:`fleetsim.noise.FLEET` (per-pass bias, drift,
  white), sampled as there;
- heading: none is sampled; with ``heading_from_track`` the drive computes the fix's
  heading as a receiver's course over ground: the true velocity plus the rate of the
  position error over the logged second that holds the fix (:meth:`Trace.rate_at`,
  :func:`course_with_errors`), so its error is what the position errors make of it.

What the fixes claim (``reported_sigmas``), measured on the data when the traces are
loaded, never typed in: per horizontal axis the RMS of all errors; the vertical sigma is
FLEET's white level. The heading sigma is what a receiver reports for a course over
ground (Android's ``bearingAccuracyDegrees``): its velocity error over its speed, per fix
(:meth:`ReplayedGnss.heading_sigma_deg`), with the velocity error per horizontal axis the
RMS of the logged error's rate (:func:`velocity_error_sigma`). One figure for all speeds
(``reported_sigma_heading_deg``, the RMS course error of the recorded fixes) would be the
drive's speeds' figure: the recorded car drove at about 25 m/s, the simulated ones at
8-14 m/s, where the same error rate turns the course about twice as far.

>>> g = gsdc()
>>> len(g.traces), round(g.reported_sigma_h_m, 2)
(2, 1.17)
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

import numpy as np

from fleetsim.noise import FLEET, GnssErrors, GnssNoise
from hdmap.geo.geodesy import EnuFrame

Array = np.ndarray

DATA = Path(__file__).resolve().parent / "data" / "gsdc2020_mtv1_phone_gnss_errors.csv"

MIN_SPEED_MPS = 3.0
"""Course-over-ground errors are measured at this speed and above (below it a course from
positions is dominated by the position noise, and receivers say so)."""


@dataclass(frozen=True)
class Trace:
    """One receiver's errors over one drive (1 Hz, a few seconds may be missing)."""

    name: str
    t: Array
    """Seconds from the trace's first sample, increasing."""
    east: Array
    north: Array
    fix_enu: Array
    """(N, 2) the receiver's fixes in a local east/north frame, m (for the course)."""

    @property
    def span_s(self) -> float:
        return float(self.t[-1] - self.t[0])

    def at(self, t: Array) -> tuple[Array, Array]:
        """East and north errors at trace times ``t`` (s; wrapped into the span)."""
        tt = np.mod(t, self.span_s) if self.span_s > 0 else np.zeros_like(t)
        return np.interp(tt, self.t, self.east), np.interp(tt, self.t, self.north)

    def rate_at(self, t: Array) -> Array:
        """(len(t), 2) East and North rate of the error over the logged interval that
        holds each trace time (wrapped into the span), m/s: what a course over ground of
        these fixes is off by, as a velocity."""
        if len(self.t) < 2:
            return np.zeros((np.size(t), 2))
        tt = np.mod(t, self.span_s) if self.span_s > 0 else np.zeros_like(t)
        i = np.clip(np.searchsorted(self.t, tt, side="right") - 1, 0, len(self.t) - 2)
        dt = self.t[i + 1] - self.t[i]
        return np.column_stack(
            [(self.east[i + 1] - self.east[i]) / dt, (self.north[i + 1] - self.north[i]) / dt]
        )

    def course_errors(self, min_speed_mps: float = MIN_SPEED_MPS) -> Array:
        """Course over ground of the recorded fixes minus that of the truth track, rad
        (consecutive 1 Hz samples, where the truth moved at ``min_speed_mps`` or more)."""
        fix = self.fix_enu
        truth = fix - np.column_stack([self.east, self.north])
        dt = np.diff(self.t)
        d_fix, d_true = np.diff(fix, axis=0), np.diff(truth, axis=0)
        speed = np.hypot(*d_true.T) / np.maximum(dt, 1e-9)
        ok = (dt > 0) & (dt <= 1.5) & (speed >= min_speed_mps)
        err = np.arctan2(d_fix[:, 0], d_fix[:, 1]) - np.arctan2(d_true[:, 0], d_true[:, 1])
        return np.angle(np.exp(1j * err[ok]))


def velocity_error_sigma(traces: tuple[Trace, ...]) -> float:
    """Per horizontal axis, the RMS of the position error's rate over the traces' logged
    intervals, each weighted by its length (as a pass drawing a uniform start second meets
    them), m/s: the velocity error a course over ground of the replayed fixes carries
    (:meth:`Trace.rate_at`; :func:`course_with_errors` adds it in whatever direction the
    simulated car drives, so both axes count alike)."""
    num, den = 0.0, 0.0
    for tr in traces:
        dt = np.diff(tr.t)
        rate = np.diff(np.column_stack([tr.east, tr.north]), axis=0) / dt[:, None]
        num += float(np.sum(dt[:, None] * rate**2))
        den += 2.0 * float(np.sum(dt))
    return float(np.sqrt(num / den)) if den > 0 else 0.0


def load_traces(path: Path = DATA) -> tuple[Trace, ...]:
    """The traces of a GSDC error file (columns ``trace, t_s, err_east_m, err_north_m,
    fix_lat, fix_lon``), in the order they first appear."""
    rows: dict[str, list[tuple[float, ...]]] = {}
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            rows.setdefault(r["trace"], []).append(
                (
                    float(r["t_s"]),
                    float(r["err_east_m"]),
                    float(r["err_north_m"]),
                    float(r["fix_lat"]),
                    float(r["fix_lon"]),
                )
            )
    out = []
    for name, vals in rows.items():
        a = np.array(sorted(vals))
        frame = EnuFrame(float(a[0, 3]), float(a[0, 4]), 0.0)
        enu = frame.from_geodetic(a[:, 3], a[:, 4], np.zeros(len(a)))
        out.append(Trace(name, a[:, 0] - a[0, 0], a[:, 1], a[:, 2], np.asarray(enu)[:, :2]))
    return tuple(out)


def course_over_ground(t: Array, enu: Array) -> Array:
    """A receiver's heading from its own fix track: the direction of travel between the
    fixes around each one (central differences; one-sided at the ends), rad from north."""
    if len(t) < 2:
        return np.zeros(len(t))
    v = np.gradient(np.asarray(enu, float)[:, :2], np.asarray(t, float), axis=0)
    return np.arctan2(v[:, 0], v[:, 1])


def fix_speed(t: Array, antenna_enu: Array) -> Array:
    """The true ground speed at each fix (central differences of the antenna track), m/s:
    what a receiver's Doppler velocity measures."""
    t = np.asarray(t, float)
    if len(t) < 2:
        return np.zeros(len(t))
    return np.hypot(*np.gradient(np.asarray(antenna_enu, float)[:, :2], t, axis=0).T)


def course_with_errors(
    t: Array, heading: Array, antenna_enu: Array, err_enu: Array, err_rate: Array | None = None
) -> Array:
    """A receiver's course over ground when its velocity is the true one plus the rate of
    its position error: the direction of ``|v| (sin heading, cos heading) + d err / dt``
    (``|v|`` by central differences over the fixes; ``d err / dt`` the given ``err_rate``,
    (M, 2) m/s, or else central differences of ``err_enu``), rad from north.

    What the drive uses (rather than :func:`course_over_ground` of the noisy fixes): the
    error of the course is then what the position errors make of it, and nothing of the
    simulated path's own geometry (a difference over a corner's start, where the path's
    curvature jumps, is off by half the turn of a fix interval)."""
    t = np.asarray(t, float)
    if len(t) < 2:
        return np.asarray(heading, float).copy()
    speed = fix_speed(t, antenna_enu)
    v = speed[:, None] * np.column_stack([np.sin(heading), np.cos(heading)])
    rate = (
        np.gradient(np.asarray(err_enu, float)[:, :2], t, axis=0)
        if err_rate is None
        else np.asarray(err_rate, float)[:, :2]
    )
    v = v + rate
    return np.arctan2(v[:, 0], v[:, 1])


@dataclass(frozen=True)
class ReplayedGnss:
    """Position errors replayed from real receivers (module docstring)."""

    traces: tuple[Trace, ...]
    vertical: GnssNoise = field(default_factory=lambda: FLEET.gnss)
    """Only its vertical terms are used (bias_v_m, walk_v_m_per_sqrt_s, white_v_m)."""
    heading_from_track: bool = True
    """The fix's heading is the course over ground of the noisy track (the drive does it)."""
    reported_sigma_h_m: float = 0.0
    reported_sigma_v_m: float = 0.0
    reported_sigma_heading_deg: float = 0.0
    """The recorded drive's RMS course error (at its own speeds; reported in the tuple)."""
    velocity_sigma_mps: float = 0.0
    """Velocity error per horizontal axis (:func:`velocity_error_sigma`); 0: every fix
    claims ``reported_sigma_heading_deg``."""

    def reported_sigmas(self) -> tuple[float, float, float]:
        return self.reported_sigma_h_m, self.reported_sigma_v_m, self.reported_sigma_heading_deg

    def heading_sigma_deg(self, speed_mps: Array) -> Array:
        """The course sigma each fix claims at its speed: ``atan(velocity_sigma_mps /
        speed)``, degrees (at most 90; 3 decimals, as on the wire).

        >>> g = gsdc()
        >>> bool(g.heading_sigma_deg(np.array([8.0]))[0] > g.heading_sigma_deg(np.array([25.0]))[0])
        True
        """
        v = np.asarray(speed_mps, float)
        if self.velocity_sigma_mps <= 0.0:
            return np.full(v.shape, self.reported_sigma_heading_deg)
        d = np.degrees(np.arctan2(self.velocity_sigma_mps, np.maximum(v, 0.0)))
        return np.round(np.maximum(d, 1e-3), 3)

    def sample(self, rng: np.random.Generator, t: Array) -> GnssErrors:
        """Errors for one pass with fix times ``t`` (s, increasing)."""
        t = np.asarray(t, float)
        n = t.size
        trace = self.traces[int(rng.integers(len(self.traces)))]
        duration = float(t[-1] - t[0]) if n else 0.0
        room = max(trace.span_s - duration, 0.0)
        start = float(rng.uniform(0.0, room)) if room > 0 else float(rng.uniform(0.0, trace.span_s))
        tt = start + (t - (t[0] if n else 0.0))
        east, north = trace.at(tt)
        v = self.vertical
        up = (
            rng.normal(0.0, v.bias_v_m)
            + np.cumsum(
                rng.normal(0.0, 1.0, n) * np.sqrt(np.maximum(np.diff(t, prepend=t[:1]), 0.0))
            )
            * v.walk_v_m_per_sqrt_s
        )
        white_up = rng.normal(0.0, 1.0, n) * v.white_v_m
        zeros = np.zeros((n, 3))
        return GnssErrors(
            bias_enu=np.column_stack([east, north, up]),
            white_enu=np.column_stack([np.zeros(n), np.zeros(n), white_up]),
            multipath=np.zeros(n, bool),
            multipath_enu=zeros,
            heading_rad=np.zeros(n),
            heading_bias_rad=0.0,
            velocity_enu=trace.rate_at(tt),
        )


@cache
def gsdc() -> ReplayedGnss:
    """The GSDC 2020 MTV-1 replay with its sigmas measured from the data (module
    docstring); loaded once."""
    traces = load_traces()
    errs = np.concatenate([np.concatenate([tr.east, tr.north]) for tr in traces])
    course = np.concatenate([tr.course_errors() for tr in traces])
    _, s_v, _ = FLEET.gnss.reported_sigmas()
    return ReplayedGnss(
        traces,
        reported_sigma_h_m=float(np.sqrt(np.mean(errs**2))),
        reported_sigma_v_m=s_v,
        reported_sigma_heading_deg=round(float(np.degrees(np.sqrt(np.mean(course**2)))), 3),
        velocity_sigma_mps=velocity_error_sigma(traces),
    )
