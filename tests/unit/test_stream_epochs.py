"""Producer epochs (issue 20): a producer restored from an old backup numbers its new
entries with ``seq`` and ``gseq`` values its consumers already applied (from the run it
lost); every entry carries its run's epoch and the tile's ``seq`` when that run began, so
a consumer resynchronises and applies the new entries, once, and nothing twice. Real
SQLite logs; the producer's answers computed by :func:`rows_since` as its replay
queryable computes them (no bus)."""

from __future__ import annotations

import sqlite3
from pathlib import Path

from hdmap.runtime.log_out import LogWriter, entries_of, rows_since
from hdmap.runtime.store import connect, transaction
from hdmap.runtime.stream import LogConsumer
from schemas import LogEntry, LogQuery

PRODUCER = "ingest-x"


class Producer:
    """A producer's log on ``path``; each instance is one run (a new epoch)."""

    def __init__(self, path: Path):
        self.path = path
        self.conn = connect(path)
        self.writer = LogWriter(self.conn, "obs", PRODUCER)

    def write(self, tiles: str) -> list[LogEntry]:
        with transaction(self.conn, [self.writer]):
            return [self.writer.append(t, t.encode()) for t in tiles.split()]

    def answer(self, req: LogQuery) -> list[bytes]:
        rows, head = rows_since(self.conn, LogQuery.from_bytes(req.to_bytes()), PRODUCER)
        return [*(e.to_bytes() for e in entries_of("obs", PRODUCER, rows)), head.to_bytes()]

    def backup(self, to: Path) -> None:
        dst = sqlite3.connect(to)
        self.conn.backup(dst)
        dst.close()

    def close(self) -> None:
        self.conn.close()


class Consumer:
    """A consumer that applies (records) what it is delivered, one transaction a batch."""

    def __init__(self, path: Path):
        self.conn = connect(path)
        self.c = LogConsumer(self.conn, "obs", [])
        self.applied: list[LogEntry] = []

    def apply(self, entries: list[LogEntry]) -> None:
        with transaction(self.conn, [self.c]):
            self.c.record(entries)
        self.applied += entries

    def live(self, entries: list[LogEntry]) -> None:
        for e in entries:
            self.apply(self.c.offer(e))

    def catch_up(self, prod: Producer, limit: int = 3) -> None:
        for _ in range(100):
            got, complete = self.c.absorb(prod.answer(self.c.query(limit)))
            self.apply(got)
            if complete and not self.c.need_catchup:
                return
            self.c.need_catchup = False
        raise AssertionError("catch-up did not complete")


def bodies(entries: list[LogEntry]) -> list[tuple[int, str, int]]:
    return [(e.epoch, e.tile, e.seq) for e in entries]


def test_a_restart_starts_a_newer_epoch_and_a_consumer_behind_it_just_catches_up(tmp_path):
    p = Producer(tmp_path / "p.sqlite")
    first = p.write("10 11 10")
    p.close()
    p = Producer(tmp_path / "p.sqlite")  # restarted: a new run on the same log
    second = p.write("10 12")
    assert second[0].epoch > first[0].epoch and second[0].base == 2 and second[1].base == 0
    c = Consumer(tmp_path / "c.sqlite")
    c.live(second[:1])  # ahead of its tile's gap: waits, no resync
    c.catch_up(p)
    assert sorted(bodies(c.applied)) == sorted(bodies(first + second))
    assert c.c.stats.resyncs == 0 and c.c.stats.duplicates == 0


def test_a_producer_restored_from_an_old_backup_loses_nothing_new_and_applies_nothing_twice(
    tmp_path,
):
    """The backup holds three entries; the run it then lost wrote five more, all applied;
    restored, the producer writes six new entries numbered like the lost ones. Live, then
    by a catch-up, then both, each new entry is applied once and no old one again."""
    for how in ("live", "catch-up", "both"):
        d = tmp_path / how
        d.mkdir()
        p = Producer(d / "p.sqlite")
        c = Consumer(d / "c.sqlite")
        c.live(p.write("10 11 10"))
        p.backup(d / "backup.sqlite")
        lost = p.write("10 11 12 10 11")
        c.live(lost)
        assert len(c.applied) == 8
        p.close()
        p = Producer(d / "backup.sqlite")  # the restore: a new run on the old log
        new = p.write("11 10 13 10 11 12")
        assert [e.seq for e in new] == [2, 3, 1, 4, 3, 1]  # seq values already applied
        assert min(e.gseq for e in new) <= max(e.gseq for e in lost)  # gseq values too
        if how in ("live", "both"):
            c.live(new[:4] if how == "both" else new)
        c.catch_up(p)
        # each once (in the new run's order live; a catch-up that meets the restore
        # applies what it met before asking again from where the new run began)
        assert sorted(bodies(c.applied[8:])) == sorted(bodies(new)), how
        if how == "live":
            assert bodies(c.applied[8:]) == bodies(new)
        assert c.c.stats.resyncs >= 1
        # a late live copy of a lost entry is not applied over the new run's
        c.live([lost[-1]])
        assert len(c.applied) == 14
        c.conn.close()
        again = Consumer(d / "c.sqlite")  # the offsets kept are the new run's
        again.live(new)
        again.catch_up(p)
        assert again.applied == []
        again.conn.close()
        p.close()


def test_a_restored_producer_is_met_by_its_head_when_no_new_entry_comes_live(tmp_path):
    """A consumer whose watermark is past where the restored producer's run began learns
    it from the run list of the producer's head, and asks again from there: new entries
    of tiles it has no gap in are not skipped."""
    p = Producer(tmp_path / "p.sqlite")
    c = Consumer(tmp_path / "c.sqlite")
    c.live(p.write("10 11"))
    c.catch_up(p)  # the consumer's watermark follows the producer
    p.backup(tmp_path / "backup.sqlite")
    c.live(p.write("12 12 12 13"))
    c.catch_up(p)
    assert c.c.watermarks[PRODUCER] == 6
    p.close()
    p = Producer(tmp_path / "backup.sqlite")
    new = p.write("20 12 21")  # gseq 3, 4, 5: below the watermark; tile 12 at seq 1
    c.catch_up(p)  # nothing came live
    assert sorted(bodies(c.applied[6:])) == sorted(bodies(new))
    assert c.c.watermarks[PRODUCER] == 5
    p.close()
