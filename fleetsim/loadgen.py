"""Load generation against a running stack: many vehicles, paced uploads, subscribed readers.

Observations are simulated once (a pool of real passes through a town, geolocated
like on a vehicle, cut into uploads of at most ``batch`` observations); during the
run each vehicle replays pool passes with fresh observation ids, pass ids and
capture times, so the matcher and solver do real work at a rate the generator
itself can sustain. Each vehicle has its own upload stream (its own key, ids and
batches); batches are paced to the target rate (a vehicle that falls behind sends
its late batches back to back until it is on schedule again).

Vehicle ids carry a per-run tag (``load-<run>-<index>``): the stack remembers every
(vehicle, observation id) it has recorded, so a second run with the same ids would
only produce duplicates. Within a run, ids are unique, so an upload's ``accepted``
(which includes ``duplicates``) is exactly what ingest recorded for it, also when
an upload is retried after a lost reply.

Latency is traced by the stages: ``Landmarks.source_time`` is when ingest
received the newest observation folded into an update; a subscribed reader
measures ``arrival - source_time`` for every landmark in every delta.
"""

from __future__ import annotations

import threading
import time
import uuid
from collections import deque
from dataclasses import dataclass, field

import numpy as np
import zenoh

from fleetsim.fleet import Fleet, FleetConfig
from fleetsim.noise import FLEET
from fleetsim.pipeline import model_for
from fleetsim.world import World, demo_town
from hdmap.geo.tiles import neighbours, quadkeys_of
from hdmap.runtime.bus import query
from schemas import DecodeError, MapDelta, ObservationBatch, Observations, UploadAck, keys
from vehicle.agent import DEFAULT_TRACKING as TRACKING
from vehicle.agent import to_observations
from vehicle.config import load_vehicle_model
from vehicle.geoloc import geolocate
from vehicle.tracking import smoothed_rays, track_rays


def new_run_id() -> str:
    """A short tag that makes this run's vehicle ids (and so its observation ids) new."""
    return uuid.uuid4().hex[:8]


@dataclass(frozen=True)
class LoadConfig:
    vehicles: int = 20
    rate: float = 5000.0
    """Target observations per second over the whole fleet."""
    duration_s: float = 30.0
    batch: int = 500
    """At most this many observations per upload (a pass is cut into uploads)."""
    subscribers: int = 2
    """Subscribed vehicles (map readers), each on every tile of the town and its halo."""
    pool_passes: int = 60
    route_length_m: tuple[float, float] = FleetConfig().route_length_m
    """Pool pass length (the fleet's default, 400-900 m: ~95 observations a pass in the
    demo town, so a pass is usually one upload). Longer passes make bigger uploads but
    also cost the matcher more per observation (more pending rays per pass)."""
    n_signs: int = 120
    n_blocks: int = 6
    seed: int = 0
    run_id: str = ""
    """Vehicle id tag; empty: a fresh one per run (:func:`new_run_id`)."""
    upload_timeout_s: float = 10.0
    max_attempts: int = 3
    """Attempts per upload (a timed-out or refused upload is resent, like a vehicle does)."""
    event_start: float | None = None
    """Capture time (Unix s) of the run's first observations; None: the wall clock (each
    upload stamped a second before it is sent)."""
    event_speedup: float = 1.0
    """With ``event_start``: event seconds per wall second (a soak run covers hours of
    traffic in minutes; capture times must stay inside ingest's admission window)."""
    event_wall0: float = 0.0
    """With ``event_start``: the wall time (Unix s) that stands for it."""

    def capture_time(self, wall: float) -> float:
        """The capture time of observations uploaded at wall time ``wall``."""
        if self.event_start is None:
            return wall - 1.0
        return self.event_start + self.event_speedup * (wall - self.event_wall0)


@dataclass
class Counters:
    """Shared between threads; every update under ``lock``."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    sent: int = 0
    """Observations uploaded (each counted once, however many attempts)."""
    accepted: int = 0
    """Observations acknowledged as durably recorded (``UploadAck.accepted``)."""
    duplicates: int = 0
    rejected: int = 0
    failed: int = 0
    """Observations of uploads never acknowledged after ``max_attempts``."""
    batches: int = 0
    retries: int = 0
    deltas: int = 0
    delta_landmarks: int = 0
    latency_count: int = 0
    """Latencies measured so far (``latencies`` keeps the newest only)."""
    latencies: deque = field(default_factory=lambda: deque(maxlen=2_000_000))
    ack_latencies: deque = field(default_factory=lambda: deque(maxlen=200_000))

    def add(self, **kw: int) -> None:
        with self.lock:
            for k, v in kw.items():
                setattr(self, k, getattr(self, k) + v)


def build_pool(cfg: LoadConfig) -> tuple[World, list[list[Observations]]]:
    """Simulated, geolocated passes (FLEET noise), each cut into uploads of <= ``batch``."""
    world = demo_town(cfg.seed, n_signs=cfg.n_signs, n_blocks=cfg.n_blocks)
    model = model_for(FLEET, load_vehicle_model())
    fleet = Fleet(
        world,
        model,
        FLEET,
        FleetConfig(n_vehicles=1, start_time=time.time(), route_length_m=cfg.route_length_m),
        seed=cfg.seed,
    )
    pool = []
    for k in range(cfg.pool_passes):
        p = fleet.drive(0, k)
        lines = geolocate(p.fixes, p.detections, model)
        if len(lines):
            track = track_rays(smoothed_rays(p.fixes, lines, TRACKING), TRACKING)
            obs = to_observations(lines, np.zeros(len(lines), np.uint64), track)
            pool.append(
                [
                    obs.take(np.arange(s, min(s + cfg.batch, len(obs))))
                    for s in range(0, len(obs), cfg.batch)
                ]
            )
    if not pool:
        raise RuntimeError("the simulated pool has no observations")
    return world, pool


def town_tiles_with_halo(world: World) -> list[str]:
    lat, lon, _ = world.signs_geodetic()
    tiles = set(quadkeys_of(lat, lon).tolist())
    return sorted(tiles | {n for t in tiles for n in neighbours(t)})


def upload_payloads(
    pool: list[list[Observations]],
    vehicle_id: str = "load-0",
    first_pass: int = 0,
    capture_time=lambda wall: wall - 1.0,
):
    """The upload payloads a vehicle sends, in order, with fresh ids (endless generator);
    ``capture_time(wall)``: the observations' time when sent at ``wall``.

    Yields (payload bytes, observation count)."""
    next_id, pass_id, batch_id, k = 1, 0, 0, first_pass
    while True:
        parts = pool[k % len(pool)]
        k += 1
        pass_id += 1
        for part in parts:
            n = len(part)
            batch_id += 1
            now = time.time()
            ids = np.arange(next_id, next_id + n, dtype=np.uint64)
            next_id += n
            t = capture_time(now)
            obs = Observations(**{**part.__dict__, "obs_id": ids, "t": np.full(n, t)})
            yield ObservationBatch(vehicle_id, pass_id, batch_id, now, obs).to_bytes(), n


class Vehicle(threading.Thread):
    """One vehicle's paced upload stream (pool passes replayed with fresh ids)."""

    def __init__(
        self,
        index: int,
        session: zenoh.Session,
        pool: list[list[Observations]],
        cfg: LoadConfig,
        counters: Counters,
        stop: threading.Event,
        run_id: str,
    ):
        super().__init__(name=f"veh-{index}", daemon=True)
        self.vehicle_id = f"load-{run_id}-{index:05d}"
        self.index, self.session, self.pool, self.cfg = index, session, pool, cfg
        self.counters, self.stop = counters, stop
        self.obs_period = cfg.vehicles / cfg.rate
        self.acked_uploads = 0
        """Uploads of this vehicle acknowledged so far (read by other threads)."""
        """Seconds of this vehicle's schedule one observation takes."""

    def run(self) -> None:
        mean_batch = np.mean([len(p) for parts in self.pool for p in parts])
        due = time.monotonic() + (self.index / self.cfg.vehicles) * mean_batch * self.obs_period
        payloads = upload_payloads(self.pool, self.vehicle_id, self.index, self.cfg.capture_time)
        for payload, n in payloads:
            if self.stop.wait(max(0.0, due - time.monotonic())):
                return
            due += n * self.obs_period
            self._upload(payload, n)

    def _upload(self, payload: bytes, n: int) -> None:
        """Send one upload until acknowledged (at most ``max_attempts``), then count it."""
        ack: UploadAck | None = None
        for attempt in range(self.cfg.max_attempts):
            if attempt:
                self.counters.add(retries=1)
                time.sleep(min(max(ack.retry_after_s, 0.1), 2.0) if ack is not None else 0.1)
            t = time.monotonic()
            ack = self._send(payload)
            if ack is not None and ack.error is None:
                with self.counters.lock:
                    c = self.counters
                    c.sent += n
                    c.batches += 1
                    c.accepted += len(ack.accepted)
                    c.duplicates += len(ack.duplicates)
                    c.rejected += len(ack.rejected)
                    c.ack_latencies.append(time.monotonic() - t)
                self.acked_uploads += 1
                return
        self.counters.add(sent=n, failed=n, batches=1)

    def _send(self, payload: bytes) -> UploadAck | None:
        ack = None
        try:
            replies = query(
                self.session,
                keys.upload(self.vehicle_id),
                payload,
                timeout=self.cfg.upload_timeout_s,
                target=zenoh.QueryTarget.ALL,  # every ingest shard; its vehicle's answers
            )
        except zenoh.ZError:
            return None
        for _k, ok, _e in replies:
            if ok is not None:
                try:
                    ack = UploadAck.from_bytes(ok)
                except DecodeError:
                    ack = None
        return ack


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
        lat = (now - d.upserts.source_time).tolist()
        with self.counters.lock:
            self.counters.deltas += 1
            self.counters.delta_landmarks += len(d.upserts)
            self.counters.latency_count += len(lat)
            self.counters.latencies.extend(lat)

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()


def percentiles(values, qs=(50, 95, 99)) -> dict[str, float | None]:
    """Percentiles of ``values``; None for each if there are none (valid JSON)."""
    a = np.asarray(values, float)
    if a.size == 0:
        return {f"p{q}": None for q in qs}
    return {f"p{q}": float(np.percentile(a, q)) for q in qs}
