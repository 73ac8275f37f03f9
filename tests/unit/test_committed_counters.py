"""Counters read from committed state, backoff of failing transactions, and corruption met
while running stopping a stage service (issue #17, point 5).

In-process services on real SQLite with the replay (catch-up) served from a list, as in
``tests/integration/test_failure_handling.py``; faults are real SQLite failures: ``PRAGMA
query_only`` (what a read-only data dir looks like to SQLite), ``PRAGMA max_page_count``
(a full disk) and pages of the file overwritten on disk (corruption). Time is the
service's injectable clock, a fake one here: no test waits or asserts on real time, and
every loop is bounded.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import sqlite3
import threading
from collections.abc import Callable, Iterator
from itertools import pairwise
from pathlib import Path

import pytest

from hdmap.runtime.catchup import InlineExecutor
from hdmap.runtime.service import Backoff, Item, Service, ServiceOptions, run_until_signalled
from hdmap.runtime.stage import StageService
from hdmap.runtime.store import EXIT_CORRUPT, DatabaseCorrupt, StorageError, connect
from schemas import LogEntry, Stats, keys
from tests.support import Clock
from tests.support.services import Sink

PAGE = 4096


class Counted(StageService):
    """A stage that counts ``received`` per entry, stores each entry (with ``pad`` bytes,
    so a full disk refuses it) and emits one output entry per input entry. ``published``
    is its producer's log (the replay serves it); ``during`` runs inside the apply, after
    each entry is counted and before it is stored."""

    name = "counted"
    input_stage = "obs"
    output_stage = "assoc"

    def __init__(self, opts: ServiceOptions, published: list[LogEntry], pad: int = 0):
        super().__init__(opts)
        self.db.execute(
            "CREATE TABLE IF NOT EXISTS applied (n INTEGER PRIMARY KEY, tile TEXT NOT NULL, "
            "seq INTEGER NOT NULL, pad BLOB NOT NULL)"
        )
        self.published = published
        self.pad = pad
        self.pubs = Sink()  # type: ignore[assignment]
        self.session = None  # type: ignore[assignment]  # no bus: the replay below
        self.use_fetch(self._replay, executor=InlineExecutor())
        self.during: Callable[[], None] = lambda: None
        self.attempts: list[float] = []
        self.clock = Clock()

    def _replay(self, _selectors: list[str], _request: bytes) -> list[bytes]:
        """The producer's whole log, as its replay queryable would answer (no head)."""
        return [e.to_bytes() for e in sorted(self.published, key=lambda e: e.gseq)]

    def _apply_in_transaction(self, entries: list[LogEntry]) -> None:
        self.attempts.append(self.clock())
        super()._apply_in_transaction(entries)

    def apply(self, entries: list[LogEntry]) -> None:
        for e in entries:
            self.count("received")
            self.during()  # counted, not yet stored
            self.db.execute(
                "INSERT INTO applied(tile, seq, pad) VALUES (?, ?, zeroblob(?))",
                (e.tile, e.seq, self.pad),
            )
            self.emit(e.tile, e.body)

    def dead_letters(self) -> int:
        return int(self.db.execute("SELECT COUNT(*) FROM dead_letters").fetchone()[0])

    def run(self, stop: threading.Event) -> None:
        """The worker loop alone (a unit test opens no bus)."""
        self._loop(stop)


def make_log(n: int) -> list[LogEntry]:
    """``n`` entries of one producer over two tiles, seq per tile, gseq in order."""
    seqs: dict[str, int] = {}
    out = []
    for g in range(1, n + 1):
        tile = ("0123", "0130")[g % 2]
        seqs[tile] = seqs.get(tile, 0) + 1
        out.append(LogEntry("obs", "ingest-x", tile, seqs[tile], g, b"obs %d" % g))
    return out


def live(e: LogEntry) -> Item:
    return Item("entry", keys.obs(e.tile), e.to_bytes())


KICK = Item("kick", "", b"")


def stats_from_another_thread(svc: Service) -> Stats:
    """Stats as the stats queryable answers them: on a thread that is not the worker."""
    got: list[Stats] = []
    t = threading.Thread(target=lambda: got.append(svc.stats()))
    t.start()
    t.join(30)
    assert got, "stats did not answer"
    return got[0]


def committed_rows(path: Path) -> int:
    """Entries applied as another connection sees them: the committed state."""
    with contextlib.closing(connect(path, readonly=True)) as c:
        return int(c.execute("SELECT COUNT(*) FROM applied").fetchone()[0])


@pytest.fixture
def service(tmp_path: Path) -> Iterator[Callable[..., Counted]]:
    made: list[Counted] = []

    def make(published: list[LogEntry], pad: int = 0) -> Counted:
        svc = Counted(ServiceOptions(data_dir=tmp_path), published, pad)
        made.append(svc)
        return svc

    yield make
    for svc in made:
        with contextlib.suppress(sqlite3.Error):
            svc.db.close()


def break_storage(db: sqlite3.Connection, fault: str) -> None:
    if fault == "read-only":
        db.execute("PRAGMA query_only=ON")
    else:
        pages = db.execute("PRAGMA page_count").fetchone()[0]
        db.execute(f"PRAGMA max_page_count={pages}")


def repair_storage(db: sqlite3.Connection, fault: str) -> None:
    if fault == "read-only":
        db.execute("PRAGMA query_only=OFF")
    else:
        db.execute("PRAGMA max_page_count=1073741823")


# -- the backoff schedule --------------------------------------------------------------------


def test_the_backoff_retries_once_at_once_then_doubles_up_to_its_cap():
    b = Backoff(first_s=0.1, max_s=5.0)
    delays = [b.failed(100.0) for _ in range(10)]
    assert delays == [0.0, 0.1, 0.2, 0.4, 0.8, 1.6, 3.2, 5.0, 5.0, 5.0]
    assert b.waiting(104.0) and not b.fire(104.0) and b.wait_s(104.0) == pytest.approx(1.0)
    assert b.fire(105.0) and not b.fire(105.0)  # taken once
    b.succeeded()
    assert b.failures == 0 and b.failed(200.0) == 0.0


# -- counts become visible at commit and vanish at rollback --------------------------------------


class Bare(Service):
    name = "bare"


def test_counts_inside_a_transaction_are_shown_at_commit_only(tmp_path: Path):
    svc = Bare(ServiceOptions(data_dir=tmp_path))
    svc.count("kept", 2)
    seen: list[Stats] = []
    with svc.transaction():
        svc.count("kept", 3)
        svc.reject("obs.lat")
        seen.append(stats_from_another_thread(svc))
    assert seen[0].counters["kept"] == 2 and seen[0].counters["applying"] == 1
    assert "obs.lat" not in seen[0].rejected and "rejected" not in seen[0].counters
    after = stats_from_another_thread(svc)
    assert after.counters["kept"] == 5 and after.counters["applying"] == 0
    assert after.rejected == {"obs.lat": 1} and after.counters["rejected"] == 1

    with pytest.raises(ValueError), svc.transaction():
        svc.count("kept", 100)
        raise ValueError("the work failed")
    after = stats_from_another_thread(svc)
    assert after.counters["kept"] == 5 and after.counters["txn_failures"] == 1
    assert after.counters["last_txn_error.ValueError"] > 0
    assert after.counters["txn_failing"] == 0  # not a storage failure: no backoff

    def other_thread() -> None:  # not the transaction's thread: counted at once
        svc.count("process_only")

    with svc.transaction():
        t = threading.Thread(target=other_thread)
        t.start()
        t.join(30)
        assert svc.counters["process_only"] == 1
    svc.db.close()
    again = Bare(ServiceOptions(data_dir=tmp_path))
    assert again.counters["kept"] == 5 and again.counters["process_only"] == 1  # durable
    again.db.close()


@pytest.mark.parametrize("fault", ["read-only", "full"])
def test_stats_never_count_uncommitted_work_and_a_failing_stage_backs_off(service, fault):
    log = make_log(40)
    published = log[:5]
    svc = service(published, pad=64 * 1024 if fault == "full" else 0)
    reads: list[tuple[Stats, int]] = []  # a stats read, and the committed count then

    def read() -> None:
        reads.append((stats_from_another_thread(svc), committed_rows(svc.db_path)))

    svc.during = read
    svc.step([live(e) for e in published])
    assert committed_rows(svc.db_path) == 5

    break_storage(svc.db, fault)
    clock = svc.clock
    assert isinstance(clock, Clock)
    start = clock.t
    failing = len(svc.attempts)
    for i in range(200):  # 10 s of fake time, a kick every 50 ms, live entries now and then
        items = [KICK]
        if i % 20 == 0 and len(published) < 20:
            published.append(log[len(published)])
            items.append(live(published[-1]))
        svc.step(items)
        read()
        clock.t += 0.05
    tries = svc.attempts[failing:]
    gaps = [round(b - a, 6) for a, b in pairwise(tries)]
    # at once, then 0.1, 0.2, 0.4 ... s (rounded up to the 50 ms kicks), never over 5 s
    assert len(tries) <= 10, tries
    assert gaps[0] == 0.0 and gaps == sorted(gaps) and max(gaps) <= 5.0 + 0.05, gaps
    assert tries[-1] - start > 5.0  # it kept trying, spaced out
    st = stats_from_another_thread(svc)
    assert committed_rows(svc.db_path) == 5 and st.counters["received"] == 5
    assert st.counters["txn_failing"] == len(tries) and st.counters["storage_errors"] >= 1
    assert st.counters["txn_failures"] == len(tries) and st.counters["retry_in_s"] > 0
    name = "SQLITE_READONLY" if fault == "read-only" else "SQLITE_FULL"
    assert f"last_txn_error.{name}" in st.counters
    assert st.counters["entries_deferred"] >= 1  # live entries left to the replay
    assert st.counters["log_entries"] == 5 and len(svc.pubs.sent) == 5  # nothing uncommitted

    repair_storage(svc.db, fault)
    published += log[len(published) : 30]
    for _ in range(40):  # bounded: the retry is due within 5 s of fake time
        if committed_rows(svc.db_path) == 30:
            break
        clock.t += 0.5
        svc.step([])  # no item: the backoff's retry alone replays
    rows = svc.db.execute("SELECT tile, seq FROM applied ORDER BY n").fetchall()
    assert rows == [(e.tile, e.seq) for e in log[:30]]  # everything once, in order
    st = stats_from_another_thread(svc)
    assert st.counters["received"] == st.counters["entries_applied"] == 30
    assert st.counters["log_entries"] == 30 and len(svc.pubs.sent) == 30
    assert st.counters["txn_failing"] == 0 and st.counters["retry_in_s"] == 0
    assert st.counters["applying"] == 0 and svc.dead_letters() == 0

    # every read, inside an apply or between turns, showed committed counts only
    read()
    assert len(reads) > 200
    for stats, committed in reads:
        assert stats.counters.get("received", 0) <= committed  # the read precedes the count
        assert stats.counters.get("entries_applied", 0) == stats.counters.get("received", 0)
    inside = [s for s, _c in reads if s.counters["applying"]]
    assert inside and all(s.counters.get("received", 0) in (0, 5) for s in inside)
    if fault == "full":  # the inserts fail: reads inside the transactions that rolled back
        assert sum(1 for s in inside if s.counters["txn_failing"]) >= len(tries) - 1
    assert reads[-1][0].counters["received"] == reads[-1][1] == 30
    svc.db.close()
    again = service(published)
    assert again.counters["received"] == 30  # durable: what stats showed was committed


def test_a_read_during_a_long_apply_that_rolls_back_is_busy_not_quiet(service):
    """What ``wait_quiet`` compares: upstream ``log_entries`` against ``entries_applied``;
    during an apply that fails at its end, the applied count stays the committed one and
    ``applying`` is 1, so the chain never looks caught up."""
    from hdmap.ops.quiesce import is_quiet

    log = make_log(6)
    svc = service(list(log))
    mid: list[Stats] = []

    def fail_late() -> None:
        mid.append(stats_from_another_thread(svc))
        raise StorageError("storage failed: database or disk is full")

    svc.during = fail_late
    svc.step([KICK])
    up = {"log_entries": 6.0, "backlog": 0.0}

    def chain(c: dict[str, float]) -> dict[str, dict[str, float]]:
        return {
            "ingest": up,
            "matcher": {**c, "log_entries": 0.0},
            "solver": {"entries_applied": 0.0},
            "publisher": {"entries_applied": 0.0, "dirty": 0.0},
        }

    assert mid and all(m.counters.get("entries_applied", 0) == 0 for m in mid)
    assert all(m.counters["applying"] == 1 for m in mid)
    assert not any(is_quiet(chain(m.counters)) for m in mid)
    assert svc.counters.get("entries_applied", 0) == 0 and svc.backoff.failures >= 1
    assert not is_quiet(chain({"entries_applied": 6.0, "applying": 1.0}))
    assert is_quiet(chain({"entries_applied": 6.0, "applying": 0.0}))


# -- corruption met while running stops the stage service ---------------------------------------


def corrupt_table(path: Path, *tables: str) -> None:
    """Overwrite the tables' pages on disk, then write from another connection so the
    service's connection reads the file again (what a failing disk does meanwhile)."""
    with contextlib.closing(sqlite3.connect(path, isolation_level=None)) as c:
        assert c.execute("PRAGMA page_size").fetchone()[0] == PAGE
        busy, _, _ = c.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchone()
        assert busy == 0
        marks = ",".join("?" * len(tables))
        sql = f"SELECT pageno FROM dbstat WHERE name IN ({marks})"
        pages = [r[0] for r in c.execute(sql, tables)]
        with open(path, "r+b") as f:
            for pg in pages:
                f.seek((pg - 1) * PAGE)
                f.write(b"\xa5" * PAGE)
        c.execute("INSERT OR REPLACE INTO meta(key, value) VALUES ('touched', '1')")


def filled_service(service, n: int = 200) -> Counted:
    """A service that applied ``n`` entries (its ``applied`` table spans many pages)."""
    log = make_log(n)
    svc = service(log[: n // 2], pad=300)
    svc.step([KICK])
    assert committed_rows(svc.db_path) == n // 2
    svc.published += log[n // 2 :]
    svc.consumer.need_catchup = True
    return svc


@pytest.mark.parametrize("tables", [("applied",), ("applied", "offsets")])
def test_corruption_met_while_applying_is_raised_not_replayed(service, tables):
    """Also when the consumer meets the damage reloading its offsets on the rollback."""
    svc = filled_service(service)
    corrupt_table(svc.db_path, *tables)
    with pytest.raises(DatabaseCorrupt) as exc:
        svc.step([KICK])
    assert exc.value.path == str(svc.db_path)
    assert svc.dead_letters() == 0 and svc.backoff.failures == 0  # not a poison, no retry


def test_a_stage_service_that_meets_corruption_exits_65_naming_the_file(service, caplog):
    svc = filled_service(service)
    corrupt_table(svc.db_path, "applied")
    svc.inbox.put(KICK)
    handlers = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        with caplog.at_level(logging.ERROR):
            code = run_until_signalled(svc)
    finally:
        for s, h in handlers.items():
            signal.signal(s, h)
    assert code == EXIT_CORRUPT
    lines = [r.getMessage() for r in caplog.records if "stopping (exit 65" in r.getMessage()]
    assert len(lines) == 1 and lines[0].startswith(f"counted: {svc.db_path}: database is corrupt")


class Flushing(Service):
    """A service whose timer swallows storage errors (as the publisher's flush does)."""

    name = "flushing"

    def flush(self, _now: float) -> None:
        try:
            with self.transaction():
                self.db.execute("INSERT INTO applied(tile, seq, pad) VALUES ('0', 1, x'00')")
        except StorageError:
            self.count("storage_errors")


def test_corruption_swallowed_by_a_service_still_stops_it(tmp_path: Path):
    svc = Flushing(ServiceOptions(data_dir=tmp_path))
    svc.db.execute("CREATE TABLE applied (n INTEGER PRIMARY KEY, tile TEXT, seq INTEGER, pad BLOB)")
    svc.db.executemany(
        "INSERT INTO applied(tile, seq, pad) VALUES ('0', ?, zeroblob(300))",
        [(i,) for i in range(200)],
    )
    svc.every(1.0, svc.flush)
    svc.step([])
    corrupt_table(svc.db_path, "applied")
    svc.clock = lambda: 1e12  # the timer is due
    with pytest.raises(DatabaseCorrupt):
        svc.step([])
    svc.db.close()
