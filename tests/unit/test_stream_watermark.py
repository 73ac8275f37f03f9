"""Catch-up by watermark: a replay query lists only the tiles active since the last
catch-up and the tiles with a gap, whatever the region ever held; nothing is lost.

The producer's answer is computed by :func:`rows_since` on its SQLite log, exactly as
its queryable does, and handed to :meth:`LogConsumer.absorb` without a bus.
"""

from __future__ import annotations

import pytest

from hdmap.runtime.log_out import SCAN_FACTOR, LogWriter, entries_of, rows_since
from hdmap.runtime.store import StorageError, connect, transaction
from hdmap.runtime.stream import LogConsumer
from schemas import LogEntry, LogHead, LogQuery

PRODUCER = "ingest-x"


class Producer:
    """A producer's log and the answers its replay queryable would give."""

    def __init__(self, path):
        self.conn = connect(path)
        self.writer = LogWriter(self.conn, "obs", PRODUCER)

    def write(self, tiles: list[str]) -> list[LogEntry]:
        out = []
        with transaction(self.conn, [self.writer]):
            for t in tiles:
                out.append(self.writer.append(t, b"x"))
        return out

    def answer(self, req: LogQuery) -> list[bytes]:
        rows, head = rows_since(self.conn, LogQuery.from_bytes(req.to_bytes()), PRODUCER)
        replies = [e.to_bytes() for e in entries_of("obs", PRODUCER, rows)]
        return [*replies, head.to_bytes()]


def catch_up(c: LogConsumer, prod: Producer, limit: int = 100) -> list[LogEntry]:
    out: list[LogEntry] = []
    for _ in range(1000):
        got, complete = c.absorb(prod.answer(c.query(limit)))
        out += got
        if complete:
            return out
    raise AssertionError("catch-up did not finish in 1000 rounds")


def apply(conn, c: LogConsumer, entries: list[LogEntry]) -> None:
    with transaction(conn, [c]):
        c.record(entries)


@pytest.fixture
def prod(tmp_path):
    p = Producer(tmp_path / "p.sqlite")
    yield p
    p.conn.close()


@pytest.fixture
def cons(tmp_path):
    conn = connect(tmp_path / "c.sqlite")
    yield conn
    conn.close()


def listed(req: LogQuery) -> int:
    return sum(len(t) for t in req.offsets.values())


def test_the_query_stays_small_however_many_tiles_were_touched(prod, cons, tmp_path):
    tiles = [f"1{i:04d}".translate(str.maketrans("456789", "012301")) for i in range(3000)]
    tiles = sorted(set(tiles))
    written = prod.write(tiles)
    c = LogConsumer(cons, "obs", [])
    got = catch_up(c, prod, limit=500)
    assert sorted((e.tile, e.seq) for e in got) == sorted((e.tile, e.seq) for e in written)
    apply(cons, c, got)
    req = c.query(500)
    assert listed(req) == 0
    assert req.after_gseq == {PRODUCER: written[-1].gseq}
    # ten live entries on new tiles: the next query lists those ten, not 3,000
    live = prod.write(tiles[:10])
    for e in live:
        assert c.offer(e) == [e]
    assert listed(c.query(500)) == 10
    assert catch_up(c, prod) == []
    assert listed(c.query(500)) == 0
    # after a restart the committed watermark holds: the first query lists nothing
    apply(cons, c, live)
    again = LogConsumer(connect(tmp_path / "c.sqlite"), "obs", [])
    assert listed(again.query(500)) == 0
    assert again.query(500).after_gseq == {PRODUCER: live[-1].gseq}


def test_an_entry_lost_live_is_replayed(prod, cons):
    c = LogConsumer(cons, "obs", [])
    apply(cons, c, catch_up(c, prod))
    a, _b, d = prod.write(["10", "11", "12"])
    assert c.offer(a) == [a] and c.offer(d) == [d]  # b (a tile never seen) is lost live
    got = catch_up(c, prod)
    assert [(e.tile, e.seq) for e in got] == [("11", 1)]


def test_a_gap_below_the_watermark_is_filled(prod, cons):
    """A tile waiting behind a gap is listed whatever its gseq: a watermark raised too
    far (a forged head, say) delays nothing that a later entry of the tile reveals."""
    c = LogConsumer(cons, "obs", [])
    first = prod.write(["10", "10", "10"])
    assert c.offer(first[0]) == [first[0]]
    c._advance(PRODUCER, 10**9)  # as if a head had claimed everything
    assert c.offer(first[2]) == []  # seq 3 waits behind the missing seq 2
    got = catch_up(c, prod)
    assert [e.seq for e in got] == [2, 3]


def test_the_watermark_stays_below_an_entry_waiting_behind_a_gap(prod, cons):
    c = LogConsumer(cons, "obs", [])
    e1, _e2, e3 = prod.write(["10", "10", "11"])
    assert c.offer(e1) == [e1]
    assert c.offer(e3) == [e3]
    buffered = LogEntry("obs", PRODUCER, "10", 3, e3.gseq + 5, b"ahead")
    assert c.offer(buffered) == []
    c._advance(PRODUCER, e3.gseq + 100)
    assert c.query(10).after_gseq[PRODUCER] == buffered.gseq - 1


def test_the_watermark_is_saved_only_with_nothing_delivered_uncommitted(prod, cons, tmp_path):
    c = LogConsumer(cons, "obs", [])
    got = catch_up(c, prod) + [e for x in prod.write(["10", "11"]) for e in c.offer(x)]
    assert len(got) == 2
    catch_up(c, prod)
    apply(cons, c, got[:1])  # "11" is delivered, not committed
    assert c.watermarks == {}
    apply(cons, c, got[1:])
    assert c.watermarks == {PRODUCER: got[1].gseq}


def test_a_rollback_rewinds_the_watermark(prod, cons):
    c = LogConsumer(cons, "obs", [])
    got = catch_up(c, prod) + catch_up(c, prod)
    got = [e for x in prod.write(["10"]) for e in c.offer(x)]
    catch_up(c, prod)
    with pytest.raises(StorageError), transaction(cons, [c]):
        c.record(got)
        cons.execute("INSERT INTO no_such_table VALUES (1)")
    assert c.watermarks == {} and c.query(10).after_gseq == {}
    assert [e.seq for e in catch_up(c, prod)] == [1]


def test_a_sparse_region_is_answered_in_bounded_scans(prod, cons):
    limit = 4
    n_other = SCAN_FACTOR * limit * 3
    written = prod.write(["2"] * n_other + ["10"])
    c = LogConsumer(cons, "obs", ["1"])
    rounds, got = 0, []
    for rounds in range(1, 100):  # noqa: B007 - the count is the result
        delivered, complete = c.absorb(prod.answer(c.query(limit)))
        got += delivered
        if complete:
            break
    assert [(e.tile, e.gseq) for e in got] == [("10", written[-1].gseq)]
    assert rounds == 4  # three scans of SCAN_FACTOR * limit entries, then the region's one


def test_a_truncated_answer_continues_where_it_stopped(prod, cons):
    written = prod.write(["10", "11"] * 30)
    c = LogConsumer(cons, "obs", [])
    rows, head = rows_since(prod.conn, c.query(7), PRODUCER)
    assert len(rows) == 7 and head.through == rows[-1][0] < head.head and not head.complete
    got = catch_up(c, prod, limit=7)
    assert [e.gseq for e in got] == [e.gseq for e in written]


def test_codec_round_trips():
    q = LogQuery("obs", {"p": {"12": 3}}, ["1"], 10, {"p": 7})
    back = LogQuery.from_bytes(q.to_bytes())
    assert back.after_gseq == {"p": 7} and back.offsets == {"p": {"12": 3}}
    assert LogQuery.from_bytes(LogQuery("obs", {}, [], 10).to_bytes()).after_gseq is None
    h = LogHead.from_bytes(LogHead("obs", "p", 3, 9).to_bytes())
    assert (h.through, h.head, h.complete) == (3, 9, False)


def test_a_quiet_producers_head_reaches_the_mark_without_new_entries(tmp_path, prod) -> None:
    """Entries applied live, then the producer falls quiet: the next catch-up's head raises
    the watermark, and an empty record commits it, so the mark reaches the producer's head
    (a paused region's consumers drain it: hdmap region split)."""
    conn = connect(tmp_path / "c.sqlite")
    c = LogConsumer(conn, "obs", [])
    live = prod.write(["0", "1", "0"])
    for e in live:
        apply(conn, c, c.offer(e))
    assert c.marks("me") == []  # live entries alone raise no watermark
    assert catch_up(c, prod) == []  # nothing missing; the head says 3
    assert c.marks_behind
    apply(conn, c, [])
    assert not c.marks_behind
    assert [(m.producer, m.gseq) for m in c.marks("me")] == [(PRODUCER, 3)]
    again = LogConsumer(conn, "obs", [])  # committed: a restart keeps it
    assert again.watermarks == {PRODUCER: 3}
