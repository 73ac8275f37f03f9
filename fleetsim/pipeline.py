"""Drive a simulated fleet through a running stack and read back what vehicles receive.

Orchestration for the demo, the integration tests and the fleet evaluation:
passes come from :class:`fleetsim.fleet.Fleet`; each vehicle is a
:class:`vehicle.agent.VehicleAgent` (geolocation, durable queue, uploads); a
:class:`vehicle.mapclient.MapClient` subscribed to the town's tiles is the
"subscribed vehicle" whose map is scored against the ground truth.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import zenoh

from fleetsim.fleet import Fleet, FleetConfig, Pass
from fleetsim.noise import NoiseModel
from fleetsim.world import World
from hdmap.geo.tiles import DEFAULT_ZOOM, quadkeys_of
from schemas.map import MapLandmarks
from vehicle.agent import VehicleAgent
from vehicle.geoloc import VehicleModel
from vehicle.mapclient import MapClient


def model_for(noise: NoiseModel, model: VehicleModel) -> VehicleModel:
    """The vehicle reports the pixel noise its detector really has."""
    return replace(model, pixel_sigma=max(noise.detector.pixel_sigma, 0.5))


def fleet_config_ending_now(
    n_vehicles: int, total_passes: int, interval_s: float = 30.0, **kw
) -> FleetConfig:
    """Pass times laid out so the last pass ends before now (ingest refuses the future)."""
    start = time.time() - (total_passes + 2) * interval_s - 600.0
    return FleetConfig(n_vehicles=n_vehicles, start_time=start, pass_interval_s=interval_s, **kw)


def town_tiles(world: World, zoom: int = DEFAULT_ZOOM) -> list[str]:
    lat, lon, _ = world.signs_geodetic()
    return sorted(set(quadkeys_of(lat, lon, zoom).tolist()))


@dataclass
class SeenCounts:
    """Per true sign: how many passes detected it (the 'number of passes' of a sign)."""

    passes: np.ndarray
    observations: int = 0
    uploaded: int = 0
    accepted: int = 0
    failed_batches: int = 0

    def add(self, world: World, p: Pass) -> None:
        ids = np.unique(p.truth.sign_id[p.truth.sign_id >= 0])
        rows = world.signs.index_of(ids)
        self.passes[rows[rows >= 0]] += 1


@dataclass
class FleetDriver:
    """Runs passes vehicle by vehicle (deterministic order) and uploads them.

    A vehicle in ``bulk`` uploads only at :meth:`flush` (a day's drives on Wi-Fi at home):
    its passes reach the services after later passes of the others, a whole batch at once.
    """

    world: World
    fleet: Fleet
    queue_dir: Path
    agents: dict[str, VehicleAgent] = field(default_factory=dict)
    bulk: frozenset[str] = frozenset()
    """Vehicles that upload only at :meth:`flush`."""
    tamper: Callable[[Pass], Pass] | None = None
    """What a pass becomes before its vehicle records it (a rogue vehicle's blind camera,
    say); None: as simulated."""
    expected_map: Callable[[], MapLandmarks] | None = None
    """The map the vehicles follow (a map client's landmarks): each pass reports the
    mapped signs it had in view and did not detect (:mod:`vehicle.absence_report`);
    None: no absences."""

    def __post_init__(self) -> None:
        self.seen = SeenCounts(np.zeros(len(self.world.signs), np.int64))

    def agent(self, vehicle_id: str) -> VehicleAgent:
        a = self.agents.get(vehicle_id)
        if a is None:
            a = self.agents[vehicle_id] = VehicleAgent(vehicle_id, self.fleet.model, self.queue_dir)
        return a

    def run(
        self,
        session: zenoh.Session,
        passes: Iterator[Pass],
        on_pass: Callable[[Pass], None] | None = None,
    ) -> None:
        for p in passes:
            if self.tamper is not None:
                p = self.tamper(p)
            a = self.agent(p.vehicle_id)
            expected = None if self.expected_map is None else self.expected_map()
            obs = a.record(p.pass_id, p.fixes, p.detections, expected_map=expected)
            self.seen.add(self.world, p)
            self.seen.observations += len(obs)
            if p.vehicle_id not in self.bulk:
                self._count(a.upload(session))
            if on_pass is not None:
                on_pass(p)

    def flush(self, session: zenoh.Session, timeout_s: float = 300.0) -> int:
        """The ``bulk`` vehicles upload what they queued (in vehicle order), each as a
        vehicle's upload loop does: again after the ``retry_after_s`` ingest answers (its
        per-vehicle rate limit holds a large upload to its rate), for at most ``timeout_s``
        in all. Returns the observations still queued."""
        deadline = time.monotonic() + timeout_s
        for v in sorted(self.bulk & self.agents.keys()):
            a = self.agents[v]
            while a.uploader.pending and time.monotonic() < deadline:
                res = a.upload(session)
                self._count(res)
                if res.permanent_fault:
                    break
                time.sleep(min(max(res.retry_after_s, 0.0), 5.0))
        return sum(self.agents[v].uploader.pending for v in self.bulk & self.agents.keys())

    def _count(self, res) -> None:
        self.seen.uploaded += res.sent
        self.seen.accepted += res.accepted
        self.seen.failed_batches += res.failed_batches

    def retry_pending(self, session: zenoh.Session) -> int:
        """Upload whatever is still queued (after an outage); what remains queued."""
        for a in self.agents.values():
            res = a.upload(session)
            self.seen.accepted += res.accepted
        return sum(a.uploader.pending for a in self.agents.values())

    def close(self) -> None:
        for a in self.agents.values():
            a.close()


def subscribed_client(session: zenoh.Session, world: World) -> MapClient:
    """A vehicle map client following every tile of the town."""
    client = MapClient(session, radius_m=0.0)
    for t in town_tiles(world):
        client.follow(t)
    return client
