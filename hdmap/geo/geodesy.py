"""WGS84 geodetic <-> ECEF <-> local ENU, all through pyproj.

Conventions
-----------
- Geodetic: latitude and longitude in degrees, ellipsoidal height ``h`` in metres
  (EPSG:4979).
- ECEF: Earth-centred Earth-fixed Cartesian metres (EPSG:4978).
- ENU: East, North, Up metres in the topocentric frame tangent to the ellipsoid at
  an origin (PROJ ``+proj=topocentric``).

Points go through pyproj; directions (free vectors) only rotate, with the ENU
basis at a geodetic latitude/longitude (:func:`enu_rotation`). Estimation runs in
ENU at a tile centre, never in raw ECEF (sums of 6.4e6 m coordinates lose precision).

>>> frame = EnuFrame(60.17, 24.94, 0.0)
>>> e, n, u = frame.from_geodetic(60.17, 24.94, 10.0)
>>> round(float(e), 6), round(float(n), 6), round(float(u), 6)
(0.0, 0.0, 10.0)
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pyproj
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

_INVERSE = pyproj.enums.TransformDirection.INVERSE


def _geodetic_to_ecef() -> pyproj.Transformer:
    return pyproj.Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)


@dataclass(frozen=True)
class Geodesy:
    """Stateless facade over the WGS84 geodetic <-> ECEF transformer.

    pyproj transformers are not free to build; create one ``Geodesy`` per
    component and reuse it (it is thread-compatible for reads).
    """

    _tr: pyproj.Transformer = field(default_factory=_geodetic_to_ecef, repr=False)

    def to_ecef(self, lat: ArrayLike, lon: ArrayLike, h: ArrayLike) -> Array:
        """Geodetic (deg, deg, m) -> ECEF (..., 3) metres."""
        lo, la, hh = np.broadcast_arrays(
            np.asarray(lon, float), np.asarray(lat, float), np.asarray(h, float)
        )
        x, y, z = self._tr.transform(lo, la, hh)
        return np.stack(np.broadcast_arrays(x, y, z), axis=-1)

    def to_geodetic(self, ecef: ArrayLike) -> tuple[Array, Array, Array]:
        """ECEF (..., 3) metres -> (lat deg, lon deg, h m)."""
        p = np.asarray(ecef, float)
        lon, lat, h = self._tr.transform(p[..., 0], p[..., 1], p[..., 2], direction=_INVERSE)
        return np.asarray(lat), np.asarray(lon), np.asarray(h)


GEODESY = Geodesy()
"""A shared, immutable default instance."""


def enu_rotation(lat_deg: ArrayLike, lon_deg: ArrayLike) -> Array:
    """Rotation matrix (..., 3, 3) whose rows are the E, N, U unit vectors in ECEF.

    ``v_enu = R @ v_ecef`` and ``v_ecef = R.T @ v_enu`` for free vectors.

    >>> R = enu_rotation(0.0, 0.0)
    >>> (R.round(12) + 0.0).tolist()
    [[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]
    """
    lat = np.radians(np.asarray(lat_deg, float))
    lon = np.radians(np.asarray(lon_deg, float))
    sl, cl = np.sin(lat), np.cos(lat)
    so, co = np.sin(lon), np.cos(lon)
    zero = np.zeros_like(sl)
    east = np.stack([-so, co, zero], axis=-1)
    north = np.stack([-sl * co, -sl * so, cl], axis=-1)
    up = np.stack([cl * co, cl * so, sl], axis=-1)
    return np.stack([east, north, up], axis=-2)


def enu_to_ecef_vectors(v_enu: ArrayLike, lat_deg: ArrayLike, lon_deg: ArrayLike) -> Array:
    """Rotate direction vectors given in ENU at (lat, lon) into ECEF."""
    r = enu_rotation(lat_deg, lon_deg)
    return np.einsum("...ji,...j->...i", r, np.asarray(v_enu, float))


def ecef_to_enu_vectors(v_ecef: ArrayLike, lat_deg: ArrayLike, lon_deg: ArrayLike) -> Array:
    """Rotate ECEF direction vectors into ENU at (lat, lon)."""
    r = enu_rotation(lat_deg, lon_deg)
    return np.einsum("...ij,...j->...i", r, np.asarray(v_ecef, float))


class EnuFrame:
    """A local East-North-Up frame at a geodetic origin.

    >>> f = EnuFrame(45.0, 7.0, 100.0)
    >>> p = f.to_geodetic(np.array([[10.0, -20.0, 3.0]]))
    >>> np.allclose(f.from_geodetic(*p), [[10.0, -20.0, 3.0]], atol=1e-6)
    True
    """

    def __init__(self, lat0: float, lon0: float, h0: float = 0.0, geodesy: Geodesy = GEODESY):
        self.lat0, self.lon0, self.h0 = float(lat0), float(lon0), float(h0)
        self._geo = geodesy
        self._topo = pyproj.Transformer.from_pipeline(
            f"+proj=topocentric +ellps=WGS84 +lat_0={self.lat0!r} +lon_0={self.lon0!r} "
            f"+h_0={self.h0!r}"
        )
        self.rotation = enu_rotation(self.lat0, self.lon0)
        self.origin_ecef = self._geo.to_ecef(self.lat0, self.lon0, self.h0)

    def __repr__(self) -> str:
        return f"EnuFrame(lat0={self.lat0}, lon0={self.lon0}, h0={self.h0})"

    def from_ecef(self, ecef: ArrayLike) -> Array:
        p = np.asarray(ecef, float)
        e, n, u = self._topo.transform(p[..., 0], p[..., 1], p[..., 2])
        return np.stack(np.broadcast_arrays(e, n, u), axis=-1)

    def to_ecef(self, enu: ArrayLike) -> Array:
        p = np.asarray(enu, float)
        x, y, z = self._topo.transform(p[..., 0], p[..., 1], p[..., 2], direction=_INVERSE)
        return np.stack(np.broadcast_arrays(x, y, z), axis=-1)

    def from_geodetic(self, lat: ArrayLike, lon: ArrayLike, h: ArrayLike) -> Array:
        return self.from_ecef(self._geo.to_ecef(lat, lon, h))

    def to_geodetic(self, enu: ArrayLike) -> tuple[Array, Array, Array]:
        return self._geo.to_geodetic(self.to_ecef(enu))

    def vectors_from_ecef(self, v_ecef: ArrayLike) -> Array:
        """Rotate ECEF free vectors into this frame (row by row: see :func:`_rotate_rows`)."""
        return _rotate_rows(np.asarray(v_ecef, float), self.rotation)

    def vectors_to_ecef(self, v_enu: ArrayLike) -> Array:
        return _rotate_rows(np.asarray(v_enu, float), self.rotation.T)

    def vectors_from_enu_at(
        self, v_enu: ArrayLike, lat_deg: ArrayLike, lon_deg: ArrayLike
    ) -> Array:
        """Directions given in ENU at other origins (lat, lon) -> this frame."""
        return self.vectors_from_ecef(enu_to_ecef_vectors(v_enu, lat_deg, lon_deg))


def _rotate_rows(v: Array, r: Array) -> Array:
    """``v @ r.T`` for vectors ``v`` (..., 3), written out so that each row's result does
    not depend on how many rows are converted together.

    Pitfall: ``v @ r.T`` goes through BLAS, whose kernels differ with the number of rows,
    so one direction converted alone and in a batch differed in its last bits; the matcher
    converts a ray once and reuses its rows (a unit's rays, then the ones it links), which
    must be the rows a conversion of those alone gives.
    """
    return v[..., 0:1] * r[:, 0] + v[..., 1:2] * r[:, 1] + v[..., 2:3] * r[:, 2]


def direction_from_angles(az: ArrayLike, el: ArrayLike) -> Array:
    """(azimuth, elevation) rad -> unit ENU directions (..., 3).

    >>> direction_from_angles(0.0, 0.0).round(12).tolist()
    [0.0, 1.0, 0.0]
    """
    a, e = np.asarray(az, float), np.asarray(el, float)
    ce = np.cos(e)
    return np.stack([ce * np.sin(a), ce * np.cos(a), np.sin(e)], axis=-1)
