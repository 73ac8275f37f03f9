"""One simulated pass: the true trajectory, GNSS fixes and sign detections.

**Timing.** The camera and the GNSS receiver run on their own clocks' rates, on one time
axis (s from the fleet's epoch): camera frames every ``1 / frame_rate_hz`` from a random
phase after the pass's start; fixes in slots every ``1 / gnss_rate_hz`` from the start,
each at its slot plus a time jitter (``gnss_jitter_s`` std, kept within a quarter period so
the times increase), each slot empty with ``gnss_miss_prob`` (at least two fixes remain).
A fix is the antenna's true pose at the fix's own time plus the receiver's errors; only
frames with detections appear in :class:`vehicle.geoloc.Detections`, with their frame
number (``image``) and capture time (``t``). ``fix_per_frame=True`` is the older timing:
a fix at every frame (same times), ``Detections.t`` still given.

**Motion.** The vehicle cruises at ``speed_mps`` and takes curves slower, braking and
speeding up as a driver does (``lateral_accel_mps2``, :func:`fleetsim.route.speed_profile`).

Per frame the vehicle's TRUE pose places the camera
(``VehicleModel`` mount and intrinsics). A sign is visible when its panel
centre is in front of the camera and inside the image, within ``max_range_m``,
facing the camera (angle between the panel normal and the direction to the
camera below ``max_view_angle_deg``), not hidden by a building footprint, and
its box is at least ``min_box_px`` tall. The box spans the projections of the
panel's top/bottom and left/right edge points (panel width = panel height).
Each visible sign is detected with the detector's probability per frame; the box centre
gets pixel noise, its width and height ``size_sigma_px`` (0 in the presets: size kept),
and it is clipped to the image as real detectors do
(a clipped box gives no range in :func:`vehicle.geoloc.box_range`). A frame
holds one false positive (random class, random plausible box) with the false
positive rate.

The GNSS antenna's true position and heading get the noise model's errors
(per-pass bias + random walk, white, multipath) and become geodetic fixes; the
heading is turned to the local North at the fix (meridian convergence), so a
noise-free pass with ``fix_per_frame`` is geometrically exact through
:func:`vehicle.geoloc.geolocate`; with its own fix times, exact on straight stretches
and within the interpolation's motion model elsewhere (:mod:`vehicle.pose`).

Headings inside the simulator are radians clockwise from the world frame's North.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from fleetsim.gnss_replay import course_with_errors, fix_speed
from fleetsim.noise import GnssErrors, NoiseModel
from fleetsim.route import Path, SpeedProfile, speed_profile
from fleetsim.world import World
from hdmap.geo.geodesy import ecef_to_enu_vectors
from vehicle.geoloc import Detections, GnssFixes, VehicleModel, vehicle_to_enu

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class DriveParams:
    """How the vehicle drives, what its camera can see, and when its sensors sample."""

    speed_mps: float = 11.0
    """Cruising speed; curves are taken slower (``lateral_accel_mps2``)."""
    lateral_accel_mps2: float | None = 3.0
    """Largest lateral acceleration a driver takes a curve with, m/s^2 (comfortable
    driving; :func:`fleetsim.route.speed_profile`, braking and speeding up at 2 m/s^2).
    None: ``speed_mps`` everywhere, corners included (the older drive: 11 m/s round a
    7 m corner is 17 m/s^2 and 1.6 rad/s, which a 1 Hz receiver cannot follow)."""
    frame_rate_hz: float = 5.0
    """Camera frames per second (not above the GNSS rate by default: the map's estimator
    takes rays as independent, docs/experiments/2026-12-sensor-timing.md)."""
    max_range_m: float = 60.0
    max_view_angle_deg: float = 70.0
    min_box_px: float | None = None
    """Smallest detectable box height, px; None = the vehicle model's ``min_box_px``."""
    false_positive_max_px: float = 80.0
    gnss_rate_hz: float = 5.0
    """GNSS fix slots per second."""
    gnss_jitter_s: float = 0.01
    """Std of a fix's time about its slot, s (clipped to a quarter of the period)."""
    gnss_miss_prob: float = 0.05
    """Share of fix slots without a fix."""
    fix_per_frame: bool = False
    """The older timing: one fix at every frame's time (the gnss_* fields unused)."""

    def __post_init__(self) -> None:
        for name in ("speed_mps", "frame_rate_hz", "max_range_m", "gnss_rate_hz"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"DriveParams.{name} must be > 0")
        if not self.gnss_jitter_s >= 0.0:
            raise ValueError("DriveParams.gnss_jitter_s must be >= 0")
        if self.lateral_accel_mps2 is not None and not self.lateral_accel_mps2 > 0.0:
            raise ValueError("DriveParams.lateral_accel_mps2 must be > 0 (or None)")
        if not 0.0 <= self.gnss_miss_prob < 1.0:
            raise ValueError("DriveParams.gnss_miss_prob must be in [0, 1)")


@dataclass(frozen=True)
class DriveTruth:
    """Ground truth of one pass."""

    sign_id: IntArray
    """Per detection: the true sign id, -1 for a false positive."""
    uv_true: Array
    """Per detection: (N, 2) noise-free box centre, px; NaN for false positives."""
    distance_m: Array
    """Per detection: true camera-to-panel-centre distance, m; NaN for false positives."""
    t: Array
    """Per camera frame (``Detections.image`` indexes these): capture time, s."""
    vehicle_enu: Array
    """Per frame: (M, 3) vehicle reference point (on the ground), world ENU m."""
    heading_rad: Array
    """Per frame: true heading, rad clockwise from the world frame's North."""
    camera_enu: Array
    """Per frame: the camera centre, world ENU m."""
    fix_t: Array
    """Per GNSS fix (the rows of the pass's fixes): its time, s."""
    antenna_enu: Array
    """Per fix: the true antenna position, world ENU m."""
    fix_heading_rad: Array
    """Per fix: the true heading, rad clockwise from the world frame's North."""
    gnss: GnssErrors
    """Per fix: the GNSS errors added to the antenna pose, by component."""
    visible_image: IntArray
    visible_sign: IntArray
    """Every (frame, sign id) pair that passed the geometric visibility test."""


def poses_along(
    path: Path, t: Array, speed: float | SpeedProfile, t0: float | None = None
) -> tuple[Array, Array]:
    """Vehicle reference points (M, 3) and headings (M,) at times ``t`` from ``t0``
    (default: ``t[0]``), at a constant ``speed`` (m/s) or along a :class:`SpeedProfile`;
    the vehicle stands at the path's ends beyond them."""
    t = np.asarray(t, float)
    start = float(t[0]) if t0 is None else t0
    along = speed.s_at(t - start) if isinstance(speed, SpeedProfile) else speed * (t - start)
    xy, psi = path.at(along)
    return np.column_stack([xy, np.zeros(len(xy))]), psi


def sensor_times(
    rng: np.random.Generator, t0: float, duration_s: float, params: DriveParams
) -> tuple[Array, Array]:
    """(camera frame times, GNSS fix times) of a pass from ``t0`` lasting ``duration_s``
    (module docstring); both strictly increasing, inside [t0, t0 + duration]."""
    if params.fix_per_frame:
        t = t0 + np.arange(0.0, duration_s, 1.0 / params.frame_rate_hz)
        return t, t
    frame_dt, fix_dt = 1.0 / params.frame_rate_hz, 1.0 / params.gnss_rate_hz
    phase = float(rng.uniform(0.0, frame_dt))
    frames = t0 + np.arange(phase, duration_s, frame_dt)
    slots = np.arange(0.0, duration_s, fix_dt)
    jitter = np.clip(rng.normal(0.0, params.gnss_jitter_s, slots.size), -fix_dt / 4, fix_dt / 4)
    fix = np.clip(slots + jitter, 0.0, duration_s)
    present = rng.random(slots.size) >= params.gnss_miss_prob
    if present.sum() < 2:
        present[: min(2, slots.size)] = True
    fix = fix[present]
    keep = np.r_[True, np.diff(fix) > 0.0]  # clipping at the ends may tie two times
    return frames, t0 + fix[keep]


def _occluded(p0: Array, p1: Array, boxes: Array) -> NDArray[np.bool_]:
    """Whether each 2D segment p0->p1 crosses any axis-aligned box (slab test)."""
    if boxes.size == 0 or p0.size == 0:
        return np.zeros(len(p0), bool)
    d = (p1 - p0)[:, None, :]
    o = p0[:, None, :]
    lo, hi = boxes[None, :, :2], boxes[None, :, 2:]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1, t2 = (lo - o) * inv, (hi - o) * inv
    t1 = np.where(d == 0.0, np.where((o >= lo) & (o <= hi), -np.inf, np.inf), t1)
    t2 = np.where(d == 0.0, np.where((o >= lo) & (o <= hi), np.inf, -np.inf), t2)
    tmin = np.max(np.minimum(t1, t2), axis=2)
    tmax = np.min(np.maximum(t1, t2), axis=2)
    hit = (tmax >= np.maximum(tmin, 0.0)) & (tmin <= 1.0)
    return hit.any(axis=1)


def visible_boxes(
    world: World,
    model: VehicleModel,
    camera_enu: Array,
    r_world_camera: Array,
    params: DriveParams,
) -> tuple[IntArray, IntArray, Array, Array]:
    """Geometric visibility of every sign from every camera pose.

    Returns (image, sign row, box (K, 4) unclipped px, distance m) of the visible pairs.
    """
    sg = world.signs
    intr = model.intrinsics
    min_box = model.min_box_px if params.min_box_px is None else params.min_box_px
    D = sg.position[None, :, :] - camera_enu[:, None, :]  # (M, N, 3)
    dist = np.linalg.norm(D, axis=-1)
    depth = np.einsum("mj,mnj->mn", r_world_camera[:, :, 2], D)  # optical-axis depth
    facing_cos = -np.einsum("nj,mnj->mn", sg.facing, D) / np.maximum(dist, 1e-9)
    cand = (
        (dist < params.max_range_m)
        & (depth > 0.5)
        & (facing_cos > np.cos(np.radians(params.max_view_angle_deg)))
    )
    mi, ni = np.nonzero(cand)
    r_cw = np.transpose(r_world_camera[mi], (0, 2, 1))  # world -> camera, (K, 3, 3)
    p_c = np.einsum("kij,kj->ki", r_cw, D[mi, ni])
    half = sg.panel_height_m[ni, None] / 2.0
    up_c = r_cw[:, :, 2]  # world Up in camera coordinates
    f = sg.facing[ni]
    side_c = np.einsum("kij,kj->ki", r_cw, np.column_stack([-f[:, 1], f[:, 0], np.zeros(len(f))]))
    pts = np.stack([p_c, p_c + half * up_c, p_c - half * up_c, p_c + half * side_c,
                    p_c - half * side_c], axis=1)  # fmt: skip
    uv, front = intr.project(pts)  # (K, 5, 2), (K, 5)
    u_min = np.minimum(uv[:, 3, 0], uv[:, 4, 0])
    u_max = np.maximum(uv[:, 3, 0], uv[:, 4, 0])
    v_min = np.minimum(uv[:, 1, 1], uv[:, 2, 1])
    v_max = np.maximum(uv[:, 1, 1], uv[:, 2, 1])
    ok = front.all(axis=1) & intr.in_image(uv[:, 0]) & ((v_max - v_min) >= min_box)
    if ok.any() and world.buildings.size:
        idx = np.flatnonzero(ok)
        blocked = _occluded(camera_enu[mi[idx], :2], sg.position[ni[idx], :2], world.buildings)
        ok[idx[blocked]] = False
    box = np.column_stack([u_min, v_min, u_max, v_max])
    return mi[ok], ni[ok], box[ok], dist[mi[ok], ni[ok]]


def _false_positives(
    rng: np.random.Generator, m: int, model: VehicleModel, noise: NoiseModel, params: DriveParams
) -> tuple[NDArray[np.bool_], IntArray, Array, Array]:
    """Per image: whether it holds a false positive, and its class, box and score.

    A plausible box: square, ``min_box_px``..``false_positive_max_px`` tall, anywhere
    across the image and centred in the band where signs appear (15-60% of the height).
    """
    intr = model.intrinsics
    has = rng.random(m) < noise.detector.false_positive_rate
    codes = model.catalog.codes
    cls = codes[rng.integers(codes.size, size=m)]
    min_box = model.min_box_px if params.min_box_px is None else params.min_box_px
    h = rng.uniform(min_box, max(params.false_positive_max_px, min_box), m)
    u = rng.uniform(0.0, 1.0, m) * (intr.width - h) + h / 2.0
    v = rng.uniform(0.15, 0.6, m) * intr.height
    box = np.column_stack([u - h / 2, v - h / 2, u + h / 2, v + h / 2])
    score = rng.uniform(*noise.detector.false_positive_score_range, m)
    return has, cls, box, score


def simulate_pass(
    world: World,
    path: Path,
    model: VehicleModel,
    noise: NoiseModel,
    rng: np.random.Generator,
    *,
    t0: float = 0.0,
    params: DriveParams | None = None,
) -> tuple[GnssFixes, Detections, DriveTruth]:
    """One pass along ``path`` starting at time ``t0`` (s); see the module docstring."""
    params = params or DriveParams()
    # spawn(3): the first two streams are those of the older spawn(2), so that
    # fix_per_frame at 5 Hz draws what the drive always drew.
    rng_gnss, rng_det, rng_time = rng.spawn(3)
    profile = speed_profile(path, params.speed_mps, params.lateral_accel_mps2)
    t, t_fix = sensor_times(rng_time, t0, profile.duration, params)
    veh, psi = poses_along(path, t, profile, t0)
    r_wv = vehicle_to_enu(psi)  # (M, 3, 3)
    camera = veh + r_wv @ model.camera_mount.t
    r_wc = r_wv @ model.camera_mount.rotation
    veh_fix, psi_fix = poses_along(path, t_fix, profile, t0)
    antenna = veh_fix + vehicle_to_enu(psi_fix) @ model.gnss_mount.t
    n_fix = t_fix.size

    # Detections.
    det = noise.detector
    intr = model.intrinsics
    img, row, box, dist = visible_boxes(world, model, camera, r_wc, params)
    k = img.size
    detected = rng_det.random(k) < det.detection_prob
    shift = rng_det.normal(0.0, 1.0, (k, 2)) * det.pixel_sigma
    score = rng_det.uniform(*det.score_range, k)
    uv_true = np.column_stack([(box[:, 0] + box[:, 2]) / 2.0, (box[:, 1] + box[:, 3]) / 2.0])
    noisy = box + np.tile(shift, 2)

    m = t.size
    fp, fp_cls, fp_box, fp_score = _false_positives(rng_det, m, model, noise, params)
    if det.size_sigma_px > 0:  # drawn last: without it the stream is what it always was
        grow = rng_det.normal(0.0, det.size_sigma_px, (k, 2)) / 2.0  # (width, height)
        noisy = noisy + np.column_stack([-grow[:, 0], -grow[:, 1], grow[:, 0], grow[:, 1]])

    all_img = np.concatenate([img[detected], np.flatnonzero(fp)])
    all_box = np.vstack([noisy[detected], fp_box[fp]])
    all_cls = np.concatenate([world.signs.sign_class[row[detected]], fp_cls[fp]])
    all_id = np.concatenate([world.signs.id[row[detected]], np.full(int(fp.sum()), -1)])
    all_score = np.concatenate([score[detected], fp_score[fp]])
    all_uv = np.vstack([uv_true[detected], np.full((int(fp.sum()), 2), np.nan)])
    all_dist = np.concatenate([dist[detected], np.full(int(fp.sum()), np.nan)])
    all_box[:, [0, 2]] = np.clip(all_box[:, [0, 2]], 0.0, intr.width - 1.0)
    all_box[:, [1, 3]] = np.clip(all_box[:, [1, 3]], 0.0, intr.height - 1.0)
    keep = ((all_box[:, 2] - all_box[:, 0]) >= 1.0) & ((all_box[:, 3] - all_box[:, 1]) >= 1.0)
    order = np.lexsort((all_box[:, 0], all_img))
    order = order[keep[order]]
    detections = Detections(
        image=all_img[order].astype(np.int64),
        sign_class=all_cls[order].astype(np.int64),
        box=all_box[order],
        score=all_score[order],
        t=t[all_img[order]],
    )

    # GNSS fixes.
    err = noise.gnss.sample(rng_gnss, t_fix)
    fix_enu = antenna + err.total_enu
    lat, lon, h = world.frame.to_geodetic(fix_enu)
    lat, lon, h = np.atleast_1d(lat), np.atleast_1d(lon), np.atleast_1d(h)
    course = (
        course_with_errors(t_fix, psi_fix, antenna, err.total_enu, err.velocity_enu)
        if noise.gnss.heading_from_track
        else psi_fix
    )
    fwd = np.column_stack([np.sin(course), np.cos(course), np.zeros(n_fix)])
    fwd_local = ecef_to_enu_vectors(world.frame.vectors_to_ecef(fwd), lat, lon)
    heading = np.arctan2(fwd_local[:, 0], fwd_local[:, 1])
    if not noise.gnss.heading_from_track:
        heading = heading + err.heading_rad
    s_h, s_v, _ = noise.gnss.reported_sigmas()
    fixes = GnssFixes(
        t=t_fix,
        lat=lat,
        lon=lon,
        h=h,
        heading_deg=np.degrees(heading) % 360.0,
        sigma_h_m=np.full(n_fix, s_h),
        sigma_v_m=np.full(n_fix, s_v),
        sigma_heading_deg=noise.gnss.heading_sigma_deg(fix_speed(t_fix, antenna)),
    )
    truth = DriveTruth(
        sign_id=all_id[order].astype(np.int64),
        uv_true=all_uv[order],
        distance_m=all_dist[order],
        t=t,
        vehicle_enu=veh,
        heading_rad=psi,
        camera_enu=camera,
        fix_t=t_fix,
        antenna_enu=antenna,
        fix_heading_rad=psi_fix,
        gnss=err,
        visible_image=img.astype(np.int64),
        visible_sign=world.signs.id[row].astype(np.int64),
    )
    return fixes, detections, truth
