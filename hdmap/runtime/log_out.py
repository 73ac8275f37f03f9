"""The producer's side of a stage log: appending entries, numbering them, and answering
the consumers' replay queries (:mod:`hdmap.runtime.stream` is the consumer's side and
says how the two keep every entry delivered once).

Each run of a producer is an epoch (:func:`new_epoch`): its entries carry it, with the
tile's ``seq`` and the producer's ``gseq`` when the run began (``LogEntry.base``,
``LogEntry.gbase``), and the answers' :class:`~schemas.LogHead` lists the latest runs, so
that a consumer meets a producer restored from an older state.
"""

from __future__ import annotations

import sqlite3
import time
from dataclasses import replace
from pathlib import Path

import zenoh

from hdmap.geo.tiles import in_region
from hdmap.runtime.log_checkpoint import checkpoint_entries
from hdmap.runtime.queries import QueryServer
from hdmap.runtime.retention import truncated_through
from schemas import DecodeError, ErrorReply, LogEntry, LogHead, LogQuery, keys
from schemas.logs import MAX_EPOCHS


class LogWriter:
    """Producer side: appends entries inside the caller's transaction.

    ``append`` stages an entry; the transaction's outcome (``on_commit`` /
    ``on_rollback``, see :func:`hdmap.runtime.store.transaction`) makes it final or drops it.
    """

    SCHEMA = """
    CREATE TABLE IF NOT EXISTS log_out (
        gseq INTEGER PRIMARY KEY, tile TEXT NOT NULL, seq INTEGER NOT NULL,
        body BLOB NOT NULL, created_at REAL NOT NULL,
        epoch INTEGER NOT NULL DEFAULT 0, base INTEGER NOT NULL DEFAULT 0,
        gbase INTEGER NOT NULL DEFAULT 0);
    CREATE UNIQUE INDEX IF NOT EXISTS log_out_tile_seq ON log_out(tile, seq);
    CREATE TABLE IF NOT EXISTS log_heads (tile TEXT PRIMARY KEY, seq INTEGER NOT NULL)
        WITHOUT ROWID;
    CREATE TABLE IF NOT EXISTS log_epochs (
        epoch INTEGER PRIMARY KEY, gbase INTEGER NOT NULL, started_at REAL NOT NULL);
    """

    def __init__(self, conn: sqlite3.Connection, stage: str, producer: str):
        self.stage, self.producer = stage, producer
        self._conn = conn
        conn.executescript(self.SCHEMA)
        columns = {r[1] for r in conn.execute("PRAGMA table_info(log_out)")}
        for col in ("epoch", "base", "gbase"):  # a log written before epochs
            if col not in columns:
                conn.execute(f"ALTER TABLE log_out ADD COLUMN {col} INTEGER NOT NULL DEFAULT 0")
        self._heads = dict(conn.execute("SELECT tile, seq FROM log_heads").fetchall())
        self._gseq = max(
            conn.execute("SELECT COALESCE(MAX(gseq), 0) FROM log_out").fetchone()[0],
            truncated_through(conn),  # a log truncated whole still numbers on
        )
        self.epoch = new_epoch(conn, self._gseq)
        self._gbase = self._gseq
        self._bases = dict(self._heads)
        """Each tile's last seq when this run began (the ``base`` of its entries)."""
        self._staged: list[LogEntry] = []
        self._staged_heads: dict[str, int] = {}

    def append(self, tile: str, body: bytes) -> LogEntry:
        seq = self._staged_heads.get(tile, self._heads.get(tile, 0)) + 1
        gseq = (self._staged[-1].gseq if self._staged else self._gseq) + 1
        self._staged_heads[tile] = seq
        base = self._bases.get(tile, 0)
        entry = LogEntry(
            self.stage, self.producer, tile, seq, gseq, body, self.epoch, base, self._gbase
        )
        self._conn.execute(
            "INSERT INTO log_out(gseq, tile, seq, body, created_at, epoch, base, gbase) "
            "VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
            (gseq, tile, seq, body, time.time(), self.epoch, base, self._gbase),
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


def new_epoch(conn: sqlite3.Connection, gseq: int) -> int:
    """Start a producer's run: an epoch above every one in its database and, as far as
    the clock tells, above any run a restored copy of it had before (microseconds of the
    wall clock), recorded with the ``gseq`` it begins after.

    Pitfall: a restored producer whose host clock is behind the lost run's start by more
    than the time since takes an older epoch; its consumers then take its new entries for
    stale ones. Keep the hosts' clocks synchronised (NTP)."""
    last = conn.execute("SELECT COALESCE(MAX(epoch), 0) FROM log_epochs").fetchone()[0]
    epoch = max(int(time.time() * 1e6), last + 1)
    conn.execute(
        "INSERT INTO log_epochs(epoch, gbase, started_at) VALUES (?, ?, ?)",
        (epoch, gseq, time.time()),
    )
    return epoch


def latest_epochs(conn: sqlite3.Connection) -> list[tuple[int, int]]:
    """The producer's latest runs, oldest first (at most :data:`MAX_EPOCHS`)."""
    rows = conn.execute(
        "SELECT epoch, gbase FROM log_epochs ORDER BY epoch DESC LIMIT ?", (MAX_EPOCHS,)
    ).fetchall()
    return [(int(e), int(g)) for e, g in reversed(rows)]


Row = tuple[int, str, int, bytes, int, int, int]
"""``(gseq, tile, seq, body, epoch, base, gbase)`` of a ``log_out`` row."""

COLUMNS = "gseq, tile, seq, body, epoch, base, gbase"
"""The ``log_out`` columns of a :data:`Row`."""


def entries_of(stage: str, producer: str, rows: list[Row]) -> list[LogEntry]:
    """``log_out`` rows as the entries they are."""
    return [LogEntry(stage, producer, t, s, g, b, *run) for g, t, s, b, *run in rows]


SCAN_FACTOR = 50
"""A replay answer reads at most this many times its ``limit`` entries past the
watermark (entries of other regions included) before it stops with ``through``."""


class LogServer(QueryServer):
    """Producer side: answers replay queries (``hdmap/v1/log/<stage>/<producer>/*``)."""

    def __init__(
        self,
        session: zenoh.Session,
        db_path: str | Path,
        stage: str,
        producer: str,
        checkpoints: bool = False,
    ):
        """``checkpoints``: a query below what retention deleted is answered with the
        tiles' checkpoints and the tail (:mod:`hdmap.runtime.log_checkpoint`)."""
        self.stage, self.producer, self.checkpoints = stage, producer, checkpoints
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
            try:
                entries, head = answer(conn, req, self.producer, self.checkpoints)
            except DecodeError as exc:
                q.reply_err(ErrorReply.of(exc).to_bytes())
                return
            for entry in entries:
                q.reply(keys.log(self.stage, self.producer, entry.tile), entry.to_bytes())
        finally:
            conn.execute("COMMIT")
        if head is not None:
            q.reply(
                keys.log(self.stage, self.producer, _head_chunk(str(q.key_expr))), head.to_bytes()
            )


def answer(
    conn: sqlite3.Connection, req: LogQuery, producer: str, checkpoints: bool = False
) -> tuple[list[LogEntry], LogHead | None]:
    """A producer's answer to a replay query (inside one read transaction): the entries
    and, for a query by watermark, the closing head. Below what retention deleted: with
    ``checkpoints``, the tiles' checkpoints and then the tail; else a :class:`DecodeError`
    naming ``after_gseq``."""
    gone = truncated_through(conn)
    after = (req.after_gseq or {}).get(producer, 0)
    cps: list[LogEntry] = []
    if gone and checkpoints and after < gone:  # the tiles' states, then the tail
        cps = checkpoint_entries(conn, req.stage, producer, req)
        req = replace(req, after_gseq={**(req.after_gseq or {}), producer: gone})
    elif gone and (req.after_gseq is None or after < gone):
        raise DecodeError(
            "after_gseq",
            f"{producer} deleted its log through gseq {gone} (every consumer it knew had "
            f"applied it); this consumer is at {after}: it must be rebuilt "
            "(docs/operations.md, Retention)",
        )
    if req.after_gseq is None:
        rows, head = rows_per_tile(conn, req, producer), None
    else:
        rows, head = rows_since(conn, req, producer)
    return [*cps, *entries_of(req.stage, producer, rows)], head


def _head_chunk(selector: str) -> str:
    """A last key chunk for the closing :class:`LogHead` that the query's selector
    matches (``0123$*`` -> ``0123``; ``*`` or ``**`` -> ``head``)."""
    last = selector.rsplit("/", 1)[-1]
    if last.endswith("$*"):
        return last[:-2] or "head"
    return "head" if "*" in last else last


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
                f"SELECT {COLUMNS} FROM log_out WHERE tile=? AND seq>? ORDER BY seq LIMIT ?",
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
            f"SELECT {COLUMNS} FROM log_out WHERE gseq IN "
            f"({','.join('?' * len(chunk))}) ORDER BY gseq",
            chunk,
        ).fetchall()
    return rows, LogHead(req.stage, producer, through, head, latest_epochs(conn))
