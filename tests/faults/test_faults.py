"""Fault injection: SIGKILL each stateful service, and the router, while a fleet uploads.

Each run starts a router and the four services as processes, drives a small simulated
fleet through them and, at a chosen pass, SIGKILLs one target while that pass's upload
is in flight. The fleet keeps driving during the outage; the target is restarted a few
passes later and the run finishes. Then:

- every acknowledged observation was applied exactly once (the durable counters along
  the chain: ingest accepted == acknowledged, matcher received == ingest accepted,
  solver observations == matcher linked);
- the final map equals a fault-free run's map (same seed) landmark by landmark;
- the subscribed vehicle's map client, which lost deltas (publisher or router down),
  re-synced: it holds exactly the publisher's snapshots;
- vehicles whose uploads failed during the outage (ingest or router down) kept them in
  their store-and-forward queue and delivered them afterwards.

Uploads go out in pass order (a pass whose upload failed is retried before any later
pass is sent), so ingest sees the same sequence as in the fault-free run and the maps
can be compared exactly. Run with ``pytest -m faults -s`` to see the counts per target.
Every wait is bounded; every process is stopped by ``Stack``, also on failure.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from fleetsim.fleet import Fleet, Pass
from fleetsim.noise import FLEET
from fleetsim.pipeline import FleetDriver, fleet_config_ending_now, model_for
from fleetsim.town_run import follow_town
from fleetsim.world import World, demo_town
from hdmap.mapping.estimator import EstimatorConfig, LandmarkSums
from hdmap.ops.quiesce import totals, wait_quiet
from hdmap.ops.stack import SERVICE_NAMES, Stack
from hdmap.ops.status import collect
from hdmap.runtime.bus import open_session, query
from hdmap.runtime.store import connect
from schemas import Landmarks, MapSnapshot, keys
from vehicle.config import load_vehicle_model
from vehicle.mapclient import MapClient

pytestmark = [pytest.mark.faults, pytest.mark.timeout(300)]

VEHICLES = 4
ROUNDS = 10
PASSES = VEHICLES * ROUNDS
SEED = 3
TARGETS = (*SERVICE_NAMES, "router")
PROBATION = """\
[matcher.trust]
probation_passes = 3
"""
"""Vehicles settle (leave probation) from about pass 12 on, inside the kill windows: their
held passes are released in the matcher and, through the assoc log, in the solver."""


def start(st: Stack) -> None:
    cfg = st.data_dir / "probation.toml"
    cfg.write_text(PROBATION)
    st.extra_service_args["matcher"] = ["--config", str(cfg)]
    st.start_all()


@dataclass(frozen=True)
class Fault:
    """SIGKILL ``target`` ``delay_s`` after pass ``at_pass`` starts uploading; restart it
    once ``down_passes`` more passes have been driven (the fleet keeps going meanwhile)."""

    target: str
    at_pass: int
    down_passes: int = 6
    delay_s: float = 0.0


PLAN = {
    "ingest": Fault("ingest", 9),
    "matcher": Fault("matcher", 13),
    "solver": Fault("solver", 17),
    "publisher": Fault("publisher", 21),
    "router": Fault("router", 25),
}


def town(seed: int = SEED) -> tuple[World, Fleet]:
    world = demo_town(seed, n_signs=16, n_blocks=2)
    model = model_for(FLEET, load_vehicle_model())
    cfg = fleet_config_ending_now(VEHICLES, PASSES, route_length_m=(300.0, 500.0))
    return world, Fleet(world, model, FLEET, cfg, seed=seed)


def by_id(lm: Landmarks) -> dict[int, np.ndarray]:
    return {int(i): np.r_[lm.lat[k], lm.lon[k], lm.h[k], lm.cov[k]] for k, i in enumerate(lm.id)}


# -- the fleet: store-and-forward uploads, in pass order ------------------------------------


@dataclass
class Backlogged:
    vehicle: str
    rows: int
    failed: bool = False


class OrderedFleet:
    """Vehicles record every pass into their durable queue (vehicle/uploader.py); queued
    passes are uploaded oldest first. An upload that fails stays queued and blocks later
    passes (which are still driven and recorded), so the order ingest sees does not
    depend on when a fault happens."""

    def __init__(self, world: World, fleet: Fleet, queue_dir: Path):
        self.world = world
        self.driver = FleetDriver(world, fleet, queue_dir)
        self.backlog: deque[Backlogged] = deque()
        self.acked = 0
        """Observation ids acknowledged as recorded (accepted, including duplicates)."""
        self.duplicates = 0
        self.failed_batches = 0
        self.failed_vehicles: set[str] = set()
        self.delivered_late: set[str] = set()

    def record(self, p: Pass) -> None:
        obs = self.driver.agent(p.vehicle_id).record(p.pass_id, p.fixes, p.detections)
        self.driver.seen.add(self.world, p)
        self.driver.seen.observations += len(obs)
        if len(obs):
            self.backlog.append(Backlogged(p.vehicle_id, len(obs)))

    def attempt(self, session, vehicle: str) -> None:
        """A vehicle tries to upload while the test knows the target is down: it must fail
        and keep everything queued."""
        up = self.driver.agent(vehicle).uploader
        if up.retry_in > 0:  # told to hold back: it does not try now
            return
        before = up.pending
        res = up.flush(session, timeout=5.0, max_batches=1)
        assert res.failed_batches == 1 and up.pending == before, "upload went through while down"
        self.failed_batches += 1
        self.failed_vehicles.add(vehicle)
        for b in self.backlog:
            if b.vehicle == vehicle:
                b.failed = True

    def deliver(self, session) -> bool:
        """Upload queued passes in order until one fails; whether the backlog is empty."""
        while self.backlog:
            head = self.backlog[0]
            up = self.driver.agent(head.vehicle).uploader
            before = up.pending
            res = up.flush(session, timeout=5.0, max_batches=math.ceil(head.rows / up.batch_size))
            self.acked += res.accepted
            self.duplicates += res.duplicates
            head.rows -= before - up.pending
            if res.failed_batches:
                self.failed_batches += res.failed_batches
                self.failed_vehicles.add(head.vehicle)
                head.failed = True
                return False
            if head.rows:  # held back by an earlier answer's retry_after_s: later
                return False
            if head.failed:
                self.delivered_late.add(head.vehicle)
            self.backlog.popleft()
        return True

    @property
    def pending(self) -> int:
        return sum(a.uploader.pending for a in self.driver.agents.values())

    def rejected(self) -> int:
        return sum(len(a.uploader.rejected()) for a in self.driver.agents.values())

    def close(self) -> None:
        self.driver.close()


# -- the fault ------------------------------------------------------------------------------


class Chaos(threading.Thread):
    """Kills and restarts one target in step with the drive (errors re-raised by the test)."""

    def __init__(self, stack: Stack, fault: Fault, started: list, done: list):
        super().__init__(name=f"chaos-{fault.target}", daemon=True)
        self.stack, self.fault, self.started, self.done = stack, fault, started, done
        self.error: BaseException | None = None
        self.down_s = 0.0
        self.killed_in_flight = False
        self.on_restarted: Callable[[], None] = lambda: None
        self.down = threading.Event()
        """Set from the kill until the restart begins (under ``lock``)."""
        self.lock = threading.Lock()

    def run(self) -> None:
        f = self.fault
        try:
            assert self.started[f.at_pass].wait(120), "drive never reached the fault"
            time.sleep(f.delay_s)
            self.killed_in_flight = not self.done[f.at_pass].is_set()
            t0 = time.monotonic()
            name = "router" if f.target == "router" else f"{f.target}-all"
            self.stack.kill(name)
            assert not self.stack.procs[name].alive
            with self.lock:
                self.down.set()
            last = min(f.at_pass + f.down_passes, PASSES - 1)
            assert self.done[last].wait(120), "drive stalled during the outage"
            with self.lock:
                self.down.clear()
            if f.target == "router":
                self.stack.restart_router()
                self.stack.wait_ready([f"{n}-all" for n in SERVICE_NAMES], 60)
            else:
                self.stack.start_service(f.target)
                self.stack.wait_ready([name], 60)
            self.down_s = time.monotonic() - t0
            self.on_restarted()
        except BaseException as exc:  # noqa: BLE001 - re-raised by the test
            self.error = exc


# -- one run --------------------------------------------------------------------------------


@dataclass
class Run:
    landmarks: Landmarks
    snapshots: Landmarks
    client_versions: dict[str, int]
    snapshot_versions: dict[str, int]
    stats: dict[str, dict[str, float]]
    fleet: dict[str, float]
    failed_vehicles: set[str] = field(default_factory=set)
    delivered_late: set[str] = field(default_factory=set)
    client: dict[str, int] = field(default_factory=dict)
    chaos: dict[str, float] = field(default_factory=dict)
    persisted: dict[str, int] = field(default_factory=dict)


def snapshots(session, tiles: list[str]) -> tuple[Landmarks, dict[str, int]]:
    rows, versions = [], {}
    for t in tiles:
        for _k, ok, _e in query(session, keys.map_snapshot(t), timeout=5.0):
            if ok is not None:
                snap = MapSnapshot.from_bytes(ok)
                versions[t] = snap.version
                rows.append(snap.landmarks)
    return Landmarks.concat(rows), versions


def persisted_rays(stack: Stack, service: str) -> int:
    """Rays in the landmark sums a service has committed, with the matcher's links held for
    its gating sums until its tick ends (services/matcher/held_links.py): what it restarts
    from."""
    conn = connect(stack.data_dir / f"{service}-all" / "state.sqlite", readonly=True)
    try:
        blobs = [r[0] for r in conn.execute("SELECT sums FROM landmarks")]
        held = 0
        if service == "matcher":
            held = conn.execute("SELECT COALESCE(SUM(n), 0) FROM held_links").fetchone()[0]
    finally:
        conn.close()
    sums = LandmarkSums(EstimatorConfig())
    rows = sums.unpack_rows(blobs)
    summed = int(np.sum(sums.solve(rows, update_reference=False).n_obs)) if blobs else 0
    return summed + int(held)


def drive(stack: Stack, tmp: Path, fault: Fault | None = None) -> Run:
    world, fleet = town()
    started = [threading.Event() for _ in range(PASSES)]
    done = [threading.Event() for _ in range(PASSES)]
    chaos = Chaos(stack, fault, started, done) if fault else None
    at_restart: dict[str, int] = {}
    with open_session(stack.bus) as s:
        client = MapClient(s, radius_m=0.0)
        follow_town(client, world)
        if chaos is not None:
            chaos.on_restarted = lambda: at_restart.update(deltas=client.stats.deltas_applied)
        vehicles = OrderedFleet(world, fleet, tmp / "vehicles")
        try:
            if chaos is not None:
                chaos.start()
            for k, p in enumerate(fleet.passes(PASSES)):
                vehicles.record(p)
                started[k].set()
                if not vehicles.deliver(s) and chaos is not None:
                    with chaos.lock:  # while down, the driving vehicle tries too, and fails
                        if chaos.down.is_set() and vehicles.backlog[0].vehicle != p.vehicle_id:
                            vehicles.attempt(s, p.vehicle_id)
                done[k].set()
            deadline = time.monotonic() + 120
            while not vehicles.deliver(s):  # the backlog of an outage that outlasted the drive
                assert time.monotonic() < deadline, "uploads never went through again"
                time.sleep(0.2)
            if chaos is not None:
                chaos.join(120)
                assert not chaos.is_alive(), "restart did not finish"
                if chaos.error is not None:
                    raise chaos.error
            assert wait_quiet(s, timeout=120.0), totals(collect(s))
            time.sleep(1.0)  # the publisher's last coalescing interval
            tiles = sorted(client.versions())
            snap, snap_versions = snapshots(s, tiles)
            deadline = time.monotonic() + 30  # a re-fetch after a gap may still be in flight
            while client.versions() != snap_versions and time.monotonic() < deadline:
                time.sleep(0.1)
            assert client.wait_idle(10.0)
            return Run(
                client.landmarks(),
                snap,
                client.versions(),
                snap_versions,
                totals(collect(s)),
                {
                    "observations": vehicles.driver.seen.observations,
                    "acked": vehicles.acked,
                    "ack_duplicates": vehicles.duplicates,
                    "failed_batches": vehicles.failed_batches,
                    "pending": vehicles.pending,
                    "rejected": vehicles.rejected(),
                },
                set(vehicles.failed_vehicles),
                set(vehicles.delivered_late),
                {
                    "gaps": client.stats.gaps,
                    "snapshots": client.stats.snapshots,
                    "deltas_after_restart": client.stats.deltas_applied
                    - at_restart.get("deltas", 0),
                    "resyncs": client.stats.resyncs,
                },
                {
                    "down_s": chaos.down_s if chaos else 0.0,
                    "killed_in_flight": float(chaos.killed_in_flight) if chaos else 0.0,
                },
                {n: persisted_rays(stack, n) for n in ("matcher", "solver")},
            )
        finally:
            for e in started + done:  # let a waiting chaos thread finish on failure
                e.set()
            client.close()
            vehicles.close()


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Run:
    tmp = tmp_path_factory.mktemp("reference")
    with Stack(tmp / "stack") as st:
        start(st)
        return drive(st, tmp)


def report(target: str, r: Run) -> str:
    f, st = r.fleet, r.stats
    m = st["matcher"]
    return (
        f"FAULT {target:<9} SIGKILL {'during' if r.chaos['killed_in_flight'] else 'after'} "
        f"an upload, down {r.chaos['down_s']:.1f} s | fleet acknowledged {f['acked']:.0f} "
        f"(of {f['observations']:.0f} recorded; {f['ack_duplicates']:.0f} re-acked as "
        f"duplicates) | ingest accepted {st['ingest']['accepted']:.0f} | matcher received "
        f"{m['received']:.0f} (linked {m['linked']:.0f}, pending {m.get('pending', 0):.0f}, "
        f"expired {m.get('expired', 0):.0f}) | solver applied {st['solver']['observations']:.0f} "
        f"| failed uploads {f['failed_batches']:.0f} batches from {len(r.failed_vehicles)} "
        f"vehicles, delivered later by {len(r.delivered_late)} | map client: gaps "
        f"{r.client['gaps']}, snapshots {r.client['snapshots']}, deltas after the restart "
        f"{r.client['deltas_after_restart']} | catch-ups "
        + ", ".join(
            f"{s} {st[s].get('catchups', 0):.0f}" for s in ("matcher", "solver", "publisher")
        )
        + f" | probation: promoted {m.get('vehicles_promoted', 0):.0f}, caught "
        f"{m.get('vehicles_caught', 0):.0f}; solver released "
        f"{st['solver'].get('vehicles_released', 0):.0f}, dropped "
        f"{st['solver'].get('vehicles_dropped', 0):.0f}"
    )


@pytest.mark.parametrize("target", TARGETS)
def test_sigkill_while_the_fleet_uploads_loses_nothing(reference, tmp_path, target):
    fault = PLAN[target]
    with Stack(tmp_path / "stack") as st:
        start(st)
        got = drive(st, tmp_path, fault)
        name = "router" if target == "router" else f"{target}-all"
        assert st.procs[name].restarts >= 1
    print(f"\n{report(target, got)}")
    stats, fl = got.stats, got.fleet

    # every acknowledged observation applied exactly once (counters are durable)
    assert fl["pending"] == 0 and fl["rejected"] == 0
    assert fl["acked"] == fl["observations"]
    assert stats["ingest"]["accepted"] == fl["acked"]
    assert stats["matcher"]["received"] == stats["ingest"]["accepted"]
    m = stats["matcher"]
    kept = m["linked"] + m.get("pending", 0) + m.get("expired", 0)
    assert m["received"] == kept + m.get("track_discarded", 0)
    assert stats["solver"]["observations"] == m["linked"]
    # ... and kept in the state a restart reloads, not only in the counters
    assert got.persisted == {"matcher": m["linked"], "solver": m["linked"]}
    assert stats["matcher"].get("entries_failed", 0) == 0
    assert stats["solver"].get("entries_failed", 0) == 0
    # vehicles left probation once each, and the solver applied each settlement once
    settled = ("vehicles_promoted", "vehicles_caught")
    ref_m, ref_s = reference.stats["matcher"], reference.stats["solver"]
    assert sum(ref_m.get(k, 0) for k in settled) >= 1
    for k in settled:
        assert m.get(k, 0) == ref_m.get(k, 0), k
    for k in ("vehicles_released", "vehicles_dropped"):
        assert stats["solver"].get(k, 0) == ref_s.get(k, 0), k

    # the same map as without faults
    want, have = by_id(reference.snapshots), by_id(got.snapshots)
    assert len(want) > 5
    assert have.keys() == want.keys()
    for i in want:
        np.testing.assert_allclose(have[i][:3], want[i][:3], rtol=0, atol=1e-9)
        np.testing.assert_allclose(have[i][3:], want[i][3:], rtol=1e-6, atol=1e-9)

    # the subscribed vehicle re-synced: it holds exactly the publisher's snapshots
    assert got.client_versions == got.snapshot_versions
    client, snaps = by_id(got.landmarks), by_id(got.snapshots)
    assert client.keys() == snaps.keys()
    for i in snaps:
        np.testing.assert_array_equal(client[i], snaps[i])
    if target in ("router", "publisher"):  # its subscriptions work again, or it re-synced
        # (a restart that ends after the last delta leaves only the resync to show it)
        assert got.client["deltas_after_restart"] > 0 or got.client["resyncs"] > 0

    if target in ("ingest", "router"):  # uploads failed, were kept, and went through later
        assert fl["failed_batches"] >= 1
        assert got.failed_vehicles and got.delivered_late == got.failed_vehicles
