"""``hdmap export``'s formats: RFC 7946 GeoJSON, OSM XML 0.6, CSV (hdmap/ops/export_formats.py),
and the landmarks an export keeps (hdmap/ops/export.py, without the bus)."""

from __future__ import annotations

import csv
import io
import json
import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from hdmap.geo.area import BBox
from hdmap.geo.ellipse import CHI2_2DOF_95
from hdmap.geo.signs import CATALOG, SignCatalog, SignClass
from hdmap.ops.export import Fetched, landmarks_in
from hdmap.ops.export_formats import (
    CSV_COLUMNS,
    ExportRow,
    csv_text,
    export_rows,
    geojson,
    osm_direction,
    osm_xml,
)
from schemas import MapSnapshot
from schemas.map import MapLandmarks
from schemas.tables import (
    EXIST_CONFIRMED,
    EXIST_DOUBTFUL,
    EXIST_UNKNOWN,
    STATUS_CANDIDATE,
    STATUS_CONFIRMED,
    STATUS_RETIRED,
    Landmarks,
)
from tests.support.messages import make_map_landmarks

T0 = 1_767_225_600.0  # 2026-01-01T00:00:00Z


def landmarks(n: int = 30, seed: int = 1) -> MapLandmarks:
    """``n`` landmarks with facings (every third unknown), every status and existence state,
    ids beyond 2^53 (as real ones: the home tile in the high bits)."""
    lm = make_map_landmarks(n, seed)
    rng = np.random.default_rng(seed)
    lm.status[:] = np.arange(n) % 3  # candidate, confirmed, retired
    lm.exist_state[:] = (np.arange(n) // 3) % 3  # unknown, confirmed, doubtful
    lm.p_exist[:] = np.where(lm.exist_state > 0, rng.uniform(0.05, 1.0, n), 0.0)
    lm.first_seen[:] = np.where(np.arange(n) % 4 == 3, 0.0, T0 + rng.uniform(0, 1e5, n))
    lm.last_seen[:] = np.where(lm.first_seen > 0, lm.first_seen + 3600.0, 0.0)
    return lm


def exported(lm: MapLandmarks) -> MapLandmarks:
    """The rows an export should carry: all but the retired ones."""
    return lm.take(np.flatnonzero(lm.status != STATUS_RETIRED))


def no_nan_json(text: str) -> object:
    def refuse(name: str) -> None:
        raise AssertionError(f"{name} is not JSON (RFC 8259)")

    return json.loads(text, parse_constant=refuse)


# -- GeoJSON ------------------------------------------------------------------------------------


def test_geojson_is_an_rfc7946_feature_collection_of_every_exported_landmark() -> None:
    lm = landmarks()
    keep = exported(lm)
    doc = no_nan_json(geojson(export_rows(lm)))
    assert isinstance(doc, dict)
    assert doc["type"] == "FeatureCollection"
    assert "crs" not in doc  # RFC 7946 4: WGS84 only, no crs member
    feats = doc["features"]
    assert isinstance(feats, list) and len(feats) == len(keep)
    by_id = {int(i): k for k, i in enumerate(keep.id)}
    for f in feats:
        assert f["type"] == "Feature" and isinstance(f["properties"], dict)
        assert isinstance(f["id"], str) and f["id"] == f["properties"]["id"]  # 3.2: str or num
        g = f["geometry"]
        assert g["type"] == "Point"
        c = g["coordinates"]
        assert len(c) in (2, 3) and all(isinstance(v, float | int) for v in c)
        k = by_id[int(f["id"])]
        # 3.1.1: longitude first, then latitude (then the height above the ellipsoid)
        assert c[0] == pytest.approx(keep.lon[k], abs=1e-7)
        assert c[1] == pytest.approx(keep.lat[k], abs=1e-7)
        assert c[2] == pytest.approx(keep.h[k], abs=1e-3)
        assert -180 <= c[0] <= 180 and -90 <= c[1] <= 90
        p = f["properties"]
        ee, en, _eu, nn, _nu, _uu = keep.cov[k]
        assert p["cov_en_m2"] == [[ee, en], [en, nn]]
        assert p["traffic_sign"] == CATALOG.by_code(int(keep.sign_class[k])).osm
        assert p["class"] == CATALOG.by_code(int(keep.sign_class[k])).name
        assert p["status"] in ("candidate", "confirmed")
        assert p["passes"] == int(keep.n_passes[k])
        if keep.facing_sigma_deg[k] > 0:
            assert p["facing_deg"] == pytest.approx(keep.facing_deg[k], abs=0.01)
        else:
            assert p["facing_deg"] is None and p["facing_sigma_deg"] is None
        assert (p["p_exist"] is None) == (keep.exist_state[k] == EXIST_UNKNOWN)
        for key in ("first_seen", "last_seen"):
            assert p[key] is None or p[key].endswith("Z")
    assert len({f["id"] for f in feats}) == len(feats)


def test_ids_beyond_2_53_survive_as_strings() -> None:
    lm = landmarks(3)
    lm.id[:] = np.array([2**63 + 1, 2**56 + 3, 2**53 + 1], np.uint64)
    lm.status[:] = STATUS_CONFIRMED
    doc = no_nan_json(geojson(export_rows(lm)))
    assert sorted(int(f["id"]) for f in doc["features"]) == sorted(int(i) for i in lm.id)


# -- the uncertainty ----------------------------------------------------------------------------


def test_sigma_is_the_major_axis_one_sigma_and_isotropic_has_azimuth_0_to_180() -> None:
    lm = landmarks(1)
    lm.status[:] = STATUS_CONFIRMED
    lm.cov[:] = [[4.0, 0.0, 0.0, 1.0, 0.0, 9.0]]  # sigma E 2 m, N 1 m, U 3 m
    (r,) = export_rows(lm)
    assert r.sigma_m == pytest.approx(2.0)
    assert r.sigma_h_m == pytest.approx(3.0)
    assert r.ellipse95_azimuth_deg == pytest.approx(90.0)  # elongated east-west
    assert r.ellipse95_major_m == pytest.approx(2.0 * math.sqrt(CHI2_2DOF_95))


# -- OSM XML ------------------------------------------------------------------------------------


def test_osm_xml_parses_and_carries_every_landmark_with_its_tags() -> None:
    lm = landmarks()
    keep = exported(lm)
    bbox = (24.5, 59.9, 25.5, 60.5)
    root = ET.fromstring(osm_xml(export_rows(lm), bbox))
    assert root.tag == "osm"
    assert root.get("version") == "0.6" and root.get("generator") == "hdmap"
    b = root.find("bounds")
    assert b is not None and float(b.get("minlon")) == bbox[0] and float(b.get("maxlat")) == 60.5
    nodes = root.findall("node")
    assert len(nodes) == len(keep)
    assert len({n.get("id") for n in nodes}) == len(nodes)
    by_id = {int(i): k for k, i in enumerate(keep.id)}
    for n in nodes:
        assert int(n.get("id")) < 0 and n.get("version") == "1"
        tags = {t.get("k"): t.get("v") for t in n.findall("tag")}
        k = by_id[int(tags["hdmap:id"])]
        assert float(n.get("lat")) == pytest.approx(keep.lat[k], abs=1e-7)
        assert float(n.get("lon")) == pytest.approx(keep.lon[k], abs=1e-7)
        cls = CATALOG.by_code(int(keep.sign_class[k]))
        assert tags["traffic_sign"] == cls.osm and tags["hdmap:class"] == cls.name
        assert int(tags["hdmap:passes"]) == int(keep.n_passes[k])
        assert tags["hdmap:status"] == ("candidate", "confirmed")[int(keep.status[k])]
        assert (
            tags["hdmap:exist_state"]
            == ("unknown", "confirmed", "doubtful")[int(keep.exist_state[k])]
        )
        for key in ("sigma_m", "ellipse95_major_m", "ellipse95_minor_m", "ellipse95_azimuth_deg"):
            assert float(tags[f"hdmap:{key}"]) >= 0
        if keep.facing_sigma_deg[k] > 0:
            d = tags["direction"]
            assert d.isdigit() and 0 <= int(d) <= 359
            assert int(d) == round(float(keep.facing_deg[k])) % 360
        else:
            assert "direction" not in tags and "hdmap:direction_sigma_deg" not in tags
        if keep.first_seen[k] > 0:
            assert tags["hdmap:first_seen"].endswith("Z")
        else:
            assert "hdmap:first_seen" not in tags
    assert {int(n.find("tag[@k='hdmap:id']").get("v")) for n in nodes} == {int(i) for i in keep.id}


def test_osm_direction_is_the_way_the_sign_faces_which_is_the_side_it_is_seen_from() -> None:
    # a sign seen from the east (its cameras east of it: facing 90) faces east, toward the
    # westbound traffic that reads it: OSM direction=90, no 180-degree turn
    assert osm_direction(90.0) == 90
    assert [osm_direction(v) for v in (0.0, 0.49, 359.4, 359.6, 180.5, 270.2)] == [
        0,
        0,
        359,
        0,
        180,  # round half to even
        270,
    ]
    assert osm_direction(None) is None and osm_direction(float("nan")) is None
    for v in np.random.default_rng(3).uniform(0, 360, 1000):
        assert 0 <= osm_direction(float(v)) <= 359


def test_osm_xml_escapes_tag_values() -> None:
    odd = SignClass(300, "odd_sign", 0.6, osm='X:1"<&>')
    catalog = SignCatalog([*CATALOG, odd])
    lm = landmarks(1)
    lm.status[:] = STATUS_CONFIRMED
    lm.sign_class[:] = 300
    root = ET.fromstring(osm_xml(export_rows(lm, catalog)))
    (node,) = root.findall("node")
    assert node.find("tag[@k='traffic_sign']").get("v") == 'X:1"<&>'


def test_a_class_outside_the_catalogue_is_exported_without_traffic_sign() -> None:
    lm = landmarks(1)
    lm.status[:] = STATUS_CANDIDATE
    lm.sign_class[:] = 4321
    (r,) = export_rows(lm)
    assert r.class_name == "class_4321" and r.traffic_sign == ""
    node = ET.fromstring(osm_xml([r])).find("node")
    assert node.find("tag[@k='traffic_sign']") is None


# -- CSV ----------------------------------------------------------------------------------------


def _parse(field: str, text: str) -> object:
    typ = ExportRow.__dataclass_fields__[field].type
    if text == "":
        return None
    if "int" in str(typ):
        return int(text)
    if "float" in str(typ):
        return float(text)
    return text


def test_csv_has_a_header_and_reads_back_every_row_exactly() -> None:
    rows = export_rows(landmarks())
    text = csv_text(rows)
    reader = csv.DictReader(io.StringIO(text))
    assert tuple(reader.fieldnames or ()) == CSV_COLUMNS
    back = list(reader)
    assert len(back) == len(rows)
    for r, b in zip(rows, back, strict=True):
        for col in CSV_COLUMNS:
            if col == "osm_direction":
                assert b[col] == ("" if r.facing_deg is None else str(osm_direction(r.facing_deg)))
                continue
            field = "class_name" if col == "class" else col
            assert _parse(field, b[col]) == getattr(r, field), col


# -- what an export keeps -----------------------------------------------------------------------


def test_retired_landmarks_are_left_out_and_doubtful_ones_kept() -> None:
    lm = landmarks(9)
    rows = export_rows(lm)
    assert len(rows) == int((lm.status != STATUS_RETIRED).sum())
    states = {r.exist_state for r in rows}
    assert states == {"unknown", "confirmed", "doubtful"}
    assert [r.id for r in rows] == sorted(r.id for r in rows)
    doubtful = [r for r in rows if r.exist_state == "doubtful"]
    assert all(r.p_exist is not None for r in doubtful)
    assert EXIST_DOUBTFUL == 2 and EXIST_CONFIRMED == 1


def test_landmarks_in_keeps_the_box_and_the_newest_revision_of_each_id() -> None:
    lm = landmarks(6)
    lm.lat[:] = [60.10, 60.15, 60.15, 60.15, 60.25, 60.15]
    lm.lon[:] = [24.95] * 6
    lm.id[:] = np.array([1, 2, 3, 3, 4, 5], np.uint64)
    lm.revision[:] = np.array([1, 1, 7, 9, 1, 1], np.uint64)
    a = MapSnapshot("0" * 16, 3, lm.take(np.arange(3)))
    b = MapSnapshot("1" * 16, 5, lm.take(np.arange(3, 6)))
    got = landmarks_in(Fetched(snapshots={"a": a, "b": b}), BBox(24.9, 60.12, 25.0, 60.2))
    assert got.id.tolist() == [2, 3, 5]  # 1 is south of the box, 4 north of it
    assert int(got.revision[got.id == 3][0]) == 9
    assert len(landmarks_in(Fetched(), BBox(24.9, 60.12, 25.0, 60.2))) == 0


def test_a_landmarks_table_without_facing_or_existence_exports_as_unknown() -> None:
    lm = landmarks(2)
    plain = Landmarks(**{name: getattr(lm, name) for name, _ in Landmarks.CODEC.cols})
    plain.status[:] = STATUS_CONFIRMED
    for r in export_rows(plain):
        assert r.facing_deg is None and r.exist_state == "unknown" and r.p_exist is None
        assert r.first_seen is None
