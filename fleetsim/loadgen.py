"""Load generation against a running stack: many vehicles, paced uploads, subscribed readers.

Observations are simulated once (a pool of real passes through a town, geolocated
like on a vehicle, cut into uploads of at most ``batch`` observations); during the
run each vehicle replays pool passes with fresh observation ids, pass ids and
capture times, so the matcher and solver do real work at a rate the generator
itself can sustain. Each vehicle has its own upload stream (its own key, ids and
batches); batches are paced to the target rate (a vehicle that falls behind sends
its late batches back to back until it is on schedule again).

A replay draws what a real fleet never repeats afresh (:meth:`Pool.replay`): each
observation is shifted by a new GNSS bias track (constant part and random walk) minus
the one its pass was simulated with and its ray turned by the new heading bias minus
the old; each false positive's ray turns by a random angle of its own; each
observation posed on a multipath fix moves by a jump of its own.

Pitfall: replaying the pool's passes as they were makes a fleet of a few dozen biases
repeated thousands of times; the estimator takes every replay for new evidence, becomes
sure of a position one pool pass's bias away from the sign, stops gating the passes
whose bias differs, and starts copies of the sign (a 30-event-hour soak: mean error
2.4 m, 95 % coverage 0.06, the matcher's landmarks 136 -> 190 on a town of 120 signs).
A false positive or a multipath jump (20-50 m) replayed as it was lands where it landed
before: landmarks no real fleet would make (35-45 m from any sign of their class, seen
by a share of the passes that keeps them). A pool of a few dozen passes also sees each
sign in a handful of passes, whose detector errors repeat: a soak wants hundreds
(``pool_passes``: 600 gives a confirmed map of the town's 120 signs, mean error 0.48 m
after 24 event hours; in-process replay, 1,000 obs/s at x120).

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
from fleetsim.noise import FLEET, GnssNoise
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


FP_TURN_RAD = np.radians(25.0)
"""A replayed false positive's ray turns by up to this (about the camera's half field of
view: it lands somewhere else every time)."""
EARTH_RADIUS_M = 6_371_000.0
"""Metres to degrees for the metre-sized shifts of a bias redraw (exact enough there)."""


@dataclass(frozen=True)
class Pool:
    """Simulated passes, each a list of uploads, with the GNSS bias each was simulated
    with (a sequence of passes: ``pool[k]`` is pass ``k`` as simulated)."""

    passes: list[list[Observations]]
    fix_t: list[np.ndarray]
    """Per pass: its GNSS fix times, s (the clock of its observations' ``t``)."""
    bias_enu: list[np.ndarray]
    """Per pass: (M, 3) the GNSS position bias at each fix, ENU m (the constant part plus
    its random walk; the white noise and multipath jumps are not in it)."""
    heading_bias_rad: np.ndarray
    """(P,) each pass's constant heading bias, rad clockwise."""
    false_positive: list[list[np.ndarray]]
    """Per pass, per upload: which observations are false positives (the simulator's truth)."""
    multipath: list[list[np.ndarray]]
    """Per pass, per upload: which observations were posed on a fix displaced by multipath
    (or between such a fix and the next)."""
    gnss: GnssNoise
    """The noise model the biases were drawn from (redraws use it again)."""

    def __len__(self) -> int:
        return len(self.passes)

    def __getitem__(self, k: int) -> list[Observations]:
        return self.passes[k]

    def __iter__(self):
        return iter(self.passes)

    def replay(self, k: int, rng: np.random.Generator) -> list[Observations]:
        """Pass ``k % len(self)`` with a fresh bias drawn from :attr:`gnss` the way the
        simulator draws it: its camera centres shifted by the new minus the old bias track
        (interpolated at each observation's time), its ray directions turned about the
        vertical by the new minus the old heading bias (a heading error turns every ray of
        a fix; the lever arm's turn, centimetres, is left); each false positive's ray is
        turned by a further angle of its own, uniform within +/- :data:`FP_TURN_RAD`; an
        observation posed on a multipath fix is moved by a new jump (the model's magnitude,
        a uniform direction; the old one is left in: the two make one at a new place)."""
        k %= len(self.passes)
        g = self.gnss
        t_fix, old = self.fix_t[k], self.bias_enu[k]
        q = np.array([g.walk_h_m_per_sqrt_s, g.walk_h_m_per_sqrt_s, g.walk_v_m_per_sqrt_s])
        dt = np.diff(t_fix, prepend=t_fix[:1])
        steps = rng.normal(0.0, 1.0, (t_fix.size, 3)) * np.sqrt(np.maximum(dt, 0.0))[:, None] * q
        new = rng.normal(0.0, 1.0, 3) * np.array([g.bias_h_m, g.bias_h_m, g.bias_v_m])
        delta = new + np.cumsum(steps, axis=0) - old
        turn = float(rng.normal(0.0, g.bias_heading_rad)) - float(self.heading_bias_rad[k])
        out = []
        for part, fp, mp in zip(
            self.passes[k], self.false_positive[k], self.multipath[k], strict=True
        ):
            angle = turn + np.where(fp, rng.uniform(-FP_TURN_RAD, FP_TURN_RAD, fp.size), 0.0)
            c, s = np.cos(angle), np.sin(angle)
            d_e, d_n, d_u = (np.interp(part.t, t_fix, delta[:, i]) for i in range(3))
            jump = np.where(mp, rng.uniform(g.multipath_min_m, g.multipath_max_m, mp.size), 0.0)
            bearing = rng.uniform(0.0, 2.0 * np.pi, mp.size)
            d_e, d_n = d_e + jump * np.sin(bearing), d_n + jump * np.cos(bearing)
            lat = part.lat + np.degrees(d_n / EARTH_RADIUS_M)
            lon = part.lon + np.degrees(d_e / (EARTH_RADIUS_M * np.cos(np.radians(part.lat))))
            u = part.direction
            turned = np.column_stack(
                [c * u[:, 0] + s * u[:, 1], c * u[:, 1] - s * u[:, 0], u[:, 2]]
            )
            moved = {"lat": lat, "lon": lon, "h": part.h + d_u, "direction": turned}
            out.append(Observations(**{**part.__dict__, **moved}))
        return out


def build_pool(cfg: LoadConfig) -> tuple[World, Pool]:
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
    passes, fix_t, bias, heading, fps, mps = [], [], [], [], [], []
    for k in range(cfg.pool_passes):
        p = fleet.drive(0, k)
        lines = geolocate(p.fixes, p.detections, model)
        if len(lines) != len(p.truth.sign_id):
            raise RuntimeError("geolocate dropped detections: the truth masks would not align")
        if len(lines):
            track = track_rays(smoothed_rays(p.fixes, lines, TRACKING), TRACKING)
            obs = to_observations(lines, np.zeros(len(lines), np.uint64), track)
            cuts = [
                np.arange(s, min(s + cfg.batch, len(obs))) for s in range(0, len(obs), cfg.batch)
            ]
            passes.append([obs.take(c) for c in cuts])
            fps.append([np.asarray(p.truth.sign_id)[c] < 0 for c in cuts])
            on_jump = _on_multipath_fix(p.truth.fix_t, p.truth.gnss.multipath, obs.t)
            mps.append([on_jump[c] for c in cuts])
            fix_t.append(np.asarray(p.truth.fix_t, float))
            bias.append(np.asarray(p.truth.gnss.bias_enu, float).reshape(-1, 3))
            heading.append(p.truth.gnss.heading_bias_rad)
    if not passes:
        raise RuntimeError("the simulated pool has no observations")
    gnss = FLEET.gnss
    assert isinstance(gnss, GnssNoise)
    return world, Pool(passes, fix_t, bias, np.array(heading, float), fps, mps, gnss)


def _on_multipath_fix(fix_t: np.ndarray, jumped: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Per time in ``t``: whether the fix at it, or either fix around it, was displaced."""
    if fix_t.size == 0:
        return np.zeros(t.shape, bool)
    after = np.clip(np.searchsorted(fix_t, t), 0, fix_t.size - 1)
    before = np.clip(after - 1, 0, fix_t.size - 1)
    jumped = np.asarray(jumped, bool)
    return jumped[after] | (jumped[before] & (fix_t[after] != t))


def town_tiles_with_halo(world: World) -> list[str]:
    lat, lon, _ = world.signs_geodetic()
    tiles = set(quadkeys_of(lat, lon).tolist())
    return sorted(tiles | {n for t in tiles for n in neighbours(t)})


def upload_payloads(
    pool: Pool,
    vehicle_id: str = "load-0",
    first_pass: int = 0,
    capture_time=lambda wall: wall - 1.0,
    rng: np.random.Generator | None = None,
):
    """The upload payloads a vehicle sends, in order, with fresh ids (endless generator);
    ``capture_time(wall)``: when the pass being sent at ``wall`` ended (its observations
    keep their times relative to that end). With ``rng`` every pass gets a fresh GNSS
    bias (:meth:`Pool.replay`); without, the passes are sent as simulated.

    Yields (payload bytes, observation count)."""
    next_id, pass_id, batch_id, k = 1, 0, 0, first_pass
    while True:
        parts = pool.replay(k, rng) if rng is not None else pool[k % len(pool)]
        k += 1
        pass_id += 1
        end = max(float(p.t.max()) for p in parts)
        shift = None
        for part in parts:
            n = len(part)
            batch_id += 1
            now = time.time()
            if shift is None:
                shift = capture_time(now) - end
            ids = np.arange(next_id, next_id + n, dtype=np.uint64)
            next_id += n
            obs = Observations(**{**part.__dict__, "obs_id": ids, "t": part.t + shift})
            yield ObservationBatch(vehicle_id, pass_id, batch_id, now, obs).to_bytes(), n


class Vehicle(threading.Thread):
    """One vehicle's paced upload stream (pool passes replayed with fresh ids)."""

    def __init__(
        self,
        index: int,
        session: zenoh.Session,
        pool: Pool,
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
        rng = np.random.default_rng([self.cfg.seed, self.index])
        payloads = upload_payloads(
            self.pool, self.vehicle_id, self.index, self.cfg.capture_time, rng
        )
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
