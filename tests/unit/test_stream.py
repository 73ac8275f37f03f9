"""Durable stage logs: ordering, duplicates, gaps, rollback, and replay over a real router."""

from __future__ import annotations

import pytest

from hdmap.runtime.catchup import catch_up
from hdmap.runtime.log_out import LogServer, LogWriter
from hdmap.runtime.store import StorageError, connect, transaction
from hdmap.runtime.stream import LogConsumer
from schemas import LogEntry


def entry(tile: str, seq: int, gseq: int | None = None, producer: str = "p1") -> LogEntry:
    return LogEntry("obs", producer, tile, seq, gseq or seq, b"body")


@pytest.fixture
def db(tmp_path):
    conn = connect(tmp_path / "c.sqlite")
    yield conn
    conn.close()


def test_in_order_entries_are_delivered_once(db):
    c = LogConsumer(db, "obs", [])
    got = [e.seq for s in (1, 2, 3) for e in c.offer(entry("7", s))]
    assert got == [1, 2, 3]
    assert c.offer(entry("7", 2)) == []
    assert c.stats.duplicates == 1


def test_gap_buffers_until_the_missing_entry_arrives(db):
    c = LogConsumer(db, "obs", [])
    assert [e.seq for e in c.offer(entry("1", 1))] == [1]
    assert c.offer(entry("1", 3)) == []
    assert c.offer(entry("1", 4)) == []
    assert c.need_catchup
    assert [e.seq for e in c.offer(entry("1", 2))] == [2, 3, 4]


def test_region_filter(db):
    c = LogConsumer(db, "obs", ["12"])
    assert c.offer(entry("1300", 1)) == []
    assert len(c.offer(entry("1203", 1))) == 1


def test_offsets_survive_a_restart_only_when_committed(tmp_path):
    path = tmp_path / "c.sqlite"
    conn = connect(path)
    c = LogConsumer(conn, "obs", [])
    delivered = c.offer(entry("1", 1)) + c.offer(entry("1", 2))
    with transaction(conn, [c]):
        c.record(delivered)
    more = c.offer(entry("1", 3))
    with pytest.raises(StorageError), transaction(conn, [c]):
        c.record(more)
        conn.execute("INSERT INTO no_such_table VALUES (1)")
    assert c.offsets == {("p1", "1"): 2}
    assert [e.seq for e in c.offer(entry("1", 3))] == [3]  # rewound after the rollback
    conn.close()
    conn = connect(path)
    again = LogConsumer(conn, "obs", [])
    assert again.offsets == {("p1", "1"): 2}
    assert again.offer(entry("1", 2)) == []
    conn.close()


def test_writer_numbers_per_tile_and_globally(db):
    w = LogWriter(db, "obs", "p1")
    with transaction(db, [w]):
        a = w.append("1", b"a")
        b = w.append("2", b"b")
        c = w.append("1", b"c")
    assert (a.seq, b.seq, c.seq) == (1, 1, 2)
    assert (a.gseq, b.gseq, c.gseq) == (1, 2, 3)
    with pytest.raises(RuntimeError), transaction(db, [w]):
        w.append("1", b"lost")
        raise RuntimeError("abort")
    with transaction(db, [w]):
        d = w.append("1", b"d")
    assert (d.seq, d.gseq) == (3, 4)
    assert LogWriter(db, "obs", "p1").heads == {"1": 3, "2": 1}


@pytest.mark.integration
def test_catch_up_replays_what_a_consumer_missed(tmp_path, router_session):
    prod = connect(tmp_path / "p.sqlite")
    w = LogWriter(prod, "obs", "ingest-x")
    with transaction(prod, [w]):
        for i in range(25):
            w.append("1202" if i % 2 else "1203", f"b{i}".encode())
    server = LogServer(router_session, tmp_path / "p.sqlite", "obs", "ingest-x")
    try:
        cons = connect(tmp_path / "c.sqlite")
        c = LogConsumer(cons, "obs", ["1202"])
        got = catch_up(c, router_session, timeout=5.0, limit=4)
        assert [e.seq for e in got] == list(range(1, 13))
        assert all(e.tile == "1202" for e in got)
        assert [e.gseq for e in got] == sorted(e.gseq for e in got)
        assert catch_up(c, router_session, timeout=5.0) == []
        cons.close()
    finally:
        server.close()
        prod.close()
