"""An area given as a bounding box in WGS84 degrees, and the tiles it covers.

``--bbox MINLON,MINLAT,MAXLON,MAXLAT`` (``hdmap export``, ``hdmap dashboard``) is parsed by
:meth:`BBox.parse`: finite, longitudes in [-180, 180], latitudes inside Web Mercator's
[-85.05, 85.05], west < east (no antimeridian crossing) and south < north. Its tiles at a
zoom are those ``mercantile.tiles`` yields (edges included), counted first so that a box of
too many is refused before they are listed.

>>> box = BBox.parse("24.94,60.17,24.9401,60.1701")
>>> box.tiles(16, limit=10)
['1201202110133102']
>>> bool(BBox.of_tiles(["1201202110133102"]).contains(60.17, 24.94))
True
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import mercantile
import numpy as np
from numpy.typing import ArrayLike, NDArray

from hdmap.geo.tiles import MAX_LAT


@dataclass(frozen=True)
class BBox:
    """A bounding box in WGS84 degrees (west, south, east, north); no antimeridian crossing."""

    west: float
    south: float
    east: float
    north: float

    @classmethod
    def parse(cls, text: str, name: str = "--bbox") -> BBox:
        """``minlon,minlat,maxlon,maxlat``; ValueError naming ``name`` (the option as the
        caller takes it) and saying what is wrong.

        >>> BBox.parse("24.9,60.1,25.0,60.2")
        BBox(west=24.9, south=60.1, east=25.0, north=60.2)
        >>> BBox.parse("25,60,24,61", name="area")
        Traceback (most recent call last):
        ...
        ValueError: area '25,60,24,61': need minlon < maxlon (no antimeridian crossing)
        """
        try:
            w, s, e, n = (float(p) for p in text.split(","))
        except ValueError:
            raise ValueError(f"{name} {text!r}: need minlon,minlat,maxlon,maxlat") from None
        if not all(math.isfinite(v) for v in (w, s, e, n)):
            raise ValueError(f"{name} {text!r}: not finite")
        if not (-180.0 <= w <= 180.0 and -180.0 <= e <= 180.0):
            raise ValueError(f"{name} {text!r}: longitudes must be in [-180, 180]")
        if not (-MAX_LAT <= s <= MAX_LAT and -MAX_LAT <= n <= MAX_LAT):
            raise ValueError(
                f"{name} {text!r}: latitudes must be in [-85.05, 85.05] (Web Mercator)"
            )
        if not w < e:
            raise ValueError(f"{name} {text!r}: need minlon < maxlon (no antimeridian crossing)")
        if not s < n:
            raise ValueError(f"{name} {text!r}: need minlat < maxlat")
        return cls(w, s, e, n)

    @classmethod
    def of_tiles(cls, quadkeys: Iterable[str]) -> BBox | None:
        """The box around tiles (quadkeys); None for none."""
        b = [mercantile.bounds(mercantile.quadkey_to_tile(q)) for q in quadkeys]
        if not b:
            return None
        return cls(min(x.west for x in b), min(x.south for x in b), max(x.east for x in b),
                   max(x.north for x in b))  # fmt: skip

    def as_tuple(self) -> tuple[float, float, float, float]:
        return self.west, self.south, self.east, self.north

    def tile_count(self, zoom: int) -> int:
        """How many tiles :meth:`tiles` lists at ``zoom``, without listing them (the corner
        tiles ``mercantile.tiles`` starts and ends with: its clamps, its epsilon).

        >>> BBox(-180.0, -MAX_LAT, 180.0, MAX_LAT).tile_count(16) == 4**16  # the whole map
        True
        """
        w, s = max(-180.0, self.west), max(-85.051129, self.south)
        e, n = min(180.0, self.east), min(85.051129, self.north)
        ul = mercantile.tile(w, n, zoom)
        lr = mercantile.tile(e - mercantile.LL_EPSILON, s + mercantile.LL_EPSILON, zoom)
        return max(lr.x - ul.x + 1, 0) * max(lr.y - ul.y + 1, 0)

    def tiles(self, zoom: int, limit: int) -> list[str]:
        """Quadkeys of the tiles at ``zoom`` that touch the box (edges included), sorted;
        ValueError when they are more than ``limit``.

        >>> BBox(24.9, 60.1, 25.0, 60.2).tiles(16, limit=100)
        Traceback (most recent call last):
        ...
        ValueError: the box covers 760 tiles at zoom 16; at most 100: take a smaller box
        """
        count = self.tile_count(zoom)
        if count > limit:
            raise ValueError(
                f"the box covers {count} tiles at zoom {zoom}; at most {limit}: take a smaller box"
            )
        found = mercantile.tiles(self.west, self.south, self.east, self.north, zoom)
        return sorted(mercantile.quadkey(t) for t in found)

    def contains(self, lat: ArrayLike, lon: ArrayLike) -> NDArray[np.bool_]:
        """Which points are inside the box (edges included).

        >>> BBox(24.9, 60.1, 25.0, 60.2).contains([60.15, 60.25, 60.2], [24.95, 24.95, 25.0])
        array([ True, False,  True])
        """
        lat, lon = np.asarray(lat, float), np.asarray(lon, float)
        return (lon >= self.west) & (lon <= self.east) & (lat >= self.south) & (lat <= self.north)
