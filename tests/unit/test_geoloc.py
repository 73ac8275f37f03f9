"""vehicle.geoloc / hdmap.geo.camera: projection lines checked against hand-computed geometry."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from hdmap.geo.camera import Intrinsics, Mount
from hdmap.geo.geodesy import EnuFrame, direction_from_angles
from hdmap.geo.signs import CATALOG
from vehicle.geoloc import (
    Detections,
    GnssFixes,
    VehicleModel,
    antenna_poses,
    azimuth_elevation,
    box_range,
    detection_reach,
    geolocate,
    vehicle_to_enu,
)
from vehicle.pose import PoseTiming, hidden_yaw_accel

FX = FY = 1400.0
CX, CY = 960.0, 540.0
W, H = 1920, 1080
INTR = Intrinsics(fx=FX, fy=FY, cx=CX, cy=CY, width=W, height=H)
LAT, LON, HGT = 60.17, 24.94, 20.0
SL30 = CATALOG.code("speed_limit_30")
CAT06 = CATALOG.with_sizes({"speed_limit_30": 0.6})


def fixes(heading_deg=0.0, sigma_heading_deg=0.0, n=1, lat=LAT, lon=LON, h=HGT) -> GnssFixes:
    def col(v):
        return np.broadcast_to(np.asarray(v, float), (n,)).copy()

    return GnssFixes(
        t=col(1.7e9),
        lat=col(lat),
        lon=col(lon),
        h=col(h),
        heading_deg=col(heading_deg),
        sigma_h_m=col(2.0),
        sigma_v_m=col(4.0),
        sigma_heading_deg=col(sigma_heading_deg),
    )


def boxes_at(uv, height_px=42.0, width_px=None) -> np.ndarray:
    """Boxes of the given pixel height centred on ``uv`` (N, 2)."""
    uv = np.atleast_2d(np.asarray(uv, float))
    hw = (height_px if width_px is None else width_px) / 2.0
    hh = height_px / 2.0
    return np.column_stack([uv[:, 0] - hw, uv[:, 1] - hh, uv[:, 0] + hw, uv[:, 1] + hh])


def dets(box, sign_class=SL30, image=None) -> Detections:
    box = np.atleast_2d(np.asarray(box, float))
    n = len(box)
    return Detections(
        image=np.zeros(n, np.int64) if image is None else np.asarray(image, np.int64),
        sign_class=np.full(n, sign_class, np.int64),
        box=box,
        score=np.full(n, 0.9),
    )


def model(**kw) -> VehicleModel:
    intr = kw.pop("intrinsics", INTR)
    kw.setdefault("catalog", CAT06)
    return VehicleModel.forward_camera(intr, **kw)


def pixel_of(x_right: float, y_down: float, depth: float, intr: Intrinsics = INTR) -> np.ndarray:
    uv, front = intr.project(np.array([x_right, y_down, depth]))
    assert front
    return uv


# --- geometry of the ray -------------------------------------------------------------


def test_sign_ahead_and_right_heading_north() -> None:
    lines = geolocate(fixes(0.0), dets(boxes_at(pixel_of(5.0, 0.0, 20.0))), model())
    az, el = azimuth_elevation(lines.direction)
    assert az[0] == pytest.approx(math.atan2(5.0, 20.0), abs=1e-6)
    assert el[0] == pytest.approx(0.0, abs=1e-6)
    np.testing.assert_allclose(np.linalg.norm(lines.direction, axis=1), 1.0, atol=1e-12)
    # (E, N, U) = (5, 20, 0) / |.|
    np.testing.assert_allclose(
        lines.direction[0], np.array([5, 20, 0]) / math.hypot(5, 20), atol=1e-6
    )


@pytest.mark.parametrize("heading", [90.0, 180.0, 270.0, -45.0, 359.0])
def test_heading_turns_the_ray(heading: float) -> None:
    lines = geolocate(fixes(heading), dets(boxes_at(pixel_of(5.0, 0.0, 20.0))), model())
    az, _ = azimuth_elevation(lines.direction)
    expected = math.radians(heading) + math.atan2(5.0, 20.0)
    assert math.remainder(az[0] - expected, 2 * math.pi) == pytest.approx(0.0, abs=1e-6)
    if heading == 90.0:
        assert az[0] == pytest.approx(math.pi / 2 + math.atan2(5.0, 20.0), abs=1e-6)


def test_sign_above_camera_has_positive_elevation() -> None:
    lines = geolocate(fixes(), dets(boxes_at(pixel_of(0.0, -3.0, 20.0))), model())
    _, el = azimuth_elevation(lines.direction)
    assert el[0] == pytest.approx(math.atan2(3.0, 20.0), abs=1e-6)


def test_range_on_axis_from_known_panel_size() -> None:
    assert FY * 0.6 / 20.0 == pytest.approx(42.0)
    lines = geolocate(fixes(), dets(boxes_at((CX, CY), 42.0)), model())
    assert lines.range_m[0] == pytest.approx(20.0, rel=1e-9)
    # sigma_range = r * hypot(sqrt(2) sigma_px / h_px, relative size sigma)
    rel = math.hypot(math.sqrt(2) * 3.0 / 42.0, 0.10)
    assert lines.sigma_range_m[0] == pytest.approx(20.0 * rel, rel=1e-9)


def test_range_off_axis_is_distance_along_the_ray() -> None:
    uv = pixel_of(5.0, 0.0, 20.0)  # (1310, 540)
    np.testing.assert_allclose(uv, [CX + 350.0, CY])
    lines = geolocate(fixes(), dets(boxes_at(uv, 42.0)), model())
    assert lines.range_m[0] == pytest.approx(math.sqrt(20.0**2 + 5.0**2), rel=1e-9)


def test_with_sizes_changes_the_range() -> None:
    box = boxes_at((CX, CY), 42.0)
    r_default = geolocate(fixes(), dets(box), model(catalog=CATALOG)).range_m[0]
    assert r_default == pytest.approx(0.64 * FY / 42.0)
    with pytest.raises(ValueError):
        CATALOG.with_sizes({"no_such_sign": 1.0})


def test_camera_centre_at_lever_arm_from_antenna() -> None:
    m = model(camera_xyz=(1.5, 0.3, 1.4), gnss_xyz=(-0.5, 0.0, 1.6))
    frame = EnuFrame(LAT, LON, HGT)  # ENU at the antenna
    box = dets(boxes_at((CX, CY)))
    # lever = camera - antenna = (2.0 fwd, 0.3 left, -0.2 up) in the vehicle frame
    for heading, expected in [(0.0, (-0.3, 2.0, -0.2)), (90.0, (2.0, 0.3, -0.2))]:
        lines = geolocate(fixes(heading), box, m)
        a = frame.from_geodetic(lines.lat, lines.lon, lines.h)
        np.testing.assert_allclose(a[0], expected, atol=1e-6)
    # antenna at the camera: A is the fix itself
    lines = geolocate(fixes(), box, model(camera_xyz=(0, 0, 1.5), gnss_xyz=(0, 0, 1.5)))
    np.testing.assert_allclose([lines.lat[0], lines.lon[0], lines.h[0]], [LAT, LON, HGT], atol=1e-9)


def test_position_sigmas() -> None:
    m = model(camera_xyz=(2.0, 0.0, 1.4), gnss_xyz=(0.0, 0.0, 1.5))
    lines = geolocate(fixes(sigma_heading_deg=1.0), dets(boxes_at((CX, CY))), m)
    assert lines.sigma_pos_h[0] == pytest.approx(math.hypot(2.0, math.radians(1.0) * 2.0))
    assert lines.sigma_pos_v[0] == pytest.approx(4.0)


@pytest.mark.parametrize("heading,yaw", [(0.0, 10.0), (30.0, 10.0), (30.0, -25.0)])
def test_camera_yaw_turns_the_ray_left(heading: float, yaw: float) -> None:
    # ISO 8855: positive yaw turns the camera to the left (counter-clockwise seen from
    # above); azimuth is clockwise, so the optical axis points at heading - yaw.
    lines = geolocate(fixes(heading), dets(boxes_at((CX, CY))), model(camera_rpy_deg=(0, 0, yaw)))
    az, el = azimuth_elevation(lines.direction)
    assert az[0] == pytest.approx(math.radians(heading - yaw), abs=1e-6)
    assert el[0] == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize("pitch", [5.0, -3.0])
def test_camera_pitch_tilts_the_ray(pitch: float) -> None:
    # ISO 8855: positive pitch is nose-down, so the optical axis has elevation -pitch.
    m = model(camera_rpy_deg=(0, pitch, 0))
    lines = geolocate(fixes(), dets(boxes_at((CX, CY))), m)
    az, el = azimuth_elevation(lines.direction)
    assert el[0] == pytest.approx(math.radians(-pitch), abs=1e-6)
    assert az[0] == pytest.approx(0.0, abs=1e-6)
    # off-axis pixel: the camera-frame ray rotated by the pitch
    x = 0.25
    lines = geolocate(fixes(), dets(boxes_at((CX + x * FX, CY))), m)
    p = math.radians(pitch)
    d_vehicle = np.array([math.cos(p), -x, -math.sin(p)]) / math.hypot(1.0, x)  # fwd, left, up
    np.testing.assert_allclose(lines.direction[0], d_vehicle @ vehicle_to_enu(0.0).T, atol=1e-6)


def test_camera_roll_tilts_image_x_axis() -> None:
    roll = math.radians(30.0)
    x = 0.25
    lines = geolocate(fixes(), dets(boxes_at((CX + x * FX, CY))), model(camera_rpy_deg=(30, 0, 0)))
    # camera x (right) = -y_vehicle, rolled about x_vehicle: (0, -cos r, -sin r)
    d_vehicle = np.array([1.0, -x * math.cos(roll), -x * math.sin(roll)]) / math.hypot(1.0, x)
    np.testing.assert_allclose(lines.direction[0], d_vehicle @ vehicle_to_enu(0.0).T, atol=1e-6)


def test_mount_from_rpy_and_matrix() -> None:
    m = Mount.from_rpy_deg((1.0, 2.0, 3.0), (0.0, 0.0, 90.0))
    np.testing.assert_allclose(m.rotation @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-15)
    t = m.matrix()
    np.testing.assert_allclose(t @ [1.0, 0.0, 0.0, 1.0], [1.0, 3.0, 3.0, 1.0], atol=1e-15)


def test_vehicle_to_enu_and_angle_helpers() -> None:
    r = vehicle_to_enu(np.radians([0.0, 90.0]))
    np.testing.assert_allclose(r[0] @ [1, 0, 0], [0, 1, 0], atol=1e-15)  # forward = North
    np.testing.assert_allclose(r[1] @ [1, 0, 0], [1, 0, 0], atol=1e-15)  # forward = East
    np.testing.assert_allclose(r[1] @ [0, 1, 0], [0, 1, 0], atol=1e-15)  # left = North
    rng = np.random.default_rng(5)
    az, el = rng.uniform(-math.pi, math.pi, 100), rng.uniform(-1.5, 1.5, 100)
    az2, el2 = azimuth_elevation(direction_from_angles(az, el))
    np.testing.assert_allclose(az2, az, atol=1e-12)
    np.testing.assert_allclose(el2, el, atol=1e-12)


# --- distortion --------------------------------------------------------------------------

DIST = Intrinsics(FX, FY, CX, CY, W, H, dist=(-0.12, 0.03, 0.001, -0.0008, 0.002))


def test_distortion_pixel_round_trip() -> None:
    gx, gy = np.meshgrid(np.linspace(-0.68, 0.68, 41), np.linspace(-0.38, 0.38, 23))
    xy = np.column_stack([gx.ravel(), gy.ravel()])
    uv = DIST.normalized_to_pixel(xy)
    assert not np.allclose(uv, INTR.normalized_to_pixel(xy))  # distortion does something
    np.testing.assert_allclose(DIST.pixel_to_normalized(uv), xy, atol=1e-9, rtol=0)
    np.testing.assert_allclose(DIST.distort(DIST.undistort(xy)), xy, atol=1e-9, rtol=0)


def test_distorted_camera_recovers_true_direction() -> None:
    p_cam = np.array([4.0, -1.5, 18.0])
    uv, _ = DIST.project(p_cam)
    lines = geolocate(fixes(), dets(boxes_at(uv, 20.0)), model(intrinsics=DIST))
    d_cam = p_cam / np.linalg.norm(p_cam)
    d_vehicle = np.array([d_cam[2], -d_cam[0], -d_cam[1]])
    np.testing.assert_allclose(lines.direction[0], d_vehicle @ vehicle_to_enu(0.0).T, atol=1e-6)


# --- angular sigmas --------------------------------------------------------------------------


@pytest.mark.parametrize("pixel_sigma,heading_sigma_deg", [(3.0, 0.5), (5.0, 0.0), (1.0, 20.0)])
def test_sigmas_at_image_centre(pixel_sigma: float, heading_sigma_deg: float) -> None:
    m = model(pixel_sigma=pixel_sigma)
    lines = geolocate(fixes(sigma_heading_deg=heading_sigma_deg), dets(boxes_at((CX, CY))), m)
    s_psi = math.radians(heading_sigma_deg)
    assert lines.sigma_az[0] == pytest.approx(
        math.sqrt((pixel_sigma / FX) ** 2 + s_psi**2), rel=0.01
    )
    assert lines.sigma_el[0] == pytest.approx(pixel_sigma / FY, rel=0.01)


def test_pitch_sigma_adds_to_elevation() -> None:
    m = model(pixel_sigma=3.0, pitch_sigma_rad=0.01)
    lines = geolocate(fixes(), dets(boxes_at((CX, CY))), m)
    assert lines.sigma_el[0] == pytest.approx(math.hypot(3.0 / FY, 0.01), rel=0.01)


@pytest.mark.parametrize("pixel_sigma,heading_sigma_deg", [(3.0, 1.0), (3.0, 0.05)])
def test_sigma_az_matches_monte_carlo_spread(pixel_sigma: float, heading_sigma_deg: float) -> None:
    """Perturb the box centre (N(0, pixel_sigma) px per axis) and the heading
    (N(0, heading_sigma) deg), 20k draws: heading-dominated and pixel-dominated cases."""
    n = 20_000
    m = model(intrinsics=DIST, pixel_sigma=pixel_sigma)
    uv0 = pixel_of(6.0, -2.0, 15.0, DIST)  # off-axis, through the distortion
    nominal = geolocate(fixes(30.0, heading_sigma_deg), dets(boxes_at(uv0)), m)
    az0, el0 = azimuth_elevation(nominal.direction)

    rng = np.random.default_rng(20240601)
    duv = rng.normal(0.0, pixel_sigma, size=(n, 2))
    heading = 30.0 + rng.normal(0.0, heading_sigma_deg, n)
    box = boxes_at(uv0 + duv)
    lines = geolocate(fixes(heading, heading_sigma_deg, n=n), dets(box, image=np.arange(n)), m)
    az, el = azimuth_elevation(lines.direction)
    daz = np.remainder(az - az0[0] + np.pi, 2 * np.pi) - np.pi
    assert np.std(daz) == pytest.approx(nominal.sigma_az[0], rel=0.05)
    assert np.std(el - el0[0]) == pytest.approx(nominal.sigma_el[0], rel=0.05)
    # the sigmas vary slowly over a few pixels
    np.testing.assert_allclose(lines.sigma_az, nominal.sigma_az[0], rtol=0.01)


# --- when there is no range ------------------------------------------------------------------


@pytest.mark.parametrize(
    "box",
    [
        (0.0, 500.0, 40.0, 542.0),  # touches the left border
        (1900.0, 500.0, 1919.0, 542.0),  # touches the right border
        (900.0, 0.0, 940.0, 42.0),  # touches the top
        (900.0, 1040.0, 940.0, 1079.0),  # touches the bottom
        (950.0, 530.0, 961.0, 541.0),  # 11 px < min_box_px = 12
    ],
)
def test_unusable_boxes_have_no_range(box) -> None:
    lines = geolocate(fixes(), dets(np.array([box])), model())
    assert lines.range_m[0] == 0.0
    assert lines.sigma_range_m[0] == 0.0
    assert np.isfinite(lines.direction).all()


def test_min_box_px_boundary() -> None:
    m = model(min_box_px=12.0)
    r, s = box_range(boxes_at((CX, CY), 12.0), np.array([SL30]), m)
    assert r[0] == pytest.approx(0.6 * FY / 12.0) and s[0] > 0
    r, _ = box_range(boxes_at((CX, CY), 11.99), np.array([SL30]), m)
    assert r[0] == 0.0


@pytest.mark.parametrize("code", [0, 999, 21])
def test_unknown_class_has_no_range(code: int) -> None:
    assert code not in CATALOG
    lines = geolocate(fixes(), dets(boxes_at((CX, CY), 42.0), sign_class=code), model())
    assert lines.range_m[0] == 0.0 and lines.sigma_range_m[0] == 0.0
    assert lines.sign_class[0] == code


def test_vectorised_over_images_and_detections() -> None:
    fx = fixes(np.array([0.0, 90.0, 180.0]), n=3)
    uv = pixel_of(5.0, 0.0, 20.0)
    d = dets(boxes_at(np.array([uv, uv, uv, uv])), image=[2, 0, 1, 0])
    lines = geolocate(fx, d, model())
    assert len(lines) == 4
    az, _ = azimuth_elevation(lines.direction)
    expected = np.radians([180.0, 0.0, 90.0, 0.0]) + math.atan2(5.0, 20.0)
    np.testing.assert_allclose(np.remainder(az - expected + np.pi, 2 * np.pi) - np.pi, 0, atol=1e-6)
    np.testing.assert_array_equal(lines.image, [2, 0, 1, 0])
    np.testing.assert_allclose(lines.t, 1.7e9)


# --- pose at a frame's time, interpolated from the fixes (vehicle.pose) ---------------

ENU0 = EnuFrame(LAT, LON, HGT)


def timed_fixes(t, enu, heading_deg, sigma_h=1.0, sigma_v=1.5, sigma_heading_deg=0.5):
    lat, lon, h = ENU0.to_geodetic(np.asarray(enu, float))
    n = len(t)
    return GnssFixes(
        t=np.asarray(t, float),
        lat=lat,
        lon=lon,
        h=h,
        heading_deg=np.asarray(heading_deg, float) % 360.0,
        sigma_h_m=np.broadcast_to(np.asarray(sigma_h, float), (n,)).copy(),
        sigma_v_m=np.broadcast_to(np.asarray(sigma_v, float), (n,)).copy(),
        sigma_heading_deg=np.full(n, sigma_heading_deg),
    )


def timed_dets(t) -> Detections:
    t = np.asarray(t, float)
    d = dets(boxes_at(np.tile([CX, CY], (t.size, 1))), image=np.arange(t.size))
    return replace(d, t=t)


def antenna_enu(pose) -> np.ndarray:
    return ENU0.from_geodetic(pose.lat, pose.lon, pose.h)


def test_pose_is_exact_on_a_straight_drive_whatever_the_timing() -> None:
    """11 m/s on a 30 deg course, climbing 0.1 m/s; fixes at about 1 Hz with one missing
    (a 1.9 s gap), frames at 30 Hz, also just past the last fix (within max_gap_s)."""
    t_fix = 100.0 + np.array([0.0, 1.02, 1.97, 3.9, 5.25, 6.3])
    az = np.radians(30.0)

    def truth(t):
        s = 11.0 * (t - 100.0)
        return np.column_stack([s * np.sin(az), s * np.cos(az), 0.1 * (t - 100.0)])

    fixes = timed_fixes(t_fix, truth(t_fix), np.full(t_fix.size, 30.0))
    t = 100.0 + np.arange(0.0, 6.9, 1.0 / 30.0)
    pose = antenna_poses(fixes, timed_dets(t))
    np.testing.assert_allclose(antenna_enu(pose), truth(t), atol=1e-6)
    np.testing.assert_allclose(np.degrees(pose.heading_rad), 30.0, atol=1e-9)
    np.testing.assert_array_equal(pose.t, t)
    # the camera centre follows: the lever arm turned by the heading
    lines = geolocate(fixes, timed_dets(t), model())
    cam = ENU0.from_geodetic(lines.lat, lines.lon, lines.h)
    fwd = np.array([np.sin(az), np.cos(az), 0.0])
    # (to 0.1 mm: the lever arm is level at the antenna, 70 m from the frame's origin)
    np.testing.assert_allclose(cam, truth(t) + 1.5 * fwd + [0.0, 0.0, -0.1], atol=1e-4)
    np.testing.assert_array_equal(lines.t, t)


def test_pose_on_a_curve_errs_by_the_chord_and_no_more() -> None:
    """A circle of radius 30 m at 10 m/s (3.3 m/s^2 across the path), fixes at 1 Hz: the
    linear interpolant's error is the constant-acceleration remainder a/2 |tau_a tau_b|
    (vehicle.pose): a bound everywhere, attained to 1 % in the middle of a gap (the
    sagitta); the heading grows linearly in time on a circle and is interpolated exactly,
    also across North (359 -> 18 deg)."""
    r, v = 30.0, 10.0
    omega = v / r
    t_fix = np.arange(0.0, 8.0)
    t = np.arange(0.0, 7.0, 1.0 / 30.0)

    def truth(tt):  # clockwise from North, starting at 340 deg
        psi = np.radians(340.0) + omega * tt
        centre = np.array([r * np.cos(np.radians(340.0)), -r * np.sin(np.radians(340.0))])
        pos = centre + r * np.column_stack([-np.cos(psi), np.sin(psi)])
        return np.column_stack([pos, np.zeros(tt.size)]), psi

    enu_f, psi_f = truth(t_fix)
    fixes = timed_fixes(t_fix, enu_f, np.degrees(psi_f))
    pose = antenna_poses(fixes, timed_dets(t))
    enu_t, psi_t = truth(t)
    np.testing.assert_allclose(np.diff(enu_t[:2], axis=0)[0] * 30.0, v * np.array(
        [np.sin(psi_t[0]), np.cos(psi_t[0]), 0.0]), rtol=0.02)  # fmt: skip
    err = np.linalg.norm(antenna_enu(pose) - enu_t, axis=1)
    tau = t - np.floor(t)
    bound = 0.5 * (v * v / r) * tau * (1.0 - tau)
    assert (err <= bound * 1.0 + 1e-6).all()
    mid = np.isclose(tau, 0.5)
    assert mid.sum() >= 6 and (err[mid] >= 0.99 * bound[mid]).all()
    dpsi = np.angle(np.exp(1j * (pose.heading_rad - psi_t)))
    assert np.abs(dpsi).max() < 1e-6
    # the motion term (the fix sigma is 1 m): the 2 m/s^2 floor alone without
    # observed_turns; with it (the default) the fixes' v^2 / R = 3.3 m/s^2 joins it and
    # covers the chord error
    floor_only = antenna_poses(fixes, timed_dets(t), PoseTiming(observed_turns=False))
    motion = np.sqrt(floor_only.sigma_h_m**2 - 1.0)
    np.testing.assert_allclose(motion, 0.5 * 2.0 * tau * (1.0 - tau), atol=1e-6)
    turn = pose
    motion = np.sqrt(turn.sigma_h_m**2 - 1.0)
    np.testing.assert_allclose(
        motion, 0.5 * np.hypot(2.0, v * v / r) * tau * (1.0 - tau), rtol=0.01, atol=1e-6
    )  # rtol: the chord speed is 0.5 % below the arc speed
    assert (err <= motion + 1e-6).all()
    assert np.round(np.degrees(psi_f[1:3]) % 360.0).tolist() == [359.0, 18.0]  # across North


def test_pose_sigmas_grow_with_the_gap() -> None:
    """At a fix: the fix's claims; between fixes a and b: (1 - w) s_a + w s_b in
    quadrature with the motion term sigma_acc / 2 |tau_a tau_b| (m; rad for the heading)."""
    t_fix = np.array([0.0, 0.2, 1.2])
    fixes = timed_fixes(t_fix, np.zeros((3, 3)), np.zeros(3), sigma_h=[1.0, 1.0, 2.0],
                        sigma_v=[1.5, 1.5, 1.5])  # fmt: skip
    timing = PoseTiming(accel_sigma_mps2=2.0, accel_v_sigma_mps2=0.5, yaw_accel_sigma_radps2=0.5)
    t = np.array([0.0, 0.1, 0.2, 0.45, 0.7, 1.2])
    pose = antenna_poses(fixes, timed_dets(t), timing)
    w = np.array([0.0, 0.5, 0.0, 0.25, 0.5, 1.0])
    ta = np.array([0.0, 0.1, 0.0, 0.25, 0.5, 1.0])
    tb = ta - np.array([0.2, 0.2, 1.0, 1.0, 1.0, 1.0])
    s_fix = np.where(t <= 0.2, 1.0, (1 - w) * 1.0 + w * 2.0)
    np.testing.assert_allclose(pose.sigma_h_m, np.hypot(s_fix, 1.0 * np.abs(ta * tb)))
    np.testing.assert_allclose(pose.sigma_v_m, np.hypot(1.5, 0.25 * np.abs(ta * tb)))
    # the yaw floor: 0.5 rad/s^2, or less where the fixes would have shown more
    # (3 sigma of what their 0.5 deg makes of a yaw acceleration: 0.34 rad/s^2 here)
    yaw = min(0.5, float(hidden_yaw_accel(t_fix, np.full(3, np.radians(0.5)))[0]))
    assert 0.3 < yaw < 0.4
    np.testing.assert_allclose(
        pose.sigma_heading_rad, np.hypot(np.radians(0.5), yaw / 2 * np.abs(ta * tb))
    )
    assert pose.sigma_h_m[4] == pytest.approx(np.hypot(1.5, 2.0 * 1.0**2 / 8.0))  # mid-gap
    # the rays carry them: horizontal with the lever arm's heading term, vertical as is
    lines = geolocate(fixes, timed_dets(t), model(), timing=timing)
    np.testing.assert_allclose(lines.sigma_pos_v, pose.sigma_v_m)
    np.testing.assert_allclose(
        lines.sigma_pos_h, np.hypot(pose.sigma_h_m, pose.sigma_heading_rad * 1.5)
    )


def test_a_detection_far_from_every_fix_is_refused_not_extrapolated() -> None:
    t_fix = np.array([0.0, 0.2, 0.4, 2.0, 2.2])
    fixes = timed_fixes(t_fix, np.zeros((5, 3)), np.zeros(5))
    t = np.array([-1.5, -0.5, 0.3, 1.2, 1.5, 2.9, 3.5])
    reach = detection_reach(fixes, timed_dets(t), PoseTiming(max_gap_s=0.7))
    assert reach.tolist() == [False, True, True, False, True, True, False]
    with pytest.raises(ValueError, match=r"^Detections.t: 3 detection\(s\) more than 0.7 s"):
        antenna_poses(fixes, timed_dets(t), PoseTiming(max_gap_s=0.7))
    assert (
        len(geolocate(fixes, timed_dets(t[reach]), model(), timing=PoseTiming(max_gap_s=0.7))) == 4
    )
    one = fixes.take(np.array([1]))  # one fix: only detections at its time
    assert detection_reach(one, timed_dets([0.2, 0.25])).tolist() == [True, False]


@pytest.mark.parametrize(
    "t_fix, match",
    [
        ([0.0, 0.2, 0.2], r"GnssFixes.t: must be strictly increasing, row 2"),
        ([0.0, 0.4, 0.2], r"GnssFixes.t: must be strictly increasing, row 2"),
        ([0.0, np.nan, 0.4], r"GnssFixes.t: must be finite"),
    ],
)
def test_bad_fix_times_are_refused_naming_the_field(t_fix, match) -> None:
    fixes = timed_fixes(np.array(t_fix), np.zeros((3, 3)), np.zeros(3))
    with pytest.raises(ValueError, match=match):
        geolocate(fixes, timed_dets([0.1]), model())
    with pytest.raises(ValueError, match=match):
        detection_reach(fixes, timed_dets([0.1]))
    with pytest.raises(ValueError, match=r"^Detections.t: must be finite"):
        geolocate(timed_fixes([0.0, 1.0], np.zeros((2, 3)), np.zeros(2)), timed_dets([np.nan]),
                  model())  # fmt: skip
    # the index form does not look at the times (one fix per image, as before)
    assert len(geolocate(fixes, dets(boxes_at((CX, CY)), image=[1]), model())) == 1


def test_pose_timing_is_checked() -> None:
    with pytest.raises(ValueError, match=r"PoseTiming\.max_gap_s"):
        PoseTiming(max_gap_s=-1.0)


def test_white_share_separates_white_noise_from_a_shared_bias_and_sets_the_interpolated_sigma():
    """Fixes at 5 Hz with a bias of std b shared by the pass and white noise of std s,
    reported as the total sqrt(b^2 + s^2): the estimated white share is within its
    sampling range of s / total, and a pose midway between two fixes gets the sigma of
    (e_a + e_b) / 2 under that split (checked by Monte-Carlo over 4,000 passes)."""
    from vehicle.pose import bracket, interpolate_sigma, white_share

    rng = np.random.default_rng(7)
    t = np.arange(300) * 0.2 + rng.normal(0.0, 0.01, 300)
    b, s = 0.02, 0.01
    total = np.hypot(b, s)
    shares = [
        white_share(
            t, 0.3 * t + rng.normal(0.0, b) + rng.normal(0.0, s, 300), np.full(300, total), True
        )
        for _ in range(20)
    ]
    # unbiased up to O(1/n): the mean of 20 draws is within t(0.9995, 19) = 3.88 of its
    # standard errors (estimated from the draws) of the true share
    spread = np.std(shares, ddof=1) / np.sqrt(len(shares))
    assert abs(np.mean(shares) - s / total) < 3.88 * spread
    br = bracket(np.array([0.0, 1.0]), np.array([0.5]))
    r = s / total
    e = rng.normal(0.0, b, 4000)[:, None] + rng.normal(0.0, s, (4000, 2))
    mc = e.mean(axis=1).std()
    got = float(interpolate_sigma(br, [total, total], r)[0])
    # a sample std of n draws has a relative standard error of 1 / sqrt(2 n): within 4
    assert abs(got - mc) < 4.0 * got / np.sqrt(2 * len(e))


def test_observed_turns_count_only_what_stands_out_of_the_heading_noise() -> None:
    """White heading noise alone (0.35 rad, the paper's, at 5 Hz) makes no observed yaw rate
    or acceleration once the claimed sigma is given: a gated yaw rate is nonzero with
    probability P(|N| > 3) = 0.0027 per interval, an interval's yaw acceleration (the
    larger of its two ends) with at most twice that; over 2,000 intervals the binomial's
    99.99 % bounds are 0.8 % and 1.25 %. A real turn well above the noise (0.5 rad/s
    against 0.07 rad/s of noise at 0.01 rad) is kept, less the noise in quadrature."""
    from vehicle.pose import observed_accels

    rng = np.random.default_rng(3)
    t = np.arange(2001) * 0.2
    xy = np.column_stack([np.zeros(t.size), 10.0 * t])
    noisy = rng.normal(0.0, 0.35, t.size)
    yaw_raw, across_raw = observed_accels(t, noisy, xy)
    yaw, across = observed_accels(t, noisy, xy, np.full(t.size, 0.35))
    assert np.mean(yaw_raw > 0) > 0.9 and np.median(across_raw) > 10.0  # m/s^2 of nothing
    assert np.mean(yaw > 0) <= 0.0125 and np.mean(across > 0) <= 0.008
    turning = 0.5 * t + rng.normal(0.0, 0.01, t.size)
    _, across = observed_accels(t, turning, xy, np.full(t.size, 0.01))
    noise = np.hypot(0.01, 0.01) / 0.2
    assert np.median(across) == pytest.approx(np.sqrt(0.5**2 - noise**2) * 10.0, rel=0.05)


def test_the_yaw_floor_is_at_most_what_the_fixes_would_have_shown() -> None:
    """A straight drive at 1 Hz, heading claimed 0.573 deg: the fixes would show any yaw
    acceleration beyond 3 sigma of their heading noise (0.07 rad/s^2), so the configured
    0.5 rad/s^2 floor ("entering a corner") does not apply, and a frame mid-gap claims the
    interpolated heading sigma plus 0.07 / 8 rad, not 0.5 / 8 (3.6 deg, which the bias
    compensation then removes from rays that never had it). At 5 Hz the fixes hide more
    than the floor (1.8 rad/s^2), and the floor stands."""
    from vehicle.geoloc import turn_sigmas
    from vehicle.pose import bracket, motion_sigma

    s = np.radians(0.573)
    for rate, floor in ((1.0, None), (5.0, 0.5)):
        t = np.arange(0.0, 20.0, 1.0 / rate)
        hidden = hidden_yaw_accel(t, np.full(t.size, s))
        assert hidden[1:-1] == pytest.approx(3 * s * np.sqrt(6) * rate**2, rel=1e-9)
        br = bracket(t, np.array([10.0 + 0.5 / rate]))
        xyz = np.column_stack([np.zeros(t.size), 10.0 * t, np.zeros(t.size)])
        _, m_psi = turn_sigmas(br, t, np.zeros(t.size), xyz, PoseTiming(), np.full(t.size, s))
        want = motion_sigma(br, floor if floor is not None else 3 * s * np.sqrt(6))
        np.testing.assert_allclose(m_psi, want, rtol=1e-9)
    assert hidden_yaw_accel(np.arange(2.0), np.full(2, s)).tolist() == [np.inf]
