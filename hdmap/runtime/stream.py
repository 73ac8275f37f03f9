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

Gaps are bounded (:class:`GapPolicy`): at most ``max_ahead`` entries wait behind gaps
(more are dropped: the producer's log still has them); a gap the catch-up did not fill is
tried again after ``retry_s``, doubling, not at every batch; one still open after
``timeout_s`` is reported (counted, logged) and its waiting entries dropped, so that an
entry no producer wrote (a forged one far ahead) cannot hold anything up for long. The
buffer only saves a replay: what it drops is fetched again from the producer's log.

So nothing committed upstream is lost (it is in the producer's log until the
consumer has it) and nothing is applied twice (offsets commit with the effects).
"""

from __future__ import annotations

import logging
import sqlite3
import time
from collections import defaultdict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import zenoh

from hdmap.geo.tiles import in_region
from hdmap.runtime.bus import query
from hdmap.runtime.gaps import GapPolicy
from hdmap.runtime.queries import QueryServer
from schemas import DecodeError, ErrorReply, LogEntry, LogHead, LogQuery, decode_replay, keys

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
        self._staged_heads: dict[str, int] = {}

    def append(self, tile: str, body: bytes) -> LogEntry:
        seq = self._staged_heads.get(tile, self._heads.get(tile, 0)) + 1
        gseq = (self._staged[-1].gseq if self._staged else self._gseq) + 1
        self._staged_heads[tile] = seq
        entry = LogEntry(self.stage, self.producer, tile, seq, gseq, body)
        self._conn.execute(
            "INSERT INTO log_out(gseq, tile, seq, body, created_at) VALUES (?, ?, ?, ?, ?)",
            (gseq, tile, seq, body, time.time()),
        )
        self._conn.execute("INSERT OR REPLACE INTO log_heads(tile, seq) VALUES (?, ?)", (tile, seq))
        self._staged.append(entry)
        return entry

    def on_commit(self) -> None:
        self._heads.update(self._staged_heads)
        if self._staged:
            self._gseq = self._staged[-1].gseq
        self._staged, self._staged_heads = [], {}

    def on_rollback(self) -> None:
        self._staged, self._staged_heads = [], {}

    @property
    def heads(self) -> dict[str, int]:
        return dict(self._heads)

    @property
    def gseq(self) -> int:
        return self._gseq


Row = tuple[int, str, int, bytes]
"""``(gseq, tile, seq, body)`` of a ``log_out`` row."""

SCAN_FACTOR = 50
"""A replay answer reads at most this many times its ``limit`` entries past the
watermark (entries of other regions included) before it stops with ``through``."""


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
        conn.execute("BEGIN")  # one snapshot of the log for the whole answer
        try:
            if req.after_gseq is None:
                rows, head = rows_per_tile(conn, req, self.producer), None
            else:
                rows, head = rows_since(conn, req, self.producer)
            for gseq, tile, seq, body in rows:
                entry = LogEntry(self.stage, self.producer, tile, seq, gseq, body)
                q.reply(keys.log(self.stage, self.producer, tile), entry.to_bytes())
        finally:
            conn.execute("COMMIT")
        if head is not None:
            q.reply(
                keys.log(self.stage, self.producer, _head_chunk(str(q.key_expr))), head.to_bytes()
            )


def _head_chunk(selector: str) -> str:
    """A last key chunk for the closing :class:`LogHead` that the query's selector
    matches (``0123$*`` -> ``0123``; ``*`` or ``**`` -> ``head``)."""
    last = selector.rsplit("/", 1)[-1]
    if last.endswith("$*"):
        return last[:-2] or "head"
    return "head" if "*" in last else last


@dataclass
class ConsumerStats:
    applied: int = 0
    duplicates: int = 0
    gaps: int = 0
    replayed: int = 0
    catchups: int = 0
    ahead_dropped: int = 0
    """Live entries not held behind a gap (the buffer was full); replayed later."""
    gaps_expired: int = 0
    """Gaps not filled within ``GapPolicy.timeout_s`` (their waiting entries dropped)."""


LAG_CAP = 1_000_000


class LogConsumer:
    """Consumer side: in-order, exactly-once delivery of a stage's entries for a region.

    Invariant (the watermark): every entry of the region with ``gseq`` up to
    ``watermark[producer]`` is delivered, except in tiles where an entry waits behind a
    gap. A catch-up therefore lists only the tiles delivered past the watermark (to skip
    what it has) and the tiles with a gap (to fill them whatever their ``gseq``), and the
    producer's :class:`LogHead` moves the watermark up: the query grows with the tiles
    active since the last catch-up, not with every tile the region ever held. The
    watermark is saved only by a transaction that leaves nothing delivered uncommitted,
    so the saved one holds for the saved offsets.

    Pitfall: the watermark trusts the producer's :class:`LogHead`. A forged head (anyone
    may answer on ``hdmap/v1/log/**`` in default mode; in secured mode only services may)
    with a large ``through`` makes the consumer skip what it has not seen in tiles with no
    gap; an entry that arrives later in such a tile reveals the gap and it is filled
    then. The stage keys and replay queryables must be the services' alone (secured
    mode's ACL) wherever the bus is not trusted.
    """

    SCHEMA = """
    CREATE TABLE IF NOT EXISTS offsets (
        stage TEXT NOT NULL, producer TEXT NOT NULL, tile TEXT NOT NULL, seq INTEGER NOT NULL,
        PRIMARY KEY (stage, producer, tile)) WITHOUT ROWID;
    CREATE TABLE IF NOT EXISTS watermarks (
        stage TEXT NOT NULL, producer TEXT NOT NULL, gseq INTEGER NOT NULL,
        PRIMARY KEY (stage, producer)) WITHOUT ROWID;
    """

    def __init__(
        self,
        conn: sqlite3.Connection,
        stage: str,
        prefixes: Sequence[str],
        gaps: GapPolicy | None = None,
        clock: Callable[[], float] = time.monotonic,
    ):
        self.stage = stage
        self.prefixes = list(prefixes)
        self.policy = gaps or GapPolicy()
        self.clock = clock
        self._conn = conn
        self._opened: dict[tuple[str, str], float] = {}
        """When each gap with entries waiting behind it opened (the consumer's clock)."""
        self._tries = 0
        """Catch-ups in a row that left a gap open (the retry delay doubles with them)."""
        self._retry_at: float | None = None
        self.more = False
        """The last catch-up round was cut short (``limit``): the next round is due now."""
        self.generation = 0
        """Bumped by every rewind: a catch-up asked before it is stale."""
        conn.executescript(self.SCHEMA)
        self._committed: dict[tuple[str, str], int] = {}
        self._committed_wm: dict[str, int] = {}
        self._ahead: dict[tuple[str, str], dict[int, LogEntry]] = defaultdict(dict)
        self._pending_commit: dict[tuple[str, str], int] = {}
        self._pending_wm: dict[str, int] = {}
        self._seen: dict[tuple[str, str], int] = {}
        self.stats = ConsumerStats()
        self._rewind()

    def _rewind(self) -> None:
        """Back to the committed state (start, rollback)."""
        rows = self._conn.execute(
            "SELECT producer, tile, seq FROM offsets WHERE stage=?", (self.stage,)
        ).fetchall()
        self._committed = {(p, t): s for p, t, s in rows}
        self._committed_wm = dict(
            self._conn.execute(
                "SELECT producer, gseq FROM watermarks WHERE stage=?", (self.stage,)
            ).fetchall()
        )
        self._delivered = dict(self._committed)
        self._watermark = dict(self._committed_wm)
        self._recent: dict[str, dict[str, tuple[int, int]]] = defaultdict(dict)
        """producer -> tile -> (delivered seq, its gseq) for deliveries past the watermark."""
        self._uncommitted: set[tuple[str, str]] = set()
        self._ahead.clear()
        self._opened.clear()
        self._pending_commit = {}
        self._pending_wm = {}
        self.need_catchup = True
        self.more = False
        self.generation += 1

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
            self._note(entry, last)
            return []
        if entry.seq > last + 1:
            self._hold(k, entry)
            return []
        out = [entry]
        buf = self._ahead.get(k)
        while buf and (nxt := buf.pop(out[-1].seq + 1, None)) is not None:
            out.append(nxt)
        if buf is not None and not buf:
            del self._ahead[k]
            self._opened.pop(k, None)
        self._delivered[k] = out[-1].seq
        self._uncommitted.add(k)
        self._note(out[-1], out[-1].seq)
        return out

    def _hold(self, k: tuple[str, str], entry: LogEntry) -> None:
        """Keep a live entry behind its tile's gap (if the buffer has room); a new gap asks
        for a catch-up at once."""
        self.stats.gaps += 1
        if self.ahead_entries >= self.policy.max_ahead:
            self.stats.ahead_dropped += 1
            self.need_catchup = True
            return
        if k not in self._opened:
            self._opened[k] = self.clock()
            self.need_catchup = True
        self._ahead[k][entry.seq] = entry

    @property
    def ahead_entries(self) -> int:
        """Live entries waiting behind gaps."""
        return sum(len(b) for b in self._ahead.values())

    def oldest_gap_s(self, now: float | None = None) -> float:
        """Seconds the oldest open gap has been open (0: none)."""
        if not self._opened:
            return 0.0
        return max(0.0, (self.clock() if now is None else now) - min(self._opened.values()))

    def wants_catchup(self, now: float) -> bool:
        """Whether a catch-up is due at ``now``: asked for (start, a new gap, a producer
        appearing, the periodic timer, a rollback), the rest of a cut-short one, or the
        retry of a gap the last one left open."""
        if self.need_catchup or self.more:
            return True
        return bool(self._ahead) and self._retry_at is not None and now >= self._retry_at

    def begin_catchup(self) -> None:
        """A catch-up starts: what asked for it is served by it."""
        self.stats.catchups += 1
        self.need_catchup = False

    def end_round(self, complete: bool, now: float) -> None:
        """A catch-up round was absorbed: another at once if it was cut short; a gap still
        open is tried again after the policy's delay (doubling), not at every batch."""
        self.more = not complete
        if self.more:
            return
        if not self._ahead:
            self._tries, self._retry_at = 0, None
            return
        delay = min(self.policy.retry_max_s, self.policy.retry_s * 2.0**self._tries)
        self._tries += 1
        self._retry_at = now + delay

    def expire_gaps(self, now: float) -> list[tuple[str, str, int, int]]:
        """Drop the entries waiting behind gaps open ``timeout_s`` or longer: each such gap
        as (producer, tile, last delivered seq, first waiting seq)."""
        out = []
        for k, t0 in list(self._opened.items()):
            if now - t0 < self.policy.timeout_s:
                continue
            buf = self._ahead.pop(k, {})
            del self._opened[k]
            self._seen[k] = self._delivered.get(k, 0)  # a forged seq claims no lag
            out.append((k[0], k[1], self._delivered.get(k, 0), min(buf, default=0)))
            self.stats.gaps_expired += 1
        return out

    def _note(self, entry: LogEntry, delivered: int) -> None:
        """Remember a tile delivered past the watermark, so catch-ups skip what it has."""
        if entry.gseq > self._watermark.get(entry.producer, 0):
            mine = self._recent[entry.producer]
            if entry.gseq > mine.get(entry.tile, (0, 0))[1]:
                mine[entry.tile] = (delivered, entry.gseq)

    def record(self, entries: Iterable[LogEntry]) -> None:
        """Write offsets for applied entries (inside the caller's transaction), and the
        watermarks if this transaction leaves nothing delivered uncommitted."""
        latest: dict[tuple[str, str], int] = {}
        for e in entries:
            k = (e.producer, e.tile)
            latest[k] = max(latest.get(k, 0), e.seq)
        self._conn.executemany(
            "INSERT OR REPLACE INTO offsets(stage, producer, tile, seq) VALUES (?, ?, ?, ?)",
            [(self.stage, p, t, s) for (p, t), s in latest.items()],
        )
        self._pending_commit.update(latest)
        done = self._committed
        self._uncommitted = {k for k in self._uncommitted if done.get(k, 0) < self._delivered[k]}
        if all(latest.get(k, 0) >= self._delivered[k] for k in self._uncommitted):
            moved = {p: w for p, w in self._watermark.items() if w > self._committed_wm.get(p, 0)}
            self._conn.executemany(
                "INSERT OR REPLACE INTO watermarks(stage, producer, gseq) VALUES (?, ?, ?)",
                [(self.stage, p, w) for p, w in moved.items()],
            )
            self._pending_wm = moved

    def on_commit(self) -> None:
        self.stats.applied += sum(
            s - self._committed.get(k, 0) for k, s in self._pending_commit.items()
        )
        self._committed.update(self._pending_commit)
        self._committed_wm.update(self._pending_wm)
        for k, seq in self._pending_commit.items():
            if seq > self._delivered.get(k, 0):  # entries re-applied after a rollback
                self._delivered[k] = seq
            if seq >= self._delivered.get(k, 0):
                self._uncommitted.discard(k)
        self._pending_commit = {}
        self._pending_wm = {}

    def on_rollback(self) -> None:
        """What was delivered but not committed will come again: rewind and catch up."""
        self._rewind()

    # -- catch-up ---------------------------------------------------------------------

    def selector(self) -> list[str]:
        stage_key = f"{keys.ROOT}/log/{self.stage}/*"
        return [f"{stage_key}/{keys.region(p)}" for p in (self.prefixes or [""])]

    def query(self, limit: int) -> LogQuery:
        """What a catch-up asks: the tiles delivered past the watermark and those with a
        gap, by seq; the rest of the region after the watermarks."""
        listed = {p: {t: s for t, (s, _g) in tiles.items()} for p, tiles in self._recent.items()}
        for p, t in self._ahead:
            listed.setdefault(p, {})[t] = self._delivered.get((p, t), 0)
        return LogQuery(self.stage, listed, self.prefixes, limit, dict(self._watermark))

    def catch_up(
        self,
        session: zenoh.Session,
        timeout: float = 5.0,
        limit: int = 2000,
        max_rounds: int = 1000,
    ) -> list[LogEntry]:
        """Fetch what producers have that we have not; return it deliverable, in order.

        Bounded: at most ``max_rounds`` queries of ``limit`` entries per producer.
        """
        self.begin_catchup()
        out: list[LogEntry] = []
        for _ in range(max_rounds):
            replies = fetch(session, self.selector(), self.query(limit).to_bytes(), timeout)
            delivered, complete = self.absorb(replies)
            out += delivered
            self.end_round(complete, self.clock())
            if complete:
                break
        return out

    def absorb(self, replies: Iterable[bytes]) -> tuple[list[LogEntry], bool]:
        """One round's replies -> (entries now deliverable, whether every producer that
        answered sent all it had). Entries are offered in each producer's ``gseq`` order;
        each producer's :class:`LogHead` then raises its watermark."""
        got: list[LogEntry] = []
        heads: dict[str, LogHead] = {}
        for data in replies:
            try:
                r = decode_replay(data)
            except DecodeError:
                log.warning("undecodable replay reply ignored")
                continue
            if isinstance(r, LogEntry):
                got.append(r)
            elif r.stage == self.stage and (
                r.producer not in heads or r.through < heads[r.producer].through
            ):
                heads[r.producer] = r
        got.sort(key=lambda e: (e.producer, e.gseq))
        out: list[LogEntry] = []
        for e in got:
            delivered = self.offer(e)
            self.stats.replayed += len(delivered)
            out += delivered
        for p, h in heads.items():
            self._advance(p, h.through)
        return out, all(h.complete for h in heads.values())

    def _advance(self, producer: str, through: int) -> None:
        """The producer's answer is delivered up to ``through``: raise its watermark there,
        below any entry still waiting behind a gap (its missing ones are below it)."""
        waiting = [
            min(buf.values(), key=lambda e: e.gseq).gseq - 1
            for (p, _t), buf in self._ahead.items()
            if p == producer and buf
        ]
        w = min([through, *waiting])
        if w <= self._watermark.get(producer, 0):
            return
        self._watermark[producer] = w
        mine = self._recent.get(producer, {})
        for t in [t for t, (_s, g) in mine.items() if g <= w]:
            del mine[t]

    @property
    def lag(self) -> int:
        """Entries seen from producers (live or replayed) but not applied yet (each
        (producer, tile) counts at most ``LAG_CAP``: a forged entry can claim any seq)."""
        return sum(
            min(max(0, s - self._committed.get(k, 0)), LAG_CAP) for k, s in list(self._seen.items())
        )

    def committed(self, producer: str, tile: str) -> int:
        """The last seq applied and committed for (producer, tile)."""
        return self._committed.get((producer, tile), 0)

    @property
    def offsets(self) -> dict[tuple[str, str], int]:
        return dict(self._committed)

    @property
    def watermarks(self) -> dict[str, int]:
        """Committed watermarks per producer."""
        return dict(self._committed_wm)


def fetch(
    session: zenoh.Session, selectors: list[str], request: bytes, timeout: float
) -> list[bytes]:
    """One catch-up round: the producers' replies to ``request`` (error replies dropped)."""
    return [
        ok
        for sel in selectors
        for _key, ok, _err in query(session, sel, request, timeout=timeout)
        if ok is not None
    ]


def rows_per_tile(conn: sqlite3.Connection, req: LogQuery, producer: str) -> list[Row]:
    """The older form: every tile's entries after its listed seq (cost: every tile the
    producer ever wrote)."""
    offsets = req.offsets.get(producer, {})
    heads = conn.execute("SELECT tile, seq FROM log_heads").fetchall()
    rows: list[Row] = []
    for tile, s in heads:
        after = offsets.get(tile, 0)
        if s > after and in_region(tile, req.prefixes):
            rows += conn.execute(
                "SELECT gseq, tile, seq, body FROM log_out WHERE tile=? AND seq>? "
                "ORDER BY seq LIMIT ?",
                (tile, after, req.limit),
            ).fetchall()
    rows.sort()
    return rows[: req.limit]


def rows_since(conn: sqlite3.Connection, req: LogQuery, producer: str) -> tuple[list[Row], LogHead]:
    """Listed tiles after their seq, the others after the watermark; cost: the listed
    tiles plus at most ``SCAN_FACTOR * limit`` entries read after the watermark."""
    listed = {t: s for t, s in req.offsets.get(producer, {}).items() if in_region(t, req.prefixes)}
    after = (req.after_gseq or {}).get(producer, 0)
    head = conn.execute("SELECT COALESCE(MAX(gseq), 0) FROM log_out").fetchone()[0]
    picked: list[int] = []
    for tile, s in listed.items():
        picked += [
            g
            for (g,) in conn.execute(
                "SELECT gseq FROM log_out WHERE tile=? AND seq>? ORDER BY seq LIMIT ?",
                (tile, s, req.limit),
            )
        ]
    through = head
    scanned = found = 0
    cursor = conn.execute("SELECT gseq, tile FROM log_out WHERE gseq>? ORDER BY gseq", (after,))
    for g, tile in cursor:
        scanned += 1
        if tile not in listed and in_region(tile, req.prefixes):
            picked.append(g)
            found += 1
        if found >= req.limit or scanned >= SCAN_FACTOR * req.limit:
            through = g  # the scan stops here: the rest of the log is not looked at
            break
    picked.sort()
    if len(picked) >= req.limit:
        picked = picked[: req.limit]
        through = min(through, picked[-1])
    picked = [g for g in picked if g <= through]
    rows: list[Row] = []
    for i in range(0, len(picked), 500):
        chunk = picked[i : i + 500]
        rows += conn.execute(
            "SELECT gseq, tile, seq, body FROM log_out WHERE gseq IN "
            f"({','.join('?' * len(chunk))}) ORDER BY gseq",
            chunk,
        ).fetchall()
    return rows, LogHead(req.stage, producer, through, head)
