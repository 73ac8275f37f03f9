"""hdmap.geo.tiles: the vectorised quadkeys against mercantile, regions and ray routing."""

from __future__ import annotations

import math

import mercantile
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hdmap.geo.geodesy import EnuFrame
from hdmap.geo.tiles import (
    DEFAULT_TARGET_RANGE_M,
    TileFrames,
    in_region,
    neighbours,
    quadkey_of,
    quadkeys_of,
    region_label,
    region_mask,
    route_rays,
    tile_bounds,
    tile_center,
    tile_id,
    tile_of,
    tiles_around,
    valid_quadkey,
)

HELSINKI = (60.17, 24.94)


def _near_tile_edge(lat: float, lon: float, zoom: int, tol: float = 1e-9) -> bool:
    """Within ``tol`` (fraction of a tile) of a tile edge, where mercantile's 1e-14
    EPSILON nudge may legitimately pick the other tile (see test_tile_edge_epsilon)."""
    n = 2.0**zoom
    x = (lon + 180.0) / 360.0 * n
    s = math.sin(math.radians(lat))
    y = (0.5 - 0.25 * math.log((1 + s) / (1 - s)) / math.pi) * n
    return any(abs(v - round(v)) < tol for v in (x, y))


@settings(max_examples=300, deadline=None, derandomize=True, database=None)
@given(
    lat=st.floats(-85.0, 85.0, allow_nan=False),
    lon=st.floats(-180.0, 180.0, allow_nan=False),
    zoom=st.integers(1, 20),
)
def test_quadkeys_of_matches_mercantile(lat: float, lon: float, zoom: int) -> None:
    if _near_tile_edge(lat, lon, zoom):
        return
    expected = mercantile.quadkey(mercantile.tile(lon, lat, zoom))
    assert quadkeys_of([lat], [lon], zoom)[0] == expected
    assert quadkey_of(lat, lon, zoom) == expected


def test_quadkeys_of_matches_mercantile_on_random_arrays() -> None:
    rng = np.random.default_rng(11)
    lat = rng.uniform(-85.0, 85.0, 2000)
    lon = rng.uniform(-180.0, 180.0, 2000)
    for zoom in range(1, 21):
        got = quadkeys_of(lat, lon, zoom)
        assert got.shape == (2000,) and got.dtype == np.dtype(f"U{zoom}")
        expected = [
            mercantile.quadkey(mercantile.tile(b, a, zoom)) for a, b in zip(lat, lon, strict=True)
        ]
        assert got.tolist() == expected


def test_quadkeys_of_extremes() -> None:
    # the antimeridian, the Mercator latitude limit (clipped) and the equator/prime meridian
    lat = np.array([0.0, 0.0, 89.0, -89.0, 0.0])
    lon = np.array([-180.0, 180.0, 10.0, 10.0, 0.0])
    got = quadkeys_of(lat, lon, 3).tolist()
    assert got[0] == "200" and got[1] == "311"
    assert got[2] == quadkey_of(85.0, 10.0, 3) and got[3] == quadkey_of(-85.0, 10.0, 3)
    assert got[4] == "300"
    assert quadkeys_of(np.array([[1.0, 2.0]]), np.array([[3.0, 4.0]]), 5).shape == (1, 2)


def test_tile_edge_epsilon() -> None:
    z = 16
    edge = 12345 / 2**z * 360.0 - 180.0
    lon = float(np.nextafter(edge, -np.inf))
    assert quadkeys_of([10.0], [lon], z)[0] == quadkey_of(10.0, lon, z)


def test_valid_quadkey_and_tile_id() -> None:
    assert valid_quadkey("0123") and valid_quadkey("0123", 4)
    assert not valid_quadkey("0123", 5)
    assert not valid_quadkey("") and not valid_quadkey("0124") and not valid_quadkey("1" * 25)
    assert tile_id("0") == 0 and tile_id("33") == 15 and tile_id("1201") == 0b01100001
    assert tile_of("1201") == mercantile.Tile(x=9, y=4, z=4)


@pytest.mark.parametrize("qk", ["0", "1201", "1201202110133102", "3333333333333333", "0000"])
def test_tile_center_inside_bounds(qk: str) -> None:
    lat, lon = tile_center(qk)
    b = tile_bounds(qk)
    assert b.south < lat < b.north and b.west < lon < b.east
    assert quadkey_of(lat, lon, len(qk)) == qk
    # the centre of the Mercator square: equal longitude margins
    assert lon - b.west == pytest.approx(b.east - lon)


def test_neighbours_of_interior_tile() -> None:
    qk = quadkey_of(*HELSINKI, 16)
    nb = neighbours(qk)
    assert len(nb) == 8 and len(set(nb)) == 8 and qk not in nb
    t = tile_of(qk)
    for q in nb:
        assert len(q) == 16
        u = tile_of(q)
        assert max(abs(u.x - t.x), abs(u.y - t.y)) == 1


def test_tiles_around_covers_own_tile_and_square() -> None:
    lat, lon = HELSINKI
    qks = tiles_around(lat, lon, 300.0, 16)
    assert quadkey_of(lat, lon, 16) in qks
    assert qks == sorted(set(qks))
    frame = EnuFrame(lat, lon)
    for e, n in [(-290, -290), (-290, 290), (290, -290), (290, 290), (0, 295)]:
        plat, plon, _ = frame.to_geodetic(np.array([float(e), float(n), 0.0]))
        assert quadkey_of(float(plat), float(plon), 16) in qks
    # a tiny radius is just the own tile (away from tile edges)
    qk = quadkey_of(lat, lon, 16)
    clat, clon = tile_center(qk)
    assert tiles_around(clat, clon, 1.0, 16) == [qk]


def test_in_region_and_region_mask() -> None:
    qk = "1201202110133102"
    assert in_region(qk, ["12012"])
    assert in_region(qk, ["3", "1201"])
    assert not in_region(qk, ["13", "1202"])
    assert in_region(qk, [])  # no prefixes = everywhere
    qks = np.array(["1201", "1202", "1301", "0000", "1201333"])
    for prefixes in (["120"], ["1201", "0"], ["2"], []):
        expected = [in_region(q, prefixes) for q in qks]
        assert region_mask(qks, prefixes).tolist() == expected
    assert region_label(["121", "120"]) == "120+121" and region_label([]) == "all"


def _expected_tile(lat, lon, h, d, r, zoom=16) -> str:
    plat, plon, _ = EnuFrame(lat, lon, h).to_geodetic(np.asarray(d) * r)
    return quadkey_of(float(plat), float(plon), zoom)


def test_route_rays_lands_in_tile_of_target() -> None:
    lat, lon, h = HELSINKI[0], HELSINKI[1], 20.0
    east = np.array([1.0, 0.0, 0.0])
    north_up = np.array([0.0, 0.8, 0.6])
    d = np.array([east, north_up, east, east])
    r = np.array([700.0, 900.0, 0.0, 5.0])
    n = len(r)
    got = route_rays(np.full(n, lat), np.full(n, lon), np.full(n, h), d, r, zoom=16)
    assert got[0] == _expected_tile(lat, lon, h, east, 700.0)
    assert got[0] != quadkey_of(lat, lon, 16)  # really moved to another tile
    assert got[1] == _expected_tile(lat, lon, h, north_up, 900.0)
    assert got[1] != quadkey_of(lat, lon, 16)
    assert got[2] == _expected_tile(lat, lon, h, east, DEFAULT_TARGET_RANGE_M)
    assert got[3] == _expected_tile(lat, lon, h, east, 5.0)


def test_route_rays_zero_range_uses_default_range() -> None:
    lat, lon, h = HELSINKI[0], HELSINKI[1], 0.0
    d = np.array([[0.0, -1.0, 0.0]])
    got = route_rays([lat], [lon], [h], d, [0.0], zoom=16, default_range_m=800.0)
    assert got[0] == _expected_tile(lat, lon, h, d[0], 800.0)
    assert got[0] != quadkey_of(lat, lon, 16)
    # a negative range (never valid on the wire) is treated like "no estimate"
    assert route_rays([lat], [lon], [h], d, [-5.0], zoom=16, default_range_m=800.0)[0] == got[0]


def test_tile_frames_cache() -> None:
    frames = TileFrames()
    qk = quadkey_of(*HELSINKI, 16)
    f = frames(qk)
    assert frames(qk) is f
    assert (f.lat0, f.lon0) == pytest.approx(tile_center(qk))
