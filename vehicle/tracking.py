"""Onboard detection tracking: the detections of one sign, followed from image to image.

A vehicle sees a sign in tens of consecutive images. Which detections belong together is
easy onboard, where the images come in order 0.2 s apart, and hard on the server, where
a street of same-class signs 8 m apart gives rays that each fit several landmarks. The
vehicle therefore labels each detection with a track (``Observations.track``); the
matcher keeps a track's rays together (:func:`hdmap.mapping.association.assign_tracks`).

Tracking runs in a local ENU frame at the pass's first fix, on a smoothed trajectory:
consecutive GNSS fixes carry independent white noise (about a metre) that would move a sign
by more than the gap to its neighbour between two images, while the pass's bias is common
to all of them and cancels. Positions are smoothed by a local quadratic fit
(Savitzky-Golay) over ``window`` fixes; each ray keeps its direction from the smoothed
origin. The heading is not smoothed: at a corner of the path a fit over two seconds is
wrong by tenths of a radian (measured: it doubled the rays' scatter; docs/estimator.md
section 15).

A track's position is the triangulation of its rays (bearing terms and the range from the
box size, :func:`hdmap.mapping.initiation.triangulate`). Each image's detections are assigned to
the open tracks of their class by the association's per-image assignment
(:func:`hdmap.mapping.association.assign_per_image`) on the gating statistic of
:func:`hdmap.mapping.association.pair_chi2` (angles and range), with the origin uncertainty
``rel_pos_sigma_m`` of the smoothed trajectory over a track's life; a detection no track
takes starts one; a track not extended for ``max_gap_images`` images is closed.

>>> import numpy as np
>>> (smooth_track(np.arange(11.0) * 2.0, 5).round(6) + 0.0).tolist()[:3]
[0.0, 2.0, 4.0]
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hdmap.geo.geodesy import GEODESY, EnuFrame, Geodesy
from hdmap.mapping.association import GateConfig, LocalRays, assign_per_image, origin_cov, pair_chi2
from hdmap.mapping.initiation import normal_terms, ray_point
from vehicle.geoloc import GnssFixes, ProjectionLines

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class TrackConfig:
    """How detections are chained into tracks (``VehicleAgent`` runs it per pass)."""

    window: int = 11
    """Fixes in the trajectory smoother's window (odd; 11 = 2 s at 5 Hz)."""
    rel_pos_sigma_m: float = 0.6
    """Per-axis error of the smoothed origin relative to the track's other origins."""
    chi2_gate: float = 16.27
    """Largest statistic (angles and range) of a detection against its track's position."""
    max_gap_images: int = 8
    """A track not extended for this many images is closed."""
    range_k: float = 4.0
    """A detection's range must agree with its track's distance within this many sigma."""

    def __post_init__(self) -> None:
        if self.window < 1 or self.window % 2 == 0:
            raise ValueError(f"window: must be a positive odd number of fixes, got {self.window}")


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


def smoothed_rays(
    fixes: GnssFixes,
    lines: ProjectionLines,
    cfg: TrackConfig,
    bad_fix: NDArray[np.bool_] | None = None,
    geodesy: Geodesy = GEODESY,
) -> LocalRays:
    """The pass's rays in an ENU frame at its first fix, on the smoothed trajectory.

    ``bad_fix`` marks fixes left out of the smoothing (multipath); they take the smoothed
    trajectory interpolated over their neighbours.
    """
    n = len(fixes.t)
    lat, lon = np.asarray(fixes.lat, float), np.asarray(fixes.lon, float)
    frame = EnuFrame(float(lat[0]), float(lon[0]), float(fixes.h[0]), geodesy)
    xyz = frame.from_geodetic(lat, lon, np.asarray(fixes.h, float))
    good = np.ones(n, bool) if bad_fix is None else ~np.asarray(bad_fix, bool)
    t = np.asarray(fixes.t, float)
    if good.sum() >= 2 and not good.all():
        xyz = np.column_stack([np.interp(t, t[good], xyz[good, k]) for k in range(3)])
    d_xyz = smooth_track(xyz, cfg.window) - xyz
    img = np.asarray(lines.image, np.int64)
    return LocalRays(
        origin=frame.from_geodetic(lines.lat, lines.lon, lines.h) + d_xyz[img],
        direction=frame.vectors_from_enu_at(lines.direction, lines.lat, lines.lon),
        sigma_az=np.asarray(lines.sigma_az, float),
        sigma_el=np.asarray(lines.sigma_el, float),
        sigma_pos_h=np.full(len(lines), cfg.rel_pos_sigma_m),
        sigma_pos_v=np.full(len(lines), cfg.rel_pos_sigma_m),
        range_m=np.asarray(lines.range_m, float),
        sigma_range_m=np.asarray(lines.sigma_range_m, float),
        image=img,
        sign_class=np.asarray(lines.sign_class, np.int64),
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


def track_rays(rays: LocalRays, cfg: TrackConfig) -> IntArray:
    """Track id (1, 2, ... in order of first detection) per ray of one pass.

    >>> d = np.array([[0.0, 1.0, 0.0]] * 3)
    >>> a = np.array([[-5.0, 0.0, 0.0], [-5.0, 2.0, 0.0], [5.0, 4.0, 0.0]])
    >>> r = LocalRays(a, d / 1.0, *np.full((4, 3), 0.01), np.array([20.0, 18.0, 16.0]),
    ...               np.full(3, 0.5), np.arange(3), np.ones(3, np.int64))
    >>> track_rays(r, TrackConfig()).tolist()  # the third ray sees another sign
    [1, 1, 2]
    """
    n = len(rays)
    out = np.zeros(n, np.int64)
    if n == 0:
        return out
    gate = GateConfig(
        chi2_gate=cfg.chi2_gate, range_k=cfg.range_k, angle_floor_rad=0.0, min_range_m=0.5
    )
    a_cov = origin_cov(rays, 0.0, 0.0)
    terms_a, terms_b = normal_terms(rays)
    # per track: class, last image, ray count, summed normal equations, position
    cls: list[int] = []
    last: list[int] = []
    count: list[int] = []
    sums: list[tuple[Array, Array]] = []
    pos: list[tuple[Array, Array]] = []
    live: list[int] = []  # tracks not yet closed (images only increase: closed for good)
    order = np.argsort(rays.image, kind="stable")
    starts = np.flatnonzero(np.r_[True, np.diff(rays.image[order]) != 0])
    for s, e in zip(starts, np.r_[starts[1:], n], strict=True):
        here = order[s:e]
        image = int(rays.image[here[0]])
        live = [k for k in live if image - last[k] <= cfg.max_gap_images]
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
                last.append(image)
                count.append(0)
                sums.append((np.zeros((3, 3)), np.zeros(3)))
                pos.append((np.zeros(3), np.eye(3)))
                live.append(k)
            out[j] = k + 1
            last[k] = image
            count[k] += 1
            sums[k] = (sums[k][0] + terms_a[j], sums[k][1] + terms_b[j])
            pos[k] = _position(rays, j, count[k], *sums[k])
    return out
