"""A producer's log kept no longer than its consumers need it (issue 20, bounded storage).

Consumers put, every few seconds, how far they have applied each producer's log
(:class:`~schemas.LogMark` on ``hdmap/v1/mark/<stage>/<producer>/<consumer>``:
:meth:`hdmap.runtime.stream.LogConsumer.marks`). The producer keeps each consumer's last
mark (table ``log_marks``) and, every :attr:`RetentionPolicy.every_s`, deletes the
entries at or below the smallest mark that are older than the floor
:attr:`RetentionPolicy.retain_s` (:meth:`LogRetention.truncate`); how far it deleted is
kept (meta ``log_truncated_through``), and a replay query that asks for less is refused
with an error naming ``after_gseq`` (the entries are gone: the consumer must be rebuilt),
instead of an answer that silently lacks them; on a log whose entries are states (the
update log) the deleted entries are folded into per-tile checkpoints first, which answer
such a query instead (:mod:`hdmap.runtime.log_checkpoint`).

Invariants: an entry goes only when every consumer that sent a mark in the last
``forget_after_s`` has applied it (a mark says that of every entry of its region up to
its ``gseq``) and it is older than the floor. A mark in a run the producer does not have
(it was restored from an older backup; :mod:`hdmap.runtime.log_out`, epochs) is refused:
its ``gseq`` counts entries the producer lost, and would delete new ones.

Pitfalls: a consumer that has never sent a mark (a new region's) is protected only by the
floor; one silent longer than ``forget_after_s`` no longer holds the log. On the obs and
assoc logs both must then start from a checkpoint of their own state (a backup, or a
region's handover: docs/operations.md, "Retention").
"""

from __future__ import annotations

import logging
import sqlite3
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from hdmap.runtime.log_checkpoint import SCHEMA as CHECKPOINT_SCHEMA
from hdmap.runtime.log_checkpoint import Fold, fold_rows
from hdmap.runtime.log_policy import RetentionPolicy
from hdmap.runtime.store import Meta
from schemas import DecodeError, LogMark, keys

if TYPE_CHECKING:
    from hdmap.runtime.service import Item, Service

log = logging.getLogger(__name__)

TRUNCATED = "log_truncated_through"
"""Meta key: the largest ``gseq`` deleted from the log (0: nothing)."""


def truncated_through(conn: sqlite3.Connection) -> int:
    """How far the log on ``conn`` was truncated (0: never; reads only)."""
    try:
        row = conn.execute("SELECT value FROM meta WHERE key=?", (TRUNCATED,)).fetchone()
    except sqlite3.OperationalError:  # no meta table: a log never truncated
        return 0
    return int(row[0]) if row is not None else 0


class LogRetention:
    """A producer's consumers' marks and the truncation of its log."""

    SCHEMA = """
    CREATE TABLE IF NOT EXISTS log_marks (
        consumer TEXT PRIMARY KEY, gseq INTEGER NOT NULL, epoch INTEGER NOT NULL,
        at REAL NOT NULL) WITHOUT ROWID;
    """
    CHUNK = 5000
    """Entries deleted per statement (the caller's transaction holds them all)."""

    def __init__(
        self,
        conn: sqlite3.Connection,
        stage: str,
        producer: str,
        policy: RetentionPolicy,
        wall: Callable[[], float] = time.time,
        fold: Fold | None = None,
    ):
        """``fold``: the log's entries are states, folded into checkpoints before they go."""
        self.conn, self.stage, self.producer, self.policy = conn, stage, producer, policy
        self.wall = wall
        self.fold = fold
        conn.executescript(self.SCHEMA)
        if fold is not None:
            conn.executescript(CHECKPOINT_SCHEMA)

    def on_mark(self, mark: LogMark) -> None:
        """Keep a consumer's mark (inside the caller's transaction); a mark for another
        log or in a run this producer does not have is a :class:`DecodeError` naming the
        field. A mark at ``gseq`` 0 is a consumer leaving for good (its region handed
        over: the instances that took it over mark for themselves): its mark is
        forgotten at once rather than holding the log for ``forget_after_s``."""
        if mark.stage != self.stage or mark.producer != self.producer:
            raise DecodeError("producer", f"{mark.stage}/{mark.producer} is not this log")
        if mark.gseq == 0:
            self.conn.execute("DELETE FROM log_marks WHERE consumer=?", (mark.consumer,))
            return
        known = self.conn.execute(
            "SELECT 1 FROM log_epochs WHERE epoch=?", (mark.epoch,)
        ).fetchone()
        if mark.epoch and known is None:
            raise DecodeError(
                "epoch", f"{mark.epoch} is not a run of {self.producer} (restored from a backup?)"
            )
        self.conn.execute(
            "INSERT OR REPLACE INTO log_marks(consumer, gseq, epoch, at) VALUES (?, ?, ?, ?)",
            (mark.consumer, mark.gseq, mark.epoch, self.wall()),
        )

    def through(self) -> int:
        """The largest ``gseq`` every live consumer has applied (0: no consumer yet)."""
        since = self.wall() - self.policy.forget_after_s
        (low,) = self.conn.execute(
            "SELECT MIN(gseq) FROM log_marks WHERE at >= ?", (since,)
        ).fetchone()
        return int(low or 0)

    def truncate(self) -> int:
        """Delete the entries every live consumer has applied and older than the floor
        (inside the caller's transaction); how many."""
        low = self.through()
        if low <= 0:
            return 0
        before = self.wall() - self.policy.retain_s
        gone = 0
        top = truncated_through(self.conn)
        for _ in range(100_000):  # bounded: CHUNK entries a round
            rows = self.conn.execute(
                "SELECT gseq FROM log_out WHERE gseq <= ? AND created_at < ? ORDER BY gseq LIMIT ?",
                (low, before, self.CHUNK),
            ).fetchall()
            if not rows:
                break
            span = (rows[0][0], rows[-1][0], before)
            if self.fold is not None:
                fold_rows(
                    self.conn,
                    self.conn.execute(
                        "SELECT tile, seq, gseq, body, epoch, base, gbase FROM log_out "
                        "WHERE gseq >= ? AND gseq <= ? AND created_at < ? ORDER BY gseq",
                        span,
                    ).fetchall(),
                    self.fold,
                )
            self.conn.execute(
                "DELETE FROM log_out WHERE gseq >= ? AND gseq <= ? AND created_at < ?", span
            )
            gone += len(rows)
            top = max(top, int(rows[-1][0]))
            if len(rows) < self.CHUNK:
                break
        if gone:
            Meta(self.conn).set(TRUNCATED, str(top))
        return gone

    def wire(self, service: Service) -> None:
        """Take this log's marks from the bus into ``service``'s inbox (items ``mark``,
        :meth:`take`) and truncate every :attr:`RetentionPolicy.every_s` (its timer)."""
        service.subscribe(keys.mark(self.stage, self.producer, keys.ANY), "mark")
        service.every(self.policy.every_s, lambda _now: self._truncate_in(service))

    def take(self, service: Service, items: list[Item]) -> None:
        """Keep the marks among ``items`` (each in a transaction of ``service``; a bad one
        refused, counted by field)."""
        for it in items:
            if it.kind != "mark":
                continue
            try:
                mark = LogMark.from_bytes(it.payload)
                with service.transaction():
                    self.on_mark(mark)
                    service.count("marks")
            except DecodeError as exc:
                service.reject(f"mark.{exc.field}")

    def _truncate_in(self, service: Service) -> None:
        with service.transaction():
            service.count("log_truncated", self.truncate())
