"""hdmap.geo.geodesy: round trips, hand-computed values and the ENU rotation."""

from __future__ import annotations

import numpy as np
import pytest

from hdmap.geo.geodesy import (
    GEODESY,
    EnuFrame,
    direction_from_angles,
    ecef_to_enu_vectors,
    enu_rotation,
    enu_to_ecef_vectors,
)

WGS84_A = 6378137.0
WGS84_B = 6356752.314245  # semi-minor axis, m (b = a (1 - f), f = 1/298.257223563)

# Latitudes from pole to pole (including within 1e-6 deg of the poles) and
# longitudes on both sides of the antimeridian.
LATS = [-90.0, -89.999999, -60.5, -12.3, 0.0, 0.001, 33.3, 60.17, 89.9999, 90.0]
LONS = [-180.0, -179.9999999, -120.0, -0.5, 0.0, 24.94, 120.0, 179.9999999, 180.0]
HEIGHTS = [-100.0, 0.0, 35.5, 1500.0, 9000.0]


def _grid() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    lat, lon, h = np.meshgrid(LATS, LONS, HEIGHTS, indexing="ij")
    return lat.ravel(), lon.ravel(), h.ravel()


def _dist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.norm(np.asarray(a) - np.asarray(b), axis=-1)


def test_geodetic_ecef_geodetic_round_trip_below_1mm() -> None:
    lat, lon, h = _grid()
    ecef = GEODESY.to_ecef(lat, lon, h)
    assert ecef.shape == (lat.size, 3)
    lat2, lon2, h2 = GEODESY.to_geodetic(ecef)
    # Compare positions, not angles: longitude is undefined at the poles and
    # jumps by 360 deg at the antimeridian.
    back = GEODESY.to_ecef(lat2, lon2, h2)
    assert _dist(back, ecef).max() < 1e-3
    assert np.abs(h2 - h).max() < 1e-3
    assert np.abs(lat2 - lat).max() < 1e-8  # 1e-8 deg ~ 1.1 mm along a meridian
    away_from_poles = np.abs(lat) < 89.0
    dlon = (lon2 - lon + 180.0) % 360.0 - 180.0
    assert np.abs(dlon[away_from_poles]).max() < 1e-8


@pytest.mark.parametrize("lat0", [-89.9999, -45.0, 0.0, 60.17, 89.9999])
@pytest.mark.parametrize("lon0", [-180.0, 24.94, 179.9999999])
def test_geodetic_enu_geodetic_round_trip_below_1mm(lat0: float, lon0: float) -> None:
    frame = EnuFrame(lat0, lon0, 50.0)
    rng = np.random.default_rng(1)
    # Points up to 2 km around the origin, -100..9000 m high; near the poles and the
    # antimeridian these cross to the other side of the pole / of +-180 deg.
    enu = np.column_stack(
        [rng.uniform(-2000, 2000, 200), rng.uniform(-2000, 2000, 200), rng.uniform(-150, 8950, 200)]
    )
    lat, lon, h = frame.to_geodetic(enu)
    assert np.all(np.abs(lat) <= 90.0)
    assert np.all((lon >= -180.0) & (lon <= 180.0))
    assert _dist(frame.from_geodetic(lat, lon, h), enu).max() < 1e-3
    # and the other way round, starting from geodetic points
    lat_g, lon_g, h_g = _grid()
    enu_g = frame.from_geodetic(lat_g, lon_g, h_g)
    back = GEODESY.to_ecef(*frame.to_geodetic(enu_g))
    assert _dist(back, GEODESY.to_ecef(lat_g, lon_g, h_g)).max() < 1e-3


def test_ecef_of_equator_prime_meridian() -> None:
    np.testing.assert_allclose(GEODESY.to_ecef(0.0, 0.0, 0.0), [WGS84_A, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(GEODESY.to_ecef(0.0, 90.0, 0.0), [0.0, WGS84_A, 0.0], atol=1e-6)
    np.testing.assert_allclose(
        GEODESY.to_ecef(0.0, 180.0, 100.0), [-(WGS84_A + 100.0), 0.0, 0.0], atol=1e-6
    )


def test_ecef_of_poles() -> None:
    np.testing.assert_allclose(GEODESY.to_ecef(90.0, 0.0, 0.0), [0.0, 0.0, WGS84_B], atol=1e-6)
    np.testing.assert_allclose(
        GEODESY.to_ecef(-90.0, 45.0, 10.0), [0.0, 0.0, -(WGS84_B + 10.0)], atol=1e-6
    )


def test_to_geodetic_of_hand_computed_ecef() -> None:
    lat, lon, h = GEODESY.to_geodetic(np.array([[WGS84_A + 5.0, 0.0, 0.0], [0.0, 0.0, WGS84_B]]))
    np.testing.assert_allclose(lat, [0.0, 90.0], atol=1e-12)
    assert lon[0] == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(h, [5.0, 0.0], atol=1e-6)


def test_same_shape_arrays_and_scalars() -> None:
    ecef = GEODESY.to_ecef(np.array([10.0, 20.0]), np.array([30.0, 30.0]), np.zeros(2))
    assert ecef.shape == (2, 3)
    one = GEODESY.to_ecef(10.0, 30.0, 0.0)
    assert one.shape == (3,)
    np.testing.assert_allclose(ecef[0], one)


def test_to_ecef_broadcasts_scalar_with_array() -> None:
    ecef = GEODESY.to_ecef(np.array([10.0, 20.0]), 30.0, 0.0)
    assert ecef.shape == (2, 3)
    one = GEODESY.to_ecef(10.0, 30.0, 0.0)
    assert one.shape == (3,)
    np.testing.assert_allclose(ecef[0], one)


@pytest.mark.parametrize("lat0,lon0,h0", [(60.17, 24.94, 0.0), (-33.9, 151.2, 58.0), (0, 180, 0)])
def test_enu_hand_cases(lat0: float, lon0: float, h0: float) -> None:
    f = EnuFrame(lat0, lon0, h0)
    np.testing.assert_allclose(f.from_geodetic(lat0, lon0, h0 + 100.0), [0, 0, 100], atol=1e-6)
    np.testing.assert_allclose(f.from_geodetic(lat0, lon0, h0), [0, 0, 0], atol=1e-6)
    np.testing.assert_allclose(f.from_ecef(f.origin_ecef), [0, 0, 0], atol=1e-6)
    # a small step north is +N, a small step east is +E (and the horizon drops by d^2/2R)
    n = f.from_geodetic(lat0 + 1e-5, lon0, h0)
    assert n[1] == pytest.approx(1.1, rel=0.02) and abs(n[0]) < 1e-6
    e = f.from_geodetic(lat0, lon0 + 1e-5, h0)
    assert e[0] > 0.5 and abs(e[1]) < 1e-4


def test_enu_frame_matches_rotation_of_ecef_difference() -> None:
    f = EnuFrame(45.0, 7.0, 100.0)
    ecef = GEODESY.to_ecef(45.01, 7.02, 250.0)
    np.testing.assert_allclose(f.from_ecef(ecef), f.rotation @ (ecef - f.origin_ecef), atol=1e-6)
    np.testing.assert_allclose(
        f.to_ecef(np.array([10.0, -20.0, 3.0])),
        f.origin_ecef + f.rotation.T @ [10.0, -20.0, 3.0],
        atol=1e-6,
    )


def test_enu_rotation_rows_orthonormal_right_handed() -> None:
    lat, lon, _ = _grid()
    r = enu_rotation(lat, lon)
    assert r.shape == (lat.size, 3, 3)
    eye = np.broadcast_to(np.eye(3), r.shape)
    np.testing.assert_allclose(r @ np.swapaxes(r, -1, -2), eye, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-12)
    # E x N = U
    np.testing.assert_allclose(np.cross(r[:, 0], r[:, 1]), r[:, 2], atol=1e-12)


def test_enu_rotation_hand_cases() -> None:
    np.testing.assert_allclose(enu_rotation(0, 0), [[0, 1, 0], [0, 0, 1], [1, 0, 0]], atol=1e-15)
    np.testing.assert_allclose(enu_rotation(0, 90), [[-1, 0, 0], [0, 0, 1], [0, 1, 0]], atol=1e-15)
    # at the north pole (lon 0): East = +Y, North = -X, Up = +Z
    np.testing.assert_allclose(enu_rotation(90, 0), [[0, 1, 0], [-1, 0, 0], [0, 0, 1]], atol=1e-15)


def test_direction_round_trip_enu_ecef_enu_is_identity() -> None:
    rng = np.random.default_rng(2)
    v = rng.normal(size=(500, 3))
    lat = rng.uniform(-90, 90, 500)
    lon = rng.uniform(-180, 180, 500)
    ecef = enu_to_ecef_vectors(v, lat, lon)
    np.testing.assert_allclose(np.linalg.norm(ecef, axis=1), np.linalg.norm(v, axis=1), rtol=1e-12)
    np.testing.assert_allclose(ecef_to_enu_vectors(ecef, lat, lon), v, atol=1e-12)
    # a single frame, the same thing
    f = EnuFrame(lat[0], lon[0])
    np.testing.assert_allclose(f.vectors_from_ecef(f.vectors_to_ecef(v)), v, atol=1e-12)
    np.testing.assert_allclose(f.vectors_to_ecef(v), enu_to_ecef_vectors(v, lat[0], lon[0]))


def test_up_vector_is_ellipsoid_normal() -> None:
    # Up at (lat, lon) is the direction from the ellipsoid point to the point 1 m above it.
    for lat, lon in [(0.0, 0.0), (45.0, 7.0), (-89.0, 170.0), (60.17, 24.94)]:
        d = GEODESY.to_ecef(lat, lon, 1.0) - GEODESY.to_ecef(lat, lon, 0.0)
        np.testing.assert_allclose(enu_to_ecef_vectors([0, 0, 1], lat, lon), d, atol=1e-8)


@pytest.mark.parametrize(
    "lat,lon,h",
    [(60.18, 24.95, 30.0), (59.0, 20.0, 0.0), (-33.9, 151.2, 5.0), (89.99, -170.0, 0.0)],
)
def test_vectors_from_enu_at_agrees_with_pyproj_points_1m_apart(
    lat: float, lon: float, h: float
) -> None:
    frame = EnuFrame(60.17, 24.94, 0.0)
    rng = np.random.default_rng(3)
    v = rng.normal(size=(50, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    # the point 1 m along v from P, through PROJ's topocentric transform at P
    at_p = EnuFrame(lat, lon, h)
    p_ecef = at_p.to_ecef(np.zeros(3))
    q_ecef = at_p.to_ecef(v)
    expected = frame.from_ecef(q_ecef) - frame.from_ecef(p_ecef)
    got = frame.vectors_from_enu_at(v, lat, lon)
    np.testing.assert_allclose(got, expected, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-12)
    # per-row origins broadcast the same way
    got_rows = frame.vectors_from_enu_at(v, np.full(50, lat), np.full(50, lon))
    np.testing.assert_allclose(got_rows, got, atol=1e-15)


def test_a_point_or_direction_converts_the_same_alone_and_in_a_batch() -> None:
    """Each row's result does not depend on the rows converted with it (the matcher reuses
    rows of a unit's conversion for the rays it links: they must be what converting those
    alone gives, to the bit)."""
    rng = np.random.default_rng(3)
    n = 300
    f = EnuFrame(60.17, 24.94, 12.0)
    lat, lon = 60.17 + rng.normal(0, 2e-3, n), 24.94 + rng.normal(0, 2e-3, n)
    h = rng.normal(10, 3, n)
    d = direction_from_angles(rng.uniform(-np.pi, np.pi, n), rng.normal(0, 0.1, n))
    points, dirs = f.from_geodetic(lat, lon, h), f.vectors_from_enu_at(d, lat, lon)
    back = f.vectors_to_ecef(dirs)
    for i in range(0, n, 7):
        one = slice(i, i + 1)
        assert np.array_equal(f.from_geodetic(lat[one], lon[one], h[one]), points[one])
        assert np.array_equal(f.vectors_from_enu_at(d[one], lat[one], lon[one]), dirs[one])
        assert np.array_equal(f.vectors_to_ecef(dirs[one]), back[one])
    np.testing.assert_allclose(dirs, f.vectors_from_ecef(back), atol=1e-15)
