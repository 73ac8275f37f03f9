"""What the dashboard draws (:mod:`hdmap.ops.dashboard.geometry`): 95 % ellipse rings from
known covariances (their axes: tests/unit/test_ellipse.py), facing arrows, the GeoJSON of a
landmark, the area's tiles and the health panel's rates. References are independent:
scipy's chi-square quantile, pyproj's geodesic (WGS84) for metre offsets.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from pyproj import Geod
from scipy.stats import chi2

from hdmap.cli import build_parser
from hdmap.cli.dashboard import area_tiles
from hdmap.geo.area import BBox
from hdmap.geo.ellipse import CHI2_2DOF_95
from hdmap.ops.dashboard.geometry import (
    MAX_AREA_TILES,
    ellipse_rings,
    facing_arrow,
    landmark_features,
    metres_to_degrees,
    offset_point,
    service_row,
    status_label,
)
from schemas import Stats
from schemas.map import MapLandmarks

GEOD = Geod(ellps="WGS84")
LAT, LON = 60.17, 24.94


def landmarks(cov6, facing=(0.0,), facing_sigma=(0.0,), status=(1,), exist=(1,), passes=(5,)):
    n = len(cov6)
    return MapLandmarks(
        id=np.arange(1, n + 1, dtype=np.uint64) + np.uint64(2**60),
        sign_class=np.full(n, 7, np.uint16),
        lat=np.full(n, LAT),
        lon=np.full(n, LON),
        h=np.full(n, 3.0),
        cov=np.asarray(cov6, float),
        status=np.asarray(status, np.uint8),
        n_obs=np.full(n, 40, np.uint32),
        n_passes=np.asarray(passes, np.uint32),
        revision=np.arange(n, dtype=np.uint64) + np.uint64(3),
        updated_at=np.full(n, 1.7e9),
        source_time=np.full(n, 1.7e9),
        facing_deg=np.asarray(facing, np.float32),
        facing_sigma_deg=np.asarray(facing_sigma, np.float32),
        exist_state=np.asarray(exist, np.uint8),
        p_exist=np.full(n, 0.9, np.float32),
        first_seen=np.full(n, 1.6e9),
        last_seen=np.full(n, 1.7e9),
    )


def enu_offsets(ring: np.ndarray) -> np.ndarray:
    """(n, 2) east/north metres of [lon, lat] vertices from (LAT, LON), by pyproj."""
    az, _baz, dist = GEOD.inv(
        np.full(len(ring), LON), np.full(len(ring), LAT), ring[:, 0], ring[:, 1]
    )
    a = np.radians(az)
    return np.stack([dist * np.sin(a), dist * np.cos(a)], axis=1)


def test_ring_vertices_lie_on_the_95_percent_contour():
    c = np.array([[6.0, 2.5], [2.5, 3.0]])
    ring = ellipse_rings([LAT], [LON], np.array([[c[0, 0], c[0, 1], c[1, 1]]]), segments=48)[0]
    assert ring.shape == (49, 2) and (ring[0] == ring[-1]).all()
    d = enu_offsets(ring[:-1])
    m2 = np.einsum("ij,jk,ik->i", d, np.linalg.inv(c), d)  # squared Mahalanobis distance
    assert m2 == pytest.approx(np.full(48, chi2.ppf(0.95, 2)), rel=1e-4)
    # counter-clockwise (positive signed area in east/north)
    area = 0.5 * np.sum(d[:, 0] * np.roll(d[:, 1], -1) - np.roll(d[:, 0], -1) * d[:, 1])
    assert area == pytest.approx(
        math.pi * chi2.ppf(0.95, 2) * math.sqrt(np.linalg.det(c)), rel=1e-2
    )


def test_metre_offsets_match_the_geodesic():
    for lat, az, dist in ((0.0, 45.0, 50.0), (60.17, 123.0, 30.0), (-33.9, 300.0, 10.0)):
        lon2, lat2 = offset_point(lat, 20.0, az, dist)
        g_lon, g_lat, _ = GEOD.fwd(20.0, lat, az, dist)
        _, _, err = GEOD.inv(lon2, lat2, g_lon, g_lat)
        assert err < 1e-3  # metres
    d_lat, d_lon = metres_to_degrees(LAT, 0.0, 0.0)
    assert (d_lat, d_lon) == (0.0, 0.0)


@pytest.mark.parametrize("azimuth", [0.0, 45.0, 90.0, 180.0, 270.0, 359.0])
def test_the_arrow_points_along_the_facing_azimuth(azimuth):
    shaft, *barbs = facing_arrow(LAT, LON, azimuth, length_m=8.0, head_m=2.0)
    (lon0, lat0), (lon1, lat1) = shaft
    assert (lon0, lat0) == (LON, LAT)  # from the landmark
    fwd, _back, dist = GEOD.inv(lon0, lat0, lon1, lat1)
    assert dist == pytest.approx(8.0, rel=1e-4)
    assert (fwd - azimuth + 180.0) % 360.0 - 180.0 == pytest.approx(0.0, abs=1e-3)
    # the head's barbs start at the tip and point back, 150 degrees off either side
    assert len(barbs) == 2
    for side, (tip, end) in zip((150.0, -150.0), barbs, strict=True):
        assert tip == [lon1, lat1]
        b_az, _b, b_dist = GEOD.inv(*tip, *end)
        assert b_dist == pytest.approx(2.0, rel=1e-3)
        assert (b_az - (azimuth + side) + 180.0) % 360.0 - 180.0 == pytest.approx(0.0, abs=0.01)


def test_landmark_features():
    cov = [[4.0, 0.0, 0.0, 1.0, 0.0, 2.0], [0.0] * 6]
    lm = landmarks(
        cov, facing=(270.0, 0.0), facing_sigma=(3.0, 0.0), status=(1, 0), exist=(2, 0),
        passes=(7, 1),
    )  # fmt: skip
    feats = landmark_features(lm, arrow_m=8.0)
    first, second = (str(int(i)) for i in lm.id)
    assert first == str(2**60 + 1)  # u8 ids as strings: beyond a JavaScript number's 2^53
    kinds = {i: [f["properties"]["kind"] for f in fs] for i, fs in feats.items()}
    assert kinds == {first: ["point", "ellipse", "arrow"], second: ["point"]}
    point = feats[first][0]["properties"]
    assert point["status"] == "doubtful" and point["passes"] == 7 and point["revision"] == 3
    assert point["facing_deg"] == 270.0 and feats[second][0]["properties"]["facing_deg"] is None
    assert point["ellipse_major_m"] == pytest.approx(2.0 * math.sqrt(CHI2_2DOF_95), abs=1e-3)
    assert point["sigma_u_m"] == pytest.approx(math.sqrt(2.0), abs=1e-3)
    for f in feats[first]:
        assert f["properties"]["id"] == first and f["properties"]["status"] == "doubtful"
    arrow = feats[first][2]["geometry"]
    assert arrow["type"] == "MultiLineString"
    (_, (tip_lon, tip_lat)) = arrow["coordinates"][0]
    assert tip_lon < LON and tip_lat == pytest.approx(LAT)  # 270: West


def test_status_labels():
    assert status_label(0, 1) == "candidate"
    assert status_label(1, 0) == "located"
    assert status_label(1, 1) == "confirmed"
    assert status_label(1, 2) == "doubtful"
    assert status_label(2, 1) == "retired"


def stats(accepted: float, rejected: float, service: str = "ingest") -> Stats:
    counters = {"backlog": 3, "rejected": rejected, "uptime_s": 10.0}
    counters["accepted" if service == "ingest" else "entries_applied"] = accepted
    return Stats(service, f"{service}-1", [], 0.0, counters, {"obs.lat": 2, "upload.size": 5})


def test_service_rows_rates():
    row, first = service_row(stats(100, 4), None, now=10.0)
    assert row["rate_per_s"] is None and row["accepted"] == 100 and row["accepted_unit"] == "obs"
    assert row["top_rejections"] == [["upload.size", 5], ["obs.lat", 2]]
    row, second = service_row(stats(160, 6), first, now=12.0)
    assert (row["rate_per_s"], row["rejected_per_s"], row["backlog"]) == (30.0, 1.0, 3)
    row, _ = service_row(stats(5, 0), second, now=14.0)  # restarted: counters went back
    assert row["rate_per_s"] is None
    row, _ = service_row(stats(9, 0, "solver"), None, now=1.0)
    assert (row["accepted"], row["accepted_unit"]) == (9, "entries")


def test_the_cli_area():
    def parse(*argv: str):
        return build_parser("dashboard").parse_args(["dashboard", *argv])

    town = BBox.parse("24.938,60.169,24.941,60.171").tiles(16, MAX_AREA_TILES)
    assert area_tiles(parse("--bbox", "24.938,60.169,24.941,60.171")) == tuple(town)
    assert area_tiles(parse("--tiles", f"{town[-1]},{town[0]}", "--tiles", town[0])) == (
        town[0],
        town[-1],
    )
    assert area_tiles(parse()) == ()  # no area: the tiles that publish
    for bad in (["--tiles", "0123"], ["--bbox", "24,60,26,62"], ["--zoom", "30"]):
        with pytest.raises(ValueError):
            area_tiles(parse(*bad))
    with pytest.raises(SystemExit):  # one area option or the other
        parse("--bbox", "24.9,60.1,25,60.2", "--tiles", town[0])
