"""Durable stage logs between services: exactly-once hand-over over a lossy-in-theory bus.

Every stage output (ingest -> obs, matcher -> assoc, solver -> update) is a log in
the producer's SQLite. An entry is appended in the same transaction as the state
change that produced it, then published live on the stage key. Entries are
numbered per (producer, tile) by ``seq`` (1, 2, 3, ...) and per producer by
``gseq`` (global order).

A consumer records, in the same transaction as the state change an entry causes,
the last ``seq`` it applied per (producer, tile). It therefore

- drops an entry it has already applied (a live duplicate after a replay),
- buffers an entry that arrives ahead of a gap and asks for the missing ones,
- catches up on start, on a gap, when a producer (re)appears and periodically,
  by querying the producers' replay queryables (``hdmap/v1/log/<stage>/*/<region>``)
  with its offsets; replayed entries are applied in ``gseq`` order.

So nothing committed upstream is lost (it is in the producer's log until the
consumer has it) and nothing is applied twice (offsets commit with the effects).
"""

from __future__ import annotations

import logging
import queue
import sqlite3
import threading
import time
from collections import defaultdict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import zenoh

from hdmap.geo.tiles import in_region
from hdmap.runtime.bus import query
from hdmap.runtime.store import connect
from schemas import DecodeError, ErrorReply, LogEntry, LogQuery, keys

log = logging.getLogger(__name__)

STAGE_KEYS: dict[str, Callable[[str], str]] = {
    "obs": keys.obs,
    "assoc": keys.assoc,
    "update": keys.update,
}


class LogWriter:
    """Producer side: appends entries inside the caller's transaction.

    ``append`` stages an entry; the transaction's outcome (``on_commit`` /
    ``on_rollback``, see :func:`hdmap.runtime.store.transaction`) makes it final or drops it.
    """

    SCHEMA = """
    CREATE TABLE IF NOT EXISTS log_out (
        gseq INTEGER PRIMARY KEY, tile TEXT NOT NULL, seq INTEGER NOT NULL,
        body BLOB NOT NULL, created_at REAL NOT NULL);
    CREATE UNIQUE INDEX IF NOT EXISTS log_out_tile_seq ON log_out(tile, seq);
    CREATE TABLE IF NOT EXISTS log_heads (tile TEXT PRIMARY KEY, seq INTEGER NOT NULL)
        WITHOUT ROWID;
    """

    def __init__(self, conn: sqlite3.Connection, stage: str, producer: str):
        self.stage, self.producer = stage, producer
        self._conn = conn
        conn.executescript(self.SCHEMA)
        self._heads = dict(conn.execute("SELECT tile, seq FROM log_heads").fetchall())
        self._gseq = conn.execute("SELECT COALESCE(MAX(gseq), 0) FROM log_out").fetchone()[0]
        self._staged: list[LogEntry] = []

    def append(self, tile: str, body: bytes) -> LogEntry:
        staged_heads = {e.tile: e.seq for e in self._staged}
        seq = staged_heads.get(tile, self._heads.get(tile, 0)) + 1
        gseq = (self._staged[-1].gseq if self._staged else self._gseq) + 1
        entry = LogEntry(self.stage, self.producer, tile, seq, gseq, body)
        self._conn.execute(
            "INSERT INTO log_out(gseq, tile, seq, body, created_at) VALUES (?, ?, ?, ?, ?)",
            (gseq, tile, seq, body, time.time()),
        )
        self._conn.execute("INSERT OR REPLACE INTO log_heads(tile, seq) VALUES (?, ?)", (tile, seq))
        self._staged.append(entry)
        return entry

    def on_commit(self) -> None:
        for e in self._staged:
            self._heads[e.tile] = e.seq
            self._gseq = e.gseq
        self._staged = []

    def on_rollback(self) -> None:
        self._staged = []

    @property
    def heads(self) -> dict[str, int]:
        return dict(self._heads)

    @property
    def gseq(self) -> int:
        return self._gseq


class QueryServer:
    """A queryable answered on its own thread from its own read-only SQLite connection.

    Keeps reads (replays, snapshots) off both the Zenoh callback threads and the
    service's worker; WAL lets it read committed state while the worker writes.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        db_path: str | Path,
        answer: Callable[[sqlite3.Connection, zenoh.Query], None],
        name: str = "query",
    ):
        self._db_path = db_path
        self._answer = answer
        self._queue: queue.Queue[zenoh.Query | None] = queue.Queue(maxsize=1024)
        self._thread = threading.Thread(target=self._serve, name=name, daemon=True)
        self._thread.start()
        self._queryable = session.declare_queryable(key, self._queue.put)

    def close(self) -> None:
        self._queryable.undeclare()
        self._queue.put(None)
        self._thread.join(timeout=5)

    def _serve(self) -> None:
        conn = connect(self._db_path, readonly=True)
        try:
            while (q := self._queue.get()) is not None:
                try:
                    self._answer(conn, q)
                except Exception:  # one bad query must not stop the thread
                    log.exception("query on %s failed", q.key_expr)
                finally:
                    q.drop()
        finally:
            conn.close()


class LogServer(QueryServer):
    """Producer side: answers replay queries (``hdmap/v1/log/<stage>/<producer>/*``)."""

    def __init__(self, session: zenoh.Session, db_path: str | Path, stage: str, producer: str):
        self.stage, self.producer = stage, producer
        super().__init__(
            session, keys.log(stage, producer, keys.ANY), db_path, self._reply, f"log-{stage}"
        )

    def _reply(self, conn: sqlite3.Connection, q: zenoh.Query) -> None:
        try:
            req = LogQuery.from_bytes(q.payload.to_bytes() if q.payload is not None else b"")
            if req.stage != self.stage:
                raise DecodeError("stage", f"this queryable serves {self.stage!r}")
        except DecodeError as exc:
            q.reply_err(ErrorReply.of(exc).to_bytes())
            return
        offsets = req.offsets.get(self.producer, {})
        heads = conn.execute("SELECT tile, seq FROM log_heads").fetchall()
        wanted = [
            (t, offsets.get(t, 0))
            for t, s in heads
            if s > offsets.get(t, 0) and in_region(t, req.prefixes)
        ]
        rows: list[tuple[int, str, int, bytes]] = []
        for tile, after in wanted:
            rows += conn.execute(
                "SELECT gseq, tile, seq, body FROM log_out WHERE tile=? AND seq>? "
                "ORDER BY seq LIMIT ?",
                (tile, after, req.limit),
            ).fetchall()
        rows.sort()
        for gseq, tile, seq, body in rows[: req.limit]:
            entry = LogEntry(self.stage, self.producer, tile, seq, gseq, body)
            q.reply(keys.log(self.stage, self.producer, tile), entry.to_bytes())


@dataclass
class ConsumerStats:
    applied: int = 0
    duplicates: int = 0
    gaps: int = 0
    replayed: int = 0
    catchups: int = 0


LAG_CAP = 1_000_000


class LogConsumer:
    """Consumer side: in-order, exactly-once delivery of a stage's entries for a region."""

    SCHEMA = """
    CREATE TABLE IF NOT EXISTS offsets (
        stage TEXT NOT NULL, producer TEXT NOT NULL, tile TEXT NOT NULL, seq INTEGER NOT NULL,
        PRIMARY KEY (stage, producer, tile)) WITHOUT ROWID;
    """

    def __init__(self, conn: sqlite3.Connection, stage: str, prefixes: Sequence[str]):
        self.stage = stage
        self.prefixes = list(prefixes)
        self._conn = conn
        conn.executescript(self.SCHEMA)
        self._committed: dict[tuple[str, str], int] = {}
        self._load()
        self._delivered = dict(self._committed)
        self._ahead: dict[tuple[str, str], dict[int, LogEntry]] = defaultdict(dict)
        self._pending_commit: dict[tuple[str, str], int] = {}
        self._seen: dict[tuple[str, str], int] = {}
        self.need_catchup = True
        self.stats = ConsumerStats()

    def _load(self) -> None:
        rows = self._conn.execute(
            "SELECT producer, tile, seq FROM offsets WHERE stage=?", (self.stage,)
        ).fetchall()
        self._committed = {(p, t): s for p, t, s in rows}

    # -- delivery ---------------------------------------------------------------------

    def offer(self, entry: LogEntry) -> list[LogEntry]:
        """A live entry -> the entries now deliverable in order (maybe none, maybe several)."""
        if not in_region(entry.tile, self.prefixes):
            return []
        k = (entry.producer, entry.tile)
        if entry.seq > self._seen.get(k, 0):
            self._seen[k] = entry.seq
        last = self._delivered.get(k, 0)
        if entry.seq <= last:
            self.stats.duplicates += 1
            return []
        if entry.seq > last + 1:
            self._ahead[k][entry.seq] = entry
            self.stats.gaps += 1
            self.need_catchup = True
            return []
        out = [entry]
        self._delivered[k] = entry.seq
        buf = self._ahead.get(k)
        while buf and (nxt := buf.pop(self._delivered[k] + 1, None)) is not None:
            out.append(nxt)
            self._delivered[k] = nxt.seq
        if buf is not None and not buf:
            del self._ahead[k]
        return out

    def record(self, entries: Iterable[LogEntry]) -> None:
        """Write offsets for applied entries (inside the caller's transaction)."""
        latest: dict[tuple[str, str], int] = {}
        for e in entries:
            k = (e.producer, e.tile)
            latest[k] = max(latest.get(k, 0), e.seq)
        self._conn.executemany(
            "INSERT OR REPLACE INTO offsets(stage, producer, tile, seq) VALUES (?, ?, ?, ?)",
            [(self.stage, p, t, s) for (p, t), s in latest.items()],
        )
        self._pending_commit.update(latest)

    def on_commit(self) -> None:
        self.stats.applied += sum(
            s - self._committed.get(k, 0) for k, s in self._pending_commit.items()
        )
        self._committed.update(self._pending_commit)
        for k, seq in self._pending_commit.items():  # entries re-applied after a rollback
            if seq > self._delivered.get(k, 0):
                self._delivered[k] = seq
        self._pending_commit = {}

    def on_rollback(self) -> None:
        """What was delivered but not committed will come again: rewind and catch up."""
        self._pending_commit = {}
        self._load()
        self._delivered = dict(self._committed)
        self._ahead.clear()
        self.need_catchup = True

    # -- catch-up ---------------------------------------------------------------------

    def selector(self) -> list[str]:
        stage_key = f"{keys.ROOT}/log/{self.stage}/*"
        return [f"{stage_key}/{keys.region(p)}" for p in (self.prefixes or [""])]

    def catch_up(
        self,
        session: zenoh.Session,
        timeout: float = 5.0,
        limit: int = 2000,
        max_rounds: int = 1000,
    ) -> list[LogEntry]:
        """Fetch what producers have after our offsets; return it deliverable, in order.

        Bounded: at most ``max_rounds`` queries of ``limit`` entries per producer.
        """
        self.stats.catchups += 1
        out: list[LogEntry] = []
        for _ in range(max_rounds):
            offsets: dict[str, dict[str, int]] = defaultdict(dict)
            for (p, t), s in self._delivered.items():
                offsets[p][t] = s
            req = LogQuery(self.stage, dict(offsets), self.prefixes, limit).to_bytes()
            got: list[LogEntry] = []
            for sel in self.selector():
                for _key, ok, _err in query(session, sel, req, timeout=timeout):
                    if ok is None:
                        continue
                    try:
                        got.append(LogEntry.from_bytes(ok))
                    except DecodeError:
                        log.warning("undecodable replay entry ignored")
            per_producer: dict[str, int] = defaultdict(int)
            got.sort(key=lambda e: (e.producer, e.gseq))
            for e in got:
                per_producer[e.producer] += 1
                delivered = self.offer(e)
                self.stats.replayed += len(delivered)
                out += delivered
            if not per_producer or max(per_producer.values()) < limit:
                break
        self.need_catchup = any(self._ahead.values())
        return out

    @property
    def lag(self) -> int:
        """Entries seen from producers (live or replayed) but not applied yet (each
        (producer, tile) counts at most ``LAG_CAP``: a forged entry can claim any seq)."""
        return sum(
            min(max(0, s - self._committed.get(k, 0)), LAG_CAP) for k, s in list(self._seen.items())
        )

    @property
    def offsets(self) -> dict[tuple[str, str], int]:
        return dict(self._committed)
