"""Web-Mercator tiles addressed by quadkey; a region is a quadkey prefix.

Scalar tile maths (bounds, neighbours, quadkey <-> x/y/z) comes from ``mercantile``.
The hot path (routing thousands of rays per batch) uses a vectorised numpy
equivalent of ``mercantile.tile`` + ``mercantile.quadkey``, tested against it.

Default zoom 16: a tile is 611 m x cos(latitude) on a side (306 m in Helsinki,
432 m at 45 deg). That keeps a tile's map to at most a few hundred signs (one
small message), a vehicle's 3x3 neighbourhood (~0.9-1.8 km) covers well past the
camera's useful 80 m range, and a quadkey has 16 digits so a landmark id can
embed its creation tile in 32 bits.

>>> quadkey_of(60.17, 24.94, 16)
'1201202110133102'
>>> in_region('1201202110133102', ['12012'])
True
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import mercantile
import numpy as np
from numpy.typing import ArrayLike, NDArray

from hdmap.geo.geodesy import GEODESY, EnuFrame, Geodesy, enu_to_ecef_vectors

DEFAULT_ZOOM = 16
MAX_ZOOM = 24
MAX_LAT = 85.0511287798066
DEFAULT_TARGET_RANGE_M = 25.0
"""Where along a ray without a range estimate its sign is assumed to be, m."""


def quadkey_of(lat: float, lon: float, zoom: int = DEFAULT_ZOOM) -> str:
    return mercantile.quadkey(mercantile.tile(lon, lat, zoom))


def tile_xy(lat: ArrayLike, lon: ArrayLike, zoom: int = DEFAULT_ZOOM):
    """Vectorised ``mercantile.tile``: (x, y) integer arrays at ``zoom``."""
    la = np.asarray(lat, float)
    lo = np.asarray(lon, float)
    n = 1 << zoom
    eps = 1e-14  # exactly as mercantile.tile, so both agree on points at a tile edge
    fx = lo / 360.0 + 0.5
    s = np.sin(np.radians(la))
    with np.errstate(divide="ignore", invalid="ignore"):
        fy = 0.5 - 0.25 * np.log((1.0 + s) / (1.0 - s)) / np.pi
    fy = np.nan_to_num(fy, nan=0.0, posinf=1.0, neginf=0.0)
    x = np.where(fx <= 0, 0, np.where(fx >= 1, n - 1, np.floor((fx + eps) * n)))
    y = np.where(fy <= 0, 0, np.where(fy >= 1, n - 1, np.floor((fy + eps) * n)))
    return np.clip(x, 0, n - 1).astype(np.int64), np.clip(y, 0, n - 1).astype(np.int64)


def quadkey_ints(x: NDArray[np.int64], y: NDArray[np.int64], zoom: int) -> NDArray[np.int64]:
    """Interleave x/y bits: the quadkey read as a base-4 integer."""
    q = np.zeros(np.shape(x), np.int64)
    for i in range(zoom - 1, -1, -1):
        q = (q << 2) | (((x >> i) & 1) | (((y >> i) & 1) << 1))
    return q


def quadkeys_of(lat: ArrayLike, lon: ArrayLike, zoom: int = DEFAULT_ZOOM) -> NDArray[np.str_]:
    """Vectorised quadkeys (numpy unicode array) of points.

    >>> quadkeys_of([60.17, 0.0], [24.94, 0.0], 4).tolist()
    ['1201', '3000']
    """
    x, y = tile_xy(lat, lon, zoom)
    q = quadkey_ints(x, y, zoom)
    digits = (q[..., None] >> (2 * np.arange(zoom - 1, -1, -1))) & 3
    chars = (digits + ord("0")).astype(np.uint8)
    return chars.view(f"S{zoom}").reshape(np.shape(q)).astype(f"U{zoom}")


def valid_quadkey(qk: str, zoom: int | None = None) -> bool:
    """Whether ``qk`` is a quadkey (of ``zoom`` digits, if given).

    >>> valid_quadkey('0123'), valid_quadkey('0129'), valid_quadkey('')
    (True, False, False)
    """
    if not qk or len(qk) > MAX_ZOOM or any(c not in "0123" for c in qk):
        return False
    return zoom is None or len(qk) == zoom


def tile_of(qk: str) -> mercantile.Tile:
    return mercantile.quadkey_to_tile(qk)


def tile_id(qk: str) -> int:
    """Quadkey as an integer (base 4); unique per zoom."""
    return int(qk, 4)


def tile_bounds(qk: str) -> mercantile.LngLatBbox:
    return mercantile.bounds(tile_of(qk))


def tile_center(qk: str) -> tuple[float, float]:
    """(lat, lon) of the tile's centre (in Mercator, mapped back)."""
    xy = mercantile.xy_bounds(tile_of(qk))
    lon, lat = mercantile.lnglat((xy.left + xy.right) / 2.0, (xy.bottom + xy.top) / 2.0)
    return float(lat), float(lon)


def neighbours(qk: str) -> list[str]:
    """The (up to) 8 tiles around ``qk`` at the same zoom."""
    return [mercantile.quadkey(t) for t in mercantile.neighbors(tile_of(qk))]


def tiles_around(lat: float, lon: float, radius_m: float, zoom: int = DEFAULT_ZOOM) -> list[str]:
    """Quadkeys of the tiles touching a square of half-side ``radius_m`` around a point."""
    dlat = radius_m / 110_574.0  # shortest metres per degree of latitude (equator)
    dlon = radius_m / (111_320.0 * max(np.cos(np.radians(lat)), 1e-6))
    west, east = lon - dlon, lon + dlon
    south, north = max(lat - dlat, -MAX_LAT), min(lat + dlat, MAX_LAT)
    return sorted(mercantile.quadkey(t) for t in mercantile.tiles(west, south, east, north, zoom))


def in_region(qk: str, prefixes: Sequence[str]) -> bool:
    """Whether a tile is inside a region (any of its prefixes; no prefixes = everywhere)."""
    return not prefixes or any(qk.startswith(p) for p in prefixes)


def region_mask(qks: NDArray[np.str_], prefixes: Sequence[str]) -> NDArray[np.bool_]:
    if not prefixes:
        return np.ones(np.shape(qks), bool)
    out = np.zeros(np.shape(qks), bool)
    for p in prefixes:
        out |= np.char.startswith(qks, p)
    return out


def route_rays(
    lat: ArrayLike,
    lon: ArrayLike,
    h: ArrayLike,
    direction_enu: ArrayLike,
    range_m: ArrayLike,
    zoom: int = DEFAULT_ZOOM,
    default_range_m: float = DEFAULT_TARGET_RANGE_M,
    geodesy: Geodesy = GEODESY,
) -> NDArray[np.str_]:
    """Quadkey of each ray's expected target point (its range, or the default)."""
    r = np.asarray(range_m, float)
    r = np.where(r > 0, r, default_range_m)
    d = np.asarray(direction_enu, float)
    ecef = geodesy.to_ecef(lat, lon, h) + enu_to_ecef_vectors(d * r[..., None], lat, lon)
    tlat, tlon, _ = geodesy.to_geodetic(ecef)
    return quadkeys_of(tlat, tlon, zoom)


class TileFrames:
    """ENU frames at tile centres, built once per tile (an explicit cache object)."""

    def __init__(self, geodesy: Geodesy = GEODESY):
        self._frames: dict[str, EnuFrame] = {}
        self._geo = geodesy

    def __call__(self, qk: str) -> EnuFrame:
        f = self._frames.get(qk)
        if f is None:
            lat, lon = tile_center(qk)
            f = self._frames[qk] = EnuFrame(lat, lon, 0.0, self._geo)
        return f


def frame_map(src: EnuFrame, dst: EnuFrame) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``(R, t)`` with ``x_dst = R x_src + t`` between two ENU frames (both affine maps
    of ECEF); ``(None, None)`` for the same frame.

    >>> f = TileFrames()
    >>> r, t = frame_map(f("1202"), f("1203"))
    >>> bool(np.allclose(r @ r.T, np.eye(3))), frame_map(f("12"), f("12"))
    (True, (None, None))
    """
    if src is dst:
        return None, None
    o = dst.from_ecef(src.to_ecef(np.zeros((1, 3))))[0]
    basis = dst.from_ecef(src.to_ecef(np.eye(3))) - o
    return basis.T, o


def region_label(prefixes: Iterable[str]) -> str:
    """A key-expression-safe chunk naming a region ('all' for everywhere).

    >>> region_label(['120', '121']), region_label([])
    ('120+121', 'all')
    """
    p = sorted(prefixes)
    return "+".join(p) if p else "all"
