"""What the dashboard draws, computed from landmark rows: no I/O, no bus, no state.

- **95 % ellipse** of a landmark's horizontal position: its semi-axes and azimuth from
  :mod:`hdmap.geo.ellipse` (the east/north block of its ENU covariance, scaled to the
  chi-square(2) 0.95 quantile), drawn as a ring of vertices around it.
- **facing arrow**: a short line from the landmark along its facing azimuth (the direction
  the sign is *seen from*, degrees clockwise from true North,
  :class:`schemas.map.MapLandmarks`, :mod:`hdmap.mapping.facing`), with a head at the tip;
  none when the facing is unknown (``facing_sigma_deg`` 0).
- metre offsets to degrees with the WGS84 radii of curvature at the landmark (exact to
  first order; the offsets are metres, the error is far below a millimetre);
- the GeoJSON features of a landmark (``kind`` point / ellipse / arrow), its display
  status, and a service's row of the health panel from its :class:`schemas.Stats`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

import mercantile
import numpy as np
from numpy.typing import ArrayLike, NDArray

from hdmap.geo.ellipse import ellipse_axes, horizontal_cov
from schemas import Stats
from schemas.map import MapLandmarks, as_map_landmarks
from schemas.tables import STATUS_CANDIDATE, STATUS_RETIRED

Array = NDArray[np.float64]

WGS84_A = 6_378_137.0
WGS84_E2 = 6.694379990141317e-3
STATUSES = ("candidate", "located", "confirmed", "doubtful", "retired")
"""Display statuses (:func:`status_label`), in the legend's order."""
MAX_AREA_TILES = 4096
"""Most tiles the area may cover (``--bbox``, ``--tiles``, the tiles followed without
one): each is one subscription and one snapshot."""


# -- ellipses and arrows -----------------------------------------------------------------


def metres_to_degrees(lat: ArrayLike, d_east: ArrayLike, d_north: ArrayLike) -> tuple[Array, Array]:
    """(d_lat, d_lon) in degrees of east/north offsets in metres at latitude ``lat``
    (WGS84 meridian and prime-vertical radii of curvature)."""
    phi = np.radians(np.asarray(lat, float))
    s2 = 1.0 - WGS84_E2 * np.sin(phi) ** 2
    meridian = WGS84_A * (1.0 - WGS84_E2) / s2**1.5
    normal = WGS84_A / np.sqrt(s2)
    d_lat = np.degrees(np.asarray(d_north, float) / meridian)
    d_lon = np.degrees(np.asarray(d_east, float) / (normal * np.maximum(np.cos(phi), 1e-9)))
    return d_lat, d_lon


def ellipse_rings(
    lat: ArrayLike, lon: ArrayLike, cov_en: ArrayLike, level: float = 0.95, segments: int = 36
) -> Array:
    """(N, segments + 1, 2) closed rings of [lon, lat] around each point: its ``level``
    ellipse (counter-clockwise, the first vertex at the end of the major axis)."""
    la = np.asarray(lat, float).reshape(-1)
    lo = np.asarray(lon, float).reshape(-1)
    major, minor, azimuth = ellipse_axes(cov_en, level)
    t = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    az = np.radians(azimuth)[:, None]
    u = np.cos(t)[None, :] * major[:, None]  # along the major axis
    v = np.sin(t)[None, :] * minor[:, None]  # along the minor axis, 90 degrees to its left
    d_east = u * np.sin(az) - v * np.cos(az)
    d_north = u * np.cos(az) + v * np.sin(az)
    d_lat, d_lon = metres_to_degrees(la[:, None], d_east, d_north)
    ring = np.stack([lo[:, None] + d_lon, la[:, None] + d_lat], axis=2)
    return np.concatenate([ring, ring[:, :1]], axis=1)


def offset_point(lat: float, lon: float, azimuth_deg: float, dist_m: float) -> tuple[float, float]:
    """(lon, lat) ``dist_m`` metres from a point along an azimuth (clockwise from North).

    >>> lon, lat = offset_point(60.0, 25.0, 90.0, 100.0)  # 100 m East
    >>> round(lat, 9), round((lon - 25.0) * 55_800, 1)  # ~55.8 km per degree at 60 N
    (60.0, 100.0)
    """
    a = math.radians(azimuth_deg)
    d_lat, d_lon = metres_to_degrees(lat, dist_m * math.sin(a), dist_m * math.cos(a))
    return lon + float(d_lon), lat + float(d_lat)


def facing_arrow(
    lat: float, lon: float, azimuth_deg: float, length_m: float = 8.0, head_m: float = 2.0
) -> list[list[list[float]]]:
    """MultiLineString coordinates: the shaft from the landmark ``length_m`` along
    ``azimuth_deg``, and a head of two ``head_m`` barbs at its tip (150 degrees off it)."""
    tip = offset_point(lat, lon, azimuth_deg, length_m)
    out = [[[lon, lat], list(tip)]]
    for side in (150.0, -150.0):
        barb = offset_point(tip[1], tip[0], azimuth_deg + side, head_m)
        out.append([list(tip), list(barb)])
    return out


# -- landmark features -------------------------------------------------------------------


def status_label(status: int, exist_state: int) -> str:
    """The display status: ``candidate`` (not yet located), ``located`` (located, existence
    unknown), ``confirmed`` / ``doubtful`` (its existence estimate), ``retired``.

    >>> [status_label(s, e) for s, e in ((0, 0), (1, 0), (1, 1), (1, 2), (2, 1))]
    ['candidate', 'located', 'confirmed', 'doubtful', 'retired']
    """
    if status == STATUS_RETIRED:
        return "retired"
    if status == STATUS_CANDIDATE:
        return "candidate"
    return {1: "confirmed", 2: "doubtful"}.get(int(exist_state), "located")


def _num(v: Any, digits: int | None = None) -> float | None:
    """A JSON number (None for NaN/inf), rounded to ``digits``."""
    f = float(v)
    if not math.isfinite(f):
        return None
    return round(f, digits) if digits is not None else f


def landmark_properties(lm: MapLandmarks) -> list[dict[str, Any]]:
    """Per row, what the page shows of a landmark and what its history keeps (JSON-able;
    ``id`` a string: u8 ids do not fit a JavaScript number)."""
    lm = as_map_landmarks(lm)
    cov = horizontal_cov(lm.cov)
    major, minor, major_az = ellipse_axes(cov)
    facing, facing_sigma, known = lm.facing()
    out = []
    for k in range(len(lm)):
        out.append(
            {
                "id": str(int(lm.id[k])),
                "sign_class": int(lm.sign_class[k]),
                "lat": _num(lm.lat[k], 8),
                "lon": _num(lm.lon[k], 8),
                "h": _num(lm.h[k], 3),
                "status": status_label(int(lm.status[k]), int(lm.exist_state[k])),
                "status_code": int(lm.status[k]),
                "exist_state": int(lm.exist_state[k]),
                "p_exist": _num(lm.p_exist[k], 4),
                "passes": int(lm.n_passes[k]),
                "n_obs": int(lm.n_obs[k]),
                "revision": int(lm.revision[k]),
                "updated_at": _num(lm.updated_at[k], 3),
                "first_seen": _num(lm.first_seen[k], 3),
                "last_seen": _num(lm.last_seen[k], 3),
                "sigma_e_m": _num(math.sqrt(max(cov[k, 0], 0.0)), 3),
                "sigma_n_m": _num(math.sqrt(max(cov[k, 2], 0.0)), 3),
                "sigma_u_m": _num(math.sqrt(max(float(lm.cov[k, 5]), 0.0)), 3),
                "ellipse_major_m": _num(major[k], 3),
                "ellipse_minor_m": _num(minor[k], 3),
                "ellipse_azimuth_deg": _num(major_az[k], 1),
                "facing_deg": _num(facing[k], 1) if known[k] else None,
                "facing_sigma_deg": _num(facing_sigma[k], 1) if known[k] else None,
            }
        )
    return out


def landmark_features(
    lm: MapLandmarks, arrow_m: float = 8.0, segments: int = 36
) -> dict[str, list[dict[str, Any]]]:
    """Landmark id (string) -> its GeoJSON features: a ``point`` (every property of
    :func:`landmark_properties`), its 95 % ``ellipse`` (a polygon; none if the covariance
    is zero), its facing ``arrow`` (a multi-line; none if the facing is unknown). Every
    feature has ``id``, ``kind``, ``status`` and ``passes``."""
    lm = as_map_landmarks(lm)
    props = landmark_properties(lm)
    rings = ellipse_rings(lm.lat, lm.lon, horizontal_cov(lm.cov), 0.95, segments)
    out: dict[str, list[dict[str, Any]]] = {}
    for k, p in enumerate(props):
        common = {"id": p["id"], "status": p["status"], "passes": p["passes"]}
        feats = [_feature("Point", [p["lon"], p["lat"]], {**p, "kind": "point"})]
        if p["ellipse_major_m"]:
            ring = np.round(rings[k], 8).tolist()
            feats.append(_feature("Polygon", [ring], {**common, "kind": "ellipse"}))
        if p["facing_deg"] is not None:
            arrow = facing_arrow(float(lm.lat[k]), float(lm.lon[k]), p["facing_deg"], arrow_m)
            feats.append(_feature("MultiLineString", arrow, {**common, "kind": "arrow"}))
        out[p["id"]] = feats
    return out


def _feature(kind: str, coordinates: Any, properties: dict[str, Any]) -> dict[str, Any]:
    return {
        "type": "Feature",
        "geometry": {"type": kind, "coordinates": coordinates},
        "properties": properties,
    }


def feature_collection(features: list[dict[str, Any]]) -> dict[str, Any]:
    return {"type": "FeatureCollection", "features": features}


# -- tiles ---------------------------------------------------------------------------------


def tile_features(versions: dict[str, int]) -> list[dict[str, Any]]:
    """Outline polygons of the followed tiles, with their map version (-1: not fetched)."""
    out = []
    for qk, version in sorted(versions.items()):
        b = mercantile.bounds(mercantile.quadkey_to_tile(qk))
        ring = [[b.west, b.south], [b.east, b.south], [b.east, b.north], [b.west, b.north]]
        out.append(_feature("Polygon", [[*ring, ring[0]]], {"tile": qk, "version": version}))
    return out


# -- service health ----------------------------------------------------------------------

ACCEPTED = MappingProxyType({"ingest": ("accepted", "obs")})
"""Service -> (counter of its accepted input, unit); the others count applied entries."""
DEFAULT_ACCEPTED = ("entries_applied", "entries")


@dataclass(frozen=True)
class Sample:
    """One service instance's throughput counters at a time (for its rates)."""

    t: float
    accepted: float
    rejected: float


def service_row(s: Stats, previous: Sample | None, now: float) -> tuple[dict[str, Any], Sample]:
    """The health panel's row of one service instance, and the sample the next row's rates
    are taken against. Rates are None on the first sample and after a counter went back
    (a restart)."""
    c = s.counters
    name, unit = ACCEPTED.get(s.service, DEFAULT_ACCEPTED)
    sample = Sample(now, float(c.get(name, 0.0)), float(c.get("rejected", 0.0)))
    rate = rejected_rate = None
    if previous is not None and now > previous.t:
        dt = now - previous.t
        if sample.accepted >= previous.accepted and sample.rejected >= previous.rejected:
            rate = (sample.accepted - previous.accepted) / dt
            rejected_rate = (sample.rejected - previous.rejected) / dt
    top = sorted(s.rejected.items(), key=lambda kv: (-kv[1], kv[0]))[:5]
    row = {
        "service": s.service,
        "instance": s.instance,
        "region": ",".join(s.region) or "all",
        "uptime_s": _num(c.get("uptime_s", 0.0), 1),
        "backlog": _num(c.get("backlog", 0.0)),
        "lag_entries": _num(c.get("lag_entries", 0.0)),
        "applying": bool(c.get("applying", 0)),
        "accepted": _num(sample.accepted),
        "accepted_unit": unit,
        "rejected": _num(sample.rejected),
        "rate_per_s": None if rate is None else round(rate, 2),
        "rejected_per_s": None if rejected_rate is None else round(rejected_rate, 2),
        "gaps_open": _num(c.get("gaps_open", 0.0)),
        "txn_failing": _num(c.get("txn_failing", 0.0)),
        "cpu_s": _num(c.get("cpu_s", 0.0), 1),
        "rss_mb": _num(float(c.get("rss_bytes", 0.0)) / 1e6, 1),
        "top_rejections": [[k, int(v)] for k, v in top],
    }
    return row, sample
