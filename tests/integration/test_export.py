"""``hdmap export`` against a real stack: a small simulated fleet is uploaded, then the
command runs as its own process for each format and must carry every landmark the
publisher's snapshots hold in the box.

Router and services are separate processes on 127.0.0.1 (free port, SQLite under
tmp_path), stopped by the ``stack`` fixture also on failure; the export subprocesses are
killed at their timeout; every wait is bounded."""

from __future__ import annotations

import csv
import io
import json
import subprocess
import sys
import time
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from fleetsim.fleet import Fleet
from fleetsim.noise import FLEET
from fleetsim.pipeline import FleetDriver, fleet_config_ending_now, model_for, town_tiles
from fleetsim.world import demo_town
from hdmap.geo.signs import CATALOG
from hdmap.geo.tiles import neighbours, tile_bounds
from hdmap.ops.quiesce import totals, wait_quiet
from hdmap.ops.status import collect
from hdmap.runtime.bus import open_session, query
from schemas import MapSnapshot, keys
from schemas.map import MapLandmarks
from tests.support.processes import REPO
from vehicle.config import load_vehicle_model

pytestmark = pytest.mark.integration

PASSES = 24
EXPORT_TIMEOUT_S = 120.0


def published(session, tiles: list[str]) -> MapLandmarks:
    """Every landmark of the publisher's snapshots of ``tiles`` (asked for under the client
    id ``probe``, not the export's)."""
    parts = []
    for tile in tiles:
        replies = [ok for _k, ok, _e in query(session, keys.map_snapshot_for("probe", tile))]
        assert len(replies) == 1 and replies[0] is not None, tile
        parts.append(MapSnapshot.from_bytes(replies[0]).landmarks)
    return MapLandmarks.concat(parts)


def export(listen: str, fmt: str, bbox: str, out) -> subprocess.CompletedProcess:
    argv = [sys.executable, "-m", "hdmap.cli", "export", "--connect", listen, "--format", fmt]
    argv += ["--bbox", bbox, "--out", str(out), "--no-progress"]
    return subprocess.run(
        argv, cwd=REPO, capture_output=True, text=True, timeout=EXPORT_TIMEOUT_S, check=False
    )


def test_export_carries_every_landmark_of_the_snapshots_in_each_format(stack, tmp_path) -> None:
    world = demo_town(0, n_signs=12, n_blocks=2)
    model = model_for(FLEET, load_vehicle_model())
    cfg = fleet_config_ending_now(4, PASSES, route_length_m=(300.0, 500.0))
    fl = Fleet(world, model, FLEET, cfg, seed=0)
    stack.start_all()
    core = town_tiles(world)
    tiles = sorted(set(core) | {n for t in core for n in neighbours(t)})
    b = [tile_bounds(t) for t in tiles]
    box = (min(x.west for x in b), min(x.south for x in b), max(x.east for x in b))
    box += (max(x.north for x in b),)
    bbox = ",".join(f"{v:.9f}" for v in box)
    with open_session(stack.bus) as s:
        driver = FleetDriver(world, fl, tmp_path / "vehicles")
        try:
            driver.run(s, fl.passes(PASSES))
        finally:
            driver.close()
        assert driver.seen.failed_batches == 0
        assert wait_quiet(s, timeout=120.0), totals(collect(s))
        time.sleep(1.0)  # the publisher's last coalescing interval (0.1 s) and flush
        ref = published(s, tiles)
    inside = (ref.lon >= box[0]) & (ref.lon <= box[2]) & (ref.lat >= box[1]) & (ref.lat <= box[3])
    ref = ref.take(np.flatnonzero(inside))
    want = {int(i) for i in ref.id}
    assert len(want) >= 3, len(want)
    row_of = {int(i): k for k, i in enumerate(ref.id)}

    runs = {fmt: export(stack.listen, fmt, bbox, tmp_path / f"map.{fmt}") for fmt in
            ("osm", "geojson", "csv")}  # fmt: skip
    for fmt, r in runs.items():
        assert r.returncode == 0, (fmt, r.stderr)
        assert f"{len(want)} landmarks from" in r.stderr, r.stderr

    root = ET.parse(tmp_path / "map.osm").getroot()
    assert root.tag == "osm" and root.get("version") == "0.6" and root.get("generator") == "hdmap"
    nodes = root.findall("node")
    assert len(nodes) == len(want)
    got = set()
    for n in nodes:
        assert int(n.get("id")) < 0 and n.get("version") == "1"
        tags = {t.get("k"): t.get("v") for t in n.findall("tag")}
        lid = int(tags["hdmap:id"])
        got.add(lid)
        k = row_of[lid]
        assert tags["traffic_sign"] == CATALOG.by_code(int(ref.sign_class[k])).osm
        assert int(tags["hdmap:passes"]) == int(ref.n_passes[k])
        assert float(n.get("lat")) == pytest.approx(float(ref.lat[k]), abs=1e-7)
        assert float(n.get("lon")) == pytest.approx(float(ref.lon[k]), abs=1e-7)
        if ref.facing_sigma_deg[k] > 0:
            assert int(tags["direction"]) == round(float(ref.facing_deg[k])) % 360
        assert float(tags["hdmap:sigma_m"]) > 0
    assert got == want

    doc = json.loads((tmp_path / "map.geojson").read_text())
    assert doc["type"] == "FeatureCollection" and "crs" not in doc
    assert {int(f["id"]) for f in doc["features"]} == want
    rows = list(csv.DictReader(io.StringIO((tmp_path / "map.csv").read_text())))
    assert {int(r["id"]) for r in rows} == want

    with open_session(stack.bus) as s:  # the map did not change under the exports
        again = published(s, tiles)
    assert {int(i) for i in again.id[np.isin(again.id, ref.id)]} == want


def test_export_refuses_a_bad_box_before_joining_the_bus(tmp_path) -> None:
    r = export("tcp/127.0.0.1:9", "csv", "24.9,60.1,24.8", tmp_path / "x.csv")
    assert r.returncode == 2 and "--bbox" in r.stderr
    assert not (tmp_path / "x.csv").exists()
