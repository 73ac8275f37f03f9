"""A town driven by a simulated fleet through the real services, scored round by round.

Used by ``hdmap demo`` (and the fleet evaluation): start a router and the four
services as processes, drive ``rounds`` x ``vehicles`` passes (deterministic), and
after each round wait until the pipeline has applied everything, then score the
map a subscribed vehicle holds against the ground truth.
"""

from __future__ import annotations

import shutil
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from fleetsim.fleet import Fleet
from fleetsim.noise import FLEET, PAPER, NoiseModel
from fleetsim.pipeline import FleetDriver, fleet_config_ending_now, model_for, town_tiles
from fleetsim.score import MapScore, score
from fleetsim.world import World, demo_town
from hdmap.geo.tiles import neighbours
from hdmap.ops.quiesce import totals, wait_quiet
from hdmap.ops.stack import Stack
from hdmap.ops.status import collect
from hdmap.runtime.bus import open_session
from schemas import Landmarks
from vehicle.config import load_vehicle_model
from vehicle.mapclient import MapClient

NOISES: dict[str, NoiseModel] = {"paper": PAPER, "fleet": FLEET}


@dataclass(frozen=True)
class TownRunConfig:
    data_dir: Path
    rounds: int = 8
    vehicles: int = 6
    noise: str = "paper"
    seed: int = 0
    town_seed: int = 0
    n_signs: int = 40
    quiet_timeout_s: float = 180.0


@dataclass
class RoundRow:
    round: int
    passes: int
    passes_per_sign: float
    observations: int
    accepted: int
    score: MapScore
    landmarks_confirmed: int
    wall_s: float

    def as_dict(self) -> dict:
        d = asdict(self)
        d.update(d.pop("score"))
        return d


@dataclass
class TownRunResult:
    world: World
    rows: list[RoundRow] = field(default_factory=list)
    landmarks: Landmarks | None = None
    passes_per_sign: np.ndarray | None = None
    services: dict = field(default_factory=dict)


def follow_town(client: MapClient, world: World) -> None:
    tiles = set(town_tiles(world))
    for tile in sorted(tiles | {n for t in tiles for n in neighbours(t)}):
        client.follow(tile)


def run_town(cfg: TownRunConfig, progress: Callable[[str], None] | None = None) -> TownRunResult:
    say = progress or (lambda msg: print(msg, file=sys.stderr, flush=True))
    noise = NOISES[cfg.noise]
    world = demo_town(cfg.town_seed, n_signs=cfg.n_signs)
    model = model_for(noise, load_vehicle_model())
    total = cfg.rounds * cfg.vehicles
    fleet = Fleet(world, model, noise, fleet_config_ending_now(cfg.vehicles, total), cfg.seed)
    if cfg.data_dir.exists():
        shutil.rmtree(cfg.data_dir)
    result = TownRunResult(world)
    t0 = time.monotonic()
    with Stack(cfg.data_dir / "var") as stack:
        say(f"starting router and services (state in {cfg.data_dir / 'var'}) ...")
        stack.start_all()
        with open_session(stack.bus) as session:
            client = MapClient(session, radius_m=0.0)
            follow_town(client, world)
            driver = FleetDriver(world, fleet, cfg.data_dir / "vehicles")
            try:
                for r in range(cfg.rounds):
                    first = r * cfg.vehicles
                    driver.run(session, fleet.passes(cfg.vehicles, first))
                    if not wait_quiet(session, timeout=cfg.quiet_timeout_s):
                        say("warning: pipeline not quiet within the timeout")
                    time.sleep(0.8)  # one publisher interval for the last delta
                    client.wait_idle(10.0)
                    lm = client.landmarks()
                    seen = driver.seen.passes
                    sc = score(world, lm, eligible=seen >= 1)
                    row = RoundRow(
                        round=r + 1,
                        passes=first + cfg.vehicles,
                        passes_per_sign=float(np.median(seen[seen > 0])) if seen.any() else 0.0,
                        observations=driver.seen.observations,
                        accepted=driver.seen.accepted,
                        score=sc,
                        landmarks_confirmed=int((lm.status == 1).sum()),
                        wall_s=time.monotonic() - t0,
                    )
                    result.rows.append(row)
                    say(
                        f"round {row.round}/{cfg.rounds}: {row.passes} passes, "
                        f"{row.passes_per_sign:.0f} per sign, {len(lm)} landmarks, "
                        f"error {sc.mean_err_m:.2f} m, coverage {sc.coverage95:.2f}, "
                        f"{row.wall_s:.0f} s"
                    )
                result.landmarks = client.landmarks()
                result.passes_per_sign = driver.seen.passes.copy()
                result.services = totals(collect(session))
            finally:
                client.close()
                driver.close()
    return result
