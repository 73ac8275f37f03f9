"""vehicle.geoloc / hdmap.geo.camera: projection lines checked against hand-computed geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hdmap.geo.camera import Intrinsics, Mount
from hdmap.geo.geodesy import EnuFrame, direction_from_angles
from hdmap.geo.signs import CATALOG
from vehicle.geoloc import (
    Detections,
    GnssFixes,
    VehicleModel,
    azimuth_elevation,
    box_range,
    geolocate,
    vehicle_to_enu,
)

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
