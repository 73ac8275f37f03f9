"""Per-client limits on snapshot queries against a real router and publisher process.

The publisher runs with small limits (``[publisher.snapshots]``: 2 queries/s per client
after a burst of 5; a total far above what the test sends). One client flooding its own
snapshot key is refused with ``rate`` while another client's queries, made meanwhile, are
all answered; anonymous queries share the one client ``anonymous``; the publisher's stats
count every refusal. A map client under its vehicle id, refused while it fetches more
tiles than its burst, fetches them all after the refusals' ``retry_after_s``. Every loop
is bounded in time; the ``stack`` fixture stops the processes.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

from hdmap.ops.status import collect
from hdmap.runtime.bus import open_session, query
from schemas import ErrorReply, MapSnapshot, keys
from tests.support import start_configured, wait_until
from vehicle.mapclient import MapClient

pytestmark = pytest.mark.integration

TILE = "1202032333101011"
LIMITS = {"per_client_per_s": 2.0, "per_client_burst": 5.0, "total_per_s": 1000.0}


def start_publisher(stack, tmp_path: Path) -> None:
    start_configured(stack, tmp_path, "publisher", "publisher.snapshots", LIMITS)


def publisher_rejected(session) -> dict[str, int]:
    (st,) = [s for s in collect(session) if s.service == "publisher"]
    return dict(st.rejected)


def ask(session, key: str) -> tuple[MapSnapshot | None, ErrorReply | None, str]:
    """One snapshot query: (snapshot, error, reply key)."""
    replies = query(session, key, timeout=10.0)
    assert len(replies) == 1, replies  # one publisher, one answer
    k, ok, err = replies[0]
    return (
        MapSnapshot.from_bytes(ok) if ok is not None else None,
        ErrorReply.from_bytes(err) if err is not None else None,
        k,
    )


def test_a_flooding_client_is_refused_and_another_client_is_served(stack, tmp_path) -> None:
    start_publisher(stack, tmp_path)
    flood_key = keys.map_snapshot_for("flood-1", TILE)
    stop = threading.Event()
    lock = threading.Lock()
    served, refused = [], []

    def flood() -> None:
        with open_session(stack.bus) as s:
            deadline = time.monotonic() + 30.0
            while not stop.is_set() and time.monotonic() < deadline:
                snap, err, _k = ask(s, flood_key)
                with lock:
                    (served if snap is not None else refused).append(err)

    def n_refused() -> int:
        with lock:
            return len(refused)

    t = threading.Thread(target=flood, daemon=True)
    started = time.monotonic()
    t.start()
    honest = []
    try:
        assert wait_until(lambda: n_refused() >= 20, timeout=20.0)
        with open_session(stack.bus) as s:
            for _ in range(5):  # within its burst of 5, while the flood goes on
                honest.append(ask(s, keys.map_snapshot_for("honest-1", TILE)))
                time.sleep(0.1)
    finally:
        stop.set()
        t.join(20.0)
    elapsed = time.monotonic() - started
    assert not t.is_alive()

    # the other client: every query answered, on its own key
    for snap, err, key in honest:
        assert err is None and snap is not None and snap.tile == TILE
        assert key == keys.map_snapshot_for("honest-1", TILE)
    # the flooder: its burst and its rate served, the rest refused with a delay
    assert len(served) <= LIMITS["per_client_burst"] + LIMITS["per_client_per_s"] * elapsed + 1
    assert len(served) >= LIMITS["per_client_burst"]
    for err in refused:
        assert err is not None and (err.code, err.field) == ("rate", "snapshot.client")
        assert 0 < err.retry_after_s <= 1.0 / LIMITS["per_client_per_s"] + 1e-6
        assert "'flood-1'" in err.reason

    with open_session(stack.bus) as s:
        # anonymous queries are the one client 'anonymous': its burst, then refused
        t0 = time.monotonic()
        anonymous = [ask(s, keys.map_snapshot(TILE)) for _ in range(12)]
        took = time.monotonic() - t0
        answered = [snap for snap, _e, _k in anonymous if snap is not None]
        errors = [e for _s, e, _k in anonymous if e is not None]
        assert len(answered) + len(errors) == 12
        assert len(answered) <= LIMITS["per_client_burst"] + LIMITS["per_client_per_s"] * took + 1
        assert errors and all("'anonymous'" in e.reason for e in errors)
        # a wildcard client is no client: the existing 'tile' refusal (charged to anonymous)
        _snap, wild, _k = ask(s, keys.map_snapshot_for(keys.ANY, TILE))
        assert wild is not None and wild.field in ("tile", "snapshot.client")
        errors.append(wild)

        rejected = publisher_rejected(s)
        limited = [e for e in refused + errors if e.field == "snapshot.client"]
        assert rejected.get("snapshot.client") == len(limited)
        assert rejected.get("snapshot.tile", 0) == len(refused) + len(errors) - len(limited)
        assert rejected.get("snapshot.total", 0) == rejected.get("snapshot.queue", 0) == 0
    log = (stack.data_dir / "logs").glob("publisher*.log")
    assert not any("Traceback" in p.read_text() for p in log)


def test_a_refused_map_client_fetches_every_tile_after_the_delay(stack, tmp_path) -> None:
    start_publisher(stack, tmp_path)
    tiles = [TILE[:-2] + a + b for a in "0123" for b in "012"]  # 12 tiles, a burst of 5
    with open_session(stack.bus) as s:
        client = MapClient(s, radius_m=0.0, client_id="veh-7")
        try:
            for tile in tiles:
                client.follow(tile)
            assert wait_until(
                lambda: all(v >= 0 for v in client.versions().values()), timeout=30.0
            ), client.versions()
            assert client.stats.snapshots == len(tiles)
            refusals = client.stats.snapshots_refused
            assert refusals >= len(tiles) - LIMITS["per_client_burst"] - 1
            assert publisher_rejected(s).get("snapshot.client") == refusals
        finally:
            client.close()
