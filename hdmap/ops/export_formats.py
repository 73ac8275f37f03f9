"""The published map as GeoJSON, OSM XML or CSV: pure formatting, no I/O (``hdmap export``).

One :class:`ExportRow` per landmark (:func:`export_rows`) carries what every format writes:

- the position: WGS84 longitude and latitude (degrees), ``h_m`` the ellipsoidal height (m;
  not OSM's ``ele``, which is above sea level);
- the horizontal uncertainty: the 2x2 east/north block of the landmark's ENU covariance
  (m^2: ``cov_ee``, ``cov_en``, ``cov_nn``), ``sigma_m`` the 1-sigma along its major axis,
  and the 95 % ellipse (:mod:`hdmap.geo.ellipse`): semi-axes ``sqrt(k^2 lambda)`` with
  ``k^2 = -2 ln 0.05 = 5.991`` (the chi-square(2) 0.95 quantile) and the major axis's
  azimuth, degrees clockwise from North in [0, 180); ``sigma_h_m`` the vertical 1-sigma;
- the facing: ``facing_deg``, the azimuth (degrees clockwise from true North) the sign is
  *seen from*, i.e. from the sign toward the cameras that saw it, and its sigma; None where
  unknown (:class:`schemas.map.MapLandmarks`);
- ``status`` (candidate, confirmed), ``exist_state`` (unknown, confirmed, doubtful),
  ``p_exist`` (None when the state is unknown), ``first_seen`` / ``last_seen`` (event time,
  ISO 8601 UTC; None when unknown), ``passes`` and ``observations``.

**What is left out.** A revoked landmark (a sign the map took down) is removed from the map
(a removal, a tombstone in the publisher's deltas): no snapshot holds it, so no export does;
a row with status ``retired`` that would still be there is skipped too. Doubtful landmarks
(``exist_state`` doubtful) are exported, with that state.

**Formats.**

- ``geojson``: an RFC 7946 FeatureCollection (no ``crs`` member: WGS84 is implied),
  one Point feature per landmark, coordinates ``[lon, lat, h]`` (RFC 7946 3.1.1: the
  third is the height above the WGS84 ellipsoid, as ``h_m`` is), rounded to 1e-7 degree
  (1 cm); the feature ``id`` and ``properties.id`` are strings (landmark ids need 56 bits,
  more than a JSON number keeps exactly in JavaScript); no NaN anywhere (``null``).
- ``osm``: OSM XML 0.6 that JOSM opens as new data: ``<osm version="0.6"
  generator="hdmap" upload="false">`` (``upload="false"``: JOSM warns before uploading; a
  machine-made map is no OSM edit without review under the import guidelines), the
  ``<bounds>`` of the export, one ``<node id="-1" lat lon version="1">`` per landmark
  (negative ids: objects new to OSM), tagged ``traffic_sign`` (the class's OSM value, e.g.
  ``FI:361[30]``), ``direction`` and ``hdmap:*`` tags (:func:`osm_tags`).
- ``csv``: a header row (:data:`CSV_COLUMNS`), then one row per landmark; empty cells for
  unknowns.

**OSM's direction.** On a traffic sign mapped as a node of its own, ``direction=<0-359>``
is the compass direction the sign *faces*, degrees clockwise from North: the way its front
points, toward the traffic that reads it, so opposite to that traffic's direction of travel
(OSM wiki, Key:direction: "the degrees ... in which the feature faces", "Stop sign facing
north-north-west: direction=NNW"; iD draws the view cone that way). Our facing is the
azimuth from the sign toward the cameras that saw it, the same side: ``direction`` is the
facing rounded to a whole degree, 360 read as 0, with no 180-degree turn
(:func:`osm_direction`). It is where the sign was seen from, which is 5-70 degrees off the
panel's normal for a roadside sign: ``hdmap:direction_sigma_deg`` gives its sigma.

>>> osm_direction(359.6), osm_direction(0.4), osm_direction(None)
(0, 0, None)
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from xml.sax.saxutils import quoteattr

import numpy as np

from hdmap.geo.ellipse import CHI2_2DOF_95, ellipse_axes, horizontal_cov
from hdmap.geo.signs import CATALOG, SignCatalog, UnknownSignClass
from schemas.map import MapLandmarks, as_map_landmarks
from schemas.tables import (
    EXIST_CONFIRMED,
    EXIST_DOUBTFUL,
    STATUS_CANDIDATE,
    STATUS_CONFIRMED,
    STATUS_RETIRED,
    Landmarks,
)

FORMATS = ("geojson", "osm", "csv")
GENERATOR = "hdmap"
COORD_DECIMALS = 7
"""Degrees are written with 7 decimals: 1e-7 degree is 1.1 cm (OSM's own precision)."""

STATUS_NAMES = {STATUS_CANDIDATE: "candidate", STATUS_CONFIRMED: "confirmed"}
EXIST_NAMES = {EXIST_CONFIRMED: "confirmed", EXIST_DOUBTFUL: "doubtful"}

CSV_COLUMNS = (
    "id",
    "class",
    "traffic_sign",
    "lat",
    "lon",
    "h_m",
    "cov_ee_m2",
    "cov_en_m2",
    "cov_nn_m2",
    "sigma_m",
    "ellipse95_major_m",
    "ellipse95_minor_m",
    "ellipse95_azimuth_deg",
    "sigma_h_m",
    "facing_deg",
    "facing_sigma_deg",
    "osm_direction",
    "status",
    "exist_state",
    "p_exist",
    "first_seen",
    "last_seen",
    "passes",
    "observations",
    "revision",
)
"""The CSV header, in order (each an :class:`ExportRow` field but ``osm_direction``)."""


@dataclass(frozen=True)
class ExportRow:
    """One landmark as every format writes it (see the module doc for each field)."""

    id: int
    sign_class: int
    class_name: str
    traffic_sign: str
    lat: float
    lon: float
    h_m: float
    cov_ee_m2: float
    cov_en_m2: float
    cov_nn_m2: float
    sigma_m: float
    ellipse95_major_m: float
    ellipse95_minor_m: float
    ellipse95_azimuth_deg: float
    sigma_h_m: float
    facing_deg: float | None
    facing_sigma_deg: float | None
    status: str
    exist_state: str
    p_exist: float | None
    first_seen: str | None
    last_seen: str | None
    passes: int
    observations: int
    revision: int


def iso_utc(t: float) -> str | None:
    """Unix seconds as ISO 8601 UTC with milliseconds and ``Z``; None for 0 (unknown).

    >>> iso_utc(1767225600.25), iso_utc(0.0)
    ('2026-01-01T00:00:00.250Z', None)
    """
    if not (math.isfinite(t) and t > 0):
        return None
    when = datetime.fromtimestamp(t, tz=UTC).isoformat(timespec="milliseconds")
    return when.replace("+00:00", "Z")


def osm_direction(facing_deg: float | None) -> int | None:
    """OSM's ``direction`` of a sign node (the way its front faces, 0-359) from our facing
    (the azimuth it is seen from: the same side, see the module doc); None if unknown."""
    if facing_deg is None or not math.isfinite(facing_deg):
        return None
    return round(facing_deg) % 360


def _class_names(code: int, catalog: SignCatalog) -> tuple[str, str]:
    try:
        c = catalog.by_code(code)
    except UnknownSignClass:
        return f"class_{code}", ""
    return c.name, c.osm


def export_rows(lm: Landmarks, catalog: SignCatalog = CATALOG) -> list[ExportRow]:
    """The exported rows of ``lm`` (a snapshot's landmarks), sorted by id; rows with status
    retired are left out (revoked ones are not in a snapshot at all)."""
    m: MapLandmarks = as_map_landmarks(lm)
    az, az_sigma, known = m.facing()
    cov_en = horizontal_cov(m.cov)
    major, minor, major_az = ellipse_axes(cov_en, 0.95)
    sigma = major / math.sqrt(CHI2_2DOF_95)
    out = []
    for i in np.argsort(m.id, kind="stable"):
        status = int(m.status[i])
        if status == STATUS_RETIRED:
            continue
        ee, en, nn = (float(v) for v in cov_en[i])
        name, osm = _class_names(int(m.sign_class[i]), catalog)
        state = int(m.exist_state[i])
        out.append(
            ExportRow(
                id=int(m.id[i]),
                sign_class=int(m.sign_class[i]),
                class_name=name,
                traffic_sign=osm,
                lat=float(m.lat[i]),
                lon=float(m.lon[i]),
                h_m=float(m.h[i]),
                cov_ee_m2=ee,
                cov_en_m2=en,
                cov_nn_m2=nn,
                sigma_m=float(sigma[i]),
                ellipse95_major_m=float(major[i]),
                ellipse95_minor_m=float(minor[i]),
                ellipse95_azimuth_deg=float(major_az[i]),
                sigma_h_m=math.sqrt(max(float(m.cov[i, 5]), 0.0)),
                facing_deg=float(az[i]) if known[i] else None,
                facing_sigma_deg=float(az_sigma[i]) if known[i] else None,
                status=STATUS_NAMES.get(status, str(status)),
                exist_state=EXIST_NAMES.get(state, "unknown"),
                p_exist=float(m.p_exist[i]) if state in EXIST_NAMES else None,
                first_seen=iso_utc(float(m.first_seen[i])),
                last_seen=iso_utc(float(m.last_seen[i])),
                passes=int(m.n_passes[i]),
                observations=int(m.n_obs[i]),
                revision=int(m.revision[i]),
            )
        )
    return out


def _r(v: float | None, nd: int) -> float | None:
    return None if v is None else round(v, nd)


# -- GeoJSON ------------------------------------------------------------------------------------


def geojson(rows: Sequence[ExportRow]) -> str:
    """An RFC 7946 FeatureCollection of the rows (see the module doc); ``allow_nan=False``
    guarantees valid JSON.

    >>> doc = json.loads(geojson([]))
    >>> doc["type"], doc["features"]
    ('FeatureCollection', [])
    """
    feats = []
    for r in rows:
        props = {
            "id": str(r.id),
            "class": r.class_name,
            "sign_class": r.sign_class,
            "traffic_sign": r.traffic_sign or None,
            "h_m": round(r.h_m, 3),
            "cov_en_m2": [[r.cov_ee_m2, r.cov_en_m2], [r.cov_en_m2, r.cov_nn_m2]],
            "sigma_m": round(r.sigma_m, 4),
            "ellipse95": {
                "major_m": round(r.ellipse95_major_m, 4),
                "minor_m": round(r.ellipse95_minor_m, 4),
                "azimuth_deg": round(r.ellipse95_azimuth_deg, 2),
            },
            "sigma_h_m": round(r.sigma_h_m, 4),
            "facing_deg": _r(r.facing_deg, 2),
            "facing_sigma_deg": _r(r.facing_sigma_deg, 2),
            "status": r.status,
            "exist_state": r.exist_state,
            "p_exist": _r(r.p_exist, 4),
            "first_seen": r.first_seen,
            "last_seen": r.last_seen,
            "passes": r.passes,
            "observations": r.observations,
            "revision": str(r.revision),
        }
        coords = [round(r.lon, COORD_DECIMALS), round(r.lat, COORD_DECIMALS), round(r.h_m, 3)]
        feats.append(
            {
                "type": "Feature",
                "id": str(r.id),
                "geometry": {"type": "Point", "coordinates": coords},
                "properties": props,
            }
        )
    return json.dumps({"type": "FeatureCollection", "features": feats}, allow_nan=False) + "\n"


# -- OSM XML ------------------------------------------------------------------------------------


def _num(v: float, nd: int) -> str:
    """A tag value: ``v`` rounded to ``nd`` decimals, without trailing zeros."""
    text = f"{v:.{nd}f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def osm_tags(r: ExportRow) -> dict[str, str]:
    """The tags of a landmark's node: ``traffic_sign`` (when its class has an OSM value),
    ``direction`` (when the facing is known) and the ``hdmap:*`` tags: id, class, status,
    exist_state, p_exist, passes, observations, sigma_m, ellipse95_major_m,
    ellipse95_minor_m, ellipse95_azimuth_deg, height_m (ellipsoidal), sigma_h_m,
    direction_sigma_deg, first_seen, last_seen."""
    tags: dict[str, str] = {}
    if r.traffic_sign:
        tags["traffic_sign"] = r.traffic_sign
    if (d := osm_direction(r.facing_deg)) is not None:
        tags["direction"] = str(d)
    tags["hdmap:id"] = str(r.id)
    tags["hdmap:class"] = r.class_name
    tags["hdmap:status"] = r.status
    tags["hdmap:exist_state"] = r.exist_state
    if r.p_exist is not None:
        tags["hdmap:p_exist"] = _num(r.p_exist, 3)
    tags["hdmap:passes"] = str(r.passes)
    tags["hdmap:observations"] = str(r.observations)
    tags["hdmap:sigma_m"] = _num(r.sigma_m, 2)
    tags["hdmap:ellipse95_major_m"] = _num(r.ellipse95_major_m, 2)
    tags["hdmap:ellipse95_minor_m"] = _num(r.ellipse95_minor_m, 2)
    tags["hdmap:ellipse95_azimuth_deg"] = _num(r.ellipse95_azimuth_deg, 1)
    tags["hdmap:height_m"] = _num(r.h_m, 2)
    tags["hdmap:sigma_h_m"] = _num(r.sigma_h_m, 2)
    if r.facing_sigma_deg is not None:
        tags["hdmap:direction_sigma_deg"] = _num(r.facing_sigma_deg, 1)
    if r.first_seen:
        tags["hdmap:first_seen"] = r.first_seen
    if r.last_seen:
        tags["hdmap:last_seen"] = r.last_seen
    return tags


def osm_xml(
    rows: Sequence[ExportRow], bbox: tuple[float, float, float, float] | None = None
) -> str:
    """OSM XML 0.6 of the rows (see the module doc): node ids -1, -2, ... in row order;
    ``bbox`` (min lon, min lat, max lon, max lat) as ``<bounds>``.

    >>> print(osm_xml([]), end="")  # doctest: +ELLIPSIS
    <?xml version="1.0" encoding="UTF-8"?>
    <!-- ... -->
    <osm version="0.6" generator="hdmap" upload="false">
    </osm>
    """
    out = io.StringIO()
    out.write('<?xml version="1.0" encoding="UTF-8"?>\n')
    out.write(
        "<!-- hdmap export: traffic signs of a crowdsourced map, for review before any "
        "upload. direction = the way the sign faces (toward the traffic that reads it), "
        "degrees clockwise from North; hdmap:* tags give the uncertainty, the pass count "
        "and the existence. -->\n"
    )
    out.write(f'<osm version="0.6" generator="{GENERATOR}" upload="false">\n')
    if bbox is not None:
        w, s, e, n = bbox
        out.write(
            f'  <bounds minlat="{s:.7f}" minlon="{w:.7f}" maxlat="{n:.7f}" maxlon="{e:.7f}"/>\n'
        )
    for k, r in enumerate(rows, start=1):
        out.write(
            f'  <node id="-{k}" lat="{r.lat:.{COORD_DECIMALS}f}" '
            f'lon="{r.lon:.{COORD_DECIMALS}f}" version="1">\n'
        )
        for key, value in osm_tags(r).items():
            out.write(f"    <tag k={quoteattr(key)} v={quoteattr(value)}/>\n")
        out.write("  </node>\n")
    out.write("</osm>\n")
    return out.getvalue()


# -- CSV ----------------------------------------------------------------------------------------


def _cell(v: object) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return repr(v)  # round-trips exactly
    return str(v)


def csv_text(rows: Sequence[ExportRow]) -> str:
    """A header row (:data:`CSV_COLUMNS`) and one row per landmark; empty cells for
    unknowns, floats written so that they read back exactly.

    >>> csv_text([]).strip() == ",".join(CSV_COLUMNS)
    True
    """
    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for r in rows:
        d = asdict(r)
        d["class"] = d.pop("class_name")
        d["osm_direction"] = osm_direction(r.facing_deg)
        w.writerow([_cell(d[c]) for c in CSV_COLUMNS])
    return out.getvalue()


def render(
    fmt: str, rows: Sequence[ExportRow], bbox: tuple[float, float, float, float] | None = None
) -> str:
    """The rows in ``fmt`` (one of :data:`FORMATS`)."""
    if fmt == "geojson":
        return geojson(rows)
    if fmt == "osm":
        return osm_xml(rows, bbox)
    if fmt == "csv":
        return csv_text(rows)
    raise ValueError(f"unknown export format {fmt!r} (known: {', '.join(FORMATS)})")
