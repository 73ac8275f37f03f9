"""Per-vehicle rate limits in ingest: token buckets (injected clock, no sleeping), the
vehicle uploader honouring ``retry_after_s``, and a flooding vehicle next to an honest one
against a real router and ingest process."""

from __future__ import annotations

import threading
import time
import tomllib
from pathlib import Path

import numpy as np
import pytest

from fleetsim.synthetic import make_observations
from hdmap.cli.service import service_config
from hdmap.ops.status import collect
from hdmap.runtime.bus import open_session, query
from hdmap.runtime.config import ConfigError, from_mapping
from hdmap.runtime.ratelimit import MAX_RETRY_AFTER_S, TokenBucket
from hdmap.runtime.service import Batching
from schemas import DecodeError, ObservationBatch, Observations, UploadAck, keys
from services.ingest.ratelimit import RateLimit, VehicleLimiter
from services.ingest.service import IngestConfig
from tests.support import Clock, start_configured, wait_until
from vehicle.uploader import Uploader

ROOT = Path(__file__).resolve().parents[2]


def test_bucket_grants_a_burst_then_the_rate() -> None:
    b = TokenBucket(rate=10.0, capacity=5.0, now=100.0)
    assert [b.take(1.0, 100.0) for _ in range(5)] == [0.0] * 5
    assert b.take(1.0, 100.0) == pytest.approx(0.1)  # refused: one token in 0.1 s
    assert b.take(1.0, 100.05) == pytest.approx(0.05)  # a refusal charges nothing
    assert b.take(1.0, 100.1) == 0.0
    assert b.take(1.0, 100.1) > 0
    # a long idle period refills to the capacity, not beyond
    assert [b.take(1.0, 5000.0) for _ in range(6)].count(0.0) == 5


def test_bucket_sustained_rate_is_exact_over_a_long_run() -> None:
    b = TokenBucket(rate=20.0, capacity=100.0, now=0.0)
    granted, t = 0, 0.0
    while t < 60.0:  # a client retrying every 10 ms for a minute
        if b.take(1.0, t) == 0.0:
            granted += 1
        t += 0.01
    assert 100 + 20 * 60 - 1 <= granted <= 100 + 20 * 60 + 1


def test_bucket_request_above_capacity_is_granted_when_full_and_leaves_debt() -> None:
    b = TokenBucket(rate=100.0, capacity=50.0, now=0.0)
    assert b.take(120.0, 0.0) == 0.0  # full: granted, 70 tokens in debt
    assert b.take(1.0, 0.0) == pytest.approx(0.71)
    assert b.take(1.0, 0.5) == pytest.approx(0.21)  # -20 tokens
    assert b.take(1.0, 0.75) == 0.0  # +5 tokens, 4 left
    assert b.take(120.0, 0.75) == pytest.approx(0.46)  # needs a full bucket again


def test_bucket_clock_going_backwards_refills_nothing() -> None:
    b = TokenBucket(rate=1.0, capacity=1.0, now=10.0)
    assert b.take(1.0, 10.0) == 0.0
    assert b.take(1.0, 5.0) > 0  # earlier than the last stamp
    assert b.take(1.0, 10.5) == pytest.approx(0.5)
    assert b.take(1.0, 11.0) == 0.0


def test_retry_after_is_bounded() -> None:
    b = TokenBucket(rate=1e-9, capacity=1.0, now=0.0)
    assert b.take(1.0, 0.0) == 0.0
    assert b.take(1.0, 0.0) == MAX_RETRY_AFTER_S


# --- per-vehicle limiter -----------------------------------------------------------------------


def test_a_flooding_vehicle_does_not_use_up_the_others_budget() -> None:
    clock = Clock()
    lim = VehicleLimiter(RateLimit(uploads_per_s=2.0, upload_burst=3.0), clock)
    flood = [lim.upload("flood") for _ in range(50)]
    assert flood[:3] == [0.0] * 3 and all(w > 0 for w in flood[3:])
    assert [lim.upload("honest") for _ in range(3)] == [0.0] * 3
    assert lim.upload("flood") == pytest.approx(0.5)
    clock.t += 0.5
    assert lim.upload("flood") == 0.0


def test_observation_budget_counts_rows() -> None:
    clock = Clock()
    lim = VehicleLimiter(RateLimit(observations_per_s=100.0, observation_burst=1000.0), clock)
    assert lim.observations("v", 600) == 0.0
    assert lim.observations("v", 600) == pytest.approx(2.0)  # 400 left, 600 needed
    assert lim.observations("v", 400) == 0.0
    assert lim.observations("v", 0) == 0.0  # an empty batch costs nothing
    clock.t += 10.0
    assert lim.observations("v", 5000) == 0.0  # bigger than the bucket: granted when full
    assert lim.observations("v", 1) == pytest.approx(40.01)  # ... and repaid


def test_a_rate_of_zero_disables_the_limit() -> None:
    lim = VehicleLimiter(RateLimit(observations_per_s=0.0, uploads_per_s=0.0), Clock())
    assert all(lim.upload("v") == 0.0 for _ in range(10_000))
    assert lim.observations("v", 10**9) == 0.0
    assert len(lim) == 0


def test_the_least_recently_seen_vehicles_are_forgotten() -> None:
    clock = Clock()
    lim = VehicleLimiter(RateLimit(uploads_per_s=1.0, upload_burst=1.0, max_vehicles=3), clock)
    for v in ("a", "b", "c"):
        assert lim.upload(v) == 0.0
    assert lim.upload("a") > 0  # 'a' is now the most recently seen
    assert lim.upload("d") == 0.0  # 'b' is forgotten
    assert len(lim) == 3
    assert lim.upload("a") > 0 and lim.upload("c") > 0 and lim.upload("d") > 0
    assert lim.upload("b") == 0.0  # a fresh bucket


def test_new_vehicles_share_one_budget_and_known_ones_take_nothing() -> None:
    clock = Clock()
    lim = VehicleLimiter(RateLimit(new_vehicles_per_s=2.0, new_vehicle_burst=3.0), clock)
    recorded = {"old-1"}
    lookups: list[str] = []

    def in_db(v: str) -> bool:
        lookups.append(v)
        return v in recorded

    assert [lim.newcomer(f"new-{i}", in_db) for i in range(3)] == [0.0] * 3
    assert lim.newcomer("new-3", in_db) == pytest.approx(0.5)  # the burst is used up
    assert lim.newcomer("old-1", in_db) == 0.0  # recorded before: not new
    assert lim.newcomer("old-1", in_db) == 0.0 and lookups.count("old-1") == 1  # remembered
    lim.admitted("new-0")  # its upload was recorded
    assert lim.newcomer("new-0", in_db) == 0.0
    clock.t += 0.5
    assert lim.newcomer("new-3", in_db) == 0.0 and lim.newcomer("new-4", in_db) > 0
    off = VehicleLimiter(RateLimit(new_vehicles_per_s=0.0), clock)
    assert all(off.newcomer(f"v{i}", in_db) == 0.0 for i in range(1000))


def test_rate_limit_config_defaults_match_the_deploy_file() -> None:
    with open(ROOT / "deploy" / "services.toml", "rb") as f:
        table = tomllib.load(f)["ingest"]
    batching, cfg = service_config("ingest", table)
    assert cfg == IngestConfig() and batching == Batching(linger_s=batching.linger_s)
    cfg = from_mapping(IngestConfig, {"rate_limit": {"uploads_per_s": 0}}, "ingest")
    assert cfg.rate_limit.uploads_per_s == 0.0
    for bad in (
        {"observations_per_s": -1.0},
        {"upload_burst": 0.5},
        {"observation_burst": float("nan")},
        {"max_vehicles": 0},
        {"new_vehicle_burst": 0.5},
        {"new_vehicles_per_s": float("inf")},
    ):
        with pytest.raises(ConfigError):
            from_mapping(IngestConfig, {"rate_limit": bad}, "ingest")
    with pytest.raises(ConfigError, match=r"rate_limit\.burst: unknown key"):
        from_mapping(IngestConfig, {"rate_limit": {"burst": 1}}, "ingest")


# --- the vehicle uploader honours retry_after_s -------------------------------------------------


def test_uploader_keeps_rate_limited_observations_and_waits_retry_after(tmp_path, monkeypatch):
    clock = Clock()
    up = Uploader("veh-1", tmp_path / "q.sqlite", batch_size=10, clock=clock)
    up.enqueue(1, make_observations(25))
    answers: list[UploadAck] = []
    sent: list[ObservationBatch] = []

    def send(_session, batch: ObservationBatch, _timeout: float) -> UploadAck:
        sent.append(batch)
        ids = batch.obs.obs_id
        if len(sent) == 2:  # the second batch hits the rate limit
            err = DecodeError("rate", "vehicle 'veh-1' sends more than 5 uploads/s")
            ack = UploadAck("veh-1", batch.batch_id, ids[:0], error=err, retry_after_s=2.0)
        else:
            ack = UploadAck("veh-1", batch.batch_id, ids)
        answers.append(ack)
        return ack

    monkeypatch.setattr(up, "_send", send)
    res = up.flush(None)
    assert (res.accepted, res.failed_batches, res.retry_after_s) == (10, 1, 2.0)
    assert up.pending == 15 and up.rejected() == []  # refused by the rate: still queued
    assert up.retry_in == 2.0

    clock.t += 1.5
    res = up.flush(None)
    assert len(sent) == 2 and res.sent == 0  # nothing sent before retry_after_s
    assert res.retry_after_s == pytest.approx(0.5)

    clock.t += 0.5
    res = up.flush(None)
    assert res.accepted == 15 and up.pending == 0 and up.retry_in == 0.0
    assert len(sent) == 4
    up.close()


# --- a flooding vehicle against a real ingest ---------------------------------------------------

LIMITS = {
    "uploads_per_s": 5.0,
    "upload_burst": 5.0,
    "observations_per_s": 200.0,
    "observation_burst": 400.0,
}


def _ingest_with_limits(stack, tmp_path: Path) -> None:
    start_configured(stack, tmp_path, "ingest", "ingest.rate_limit", LIMITS)


def _obs(n: int, first_id: int) -> Observations:
    o = make_observations(n, seed=first_id)
    return Observations(
        **{**o.__dict__, "obs_id": np.arange(first_id, first_id + n, dtype=np.uint64)}
    )


@pytest.mark.integration
def test_a_flooding_vehicle_is_limited_and_an_honest_one_is_not(stack, tmp_path) -> None:
    _ingest_with_limits(stack, tmp_path)
    stop = threading.Event()
    lock = threading.Lock()
    flood_acks: list[UploadAck] = []
    ids = iter(range(1, 10**9, 50))

    def flood() -> None:
        with open_session(stack.bus) as s:
            deadline = time.monotonic() + 60.0
            while not stop.is_set() and time.monotonic() < deadline:
                with lock:
                    first = next(ids)
                batch = ObservationBatch("flood-1", 1, first, time.time(), _obs(50, first))
                for _k, ok, _e in query(s, keys.upload("flood-1"), batch.to_bytes(), timeout=10):
                    if ok is not None:
                        with lock:
                            flood_acks.append(UploadAck.from_bytes(ok))

    def rate_limited() -> list[UploadAck]:
        with lock:
            return [a for a in flood_acks if a.error is not None and a.error.field == "rate"]

    threads = [threading.Thread(target=flood, daemon=True) for _ in range(3)]
    started = time.monotonic()
    for t in threads:
        t.start()
    honest: list[UploadAck] = []
    try:
        assert wait_until(lambda: len(rate_limited()) >= 3, timeout=30.0)
        with open_session(stack.bus) as s:
            for k in range(10):  # 4 uploads/s of 20 observations: under both limits
                batch = ObservationBatch("honest-1", 1, k + 1, time.time(), _obs(20, 100 * k + 1))
                replies = query(s, keys.upload("honest-1"), batch.to_bytes(), timeout=20)
                honest.append(UploadAck.from_bytes(replies[0][1]))
                time.sleep(0.25)
    finally:
        stop.set()
        for t in threads:
            t.join(30)
    elapsed = time.monotonic() - started
    assert not any(t.is_alive() for t in threads)

    # the honest vehicle: every upload acknowledged in full, while the flood went on
    assert [(a.error, len(a.accepted)) for a in honest] == [(None, 20)] * 10
    # the flooder: refused with field 'rate' and a delay, nothing recorded for those
    limited = rate_limited()
    assert len(limited) >= 3
    for a in limited:
        assert a.retry_after_s > 0 and len(a.accepted) == 0 and "flood-1" in a.error.reason
    granted = [a for a in flood_acks if a.error is None]
    assert len(granted) + len(limited) == len(flood_acks)  # no other kind of answer
    n_obs = sum(len(a.accepted) for a in granted)
    assert n_obs <= LIMITS["observation_burst"] + LIMITS["observations_per_s"] * elapsed
    assert len(granted) <= LIMITS["upload_burst"] + LIMITS["uploads_per_s"] * elapsed

    with open_session(stack.bus) as s:
        stats = {st.service: st for st in collect(s)}["ingest"]
        assert stats.rejected.get("rate_limited") == len(limited)
        assert stats.counters["accepted"] == n_obs + 200

        # the vehicle uploader keeps what the rate refused and waits as told
        clock = Clock()
        up = Uploader("flood-2", tmp_path / "flood-2.sqlite", batch_size=500, clock=clock)
        try:
            up.enqueue(1, _obs(1200, 10**6))
            res = up.flush(s)  # 500 granted (full bucket, in debt), the next 500 refused
            assert (res.accepted, res.failed_batches) == (500, 1)
            assert res.retry_after_s > 0 and up.pending == 700 and up.rejected() == []
            uploads = _uploads(s)
            again = up.flush(s)
            assert again.sent == 0 and _uploads(s) == uploads  # nothing sent meanwhile
            time.sleep(res.retry_after_s + 0.05)  # the server's clock must pass it too
            clock.t += res.retry_after_s
            res = up.flush(s)
            assert res.accepted == 500 and up.pending == 200
        finally:
            up.close()


def _uploads(session) -> float:
    return {st.service: st for st in collect(session)}["ingest"].counters["uploads"]


@pytest.mark.integration
def test_new_vehicle_ids_are_admitted_at_the_budget_and_known_ones_always(stack, tmp_path):
    """A client inventing a vehicle id per upload gets the budget of new vehicles and no
    more; a vehicle ingest has recorded is never new again, also after ingest restarts
    (known from its database)."""
    budget = {"new_vehicles_per_s": 0.01, "new_vehicle_burst": 3}
    start_configured(stack, tmp_path, "ingest", "ingest.rate_limit", budget)

    def upload(s, vehicle: str, first: int) -> UploadAck:
        batch = ObservationBatch(vehicle, 1, first, time.time(), _obs(5, first))
        replies = query(s, keys.upload(vehicle), batch.to_bytes(), timeout=20)
        return UploadAck.from_bytes(replies[0][1])

    with open_session(stack.bus) as s:
        acks = [upload(s, f"sybil-{i}", 10 * i + 1) for i in range(6)]
        assert [a.error is None for a in acks] == [True] * 3 + [False] * 3
        for a in acks[3:]:
            assert a.error.field == "vehicle.new" and a.retry_after_s > 0
            assert len(a.accepted) == 0
        assert upload(s, "sybil-0", 1000).error is None  # known: no budget needed
        stats = {st.service: st for st in collect(s)}["ingest"]
        assert stats.rejected.get("vehicle.new") == 3
    stack.restart("ingest-all")
    stack.wait_ready(["ingest-all"], 60)
    with open_session(stack.bus) as s:
        assert [upload(s, f"later-{i}", 10 * i + 1).error is None for i in range(4)] == [
            True,
            True,
            True,
            False,
        ]
        assert upload(s, "sybil-1", 2000).error is None  # recorded before the restart
