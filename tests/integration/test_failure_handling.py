"""Quick failure-handling tests: a full or read-only data dir at ingest, and the stage loop
(hdmap/runtime/stage.py) under poison entries, storage failures and replays.

Ingest runs in this process (its worker on a thread) against a real router process, so
the test can break its database on the worker thread: ``PRAGMA query_only`` is what a
read-only data dir looks like to SQLite (SQLITE_READONLY), ``PRAGMA max_page_count`` at
the current size a full disk (SQLITE_FULL). Where the test may mount a tmpfs (root on
Linux), a real full disk is tested too, on an ingest process. The stage tests drive
``StageService.handle`` directly, with the replay (catch-up) served from a list.
"""

from __future__ import annotations

import contextlib
import errno
import os
import queue
import sqlite3
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from fleetsim.synthetic import make_observations
from hdmap.ops.status import collect
from hdmap.runtime.bus import open_session, query
from hdmap.runtime.catchup import InlineExecutor
from hdmap.runtime.service import Item, ServiceOptions
from hdmap.runtime.stage import StageService
from hdmap.runtime.store import EXIT_RESTART, StorageError, connect, transaction
from schemas import LogEntry, LogQuery, ObservationBatch, ObsGroup, UploadAck, keys
from services.ingest.service import IngestService

# -- ingest on a broken data dir -------------------------------------------------------------


class BreakableIngest(IngestService):
    """Ingest whose worker runs the statements queued in ``breaks`` before its next batch."""

    def __init__(self, opts: ServiceOptions):
        super().__init__(opts)
        self.breaks: queue.Queue[Callable[[sqlite3.Connection], object]] = queue.Queue()
        self.worker: threading.Thread | None = None

    def handle(self, items: list[Item]) -> None:
        while not self.breaks.empty():
            self.breaks.get_nowait()(self.db)
        super().handle(items)


def read_only(db: sqlite3.Connection) -> None:
    db.execute("PRAGMA query_only=ON")


def full(db: sqlite3.Connection) -> None:
    pages = db.execute("PRAGMA page_count").fetchone()[0]
    db.execute(f"PRAGMA max_page_count={pages}")


def repaired(db: sqlite3.Connection) -> None:
    db.execute("PRAGMA query_only=OFF")
    db.execute("PRAGMA max_page_count=4294967294")


@pytest.fixture
def ingest_in_process(stack, tmp_path) -> Iterator[BreakableIngest]:
    stack.start_router()
    svc = BreakableIngest(ServiceOptions(data_dir=tmp_path / "data", bus=stack.bus))
    stop = threading.Event()
    worker = svc.worker = threading.Thread(target=svc.run, args=(stop,), daemon=True)
    worker.start()
    try:
        with open_session(stack.bus) as s:
            deadline = time.monotonic() + 30
            while not any(st.service == "ingest" for st in collect(s, 1.0)):
                assert time.monotonic() < deadline and worker.is_alive()
                time.sleep(0.05)
        yield svc
    finally:
        stop.set()
        worker.join(15)
        assert not worker.is_alive()


def upload(s, vehicle: str, batch_id: int, obs) -> UploadAck:
    payload = ObservationBatch(vehicle, 1, batch_id, time.time(), obs).to_bytes()
    replies = [ok for _k, ok, _e in query(s, keys.upload(vehicle), payload, 10.0) if ok]
    assert len(replies) == 1
    return UploadAck.from_bytes(replies[0])


def logged_obs(s) -> list[int]:
    """Observation ids in ingest's obs log (what the matcher would replay)."""
    req = LogQuery("obs", {}, [], 10_000).to_bytes()
    ids: list[int] = []
    for _k, ok, _e in query(s, f"{keys.ROOT}/log/obs/*/*", req, 10.0):
        if ok is not None:
            ids += ObsGroup.from_bytes(LogEntry.from_bytes(ok).body).obs.obs_id.tolist()
    return sorted(ids)


def batch(first: int, n: int, seed: int):
    obs = make_observations(n, seed=seed)
    obs.obs_id[:] = np.arange(first, first + n, dtype=np.uint64)
    return obs


def refuses_then_recovers(
    s, stats: Callable[[], dict], break_it: Callable[[], None], repair: Callable[[], None]
) -> None:
    """The scenario shared by every storage failure (``s``: a session on the router)."""
    a, b = batch(1, 40, 1), batch(1000, 300, 2)
    ok = upload(s, "veh-1", 1, a)
    assert ok.error is None and len(ok.accepted) == 40

    break_it()
    for attempt in range(3):  # refused every time, with the reason, and a hint to retry
        ack = upload(s, "veh-1", 2 + attempt, b)
        assert ack.error is not None and ack.error.field == "storage", ack
        assert len(ack.accepted) == 0 and ack.retry_after_s and ack.retry_after_s > 0
    again = upload(s, "veh-1", 5, a)  # already recorded: acked again if SQLite still can
    assert (again.error is not None and again.error.field == "storage") or (
        again.error is None and len(again.duplicates) == 40
    )
    st = stats()
    assert st["storage_errors"] >= 3
    assert st["accepted"] == 40
    assert logged_obs(s) == list(range(1, 41))  # what was accepted is still there

    repair()
    ack = upload(s, "veh-1", 6, b)
    assert ack.error is None and len(ack.accepted) == 300 and len(ack.duplicates) == 0
    again = upload(s, "veh-1", 7, a)
    assert again.error is None and len(again.duplicates) == 40
    assert stats()["accepted"] == 340
    assert logged_obs(s) == list(range(1, 41)) + list(range(1000, 1300))


@pytest.mark.integration
@pytest.mark.parametrize("fault", [read_only, full], ids=["read-only", "disk-full"])
def test_ingest_refuses_uploads_it_cannot_store_and_recovers(ingest_in_process, stack, fault):
    svc = ingest_in_process
    with open_session(stack.bus) as s:

        def stats() -> dict:
            return {st.service: st.counters for st in collect(s)}["ingest"]

        refuses_then_recovers(
            s, stats, lambda: svc.breaks.put(fault), lambda: svc.breaks.put(repaired)
        )
    assert svc.worker.is_alive()


def can_mount_tmpfs(where: Path) -> bool:
    where.mkdir(parents=True, exist_ok=True)
    try:
        r = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(where)],
            capture_output=True,
            timeout=10,
        )
    except (OSError, subprocess.TimeoutExpired):
        return False
    return r.returncode == 0


def fill(path: Path) -> None:
    """Write ``path`` until the file system has no block left."""
    with open(path, "wb", buffering=0) as f:
        for chunk in (1 << 16, 1 << 12, 1):
            with contextlib.suppress(OSError):
                while True:
                    f.write(b"\0" * chunk)
    with pytest.raises(OSError) as exc, open(path.with_suffix(".probe"), "wb") as f:
        f.write(b"\0" * 4096)
        f.flush()
        os.fsync(f.fileno())
    assert exc.value.errno == errno.ENOSPC


@pytest.mark.integration
def test_ingest_on_a_real_full_disk(stack, tmp_path):
    """An ingest process whose data dir is a 4 MB tmpfs: filled up, then emptied."""
    mnt = stack.data_dir / "ingest-all"
    if not can_mount_tmpfs(mnt):
        pytest.skip("cannot mount a tmpfs here (needs root on Linux)")
    try:
        stack.start_router()
        stack.start_service("ingest")
        stack.wait_ready(["ingest-all"], 60)
        ballast = mnt / "ballast"
        with open_session(stack.bus) as s:

            def stats() -> dict:
                return {st.service: st.counters for st in collect(s)}["ingest"]

            def repair() -> None:
                for p in (ballast, ballast.with_suffix(".probe")):
                    p.unlink(missing_ok=True)

            refuses_then_recovers(s, stats, lambda: fill(ballast), repair)
            assert stack.procs["ingest-all"].alive and stack.procs["ingest-all"].restarts == 0
    finally:
        stack.stop_all()
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True, timeout=10)


# -- the stage loop: poison entries, storage failures, replays -------------------------------


class Recorder(StageService):
    """A consumer of the obs stage that records what it applies in its own table: body
    b"poison" raises, b"bad-sql" breaks a constraint, anything else is applied."""

    name = "recorder"
    input_stage = "obs"

    def __init__(self, opts: ServiceOptions, log: list[LogEntry]):
        super().__init__(opts)
        self.db.execute(
            "CREATE TABLE IF NOT EXISTS applied (n INTEGER PRIMARY KEY, tile TEXT NOT NULL, "
            "seq INTEGER NOT NULL)"
        )
        self.log = log
        self.session = None  # never opened: the replay below stands in for the bus
        self.use_fetch(self._replay, executor=InlineExecutor())  # the producers' replay
        self.consumer.need_catchup = False

    def _replay(self, _selectors, _request) -> list[bytes]:
        """The producer's whole log, as its replay queryable would answer (no head)."""
        return [e.to_bytes() for e in sorted(self.log, key=lambda e: e.gseq)]

    def apply(self, entries: list[LogEntry]) -> None:
        for e in entries:
            if e.body == b"poison":
                raise ValueError("poison")
            tile = None if e.body == b"bad-sql" else e.tile  # NOT NULL constraint
            self.db.execute("INSERT INTO applied(tile, seq) VALUES (?, ?)", (tile, e.seq))

    def applied(self) -> list[tuple[str, int]]:
        return [(t, s) for t, s in self.db.execute("SELECT tile, seq FROM applied ORDER BY n")]

    def dead(self) -> int:
        with contextlib.suppress(sqlite3.OperationalError):
            return int(self.db.execute("SELECT COUNT(*) FROM dead_letters").fetchone()[0])
        return 0

    def live(self, *entries: LogEntry) -> None:
        self.handle([Item("entry", keys.obs(e.tile), e.to_bytes()) for e in entries])


def entries(spec: str) -> list[LogEntry]:
    """'A A B A:poison' -> entries of one producer, seq per tile, gseq in order."""
    seqs: dict[str, int] = {}
    out = []
    for g, word in enumerate(spec.split(), start=1):
        tile, _, body = word.partition(":")
        tile = {"A": "0123", "B": "0130"}[tile]
        seqs[tile] = seqs.get(tile, 0) + 1
        out.append(LogEntry("obs", "ingest-x", tile, seqs[tile], g, (body or "ok").encode()))
    return out


@pytest.fixture
def recorder(tmp_path):
    made: list[Recorder] = []

    def make(log: list[LogEntry]) -> Recorder:
        r = Recorder(ServiceOptions(data_dir=tmp_path), log)
        made.append(r)
        return r

    yield make
    for r in made:
        r.db.close()


def test_a_poison_entry_is_set_aside_and_the_others_applied_exactly_once(recorder):
    log = entries("A A:poison A B A:bad-sql B A")
    r = recorder(log)
    r.live(*log[:5])  # one batch: it fails, is retried entry by entry
    assert r.applied() == [("0123", 1), ("0123", 3), ("0130", 1)]
    assert r.dead() == 2
    r.live(*log[5:])  # later entries, then a full replay: nothing is applied twice
    r.consumer.need_catchup = True
    r.live()
    assert r.applied() == [("0123", 1), ("0123", 3), ("0130", 1), ("0130", 2), ("0123", 5)]
    assert r.dead() == 2
    assert r.counters["entries_failed"] == 2 and r.counters["entries_applied"] == 7


def test_replayed_and_live_entries_are_applied_in_the_producers_order(recorder):
    log = entries("A B A B A B")
    r = recorder(log)
    r.live(log[4])  # a live entry ahead of a gap (just after a restart): replay, merge
    assert [s for _t, s in r.applied()] == [1, 1, 2, 2, 3, 3]
    assert [t for t, _s in r.applied()] == ["0123", "0130"] * 3


def test_a_storage_failure_leaves_entries_unapplied_until_storage_is_back(recorder):
    log = entries("A B A")
    r = recorder(log)
    r.db.execute("PRAGMA query_only=ON")  # the data dir became read-only
    r.live(*log)
    assert r.applied() == [] and r.dead() == 0
    assert r.counters["storage_errors"] == 1
    r.db.execute("PRAGMA query_only=OFF")
    r.live()  # the rollback asked for a replay
    assert r.applied() == [("0123", 1), ("0130", 1), ("0123", 2)]


def test_transaction_tells_storage_failures_from_statement_errors(tmp_path):
    db = connect(tmp_path / "t.sqlite")
    db.execute("CREATE TABLE t (x INTEGER NOT NULL)")
    with pytest.raises(StorageError) as exc, transaction(db):
        db.execute("INSERT INTO t VALUES (NULL)")
    assert not exc.value.transient  # a bug in the statement: retrying fails the same way
    db.execute("PRAGMA query_only=ON")
    with pytest.raises(StorageError) as exc, transaction(db):
        db.execute("INSERT INTO t VALUES (1)")
    assert exc.value.transient
    db.execute("PRAGMA query_only=OFF")
    db.execute(f"PRAGMA max_page_count={db.execute('PRAGMA page_count').fetchone()[0]}")
    with pytest.raises(StorageError) as exc, transaction(db):
        db.execute(
            "INSERT INTO t SELECT 1 FROM (WITH RECURSIVE c(n) AS (SELECT 1 UNION ALL "
            "SELECT n + 1 FROM c WHERE n < 100000) SELECT n FROM c)"
        )
    assert exc.value.transient
    db.close()


def test_a_database_that_cannot_be_opened_is_a_storage_error_naming_it(tmp_path):
    (tmp_path / "state.sqlite").mkdir()  # e.g. a broken restore
    with pytest.raises(StorageError, match=r"state\.sqlite: cannot open"):
        connect(tmp_path / "state.sqlite")


def test_live_entries_dropped_on_a_full_inbox_are_replayed(recorder):
    """A stage's subscriber drops live entries when its inbox is full (so its producer
    is never held up); the next batch replays them from the producer's log."""
    log = entries("A B A B")
    r = recorder(log[:1])
    r.live(log[0])
    assert r.applied() == [("0123", 1)] and not r.consumer.need_catchup
    r.log.extend(log[1:])  # the producer wrote three more; their live copies were dropped
    r.live()
    assert r.applied() == [("0123", 1)]  # nothing tells the consumer yet
    r.inbox_dropped.set()  # what the subscriber callback does on queue.Full
    r.live()
    assert r.applied() == [("0123", 1), ("0130", 1), ("0123", 2), ("0130", 2)]
    assert r.extra_counters()["inbox_overflows"] == 1
    assert not r.inbox_dropped.is_set()


def test_state_not_reloaded_after_a_rollback_restarts_the_service(recorder):
    """A rollback whose reload of in-memory state fails (an I/O error) must not set the
    batch aside as poison: nothing is dead-lettered and the service exits to be restarted
    (EXIT_RESTART), which reloads its state from the file."""
    log = entries("A:poison B")
    r = recorder(log)

    def reload_fails() -> None:
        raise sqlite3.OperationalError("disk I/O error")

    r.consumer.on_rollback = reload_fails
    r.live(*log)
    assert r.dead() == 0 and r.applied() == []
    with pytest.raises(SystemExit) as stop:
        r.step([])
    assert stop.value.code == EXIT_RESTART
