"""The vehicle side against real services: store-and-forward uploads and the map client.

Every router and service is its own process on 127.0.0.1 (random free port, multicast
scouting off, SQLite under tmp_path), stopped by the ``stack`` fixture (or the
module's ``town`` fixture), also on failure. Every wait is bounded; nothing asserts
on timing.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import pytest

from fleetsim.fleet import Fleet
from fleetsim.noise import FLEET
from fleetsim.pipeline import FleetDriver, fleet_config_ending_now, model_for, town_tiles
from fleetsim.town_run import follow_town
from fleetsim.world import World, demo_town
from hdmap.geo.tiles import tiles_around
from hdmap.ops.quiesce import totals, wait_quiet
from hdmap.ops.stack import Stack
from hdmap.ops.status import collect
from hdmap.runtime.bus import open_session, query
from schemas import (
    Landmarks,
    LogEntry,
    LogQuery,
    MapDelta,
    MapSnapshot,
    ObservationBatch,
    ObsGroup,
    keys,
)
from schemas.tables import Removals
from tests.support import wait_until
from vehicle.agent import VehicleAgent
from vehicle.config import load_vehicle_model
from vehicle.mapclient import MapClient

pytestmark = pytest.mark.integration

PASSES = 16
FAKE_ID = 10**9


def fleet(world: World, n_vehicles: int, n_passes: int, seed: int = 0) -> Fleet:
    model = model_for(FLEET, load_vehicle_model())
    cfg = fleet_config_ending_now(n_vehicles, n_passes, route_length_m=(300.0, 500.0))
    return Fleet(world, model, FLEET, cfg, seed=seed)


def ingest_counters(session) -> dict[str, float]:
    return totals(collect(session)).get("ingest", {})


def logged_observations(session) -> int:
    """Observations in ingest's durable obs log (replayed from the start)."""
    total = 0
    for _k, ok, _e in query(
        session, f"{keys.ROOT}/log/obs/*/*", LogQuery("obs", {}, [], 10_000).to_bytes()
    ):
        if ok is not None:
            total += len(ObsGroup.from_bytes(LogEntry.from_bytes(ok).body).obs)
    return total


# -- store-and-forward ------------------------------------------------------------------------


def test_queue_survives_outage_and_vehicle_restart_and_drains_exactly_once(stack, tmp_path):
    world = demo_town(0, n_signs=16, n_blocks=2)
    fl = fleet(world, n_vehicles=1, n_passes=4)
    passes = list(fl.passes(4))
    vid, qdir = passes[0].vehicle_id, tmp_path / "vehicle"
    stack.start_router()
    stack.start_service("ingest")
    stack.wait_ready(["ingest-all"], 60)
    recorded: list[int] = []
    with open_session(stack.bus) as s:
        agent = VehicleAgent(vid, fl.model, qdir, batch_size=50)
        try:
            # ingest up: the first pass is acknowledged and leaves the queue
            obs0 = agent.record(passes[0].pass_id, passes[0].fixes, passes[0].detections)
            recorded.append(len(obs0))
            res = agent.upload(s)
            assert len(obs0) > 50  # several batches per pass
            assert (res.accepted, res.rejected, res.failed_batches) == (len(obs0), 0, 0)
            assert agent.uploader.pending == 0

            # ingest down: uploads fail, the queue keeps everything
            stack.stop("ingest-all")
            obs1 = agent.record(passes[1].pass_id, passes[1].fixes, passes[1].detections)
            obs2 = agent.record(passes[2].pass_id, passes[2].fixes, passes[2].detections)
            recorded += [len(obs1), len(obs2)]
            res = agent.upload(s, timeout=3.0)
            assert res.accepted == 0 and res.failed_batches == 1
            assert agent.uploader.pending == len(obs1) + len(obs2)
        finally:
            agent.close()

        # the vehicle process restarts on the same queue file
        agent = VehicleAgent(vid, fl.model, qdir, batch_size=50)
        try:
            assert agent.uploader.pending == len(obs1) + len(obs2)
            obs3 = agent.record(passes[3].pass_id, passes[3].fixes, passes[3].detections)
            recorded.append(len(obs3))
            earlier = np.concatenate([obs0.obs_id, obs1.obs_id, obs2.obs_id])
            assert obs3.obs_id.min() > earlier.max()  # ids stay unique across the restart
            assert agent.upload(s, timeout=3.0).failed_batches == 1
            assert agent.uploader.pending == sum(recorded[1:])

            stack.start_service("ingest")
            stack.wait_ready(["ingest-all"], 60)
            # pass 1 reaches ingest but its ack is lost (as if the old process had sent it
            # and died before recording the ack): the queue still holds it
            lost = ObservationBatch(vid, passes[1].pass_id, 999, time.time(), obs1)
            replies = query(s, keys.upload(vid), lost.to_bytes(), timeout=10.0)
            assert [ok is not None for _k, ok, _e in replies] == [True]

            res = agent.upload(s)
            assert res.failed_batches == 0 and res.rejected == 0
            assert res.duplicates == len(obs1)  # acknowledged again, recorded once
            assert agent.uploader.pending == 0
            again = agent.upload(s)
            assert again.sent == 0 and again.accepted == 0
        finally:
            agent.close()

        total = sum(recorded)
        c = ingest_counters(s)
        assert c["accepted"] == total  # counters survive the ingest restart
        assert c["duplicates"] == len(obs1)
        assert logged_observations(s) == total


# -- map client -------------------------------------------------------------------------------


@dataclass
class DrivenTown:
    stack: Stack
    world: World
    reference: Landmarks
    """The map a client following the whole town holds after the drive (deltas only)."""
    deltas_applied: int


@pytest.fixture(scope="module")
def town(tmp_path_factory) -> Iterator[DrivenTown]:
    """A stack with a small town driven through it, shared by the map client tests."""
    tmp = tmp_path_factory.mktemp("town")
    world = demo_town(0, n_signs=16, n_blocks=2)
    fl = fleet(world, n_vehicles=4, n_passes=PASSES)
    with Stack(tmp / "stack") as st:
        st.start_all()
        with open_session(st.bus) as s:
            client = MapClient(s, radius_m=0.0, client_id="town-reader")
            driver = FleetDriver(world, fl, tmp / "vehicles")
            try:
                follow_town(client, world)
                assert client.wait_idle(20.0)
                driver.run(s, fl.passes(PASSES))
                assert driver.seen.failed_batches == 0
                assert wait_quiet(s, timeout=120.0), totals(collect(s))
                # the publisher's last coalescing interval, then the last deltas
                assert wait_until(lambda: client.stats.deltas_applied > 0, 10.0)
                time.sleep(1.0)
                assert client.wait_idle(10.0)
                ref, applied = client.landmarks(), client.stats.deltas_applied
            finally:
                client.close()
                driver.close()
        assert len(ref) >= 5, len(ref)
        yield DrivenTown(st, world, ref, applied)


def ids(lm: Landmarks) -> set[int]:
    return {int(i) for i in lm.id}


def snapshot_version(session, tile: str) -> int:
    """The publisher's version of ``tile`` (asked for under the client id ``probe``: every
    client of this module has its own snapshot budget, none shares the anonymous one)."""
    key = keys.map_snapshot_for("probe", tile)
    replies = [ok for _k, ok, _e in query(session, key) if ok is not None]
    assert len(replies) == 1
    return MapSnapshot.from_bytes(replies[0]).version


def ground_m(lat0: float, lon0: float, lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
    """Horizontal distances on a local sphere (independent of hdmap.geo.geodesy)."""
    r = 6_371_000.0
    dn = np.radians(lat - lat0) * r
    de = np.radians(lon - lon0) * r * math.cos(math.radians(lat0))
    return np.hypot(de, dn)


def test_snapshot_on_start_and_near(town):
    assert town.deltas_applied >= 1  # the client that followed during the drive got deltas
    with open_session(town.stack.bus) as s:
        client = MapClient(s, radius_m=0.0, client_id="late-reader")
        try:
            follow_town(client, town.world)
            assert client.wait_idle(20.0)
            # a client joining late starts every tile from its snapshot: same map, no delta
            assert client.stats.snapshots == len(client.versions())
            assert client.stats.deltas_applied == 0
            lm = client.landmarks()
            assert ids(lm) == ids(town.reference)
            for tile in town_tiles(town.world):
                assert client.versions()[tile] == snapshot_version(s, tile) >= 1

            k = int(np.argmax(lm.n_obs))
            lat, lon = float(lm.lat[k]), float(lm.lon[k])
            assert int(lm.id[k]) in ids(client.near(lat, lon, 0.5))
            d = ground_m(lat, lon, lm.lat, lm.lon)
            for radius in (15.0, 60.0, 1e4):
                got = ids(client.near(lat, lon, radius))
                sure = {int(i) for i, di in zip(lm.id, d, strict=True) if abs(di - radius) > 0.5}
                want = {int(i) for i, di in zip(lm.id, d, strict=True) if di <= radius}
                assert got & sure == want & sure, radius
            assert ids(client.near(lat, lon, 1e4)) == ids(lm)
            assert len(client.near(lat + 0.05, lon, 500.0)) == 0  # 5.5 km north
        finally:
            client.close()


def test_follows_tiles_around_a_moving_position(town):
    lat0, lon0 = town.world.lat0, town.world.lon0
    far = (lat0, lon0 + 0.06)  # about 3.3 km east: no tile in common
    with open_session(town.stack.bus) as s:
        client = MapClient(s, radius_m=150.0, client_id="moving-reader")
        try:
            here = client.update_position(lat0, lon0)
            assert here == tiles_around(lat0, lon0, 150.0) and len(here) >= 1
            assert set(client.versions()) == set(here)
            assert client.wait_idle(20.0)
            assert client.stats.snapshots == len(here)
            near_here = ids(client.near(lat0, lon0, 100.0))
            assert near_here and near_here <= ids(town.reference)

            # moving a little keeps the tiles that are still near
            moved = client.update_position(lat0 + 0.0005, lon0)
            assert set(client.versions()) == set(moved)
            assert client.stats.dropped == len(set(here) - set(moved))

            there = client.update_position(*far)
            assert set(client.versions()) == set(there)
            assert not set(there) & set(here)
            assert client.wait_idle(20.0)
            assert len(client.landmarks()) == 0  # the town's tiles were dropped
            assert client.stats.subscribed == len(set(here) | set(moved) | set(there))

            back = client.update_position(lat0, lon0)
            assert back == here and set(client.versions()) == set(here)
            assert client.wait_idle(20.0)
            assert ids(client.near(lat0, lon0, 100.0)) == near_here  # fetched again
        finally:
            client.close()


def forged(lm: Landmarks, tile: str, frm: int) -> bytes:
    """A delta ``frm -> frm + 1`` of ``tile`` the publisher never made (one fake row)."""
    fake = lm.take(np.array([0]))
    fake.id[:] = FAKE_ID
    return MapDelta(tile, frm, frm + 1, time.time(), fake, Removals.empty()).to_bytes()


def followed_town(s, town: DrivenTown) -> tuple[MapClient, Landmarks, str, int]:
    """A client holding the town from the snapshots; its map, its newest tile, that version."""
    client = MapClient(s, radius_m=0.0, client_id="followed-reader")
    follow_town(client, town.world)
    assert client.wait_idle(20.0)
    tile = max(town_tiles(town.world), key=lambda t: client.versions()[t])
    return client, client.landmarks(), tile, client.versions()[tile]


def test_version_gap_refetches_the_snapshot(town):
    with open_session(town.stack.bus) as s:
        client, lm, tile, v = followed_town(s, town)
        try:
            snaps = client.stats.snapshots
            s.put(keys.map_delta(tile), forged(lm, tile, v - 1))  # covered by the snapshot
            assert wait_until(lambda: client.stats.deltas_stale >= 1, 10.0)
            assert client.stats.gaps == 0

            # a delta ahead of the client's version: a gap, so the snapshot is fetched again
            s.put(keys.map_delta(tile), forged(lm, tile, v + 5))
            assert wait_until(lambda: client.stats.gaps >= 1, 10.0)
            assert wait_until(lambda: client.stats.snapshots > snaps, 10.0)
            assert client.wait_idle(10.0)
            settled = (client.stats.snapshots, client.stats.gaps)
            assert client.wait_idle(10.0)
            assert (client.stats.snapshots, client.stats.gaps) == settled  # no refetch loop
            assert settled == (snaps + 1, 1)
            assert client.stats.ahead_of_snapshot == 1  # still ahead of the fresh snapshot
            assert client.versions()[tile] == snapshot_version(s, tile) == v
            assert FAKE_ID not in ids(client.landmarks())
            assert ids(client.landmarks()) == ids(lm)
        finally:
            client.close()


def test_gap_while_the_publisher_is_down_is_refetched_when_it_is_back(town):
    st = town.stack
    with open_session(st.bus) as s:
        client, lm, tile, v = followed_town(s, town)
        try:
            snaps = client.stats.snapshots
            st.stop("publisher-all")
            s.put(keys.map_delta(tile), forged(lm, tile, v + 5))
            assert wait_until(lambda: client.stats.gaps == 1, 10.0)
            assert client.wait_idle(20.0)  # the re-fetch found no publisher
            assert client.versions()[tile] == -1 and client.stats.snapshots == snaps
            s.put(keys.map_delta(tile), forged(lm, tile, v + 6))
            assert client.wait_idle(20.0)
            assert client.versions()[tile] == -1

            # the publisher comes back: its liveliness token makes the client refetch every
            # followed tile, with no delta needed (a tile may not change again)
            resyncs = client.stats.resyncs
            st.start_service("publisher")
            st.wait_ready(["publisher-all"], 60)
            assert wait_until(lambda: client.versions()[tile] >= 0, 20.0)
            assert client.wait_idle(20.0)
            assert client.stats.resyncs == resyncs + 1
            assert client.versions()[tile] == v and client.stats.snapshots > snaps
            assert ids(client.landmarks()) == ids(lm)
            assert all(v >= 0 for v in client.versions().values())
        finally:
            client.close()
            if not st.procs["publisher-all"].alive:
                st.start_service("publisher")


def test_update_position_from_several_threads_keeps_one_subscription_per_tile(town):
    """A GPS thread and an application thread may both move the client: concurrent calls
    leave exactly the tiles of the last position followed, each with one subscription
    (subscribed - dropped = tiles held), each tile at the publisher's version after its
    fetch. Without the serialisation: 174 subscribed, 150 dropped, 9 tiles held."""
    lat0, lon0 = town.world.lat0, town.world.lon0
    spots = [(lat0, lon0), (lat0 + 0.004, lon0), (lat0, lon0 + 0.006), (lat0 - 0.003, lon0)]
    with open_session(town.stack.bus) as s:
        client = MapClient(s, radius_m=300.0, client_id="threaded-reader")
        errors: list[BaseException] = []

        def drive(k: int) -> None:
            try:
                for i in range(12):
                    client.update_position(*spots[(i + k) % len(spots)])
            except BaseException as exc:  # noqa: BLE001 - reported by the main thread
                errors.append(exc)

        threads = [threading.Thread(target=drive, args=(k,)) for k in range(4)]
        try:
            for t in threads:
                t.start()
            for t in threads:
                t.join(timeout=60.0)
            assert not any(t.is_alive() for t in threads)
            assert not errors, errors
            here = client.update_position(lat0, lon0)
            assert set(client.versions()) == set(here)
            assert client.stats.subscribed - client.stats.dropped == len(here)
            assert client.wait_idle(20.0)
            for tile, version in client.versions().items():  # each at the publisher's
                assert version == snapshot_version(s, tile), tile
            assert ids(client.near(lat0, lon0, 100.0)) <= ids(town.reference)
        finally:
            client.close()
