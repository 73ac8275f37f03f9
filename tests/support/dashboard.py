"""Builders of the ``hdmap dashboard`` tests: a small driven town, the publisher's map,
the dashboard as a subprocess."""

from __future__ import annotations

import json
import sys
import urllib.request

from fleetsim.fleet import Fleet
from fleetsim.noise import FLEET
from fleetsim.pipeline import fleet_config_ending_now, model_for, town_tiles
from fleetsim.world import World, demo_town
from hdmap.geo.tiles import neighbours
from hdmap.runtime.bus import query
from schemas import MapSnapshot, keys
from vehicle.config import load_vehicle_model


def town(n_vehicles: int, n_passes: int) -> tuple[World, Fleet, list[str]]:
    """The 16-sign demo town, a fleet over it, and its tiles with their neighbours."""
    world = demo_town(0, n_signs=16, n_blocks=2)
    model = model_for(FLEET, load_vehicle_model())
    cfg = fleet_config_ending_now(n_vehicles, n_passes, route_length_m=(300.0, 500.0))
    tiles = set(town_tiles(world))
    tiles |= {n for t in tiles for n in neighbours(t)}
    return world, Fleet(world, model, FLEET, cfg, seed=0), sorted(tiles)


def publisher_map(session, tiles: list[str]) -> dict[str, tuple[int, int]]:
    """id -> (revision, passes) of the landmarks the publisher serves on ``tiles``."""
    out: dict[str, tuple[int, int]] = {}
    for tile in tiles:
        for _k, ok, _err in query(session, keys.map_snapshot(tile), timeout=5.0):
            if ok is None:
                continue
            lm = MapSnapshot.from_bytes(ok).landmarks
            for i, rev, n in zip(lm.id, lm.revision, lm.n_passes, strict=True):
                if int(rev) >= out.get(str(int(i)), (-1, 0))[0]:
                    out[str(int(i))] = (int(rev), int(n))
    return out


def dashboard_argv(endpoint: str, port: int, *extra: str) -> list[str]:
    return [
        sys.executable, "-m", "hdmap.cli", "dashboard", "--connect", endpoint,
        "--listen", f"127.0.0.1:{port}", "--stats-interval", "1", *extra,
    ]  # fmt: skip


def http_json(url: str, headers: dict[str, str] | None = None) -> object:
    req = urllib.request.Request(url, headers=headers or {})
    with urllib.request.urlopen(req, timeout=5.0) as r:
        return json.loads(r.read())


def served_landmarks(url: str) -> dict[str, tuple[int, int]]:
    """id -> (revision, passes) of the dashboard's ``/api/landmarks``."""
    fc = http_json(url + "api/landmarks")
    return {
        f["properties"]["id"]: (f["properties"]["revision"], f["properties"]["passes"])
        for f in fc["features"]  # type: ignore[index]
        if f["properties"]["kind"] == "point"
    }
