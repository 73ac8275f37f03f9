"""Onboard geolocalisation: GNSS fix + detection -> projection line (paper III-A.2).

The paper's eq. (2)-(3): the line through ``A = X^C`` (camera centre) and
``B = X^C + (T_W^C)^-1 K^-1 (u, v, 1)^T``. Here, per detection:

1. the GNSS antenna position and heading place the vehicle (eq. 1 inverted through
   the GNSS mount); GNSS gives no pitch or roll, so the vehicle frame is level;
2. the camera mount places the camera centre ``A`` and its attitude;
3. the box centre, undistorted and lifted by ``K^-1``, gives the unit direction
   ``d`` in ENU at ``A``;
4. first-order propagation gives the angular standard deviations of ``d`` in
   azimuth (about Up) and elevation, from pixel noise, heading noise and an
   assumed pitch noise (the level-vehicle assumption);
5. where the box is whole and tall enough, the sign's standard panel height gives
   the distance along the ray: ``r = f_y H / h_px * |K^-1 (u, v, 1)|``.

Azimuth is measured clockwise from North, like the heading; elevation upward from
the horizontal: ``d = (cos e sin a, cos e cos a, sin e)`` in (E, N, U).

>>> azimuth_elevation(np.array([[1.0, 1.0, 0.0]]) / np.sqrt(2))[0].round(6).tolist()
[0.785398]
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hdmap.geo.camera import R_VEHICLE_CAMERA_FORWARD, Intrinsics, Mount
from hdmap.geo.geodesy import (
    GEODESY,
    EnuFrame,
    Geodesy,
    ecef_to_enu_vectors,
    enu_to_ecef_vectors,
)
from hdmap.geo.signs import CATALOG, SignCatalog
from vehicle.pose import (
    WHITE_SHARE_MIN_FIXES,
    Bracket,
    PoseTiming,
    bracket,
    check_increasing,
    hidden_yaw_accel,
    interpolate,
    interpolate_angle,
    interpolate_sigma,
    motion_sigma,
    observed_accels,
    reachable,
    view_shares,
    white_share,
    wrap_angle,
)

Array = NDArray[np.float64]


def azimuth_elevation(d: ArrayLike) -> tuple[Array, Array]:
    """Unit ENU directions (..., 3) -> (azimuth clockwise from North, elevation), rad."""
    v = np.asarray(d, float)
    az = np.arctan2(v[..., 0], v[..., 1])
    el = np.arcsin(np.clip(v[..., 2], -1.0, 1.0))
    return az, el


def vehicle_to_enu(heading_rad: ArrayLike) -> Array:
    """Rotation (..., 3, 3) vehicle frame (x fwd, y left, z up) -> ENU, level vehicle.

    >>> vehicle_to_enu(0.0).round(12).tolist()  # heading North: x->N, y->W
    [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    """
    psi = np.asarray(heading_rad, float)
    s, c = np.sin(psi), np.cos(psi)
    z, o = np.zeros_like(s), np.ones_like(s)
    return np.stack(
        [np.stack([s, -c, z], -1), np.stack([c, s, z], -1), np.stack([z, z, o], -1)], axis=-2
    )


@dataclass(frozen=True)
class VehicleModel:
    """Calibration and noise model of one vehicle (loaded from a TOML file by ``vehicle``)."""

    intrinsics: Intrinsics
    camera_mount: Mount
    gnss_mount: Mount = field(default_factory=Mount)
    pixel_sigma: float = 3.0
    """Standard deviation of the detected box centre, pixels (per axis)."""
    pitch_sigma_rad: float = 0.0
    """Bound on the unmodelled vehicle pitch (GNSS gives none), rad. The agent measures the
    white pitch of each pass from its own tracks and uses the smaller of the two
    (``vehicle/pitch.py``); ``geolocate`` called directly adds this value itself."""
    min_box_px: float = 12.0
    """Boxes shorter than this give no range estimate."""
    catalog: SignCatalog = CATALOG

    @staticmethod
    def forward_camera(
        intrinsics: Intrinsics,
        camera_xyz: ArrayLike = (1.5, 0.0, 1.4),
        camera_rpy_deg: ArrayLike = (0.0, 0.0, 0.0),
        gnss_xyz: ArrayLike = (0.0, 0.0, 1.5),
        **kw,
    ) -> VehicleModel:
        """A camera looking forward (rpy adds to the straight-ahead attitude)."""
        cam = Mount.from_rpy_deg(camera_xyz, camera_rpy_deg, base=R_VEHICLE_CAMERA_FORWARD)
        return VehicleModel(intrinsics, cam, Mount.from_rpy_deg(gnss_xyz), **kw)


@dataclass(frozen=True)
class GnssFixes:
    """GNSS fixes of one pass (struct of arrays): a time series of their own.

    ``t`` is the fix's time, s, on the clock of :attr:`Detections.t` (the vehicle's, e.g.
    Unix seconds); any rate, gaps allowed; strictly increasing where detections carry
    times (:func:`geolocate` refuses it otherwise, naming ``GnssFixes.t``). ``lat``,
    ``lon`` (deg), ``h`` (m, ellipsoidal) place the GNSS antenna; ``heading_deg`` is the
    course over ground, degrees clockwise from true North at the fix. The sigmas are what
    the receiver claims, 1 sigma: horizontal per axis and vertical (m), heading (deg).

    Older callers give one fix per camera image (:attr:`Detections.image` indexes the rows,
    no :attr:`Detections.t`); that form still works.
    """

    t: Array
    lat: Array
    lon: Array
    h: Array
    heading_deg: Array
    sigma_h_m: Array
    sigma_v_m: Array
    sigma_heading_deg: Array

    def __len__(self) -> int:
        return int(np.asarray(self.t).size)

    def take(self, idx: NDArray) -> GnssFixes:
        return GnssFixes(
            **{k: np.asarray(getattr(self, k))[idx] for k in self.__dataclass_fields__}
        )


@dataclass(frozen=True)
class Detections:
    """Sign detections of one pass (struct of arrays), one row per box.

    ``image`` is the camera frame's number within the pass (increasing with the frame's
    time; frames without detections are not listed); ``t`` its capture time, s, on the
    clock of :attr:`GnssFixes.t` (mid-exposure; every row of one frame has the same
    time). The pose at ``t`` is interpolated from the fixes around it
    (:mod:`vehicle.pose`). Without ``t`` (None, the older form) ``image`` indexes the row
    of :class:`GnssFixes` taken at that image.
    """

    image: NDArray[np.int64]
    sign_class: NDArray[np.int64]
    box: Array
    """(N, 4) pixels: u_min, v_min, u_max, v_max."""
    score: Array
    t: Array | None = None
    """Per detection: its frame's capture time, s (None: ``image`` indexes the fixes)."""

    def __len__(self) -> int:
        return int(np.asarray(self.image).size)

    def take(self, idx: NDArray) -> Detections:
        return Detections(
            **{
                k: None if getattr(self, k) is None else np.asarray(getattr(self, k))[idx]
                for k in self.__dataclass_fields__
            }
        )


@dataclass(frozen=True)
class ProjectionLines:
    """Projection lines (struct of arrays), one per detection."""

    t: Array
    image: NDArray[np.int64]
    sign_class: NDArray[np.int64]
    score: Array
    lat: Array
    lon: Array
    h: Array
    """Camera centre A, geodetic (deg, deg, m)."""
    direction: Array
    """(N, 3) unit direction in ENU at A."""
    sigma_az: Array
    sigma_el: Array
    """Angular standard deviations of the direction, rad."""
    sigma_pos_h: Array
    sigma_pos_v: Array
    """Standard deviations of A: horizontal per axis and vertical, m."""
    range_m: Array
    """Distance from A to the sign along the ray, m; 0 where unusable."""
    sigma_range_m: Array

    def __len__(self) -> int:
        return int(self.t.size)

    def take(self, idx: NDArray) -> ProjectionLines:
        return ProjectionLines(**{k: getattr(self, k)[idx] for k in self.__dataclass_fields__})


def angles_in_vehicle(intr: Intrinsics, cam: Mount, uv: Array) -> tuple[Array, Array, Array]:
    """Pixel -> (direction in vehicle frame, azimuth at heading 0, elevation)."""
    xy = intr.pixel_to_normalized(uv)
    ray_c = np.concatenate([xy, np.ones((*xy.shape[:-1], 1))], axis=-1)
    ray_c /= np.linalg.norm(ray_c, axis=-1, keepdims=True)
    d_v = ray_c @ cam.rotation.T
    az, el = azimuth_elevation(d_v @ vehicle_to_enu(0.0).T)
    return d_v, az, el


@dataclass(frozen=True)
class FixCheck:
    """Onboard integrity check of GNSS fixes against their neighbours' track."""

    window: int = 7
    """Fixes in the sliding window (odd): the track at a fix is the window's median."""
    k_sigma: float = 6.0
    """A fix is suspect beyond this many reported horizontal sigmas from the track ..."""
    floor_m: float = 10.0
    """... and beyond this many metres (the spread of a window along the track)."""


def fix_outliers(
    fixes: GnssFixes, check: FixCheck | None = None, geodesy: Geodesy = GEODESY
) -> NDArray[np.bool_]:
    """Fixes that jump away from the track of their neighbours (multipath): per fix, the
    horizontal distance to the componentwise median of the ``window`` fixes around it
    (fewer at the ends), against ``max(floor_m, k_sigma * sigma_h)``. One jump moves a
    window's median by one rank only, so the jump stands out by about its size; a bias
    the whole pass shares does not. A receiver-level check any vehicle can run (an INS
    would do better); its rays are not uploaded.

    >>> t = np.arange(9) * 0.2
    >>> lat = 60.0 + np.arange(9) * 2.5e-5  # 2.8 m per fix northward
    >>> lat[4] += 30.0 / 111_000            # a 30 m multipath jump
    >>> f = GnssFixes(t, lat, np.full(9, 25.0), np.zeros(9), np.zeros(9), np.ones(9),
    ...               np.ones(9), np.full(9, 0.5))
    >>> np.flatnonzero(fix_outliers(f)).tolist()
    [4]
    """
    c = check or FixCheck()
    n = len(fixes)
    out = np.zeros(n, bool)
    if n < 3:
        return out
    lat = np.asarray(fixes.lat, float)
    lon = np.asarray(fixes.lon, float)
    ecef = geodesy.to_ecef(lat, lon, np.asarray(fixes.h, float))
    xy = ecef_to_enu_vectors(ecef - ecef[0], lat[0], lon[0])[:, :2]
    half = max(c.window // 2, 1)
    padded = np.full((n + 2 * half, 2), np.nan)
    padded[half : half + n] = xy
    windows = np.lib.stride_tricks.sliding_window_view(padded, 2 * half + 1, axis=0)
    track = np.nanmedian(windows, axis=-1)
    dev = np.hypot(*(xy - track).T)
    limit = np.maximum(c.floor_m, c.k_sigma * np.asarray(fixes.sigma_h_m, float))
    return dev > limit


@dataclass(frozen=True)
class AntennaPoses:
    """The GNSS antenna's pose and claimed sigmas at each detection (struct of arrays)."""

    t: Array
    lat: Array
    lon: Array
    h: Array
    heading_rad: Array
    sigma_h_m: Array
    sigma_v_m: Array
    sigma_heading_rad: Array


DEFAULT_TIMING = PoseTiming()


def detection_reach(
    fixes: GnssFixes, det: Detections, timing: PoseTiming = DEFAULT_TIMING
) -> NDArray[np.bool_]:
    """Per detection: whether it has a pose (:func:`vehicle.pose.reachable`: a fix within
    ``timing.max_gap_s``); always true for detections without times (the index form).
    Raises ValueError naming ``GnssFixes.t`` unless the fix times increase strictly."""
    if det.t is None:
        return np.ones(len(det), bool)
    ft = check_increasing(fixes.t, "GnssFixes.t")
    return reachable(bracket(ft, np.asarray(det.t, float)), timing)


def antenna_poses(
    fixes: GnssFixes,
    det: Detections,
    timing: PoseTiming = DEFAULT_TIMING,
    geodesy: Geodesy = GEODESY,
) -> AntennaPoses:
    """The antenna's pose at each detection: the fix of its image (no ``det.t``), or
    interpolated at ``det.t`` from the fixes around it (:mod:`vehicle.pose`: position
    linearly in an ENU frame at the first fix, heading on the circle, sigmas grown with
    the gap). A detection no fix reaches (:func:`detection_reach`) is refused with a
    ValueError naming ``Detections.t``: filter first, it is never extrapolated."""
    if det.t is None:
        idx = np.asarray(det.image, np.int64)
        return AntennaPoses(
            t=np.asarray(fixes.t, float)[idx],
            lat=np.asarray(fixes.lat, float)[idx],
            lon=np.asarray(fixes.lon, float)[idx],
            h=np.asarray(fixes.h, float)[idx],
            heading_rad=np.radians(np.asarray(fixes.heading_deg, float)[idx]),
            sigma_h_m=np.asarray(fixes.sigma_h_m, float)[idx],
            sigma_v_m=np.asarray(fixes.sigma_v_m, float)[idx],
            sigma_heading_rad=np.radians(np.asarray(fixes.sigma_heading_deg, float)[idx]),
        )
    t = np.asarray(det.t, float).reshape(-1)
    if t.size == 0:
        e = np.zeros(0)
        return AntennaPoses(e, e, e, e, e, e, e, e)
    if not np.isfinite(t).all():
        raise ValueError("Detections.t: must be finite")
    ft = check_increasing(fixes.t, "GnssFixes.t")
    br = bracket(ft, t)
    far = ~reachable(br, timing)
    if far.any():
        k = int(np.flatnonzero(far)[0])
        raise ValueError(
            f"Detections.t: {int(far.sum())} detection(s) more than {timing.max_gap_s:g} s "
            f"from a fix (first: row {k}, t={float(t[k])!r}); drop them first (detection_reach)"
        )
    lat, lon = np.asarray(fixes.lat, float), np.asarray(fixes.lon, float)
    h = np.asarray(fixes.h, float)
    frame = EnuFrame(float(lat[0]), float(lon[0]), float(h[0]), geodesy)
    xyz = frame.from_geodetic(lat, lon, h)
    lat_i, lon_i, h_i = frame.to_geodetic(interpolate(br, xyz))
    psi = np.radians(np.asarray(fixes.heading_deg, float))
    s_psi = np.radians(np.asarray(fixes.sigma_heading_deg, float))
    m_v = motion_sigma(br, timing.accel_v_sigma_mps2)
    # The heading's white share: the bias compensation takes the rays' angular variance
    # as told (docs/experiments/2026-12-interpolated-sigma-overcompensation.md). The
    # positions keep the upper bound between fixes: they only widen gates and weights.
    r_psi = white_share(ft, psi, s_psi, angle=True)
    # turns count beyond the noise of consecutive fixes' differences: their white part
    # (white_share gives 0, the upper bound, where it has too few fixes to tell)
    r_turn = r_psi if ft.size >= WHITE_SHARE_MIN_FIXES else 1.0
    m_h, m_psi = turn_sigmas(br, ft, psi, xyz, timing, r_turn * s_psi)
    # What of it changes within a view of a sign: the estimator's bias compensation
    # removes, per ray, the curvature its claimed variance would put in the sums, which
    # an error the whole view shares does not (docs/estimator.md section 3;
    # docs/experiments/2026-12-shared-heading-compensation.md).
    r_view, r_view_h, r_view_v = view_shares(
        ft, psi, s_psi, timing.view_lag_s, xyz, fixes.sigma_h_m, fixes.sigma_v_m
    )
    # of that part, the share consecutive fixes do not share (interpolation averages it)
    r_white = min(r_psi / r_view, 1.0) if r_view > 0.0 else 1.0
    return AntennaPoses(
        t=t,
        lat=np.atleast_1d(lat_i),
        lon=np.atleast_1d(lon_i),
        h=np.atleast_1d(h_i),
        heading_rad=interpolate_angle(br, psi),
        sigma_h_m=np.hypot(r_view_h * interpolate_sigma(br, fixes.sigma_h_m), m_h),
        sigma_v_m=np.hypot(r_view_v * interpolate_sigma(br, fixes.sigma_v_m), m_v),
        sigma_heading_rad=np.hypot(interpolate_sigma(br, r_view * s_psi, r_white), m_psi),
    )


def turn_sigmas(
    br: Bracket,
    fix_t: Array,
    psi: Array,
    xyz: Array,
    timing: PoseTiming,
    heading_sigma: Array | None = None,
) -> tuple[Array, Array]:
    """The interpolation's horizontal (m, per axis) and heading (rad) sigmas at the
    bracketed times: the configured accelerations, with ``timing.observed_turns`` raised
    in quadrature by what the fixes show of the interval's turn
    (:func:`vehicle.pose.observed_accels`; only what stands out of the fixes' claimed
    heading noise ``heading_sigma``, rad)."""
    if fix_t.size < 2 or not timing.observed_turns:
        return motion_sigma(br, timing.accel_sigma_mps2), motion_sigma(
            br, timing.yaw_accel_sigma_radps2
        )
    yaw, across = observed_accels(fix_t, psi, xyz[:, :2], heading_sigma)
    a_h = np.hypot(timing.accel_sigma_mps2, across[br.ia])
    floor = timing.yaw_accel_sigma_radps2
    if heading_sigma is not None:  # what the fixes would have shown is not unmodelled
        floor = np.minimum(floor, hidden_yaw_accel(fix_t, heading_sigma)[br.ia])
    a_psi = np.hypot(floor, yaw[br.ia])
    return motion_sigma(br, a_h), motion_sigma(br, a_psi)


def geolocate(
    fixes: GnssFixes,
    det: Detections,
    model: VehicleModel,
    geodesy: Geodesy = GEODESY,
    timing: PoseTiming = DEFAULT_TIMING,
) -> ProjectionLines:
    """Vectorised projection lines for detections, from the antenna pose at each
    (:func:`antenna_poses`: the fix of its image, or interpolated at its time)."""
    pose = antenna_poses(fixes, det, timing, geodesy)
    idx = np.asarray(det.image, np.int64)
    box = np.asarray(det.box, float).reshape(-1, 4)
    intr, cam = model.intrinsics, model.camera_mount
    uv = np.stack([(box[:, 0] + box[:, 2]) / 2.0, (box[:, 1] + box[:, 3]) / 2.0], axis=-1)

    r_wv = vehicle_to_enu(pose.heading_rad)
    d_v, _, _ = angles_in_vehicle(intr, cam, uv)
    d_fix = np.einsum("nij,nj->ni", r_wv, d_v)

    lat_f, lon_f, h_f = pose.lat, pose.lon, pose.h
    lever = cam.t - model.gnss_mount.t
    offset_enu = np.einsum("nij,j->ni", r_wv, lever)
    origin_ecef = geodesy.to_ecef(lat_f, lon_f, h_f) + enu_to_ecef_vectors(offset_enu, lat_f, lon_f)
    lat, lon, h = geodesy.to_geodetic(origin_ecef)
    direction = ecef_to_enu_vectors(enu_to_ecef_vectors(d_fix, lat_f, lon_f), lat, lon)
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)

    # First-order propagation: pixel noise through the camera model (central
    # differences, so distortion is included), heading straight into azimuth.
    step = 0.5
    grads = []
    for du, dv in ((step, 0.0), (0.0, step)):
        delta = np.array([du, dv])
        _, a_p, e_p = angles_in_vehicle(intr, cam, uv + delta)
        _, a_m, e_m = angles_in_vehicle(intr, cam, uv - delta)
        grads.append((wrap_angle(a_p - a_m) / (2 * step), (e_p - e_m) / (2 * step)))
    (da_du, de_du), (da_dv, de_dv) = grads
    s_px2 = model.pixel_sigma**2
    s_psi = pose.sigma_heading_rad
    sigma_az = np.sqrt(s_px2 * (da_du**2 + da_dv**2) + s_psi**2)
    sigma_el = np.sqrt(s_px2 * (de_du**2 + de_dv**2) + model.pitch_sigma_rad**2)

    lever_xy = float(np.hypot(lever[0], lever[1]))
    sigma_pos_h = np.hypot(pose.sigma_h_m, s_psi * lever_xy)
    sigma_pos_v = pose.sigma_v_m.copy()

    range_m, sigma_range = box_range(box, np.asarray(det.sign_class), model)

    return ProjectionLines(
        t=pose.t,
        image=idx,
        sign_class=np.asarray(det.sign_class, np.int64),
        score=np.asarray(det.score, float),
        lat=lat,
        lon=lon,
        h=h,
        direction=direction,
        sigma_az=sigma_az,
        sigma_el=sigma_el,
        sigma_pos_h=sigma_pos_h,
        sigma_pos_v=sigma_pos_v,
        range_m=range_m,
        sigma_range_m=sigma_range,
    )


def box_range(box: Array, sign_class: NDArray, model: VehicleModel) -> tuple[Array, Array]:
    """Distance along the ray from the sign's standard panel height; 0 where unusable.

    A box is usable when it lies wholly inside the image (not cut by the border),
    is at least ``min_box_px`` tall and its class has a known size.
    """
    intr = model.intrinsics
    b = np.asarray(box, float).reshape(-1, 4)
    uc = (b[:, 0] + b[:, 2]) / 2.0
    top = intr.pixel_to_normalized(np.stack([uc, b[:, 1]], -1))
    bot = intr.pixel_to_normalized(np.stack([uc, b[:, 3]], -1))
    ctr = intr.pixel_to_normalized(np.stack([uc, (b[:, 1] + b[:, 3]) / 2.0], -1))
    h_norm = bot[:, 1] - top[:, 1]
    h_px = b[:, 3] - b[:, 1]
    panel = model.catalog.heights(sign_class)
    usable = (
        (b[:, 0] >= 1.0)
        & (b[:, 1] >= 1.0)
        & (b[:, 2] <= intr.width - 2.0)
        & (b[:, 3] <= intr.height - 2.0)
        & (h_px >= model.min_box_px)
        & (panel > 0)
        & (h_norm > 0)
    )
    ray_len = np.sqrt(1.0 + ctr[:, 0] ** 2 + ctr[:, 1] ** 2)
    depth = np.where(usable, panel / np.where(usable, h_norm, 1.0), 0.0)
    rng = depth * ray_len
    rel = np.hypot(
        np.sqrt(2.0) * model.pixel_sigma / np.where(usable, h_px, 1.0),
        model.catalog.rel_sigmas(sign_class),
    )
    return rng, np.where(usable, rng * rel, 0.0)
