"""Retention (issue 20, bounded storage): a producer deletes the entries every consumer
that sent a mark has applied, once older than the floor; a consumer left behind gets a
refusal naming ``after_gseq`` instead of an answer that silently lacks entries; numbering
goes on after the log was truncated whole. Real SQLite; the refusal over a real router."""

from __future__ import annotations

import time

import pytest

from hdmap.runtime.catchup import catch_up
from hdmap.runtime.log_out import LogServer, LogWriter
from hdmap.runtime.log_policy import RetentionPolicy
from hdmap.runtime.retention import LogRetention, truncated_through
from hdmap.runtime.store import connect, transaction
from hdmap.runtime.stream import LogConsumer
from schemas import DecodeError, LogEntry, LogHead, LogMark

P = "ingest-x"
DAY = 86_400.0


class Wall:
    def __init__(self) -> None:
        self.t = time.time()

    def __call__(self) -> float:
        return self.t


def producer(path, wall: Wall, **policy):
    conn = connect(path)
    w = LogWriter(conn, "obs", P)
    r = LogRetention(conn, "obs", P, RetentionPolicy(**policy), wall)
    return conn, w, r


def write(conn, w: LogWriter, n: int) -> None:
    with transaction(conn, [w]):
        for i in range(n):
            w.append("1202" if i % 2 else "1203", b"x")


def rows(conn) -> list[int]:
    return [g for (g,) in conn.execute("SELECT gseq FROM log_out ORDER BY gseq")]


def mark(consumer: str, gseq: int, w: LogWriter) -> LogMark:
    return LogMark("obs", P, consumer, gseq, w.epoch)


def test_entries_go_once_every_consumer_has_them_and_they_are_older_than_the_floor(tmp_path):
    wall = Wall()
    conn, w, r = producer(tmp_path / "p.sqlite", wall, retain_s=60.0, forget_after_s=DAY)
    write(conn, w, 50)
    with transaction(conn):
        assert r.truncate() == 0  # no consumer has said anything: nothing goes
        r.on_mark(mark("matcher-a", 30, w))
        r.on_mark(mark("matcher-b", 20, w))
        assert r.truncate() == 0  # all younger than the floor
    wall.t += 120.0
    with transaction(conn):
        assert r.truncate() == 20  # the slower consumer's mark
    assert rows(conn)[0] == 21 and truncated_through(conn) == 20
    wall.t += 2 * DAY  # b went silent: it no longer holds the log
    with transaction(conn):
        r.on_mark(mark("matcher-a", 50, w))
        assert r.truncate() == 30
    assert rows(conn) == [] and truncated_through(conn) == 50
    conn.close()
    conn, w, r = producer(tmp_path / "p.sqlite", wall)  # restarted on an empty log
    write(conn, w, 1)
    assert rows(conn) == [51]  # numbering goes on
    conn.close()


def test_a_mark_for_another_log_or_a_run_the_producer_lost_is_refused(tmp_path):
    wall = Wall()
    conn, w, r = producer(tmp_path / "p.sqlite", wall, retain_s=1.0)
    write(conn, w, 10)
    with pytest.raises(DecodeError) as e:
        r.on_mark(LogMark("obs", P, "m", 5, w.epoch + 1))  # from a run it does not have
    assert e.value.field == "epoch"
    with pytest.raises(DecodeError) as e:
        r.on_mark(LogMark("assoc", P, "m", 5, w.epoch))
    assert e.value.field == "producer"
    wall.t += 10.0
    with transaction(conn):
        assert r.truncate() == 0
    conn.close()


def test_a_consumer_marks_its_committed_watermark_but_not_across_a_gap(tmp_path):
    conn = connect(tmp_path / "c.sqlite")
    c = LogConsumer(conn, "obs", [])
    es = [LogEntry("obs", P, "1203", s, s, b"x", 7, 0, 0) for s in (1, 2, 3)]
    got, _ = c.absorb([e.to_bytes() for e in es] + [LogHead("obs", P, 3, 3).to_bytes()])
    with transaction(conn, [c]):
        c.record(got)
    assert [(m.producer, m.consumer, m.gseq, m.epoch) for m in c.marks("matcher-1")] == [
        (P, "matcher-1", 3, 7)
    ]
    assert c.offer(LogEntry("obs", P, "1203", 5, 5, b"x", 7, 0, 0)) == []  # 4 missing
    assert c.marks("matcher-1") == []
    conn.close()


@pytest.mark.integration
def test_a_consumer_behind_a_truncated_log_is_refused_naming_after_gseq(tmp_path, router_session):
    wall = Wall()
    conn, w, r = producer(tmp_path / "p.sqlite", wall, retain_s=1.0)
    write(conn, w, 40)
    server = LogServer(router_session, tmp_path / "p.sqlite", "obs", P)
    try:
        ok = LogConsumer(connect(tmp_path / "ok.sqlite"), "obs", [])
        assert len(catch_up(ok, router_session, timeout=5.0)) == 40
        wall.t += 10.0
        with transaction(conn):
            r.on_mark(mark("matcher-a", 40, w))
            assert r.truncate() == 40
        write(conn, w, 10)
        got = catch_up(ok, router_session, timeout=5.0)
        assert [e.gseq for e in got] == list(range(41, 51)) and ok.stats.replay_refused == 0
        late = LogConsumer(connect(tmp_path / "late.sqlite"), "obs", [])  # never marked
        assert catch_up(late, router_session, timeout=5.0) == []
        assert late.stats.replay_refused == 1
    finally:
        server.close()
        conn.close()


def test_a_consumer_leaving_for_good_no_longer_holds_the_log(tmp_path):
    """A mark at gseq 0 (an instance stopped by a region's handover) forgets the consumer
    at once; the others' marks decide alone."""
    wall = Wall()
    conn, w, r = producer(tmp_path / "p.sqlite", wall, retain_s=1.0)
    write(conn, w, 20)
    wall.t += 10.0
    with transaction(conn):
        r.on_mark(mark("matcher-old", 5, w))
        r.on_mark(mark("matcher-new", 20, w))
    assert r.through() == 5
    with transaction(conn):
        r.on_mark(mark("matcher-old", 0, w))
        assert r.through() == 20 and r.truncate() == 20
    conn.close()
