"""Ingest over a real router, as its own process: acks, retries, bad input, durability."""

from __future__ import annotations

import time

import numpy as np
import pytest

from fleetsim.synthetic import make_observations
from hdmap.ops.status import collect
from hdmap.runtime.bus import open_session, query
from schemas import LogEntry, LogQuery, ObservationBatch, ObsGroup, UploadAck, keys
from tests.support import wait_until

pytestmark = pytest.mark.integration


def upload(session, vehicle: str, payload: bytes) -> UploadAck:
    replies = query(session, keys.upload(vehicle), payload, timeout=10.0)
    assert len(replies) == 1 and replies[0][1] is not None
    return UploadAck.from_bytes(replies[0][1])


@pytest.fixture
def ingest(stack):
    stack.start_router()
    stack.start_service("ingest")
    stack.wait_ready(["ingest-all"], 60)
    with open_session(stack.bus) as s:
        yield stack, s


def test_upload_ack_retry_and_bad_input(ingest):
    _stack, s = ingest
    seen: list[LogEntry] = []
    sub = s.declare_subscriber(
        keys.obs("*"), lambda smp: seen.append(LogEntry.from_bytes(smp.payload.to_bytes()))
    )
    try:
        obs = make_observations(40)
        good = ObservationBatch("veh-1", 1, 1, time.time(), obs).to_bytes()
        ack = upload(s, "veh-1", good)
        assert ack.error is None and len(ack.accepted) == 40 and len(ack.duplicates) == 0

        again = upload(s, "veh-1", good)  # a retried batch: acked again, recorded once
        assert sorted(again.accepted.tolist()) == sorted(ack.accepted.tolist())
        assert len(again.duplicates) == 40

        bad = make_observations(5)
        bad.lat[1] = np.nan
        bad.lon[2] = 200.0
        bad.direction[3] = [0.0, 0.0, 0.0]
        bad.obs_id[:] = np.arange(100, 105)
        mixed = upload(s, "veh-1", ObservationBatch("veh-1", 1, 2, time.time(), bad).to_bytes())
        assert {r.obs_id: r.field for r in mixed.rejected} == {
            101: "obs.lat",
            102: "obs.lon",
            103: "obs.direction",
        }
        assert sorted(mixed.accepted.tolist()) == [100, 104]

        for payload, field in [
            (b"\x00\x01garbage", "message"),
            (good[: len(good) // 2], "message"),
            (ObservationBatch("veh-2", 1, 3, time.time(), obs).to_bytes(), "vehicle_id"),
        ]:
            err = upload(s, "veh-1", payload)
            assert err.error is not None and err.error.field == field
            assert len(err.accepted) == 0

        future = make_observations(3, t=time.time() + 3600)
        future.obs_id[:] = [200, 201, 202]
        fut = upload(s, "veh-1", ObservationBatch("veh-1", 1, 4, time.time(), future).to_bytes())
        assert {r.field for r in fut.rejected} == {"obs.t"}

        assert wait_until(lambda: sum(len(ObsGroup.from_bytes(e.body).obs) for e in seen) == 42)
        stats = {st.service: st for st in collect(s)}["ingest"]
        assert stats.counters["accepted"] == 42
        assert stats.counters["duplicates"] == 40
        assert stats.rejected["obs.lat"] == 1 and stats.rejected["batch.message"] == 2
        assert stats.rejected["batch.vehicle_id"] == 1
    finally:
        sub.undeclare()


def test_acknowledged_observations_survive_sigkill(ingest):
    stack, s = ingest
    obs = make_observations(30, seed=4)
    ack = upload(s, "veh-9", ObservationBatch("veh-9", 2, 1, time.time(), obs).to_bytes())
    assert len(ack.accepted) == 30
    stack.kill("ingest-all")
    stack.start_service("ingest")
    stack.wait_ready(["ingest-all"], 60)
    again = upload(s, "veh-9", ObservationBatch("veh-9", 2, 1, time.time(), obs).to_bytes())
    assert len(again.duplicates) == 30  # still recorded after the kill
    replies = query(s, f"{keys.ROOT}/log/obs/*/*", LogQuery("obs", {}, [], 100).to_bytes())
    total = sum(
        len(ObsGroup.from_bytes(LogEntry.from_bytes(r[1]).body).obs)
        for r in replies
        if r[1] is not None
    )
    assert total == 30
