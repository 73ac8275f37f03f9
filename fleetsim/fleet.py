"""A fleet of simulated vehicles driving many passes through a world.

Vehicle ``v`` (id ``veh-0001`` for v = 0 ... ) drives its passes k = 0, 1, ...;
each pass draws a random route on the world's directed road graph (no U-turns,
length within ``route_length_m``; on :func:`fleetsim.world.straight_road` the
only directed edge is northbound, so every pass drives the whole road
northbound), a uniform random speed and its sensor noise, all from the seed
``(fleet seed, v, k)``: any pass can be regenerated alone, in any order.

Pass ``k`` of vehicle ``v`` starts at ``start_time + (k * n_vehicles + v) *
pass_interval_s``; :meth:`Fleet.passes` yields them in that (time) order. Given a
:class:`fleetsim.changes.ChangeSchedule`, a pass sees the signs standing at its start
time (:meth:`Fleet.world_at`); without one (or before any change), the world's own.

>>> from fleetsim.world import straight_road
>>> from vehicle.config import load_vehicle_model
>>> fleet = Fleet(straight_road(), load_vehicle_model(), FLEET, FleetConfig(n_vehicles=2))
>>> [(p.vehicle_id, p.pass_id, p.route) for p in fleet.passes(3)]
[('veh-0001', 0, (0, 1)), ('veh-0002', 0, (0, 1)), ('veh-0001', 1, (0, 1))]
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from fleetsim.changes import ChangeSchedule
from fleetsim.drive import DriveParams, DriveTruth, simulate_pass
from fleetsim.noise import FLEET, NoiseModel
from fleetsim.route import Path, random_route
from fleetsim.world import World
from vehicle.geoloc import Detections, GnssFixes, VehicleModel


def vehicle_id(index: int) -> str:
    """``veh-0001`` for index 0."""
    return f"veh-{index + 1:04d}"


@dataclass(frozen=True)
class FleetConfig:
    n_vehicles: int = 10
    speed_range_mps: tuple[float, float] = (8.0, 14.0)
    frame_rate_hz: float = DriveParams.frame_rate_hz
    """Camera frames per second (:class:`fleetsim.drive.DriveParams`, like the next ones)."""
    max_range_m: float = 60.0
    route_length_m: tuple[float, float] = (400.0, 900.0)
    start_time: float = 1.7e9
    """Unix time of the first pass, s."""
    pass_interval_s: float = 60.0
    """Time between consecutive pass starts across the fleet, s."""
    gnss_rate_hz: float = DriveParams.gnss_rate_hz
    gnss_jitter_s: float = DriveParams.gnss_jitter_s
    gnss_miss_prob: float = DriveParams.gnss_miss_prob
    fix_per_frame: bool = DriveParams.fix_per_frame
    """The older timing: a fix at every camera frame."""

    def __post_init__(self) -> None:
        if self.n_vehicles < 1:
            raise ValueError("FleetConfig.n_vehicles must be >= 1")
        lo, hi = self.speed_range_mps
        if not 0.0 < lo <= hi:
            raise ValueError("FleetConfig.speed_range_mps must satisfy 0 < lo <= hi")


@dataclass(frozen=True)
class Pass:
    """One pass of one vehicle: what it recorded and what really happened."""

    vehicle_id: str
    vehicle_index: int
    pass_id: int
    """Per-vehicle pass counter k."""
    start_time: float
    route: tuple[int, ...]
    path: Path
    speed_mps: float
    fixes: GnssFixes
    detections: Detections
    truth: DriveTruth


class Fleet:
    """Generates passes deterministically per (seed, vehicle, pass)."""

    def __init__(
        self,
        world: World,
        model: VehicleModel,
        noise: NoiseModel = FLEET,
        config: FleetConfig | None = None,
        seed: int = 0,
        schedule: ChangeSchedule | None = None,
    ):
        if schedule is not None:
            schedule.check(world.signs)
        self.world = world
        self.model = model
        self.noise = noise
        self.config = config or FleetConfig()
        self.seed = int(seed)
        self.schedule = schedule

    @property
    def vehicle_ids(self) -> list[str]:
        return [vehicle_id(v) for v in range(self.config.n_vehicles)]

    def start_time(self, vehicle: int, k: int) -> float:
        c = self.config
        return c.start_time + (k * c.n_vehicles + vehicle) * c.pass_interval_s

    def world_at(self, t: float) -> World:
        """The world with the signs standing at time ``t`` (the world itself when no
        scheduled change is in effect)."""
        return self.world if self.schedule is None else self.schedule.world_at(self.world, t)

    def drive(self, vehicle: int, k: int) -> Pass:
        """Pass ``k`` of vehicle index ``vehicle``."""
        if not 0 <= vehicle < self.config.n_vehicles or k < 0:
            raise ValueError(f"no pass ({vehicle}, {k}) in this fleet")
        c = self.config
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, vehicle, k]))
        rng_route, rng_drive = rng.spawn(2)
        min_len = float(rng_route.uniform(*c.route_length_m))
        route = random_route(self.world, rng_route, min_len)
        speed = float(rng_route.uniform(*c.speed_range_mps))
        path = Path.along(self.world, route)
        params = DriveParams(
            speed_mps=speed,
            frame_rate_hz=c.frame_rate_hz,
            max_range_m=c.max_range_m,
            gnss_rate_hz=c.gnss_rate_hz,
            gnss_jitter_s=c.gnss_jitter_s,
            gnss_miss_prob=c.gnss_miss_prob,
            fix_per_frame=c.fix_per_frame,
        )
        t0 = self.start_time(vehicle, k)
        fixes, det, truth = simulate_pass(
            self.world_at(t0), path, self.model, self.noise, rng_drive, t0=t0, params=params
        )
        return Pass(
            vehicle_id=vehicle_id(vehicle),
            vehicle_index=vehicle,
            pass_id=k,
            start_time=t0,
            route=tuple(route),
            path=path,
            speed_mps=speed,
            fixes=fixes,
            detections=det,
            truth=truth,
        )

    def passes(self, n_passes: int, first: int = 0) -> Iterator[Pass]:
        """Passes number ``first`` .. ``first + n_passes - 1`` of the fleet, in start order."""
        n = self.config.n_vehicles
        for g in range(first, first + n_passes):
            yield self.drive(g % n, g // n)

    def find_pass(
        self, accept: Callable[[Pass], bool], vehicle: int = 0, max_tries: int = 50
    ) -> Pass:
        """The first pass k = 0, 1, ... of ``vehicle`` that ``accept`` takes (else the last)."""
        p = self.drive(vehicle, 0)
        for k in range(1, max_tries):
            if accept(p):
                return p
            p = self.drive(vehicle, k)
        return p


def distinct_signs_seen(p: Pass) -> int:
    """How many different true signs a pass detected."""
    ids = p.truth.sign_id
    return int(np.unique(ids[ids >= 0]).size)
