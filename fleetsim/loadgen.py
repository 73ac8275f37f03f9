"""Load generation against a running stack: many vehicles, paced uploads, subscribed readers.

Observations are simulated once (a pool of real passes through a town, geolocated
like on a vehicle); during the run each vehicle replays pool passes with fresh
observation ids, pass ids and capture times, so the matcher and solver do real
work at a rate the generator itself can sustain. Each vehicle has its own upload
stream (its own key, ids and batches); batches are paced to the target rate.

Latency is traced by the stages: ``Landmarks.source_time`` is when ingest
received the newest observation folded into an update; a subscribed reader
measures ``arrival - source_time`` for every landmark in every delta.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np
import zenoh

from fleetsim.fleet import Fleet, FleetConfig
from fleetsim.noise import FLEET
from fleetsim.pipeline import model_for
from fleetsim.world import World, demo_town
from hdmap import keys
from hdmap.bus import query
from hdmap.geoloc import geolocate
from hdmap.tiles import neighbours, quadkeys_of
from schemas import DecodeError, MapDelta, ObservationBatch, Observations, UploadAck
from vehicle.agent import to_observations
from vehicle.config import load_vehicle_model


@dataclass(frozen=True)
class LoadConfig:
    vehicles: int = 20
    rate: float = 5000.0
    """Target observations per second over the whole fleet."""
    duration_s: float = 30.0
    batch: int = 500
    """Observations per upload batch (a vehicle uploading every few seconds)."""
    subscribers: int = 2
    pool_passes: int = 60
    n_signs: int = 120
    n_blocks: int = 6
    seed: int = 0


@dataclass
class Counters:
    """Shared between threads; every update under ``lock``."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    sent: int = 0
    accepted: int = 0
    duplicates: int = 0
    rejected: int = 0
    failed: int = 0
    batches: int = 0
    deltas: int = 0
    delta_landmarks: int = 0
    latencies: deque = field(default_factory=lambda: deque(maxlen=2_000_000))

    def add(self, **kw: int) -> None:
        with self.lock:
            for k, v in kw.items():
                setattr(self, k, getattr(self, k) + v)


def build_pool(cfg: LoadConfig) -> tuple[World, list[Observations]]:
    """Simulated, geolocated passes to replay (FLEET noise)."""
    world = demo_town(cfg.seed, n_signs=cfg.n_signs, n_blocks=cfg.n_blocks)
    model = model_for(FLEET, load_vehicle_model())
    fleet = Fleet(
        world, model, FLEET, FleetConfig(n_vehicles=1, start_time=time.time()), seed=cfg.seed
    )
    pool = []
    for k in range(cfg.pool_passes):
        p = fleet.drive(0, k)
        lines = geolocate(p.fixes, p.detections, model)
        if len(lines):
            pool.append(to_observations(lines, np.zeros(len(lines), np.uint64)))
    return world, pool


def town_tiles_with_halo(world: World) -> list[str]:
    lat, lon, _ = world.signs_geodetic()
    tiles = set(quadkeys_of(lat, lon).tolist())
    return sorted(tiles | {n for t in tiles for n in neighbours(t)})


class Vehicle(threading.Thread):
    """One vehicle's paced upload stream (pool passes replayed with fresh ids)."""

    def __init__(
        self,
        index: int,
        session: zenoh.Session,
        pool: list[Observations],
        cfg: LoadConfig,
        counters: Counters,
        stop: threading.Event,
    ):
        super().__init__(name=f"veh-{index}", daemon=True)
        self.vehicle_id = f"load-{index:05d}"
        self.index, self.session, self.pool, self.cfg = index, session, pool, cfg
        self.counters, self.stop = counters, stop
        self.period = cfg.batch / (cfg.rate / cfg.vehicles)

    def batches(self):
        next_id, pass_id, k = 1, 0, self.index
        while True:
            obs = self.pool[k % len(self.pool)]
            k += 1
            pass_id += 1
            for s in range(0, len(obs), self.cfg.batch):
                part = obs.take(np.arange(s, min(s + self.cfg.batch, len(obs))))
                yield part, pass_id, next_id
                next_id += len(part)

    def run(self) -> None:
        due = time.monotonic() + (self.index / self.cfg.vehicles) * self.period
        for batch_id, (part, pass_id, first) in enumerate(self.batches(), start=1):
            if self.stop.wait(max(0.0, due - time.monotonic())):
                return
            due += self.period * len(part) / self.cfg.batch
            n = len(part)
            ids = np.arange(first, first + n, dtype=np.uint64)
            now = time.time()
            obs = Observations(**{**part.__dict__, "obs_id": ids, "t": np.full(n, now - 1.0)})
            payload = ObservationBatch(self.vehicle_id, pass_id, batch_id, now, obs).to_bytes()
            ack = None
            for _k, ok, _e in query(
                self.session,
                keys.upload(self.vehicle_id),
                payload,
                timeout=10.0,
                target=zenoh.QueryTarget.BEST_MATCHING,
            ):
                if ok is not None:
                    try:
                        ack = UploadAck.from_bytes(ok)
                    except DecodeError:
                        ack = None
            if ack is None or ack.error is not None:
                self.counters.add(sent=n, failed=n, batches=1)
            else:
                self.counters.add(
                    sent=n,
                    accepted=len(ack.accepted),
                    duplicates=len(ack.duplicates),
                    rejected=len(ack.rejected),
                    batches=1,
                )


class Reader:
    """A subscribed vehicle: counts deltas and the latency of every landmark in them."""

    def __init__(self, session: zenoh.Session, tiles: list[str], counters: Counters):
        self.counters = counters
        self.subs = [session.declare_subscriber(keys.map_delta(t), self._on) for t in tiles]

    def _on(self, sample: zenoh.Sample) -> None:
        now = time.time()
        try:
            d = MapDelta.from_bytes(sample.payload.to_bytes())
        except DecodeError:
            return
        lat = now - d.upserts.source_time
        with self.counters.lock:
            self.counters.deltas += 1
            self.counters.delta_landmarks += len(d.upserts)
            self.counters.latencies.extend(lat.tolist())

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()


def percentiles(values, qs=(50, 95, 99)) -> dict[str, float]:
    a = np.asarray(values, float)
    if a.size == 0:
        return {f"p{q}": float("nan") for q in qs}
    return {f"p{q}": float(np.percentile(a, q)) for q in qs}
