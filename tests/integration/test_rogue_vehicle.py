"""A vehicle with consistently shifted observations (bad calibration, or on purpose) must
not move a landmark that honest vehicles have passed 20 times by more than its reported
1 sigma; the matcher lowers its weight and shows it in stats.

Real router and services (the ``stack`` fixture); one sign beside a straight road, seen by
every pass; the FLEET noise (per-pass GNSS bias 2.5 m, drift, multipath, 3 px). The same
honest passes are driven twice, without and with a rogue vehicle whose GNSS fixes are all
shifted by 5 m east and 3 m north (each rogue pass interleaved with the honest ones).
The matcher runs with its defaults: every new vehicle is on probation (its passes held
apart in the sums, hdmap/mapping/trust.py) until promoted or caught.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest

from fleetsim.fleet import Fleet, Pass
from fleetsim.noise import FLEET
from fleetsim.pipeline import FleetDriver, fleet_config_ending_now, model_for
from fleetsim.town_run import follow_town
from fleetsim.truth import match_landmarks
from fleetsim.world import World, straight_road
from hdmap.ops.quiesce import totals, wait_quiet
from hdmap.ops.stack import Stack
from hdmap.ops.status import collect
from hdmap.runtime.bus import open_session
from schemas import Landmarks
from vehicle.config import load_vehicle_model
from vehicle.mapclient import MapClient

pytestmark = pytest.mark.integration

HONEST = 3
ROGUE = "veh-0004"
SHIFT_EN = np.array([5.0, 3.0])
N_PASSES = 4 * 24


def shifted(world: World, p: Pass, shift_en: np.ndarray) -> Pass:
    f = p.fixes
    enu = world.frame.from_geodetic(f.lat, f.lon, f.h)
    enu[:, :2] += shift_en
    lat, lon, h = world.frame.to_geodetic(enu)
    return replace(p, fixes=replace(f, lat=lat, lon=lon, h=h))


def make_fleet(world: World) -> Fleet:
    model = model_for(FLEET, load_vehicle_model())
    cfg = fleet_config_ending_now(HONEST + 1, N_PASSES, route_length_m=(170.0, 180.0))
    return Fleet(world, model, FLEET, cfg, seed=7)


def passes(fleet: Fleet, with_rogue: bool) -> list[Pass]:
    world = fleet.world
    out = []
    for p in fleet.passes(N_PASSES):
        if p.vehicle_id == ROGUE:
            if with_rogue:
                out.append(shifted(world, p, SHIFT_EN))
        else:
            out.append(p)
    return out


def drive(stack: Stack, fleet: Fleet, ps: list[Pass], tmp: Path) -> tuple[Landmarks, dict]:
    tmp.mkdir(parents=True, exist_ok=True)
    stack.start_all()
    with open_session(stack.bus) as s:
        client = MapClient(s, radius_m=0.0)
        driver = FleetDriver(fleet.world, fleet, tmp)
        try:
            follow_town(client, fleet.world)
            driver.run(s, iter(ps))
            assert wait_quiet(s, timeout=120.0)
            assert client.wait_idle(20.0)
            return client.landmarks(), totals(collect(s))
        finally:
            client.close()
            driver.close()


def the_landmark(world: World, lm: Landmarks) -> int:
    m = match_landmarks(world, lm.lat, lm.lon, lm.h, lm.sign_class, gate_m=10.0)
    assert m.landmark.size == 1, m
    return int(m.landmark[0])


@dataclass
class Runs:
    world: World
    moved_en: np.ndarray
    sigma_en: np.ndarray
    matcher: dict
    solver: dict


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Runs:
    """The same honest passes without and with the rogue (two stacks, one after the other)."""
    tmp = tmp_path_factory.mktemp("rogue")
    world = straight_road()
    fleet = make_fleet(world)
    honest = passes(fleet, with_rogue=False)
    mixed = passes(fleet, with_rogue=True)
    assert len(honest) >= 20 and len(mixed) > len(honest)
    with Stack(tmp / "honest") as st:
        ref, _ = drive(st, fleet, honest, tmp / "v1")
    with Stack(tmp / "mixed") as st:
        got, stats = drive(st, fleet, mixed, tmp / "v2")
    i, j = the_landmark(world, ref), the_landmark(world, got)
    e = world.frame.from_geodetic(got.lat[j : j + 1], got.lon[j : j + 1], got.h[j : j + 1])[0]
    r = world.frame.from_geodetic(ref.lat[i : i + 1], ref.lon[i : i + 1], ref.h[i : i + 1])[0]
    sd = np.sqrt([got.cov[j, 0], got.cov[j, 3]])
    return Runs(world, e[:2] - r[:2], sd, stats["matcher"], stats["solver"])


def test_the_rogue_vehicle_is_found_out_and_weighs_less(runs):
    m = runs.matcher
    print({k: v for k, v in m.items() if k.startswith(("weight.", "vehicles_", "held"))})
    assert m["vehicles_downweighted"] >= 1
    assert m[f"weight.{ROGUE}"] < 0.5
    assert m["downweighted"] > 0 and m["shift_corrected"] > 0
    # on probation until settled: the honest ones promoted, the rogue caught
    assert m["vehicles_promoted"] == HONEST and m["vehicles_caught"] == 1
    assert m["held"] > 0


def test_the_solver_applied_the_settlements(runs):
    s = runs.solver
    assert s["vehicles_released"] >= HONEST and s["vehicles_dropped"] >= 1


def test_rogue_vehicle_moves_no_landmark_beyond_one_sigma(runs):
    """New vehicles weigh 0.05 and their passes are held until their offsets show them
    honest (promoted: the held passes count in full) or shifted (caught: taken out)."""
    print(f"moved by {runs.moved_en.round(3)} m, reported sigma {runs.sigma_en.round(3)} m")
    assert np.all(np.abs(runs.moved_en) <= runs.sigma_en), (runs.moved_en, runs.sigma_en)
