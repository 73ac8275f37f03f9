"""Onboard detection tracking: the detections of one sign, followed from frame to frame.

A vehicle sees a sign in tens of consecutive camera frames. Which detections belong
together is easy onboard, where the frames come in order a fraction of a second apart, and
hard on the server, where a street of same-class signs 8 m apart gives rays that each fit
several landmarks. The vehicle therefore labels each detection with a track
(``Observations.track``); the matcher keeps a track's rays together
(:func:`hdmap.mapping.association.assign_tracks`).

Everything here runs on times, not on fix or frame counts: fixes and frames come at their
own rates, fixes go missing, frames without detections are not listed.

Tracking runs in a local ENU frame at the pass's first fix, on a smoothed trajectory:
consecutive GNSS fixes carry independent white noise (about a metre) that would move a sign
by more than the gap to its neighbour between two frames, while the pass's bias is common
to all of them and cancels. Fix positions are smoothed by a local quadratic fit in time
over the fixes within ``window_s`` centred on each (:func:`smooth_in_time`; fewer than 4
fixes: no smoothing); a ray's origin moves by the smoothing correction interpolated at its
time. The heading is not smoothed: at a corner of the path a fit over two seconds is wrong
by tenths of a radian (measured: it doubled the rays' scatter; docs/estimator.md
section 15).

**The origin's tolerance** (its sigma relative to the track's other origins, per axis):

    sigma_rel^2 = rel_pos_sigma_m^2 + lev(t) sigma_fix(t)^2 + sigma_motion(t)^2

with ``sigma_fix`` the fix's reported sigma (``sigma_h_m`` horizontally, ``sigma_v_m``
vertically) and ``lev`` the smoother's leverage at that fix, the variance factor of a
fitted value under white noise (``e0' (V'V)^-1 e0``: 1 without smoothing, 0.21 for 11
fixes in the window), both interpolated to the ray's time like the pose
(:func:`vehicle.pose.interpolate_sigma`); ``sigma_motion`` is the pose interpolation's
error (:func:`vehicle.geoloc.turn_sigmas`). The receiver's reported sigma is taken as its
white noise (what a receiver can know; its bias is common to a track's rays and cancels),
and ``rel_pos_sigma_m`` stands for what the fixes do not report: the bias's drift over a
track's life (0.2 m/sqrt(s) over 4 s: 0.4 m). The old fixed 0.6 m on both axes
(``sigma_from_fixes=False``, ``rel_pos_sigma_m=0.6``) split one sign into 1.9 tracks per
pass with 3 m of vertical noise (docs/experiments/2026-12-sensor-timing.md).

A track's position is the triangulation of its rays (bearing terms and the range from the
box size, :func:`hdmap.mapping.initiation.triangulate`). Each frame's detections are
assigned to the open tracks of their class by the association's per-image assignment
(:func:`hdmap.mapping.association.assign_per_image`) on the gating statistic of
:func:`hdmap.mapping.association.pair_chi2` (angles and range, with the origin tolerance
above); a detection no track takes starts one; a track not extended for more than
``max_gap_s`` seconds is closed.

>>> import numpy as np
>>> (smooth_track(np.arange(11.0) * 2.0, 5).round(6) + 0.0).tolist()[:3]
[0.0, 2.0, 4.0]
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hdmap.geo.geodesy import GEODESY, EnuFrame, Geodesy
from hdmap.mapping.association import GateConfig, LocalRays, assign_per_image, origin_cov, pair_chi2
from hdmap.mapping.initiation import normal_terms, ray_point
from vehicle.geoloc import DEFAULT_TIMING, GnssFixes, ProjectionLines, turn_sigmas
from vehicle.pose import (
    PoseTiming,
    bracket,
    check_increasing,
    interpolate,
    interpolate_sigma,
    motion_sigma,
    view_shares,
)

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class TrackConfig:
    """How detections are chained into tracks (``VehicleAgent`` runs it per pass)."""

    window_s: float = 2.0
    """Width of the trajectory smoother's window, s (centred on each fix)."""
    rel_pos_sigma_m: float = 0.4
    """Per-axis origin tolerance the fixes do not report (the bias's drift over a track's
    life), m; with ``sigma_from_fixes=False`` the whole tolerance, both axes."""
    sigma_from_fixes: bool = True
    """Add the smoothed reported fix sigmas and the interpolation error (module docstring)."""
    chi2_gate: float = 16.27
    """Largest statistic (angles and range) of a detection against its track's position."""
    max_gap_s: float = 1.6
    """A track not extended for more than this many seconds is closed."""
    range_k: float = 4.0
    """A detection's range must agree with its track's distance within this many sigma."""

    def __post_init__(self) -> None:
        for name in ("window_s", "rel_pos_sigma_m", "max_gap_s", "chi2_gate", "range_k"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0.0):
                raise ValueError(f"TrackConfig.{name}: must be finite and >= 0, got {v!r}")


@dataclass(frozen=True)
class TimedRays(LocalRays):
    """:class:`LocalRays` with each ray's capture time ``t`` (s), as the tracker needs.
    Pitfall: ``LocalRays.concat`` returns plain rays (no ``t``)."""

    t: Array | None = None

    def take(self, idx: NDArray) -> TimedRays:
        return TimedRays(
            **{
                k: None if getattr(self, k) is None else getattr(self, k)[idx]
                for k in self.__dataclass_fields__
            }
        )


def smooth_track(values: Array, window: int) -> Array:
    """Local quadratic fit over ``window`` samples (fewer samples: returned unchanged).

    >>> smooth_track(np.array([0.0, 1.0, 0.0]), 5).tolist()
    [0.0, 1.0, 0.0]
    """
    v = np.asarray(values, float)
    w = min(window, v.shape[0] - (1 - v.shape[0] % 2))
    if w < 5:
        return v.copy()
    return _quadratic_fit(v, w)


def _quadratic_fit(v: Array, w: int) -> Array:
    """Savitzky-Golay smoothing of order 2 along axis 0 (scipy's ``savgol_filter`` with
    ``mode="interp"``): each sample is the value at its own position of the least-squares
    quadratic over the ``w`` samples centred on it; the first and last ``w // 2`` samples
    take the quadratic of the first and last ``w`` samples."""
    t = np.arange(w, dtype=float) - w // 2
    vand = np.stack([np.ones(w), t, t * t], 1)
    hat = vand @ np.linalg.pinv(vand)  # (w, w): fitted values from the window's samples
    c = w // 2
    windows = np.lib.stride_tricks.sliding_window_view(v, w, axis=0)  # (n - w + 1, ..., w)
    out = np.empty_like(v)
    out[c : v.shape[0] - c] = windows @ hat[c]
    out[:c] = np.tensordot(hat[:c], v[:w], axes=(1, 0))
    out[v.shape[0] - c :] = np.tensordot(hat[c + 1 :], v[-w:], axes=(1, 0))
    return out


def smooth_in_time(t: ArrayLike, values: ArrayLike, window_s: float) -> tuple[Array, Array]:
    """Local quadratic fit in time: each sample (rows of ``values``, times ``t`` strictly
    increasing) becomes the value at its own time of the least-squares quadratic through
    the samples within ``window_s / 2`` of it (fewer at the ends of the series and around
    gaps: the window is a time span, never a count). Returns the smoothed values and the
    leverage per sample, ``e0' (V'V)^-1 e0``: the fitted value's variance over the
    samples' under white noise (1 where fewer than 4 samples leave the value as it was).

    >>> t = np.array([0.0, 0.2, 0.4, 0.6, 0.8, 1.0, 1.4])  # one sample missing
    >>> v, lev = smooth_in_time(t, 3.0 * t**2 - t, 1.0)
    >>> bool(np.allclose(v, 3.0 * t**2 - t)), lev.round(3).tolist()
    (True, [1.0, 0.55, 0.486, 0.486, 0.55, 0.673, 1.0])
    """
    tt = check_increasing(t, "GnssFixes.t")
    v = np.asarray(values, float)
    n = tt.size
    half = window_s / 2.0
    eps = 1e-9 * max(half, 1.0)
    lo = np.searchsorted(tt, tt - half - eps, side="left")
    hi = np.searchsorted(tt, tt + half + eps, side="right")
    cnt = hi - lo
    ok = cnt >= 4
    out, lev = v.copy(), np.ones(n)
    if not ok.any():
        return out, lev
    rows = np.flatnonzero(ok)
    j = lo[rows, None] + np.arange(int(cnt[rows].max()))[None, :]
    inside = j < hi[rows, None]
    j = np.minimum(j, n - 1)
    tau = (tt[j] - tt[rows, None]) / max(half, eps)  # scaled: a well-conditioned basis
    basis = np.stack([np.ones_like(tau), tau, tau * tau], -1) * inside[..., None]
    gram = np.einsum("rmi,rmj->rij", basis, basis)
    vj = v[j].reshape((*j.shape, -1))
    coef = np.linalg.solve(gram, np.einsum("rmi,rmk->rik", basis, vj))
    out[rows] = coef[:, 0, :].reshape((rows.size, *v.shape[1:]))
    lev[rows] = np.linalg.inv(gram)[:, 0, 0]
    return out, lev


def smoothed_rays(
    fixes: GnssFixes,
    lines: ProjectionLines,
    cfg: TrackConfig,
    bad_fix: NDArray[np.bool_] | None = None,
    geodesy: Geodesy = GEODESY,
    timing: PoseTiming = DEFAULT_TIMING,
) -> TimedRays:
    """The pass's rays in an ENU frame at its first fix, on the smoothed trajectory, with
    each ray's time (``lines.t``) and origin tolerance (module docstring).

    ``bad_fix`` marks fixes left out of the smoothing (multipath); rays near them take the
    smoothing correction interpolated over their neighbours. ``timing`` is the motion model
    the lines' poses were interpolated with (:func:`vehicle.geoloc.geolocate`).
    """
    good = np.ones(len(fixes), bool) if bad_fix is None else ~np.asarray(bad_fix, bool)
    lat, lon = np.asarray(fixes.lat, float), np.asarray(fixes.lon, float)
    frame = EnuFrame(float(lat[0]), float(lon[0]), float(fixes.h[0]), geodesy)
    fg = fixes if good.all() else fixes.take(np.flatnonzero(good))
    ft = check_increasing(fg.t, "GnssFixes.t")
    xyz = frame.from_geodetic(fg.lat, fg.lon, np.asarray(fg.h, float))
    smooth, lev = smooth_in_time(ft, xyz, cfg.window_s)
    t = np.asarray(lines.t, float)
    br = bracket(ft, t)
    n = len(lines)
    if cfg.sigma_from_fixes:
        root = np.sqrt(lev)
        psi = np.radians(np.asarray(fg.heading_deg, float))
        s_psi = np.radians(np.asarray(fg.sigma_heading_deg, float))
        move_h, _ = turn_sigmas(br, ft, psi, xyz, timing)
        move_v = motion_sigma(br, timing.accel_v_sigma_mps2)
        # of the reported sigma, the part that changes within a track's life (a receiver
        # reporting its total error includes a bias the track's rays share)
        _, r_h, r_v = view_shares(
            ft, psi, s_psi, timing.view_lag_s, xyz, fg.sigma_h_m, fg.sigma_v_m
        )
        white_h = interpolate_sigma(br, r_h * root * np.asarray(fg.sigma_h_m, float))
        white_v = interpolate_sigma(br, r_v * root * np.asarray(fg.sigma_v_m, float))
        floor2 = cfg.rel_pos_sigma_m**2
        s_h = np.sqrt(floor2 + white_h**2 + move_h**2)
        s_v = np.sqrt(floor2 + white_v**2 + move_v**2)
    else:
        s_h = s_v = np.full(n, cfg.rel_pos_sigma_m)
    return TimedRays(
        origin=frame.from_geodetic(lines.lat, lines.lon, lines.h) + interpolate(br, smooth - xyz),
        direction=frame.vectors_from_enu_at(lines.direction, lines.lat, lines.lon),
        sigma_az=np.asarray(lines.sigma_az, float),
        sigma_el=np.asarray(lines.sigma_el, float),
        sigma_pos_h=s_h,
        sigma_pos_v=s_v,
        range_m=np.asarray(lines.range_m, float),
        sigma_range_m=np.asarray(lines.sigma_range_m, float),
        image=np.asarray(lines.image, np.int64),
        sign_class=np.asarray(lines.sign_class, np.int64),
        t=t,
    )


def _position(rays: LocalRays, last: int, n: int, big_a: Array, b: Array) -> tuple[Array, Array]:
    """A track's position and covariance from its summed normal equations (``n`` rays, the
    latest ``last``): their solution (:func:`hdmap.mapping.initiation.triangulate`), or for one
    ray without a range, :func:`hdmap.mapping.initiation.ray_point`."""
    if n >= 2 or rays.range_m[last] > 0:
        try:
            cov = np.linalg.inv(big_a)
        except np.linalg.LinAlgError:
            cov = np.linalg.pinv(big_a)
        x = cov @ b
        if np.isfinite(x).all() and np.isfinite(cov).all():
            return x, cov
    return ray_point(rays, last)


def track_rays(rays: LocalRays, cfg: TrackConfig, t: ArrayLike | None = None) -> IntArray:
    """Track id (1, 2, ... in order of first detection) per ray of one pass; ``t`` is each
    ray's capture time, s (default: ``rays.t`` of :class:`TimedRays`). Rays of one frame
    (same ``image``) are assigned together, frames in time order.

    >>> d = np.array([[0.0, 1.0, 0.0]] * 3)
    >>> a = np.array([[-5.0, 0.0, 0.0], [-5.0, 2.0, 0.0], [5.0, 4.0, 0.0]])
    >>> r = LocalRays(a, d / 1.0, *np.full((4, 3), 0.01), np.array([20.0, 18.0, 16.0]),
    ...               np.full(3, 0.5), np.arange(3), np.ones(3, np.int64))
    >>> track_rays(r, TrackConfig(), t=[0.0, 0.2, 0.4]).tolist()  # the third: another sign
    [1, 1, 2]
    """
    if t is None:
        t = getattr(rays, "t", None)
    if t is None:
        raise ValueError("t: track_rays needs each ray's time (TimedRays, or t=...)")
    times = np.asarray(t, float).reshape(-1)
    if times.size != len(rays) or not np.isfinite(times).all():
        raise ValueError(f"t: need {len(rays)} finite times, got {times.size}")
    n = len(rays)
    out = np.zeros(n, np.int64)
    if n == 0:
        return out
    gate = GateConfig(
        chi2_gate=cfg.chi2_gate, range_k=cfg.range_k, angle_floor_rad=0.0, min_range_m=0.5
    )
    a_cov = origin_cov(rays, 0.0, 0.0)
    terms_a, terms_b = normal_terms(rays)
    # per track: class, last time, ray count, summed normal equations, position
    cls: list[int] = []
    last: list[float] = []
    count: list[int] = []
    sums: list[tuple[Array, Array]] = []
    pos: list[tuple[Array, Array]] = []
    live: list[int] = []  # tracks not yet closed (times only increase: closed for good)
    img = np.asarray(rays.image, np.int64)
    order = np.lexsort((img, times))
    new_frame = (np.diff(img[order]) != 0) | (np.diff(times[order]) != 0)
    starts = np.flatnonzero(np.r_[True, new_frame])
    for s, e in zip(starts, np.r_[starts[1:], n], strict=True):
        here = order[s:e]
        now = float(times[here[0]])
        live = [k for k in live if now - last[k] <= cfg.max_gap_s]
        best = np.full(here.size, -1, np.int64)  # per ray of this image: its track
        if live:
            opened = np.array(live, np.int64)
            hi, ti = np.nonzero(rays.sign_class[here][:, None] == np.array(cls)[opened][None, :])
            if hi.size:
                ri, tk = here[hi], opened[ti]
                x = np.array([pos[k][0] for k in tk])
                cov = np.array([pos[k][1] for k in tk])
                chi2, ok = pair_chi2(rays, ri, x, cov, a_cov, gate)
                cost = np.where(ok, chi2, np.inf)
                # one detection per track and image: the association's per-image assignment
                best = assign_per_image(here.size, np.zeros(here.size, np.int64), hi, tk, cost,
                                        cfg.chi2_gate)  # fmt: skip
        for j, k in zip(here.tolist(), best.tolist(), strict=True):
            if k < 0:
                k = len(cls)
                cls.append(int(rays.sign_class[j]))
                last.append(now)
                count.append(0)
                sums.append((np.zeros((3, 3)), np.zeros(3)))
                pos.append((np.zeros(3), np.eye(3)))
                live.append(k)
            out[j] = k + 1
            last[k] = now
            count[k] += 1
            sums[k] = (sums[k][0] + terms_a[j], sums[k][1] + terms_b[j])
            pos[k] = _position(rays, j, count[k], *sums[k])
    return out
