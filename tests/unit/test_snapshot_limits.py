"""The publisher's limits on snapshot queries (services/publisher/limits.py), with an
injected clock (no sleeping): the per-client burst and refill, the total budget over all
clients, the client LRU, the config from TOML; and the map client's retry delay."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from hdmap.cli.service import service_config
from hdmap.runtime.config import ConfigError, from_mapping
from hdmap.runtime.ratelimit import TokenBucket
from hdmap.runtime.service import Batching
from services.publisher.limits import SnapshotLimiter, SnapshotLimits
from services.publisher.service import PublisherConfig
from tests.support import Clock
from vehicle.mapclient import MIN_RETRY_S, RETRY_JITTER, retry_delay

ROOT = Path(__file__).resolve().parents[2]

NO_TOTAL = {"total_per_s": 0.0}


def served(lim: SnapshotLimiter, client: str, n: int) -> int:
    return sum(lim.check(client) is None for _ in range(n))


def test_a_client_gets_its_burst_then_its_rate() -> None:
    clock = Clock()
    lim = SnapshotLimiter(SnapshotLimits(per_client_per_s=20, per_client_burst=200), clock)
    assert served(lim, "veh-1", 250) == 200  # a vehicle fetching every tile around it
    err = lim.check("veh-1")
    assert err is not None
    assert (err.code, err.field) == ("rate", "snapshot.client")
    assert err.retry_after_s == pytest.approx(0.05) and "'veh-1'" in err.reason
    clock.t += 0.05  # one token back
    assert lim.check("veh-1") is None and lim.check("veh-1") is not None
    clock.t += 1.0
    assert served(lim, "veh-1", 100) == 20
    clock.t += 3600.0  # an idle hour refills to the burst, not beyond
    assert served(lim, "veh-1", 300) == 200


def test_a_flooding_client_leaves_the_others_their_budget() -> None:
    clock = Clock()
    lim = SnapshotLimiter(SnapshotLimits(per_client_per_s=5, per_client_burst=10), clock)
    assert served(lim, "flood", 10_000) == 10
    assert served(lim, "honest", 10) == 10
    assert served(lim, "anonymous", 10) == 10  # the anonymous key's one shared client


def test_the_total_budget_holds_many_ids_and_gives_back_the_clients_token() -> None:
    clock = Clock()
    limits = SnapshotLimits(per_client_per_s=1, per_client_burst=2, total_per_s=100, total_burst=50)
    lim = SnapshotLimiter(limits, clock)
    answers = [lim.check(f"sybil-{k}") for k in range(80)]  # a new id each query
    assert sum(a is None for a in answers) == 50
    refused = [a for a in answers if a is not None]
    assert {(a.code, a.field) for a in refused} == {("busy", "snapshot.total")}
    assert refused[0].retry_after_s == pytest.approx(0.01)
    # a client refused by the total was not charged: its own burst is still whole
    clock.t += 1.0  # +100 total tokens, capped at 50
    assert [lim.check("sybil-79") for _ in range(3)][:2] == [None, None]
    # long run: the total rate, whatever the ids
    clock.t += 10.0
    n = 0
    for step in range(1000):  # 10 s at 100 queries/s of 10 ids each
        clock.t += 0.01
        n += sum(lim.check(f"s-{step}-{i}") is None for i in range(10))
    assert 50 + 1000 - 2 <= n <= 50 + 1000 + 2


def test_the_least_recently_seen_clients_are_forgotten() -> None:
    clock = Clock()
    limits = SnapshotLimits(per_client_per_s=1, per_client_burst=1, max_clients=3, **NO_TOTAL)
    lim = SnapshotLimiter(limits, clock)
    for c in ("a", "b", "c"):
        assert lim.check(c) is None
    assert lim.check("a") is not None  # 'a' is now the most recently seen
    assert lim.check("d") is None  # 'b' is forgotten
    assert len(lim) == 3
    assert all(lim.check(c) is not None for c in ("a", "c", "d"))
    assert lim.check("b") is None  # a fresh bucket
    assert len(lim) == 3


def test_a_rate_of_zero_disables_that_limit() -> None:
    clock = Clock()
    lim = SnapshotLimiter(SnapshotLimits(per_client_per_s=0, **NO_TOTAL), clock)
    assert served(lim, "v", 10_000) == 10_000 and len(lim) == 0
    only_total = SnapshotLimiter(SnapshotLimits(per_client_per_s=0, total_burst=5), clock)
    assert served(only_total, "v", 10) == 5


def test_queue_busy_reply_and_its_delay() -> None:
    err = SnapshotLimits(max_queued=1000, total_per_s=2000).queue_busy()
    assert (err.code, err.field, err.retry_after_s) == ("busy", "snapshot.queue", 0.5)
    assert SnapshotLimits(max_queued=1).queue_retry_s == 0.1
    assert SnapshotLimits(total_per_s=0).queue_retry_s == 1.0


def test_bucket_refund_never_exceeds_the_capacity() -> None:
    b = TokenBucket(rate=1.0, capacity=2.0, now=0.0)
    assert b.take(1.0, 0.0) == 0.0
    b.refund(5.0)
    assert b.tokens == 2.0
    assert [b.take(1.0, 0.0) for _ in range(3)][:2] == [0.0, 0.0]


def test_snapshot_limits_config_defaults_match_the_deploy_file() -> None:
    with open(ROOT / "deploy" / "services.toml", "rb") as f:
        table = tomllib.load(f)["publisher"]
    batching, cfg = service_config("publisher", table)
    assert cfg == PublisherConfig() and batching == Batching(linger_s=batching.linger_s)
    cfg = from_mapping(PublisherConfig, {"snapshots": {"per_client_per_s": 5}}, "publisher")
    assert (
        cfg.snapshots.per_client_per_s == 5.0
        and cfg.snapshots.total_per_s == PublisherConfig().snapshots.total_per_s
    )
    for bad, name in (
        ({"per_client_per_s": -1.0}, "per_client_per_s"),
        ({"per_client_burst": 0.5}, "per_client_burst"),
        ({"total_per_s": float("inf")}, "total_per_s"),
        ({"total_burst": 0.0}, "total_burst"),
        ({"max_clients": 0}, "max_clients"),
        ({"max_queued": 0}, "max_queued"),
    ):
        with pytest.raises(ConfigError, match=rf"snapshots\.{name}: "):
            from_mapping(PublisherConfig, {"snapshots": bad}, "publisher")
    with pytest.raises(ConfigError, match=r"snapshots\.rate: unknown key"):
        from_mapping(PublisherConfig, {"snapshots": {"rate": 1}}, "publisher")


def test_map_client_retry_delay_is_bounded_and_jittered() -> None:
    assert retry_delay(0.0, 0.0) == MIN_RETRY_S  # no advice: still no busy loop
    assert retry_delay(-5.0, 0.99) < MIN_RETRY_S * (1 + RETRY_JITTER)
    assert retry_delay(2.0, 0.0) == 2.0
    assert retry_delay(2.0, 0.999) == pytest.approx(2.0 * (1 + RETRY_JITTER), rel=1e-2)
    assert retry_delay(86400.0, 0.999, max_s=60.0) <= 60.0 * (1 + RETRY_JITTER)
    delays = {retry_delay(1.0, u / 10) for u in range(10)}
    assert len(delays) == 10 and min(delays) == 1.0 and max(delays) < 1.0 + RETRY_JITTER
