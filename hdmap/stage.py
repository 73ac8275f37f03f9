"""A service that consumes one stage log and (optionally) produces the next.

The exactly-once loop of :mod:`hdmap.stream`, wired once for matcher, solver and
publisher:

1. live entries arrive on the input stage key for the region; the consumer puts
   them in order, drops duplicates and notices gaps;
2. on start, on a gap, when an upstream producer appears, and every
   ``catchup_interval_s``, the consumer replays what it is missing;
3. ``apply(entries)`` runs inside one SQLite transaction together with the
   offsets of those entries and the output entries it appends;
4. after the commit, the output entries are published live.
"""

from __future__ import annotations

import logging
import time

import zenoh

from hdmap import keys
from hdmap.service import Item, Service, ServiceOptions
from hdmap.store import StorageError
from hdmap.stream import STAGE_KEYS, LogConsumer, LogServer, LogWriter
from schemas import DecodeError, LogEntry

log = logging.getLogger(__name__)


class StageService(Service):
    """Subclasses set ``input_stage``/``upstream`` and, if they produce, ``output_stage``."""

    input_stage: str = ""
    upstream: str = ""
    """Name of the service producing ``input_stage`` (its liveliness triggers catch-up)."""
    output_stage: str | None = None

    def __init__(self, opts: ServiceOptions):
        super().__init__(opts)
        self.consumer = LogConsumer(self.db, self.input_stage, self.region)
        self.writer = (
            LogWriter(self.db, self.output_stage, self.instance) if self.output_stage else None
        )
        self._log_server: LogServer | None = None
        self._outbox: list[LogEntry] = []

    # -- hooks for subclasses ----------------------------------------------------------------

    def apply(self, entries: list[LogEntry]) -> None:
        """Apply in-order input entries; append outputs with :meth:`emit` (in a transaction)."""
        raise NotImplementedError

    def after_commit(self) -> None:
        """Publish derived state after a successful apply (beyond the output log)."""

    def handle_other(self, items: list[Item]) -> None:
        """Items that are not stage entries (queries of this service)."""
        for it in items:
            if it.query is not None:
                it.query.drop()

    # -- wiring -------------------------------------------------------------------------------

    def setup(self) -> None:
        for prefix in self.region or [""]:
            self.subscribe(STAGE_KEYS[self.input_stage](keys.region(prefix)), "entry")
        if self.output_stage:
            self._log_server = LogServer(
                self.session, self.db_path, self.output_stage, self.instance
            )
        if self.upstream:

            def on_alive(sample: zenoh.Sample) -> None:
                if sample.kind == zenoh.SampleKind.PUT:
                    self.inbox.put(Item("producer_up", str(sample.key_expr), b""))

            self.declare(
                self.session.liveliness().declare_subscriber(
                    keys.alive(self.upstream, "*", "*"), on_alive
                )
            )
        self.every(self.opts.catchup_interval_s, lambda _now: self._mark_catchup())
        self.inbox.put(Item("kick", "", b""))

    def teardown(self) -> None:
        if self._log_server is not None:
            self._log_server.close()

    def _mark_catchup(self) -> None:
        self.consumer.need_catchup = True
        self.inbox.put(Item("kick", "", b""))

    def emit(self, tile: str, body: bytes) -> LogEntry:
        """Append an output entry (inside apply's transaction); published after commit."""
        assert self.writer is not None
        e = self.writer.append(tile, body)
        self._outbox.append(e)
        return e

    def handle(self, items: list[Item]) -> None:
        deliver: list[LogEntry] = []
        others: list[Item] = []
        for it in items:
            if it.kind == "entry":
                try:
                    entry = LogEntry.from_bytes(it.payload)
                except DecodeError as exc:
                    self.reject(f"bad entry: {exc.field}")
                    continue
                deliver += self.consumer.offer(entry)
            elif it.kind == "producer_up":
                self.consumer.need_catchup = True
            elif it.kind != "kick":
                others.append(it)
        if self.consumer.need_catchup:
            try:
                deliver += self.consumer.catch_up(self.session)
            except zenoh.ZError as exc:
                log.warning("catch-up failed: %s", exc)
        if deliver:
            self._apply_and_publish(deliver)
        if others:
            self.handle_other(others)

    def _apply_and_publish(self, entries: list[LogEntry]) -> None:
        """Apply a batch in one transaction; a batch that raises is retried entry by entry,
        and an entry that still raises is set aside (dead-lettered, counted, logged) so one
        poisonous entry cannot stop the stage. Storage failures are not set aside: the
        entries stay unapplied and are replayed."""
        try:
            self._apply_in_transaction(entries)
        except StorageError as exc:
            log.error("%s: %s; entries will be replayed", self.name, exc)
            self.count("storage_errors")
            self._outbox = []
        except Exception:  # any bug in apply: isolate the entry that causes it
            if len(entries) > 1:
                for e in entries:
                    self._apply_and_publish([e])
                return
            log.exception("%s: entry %s failed; dead-lettered", self.name, _describe(entries[0]))
            self._dead_letter(entries[0])

    def _apply_in_transaction(self, entries: list[LogEntry]) -> None:
        participants = [self.consumer] + ([self.writer] if self.writer else [])
        participants += self.participants()
        self._outbox = []
        try:
            with self.transaction(participants):
                self.apply(entries)
                self.consumer.record(entries)
                self.count("entries_applied", len(entries))
                self.count("log_entries", len(self._outbox))
        except BaseException:
            self._outbox = []
            raise
        for e in self._outbox:
            self.pubs.put(STAGE_KEYS[e.stage](e.tile), e.to_bytes())
        self._outbox = []
        self.after_commit()

    def _dead_letter(self, entry: LogEntry) -> None:
        """Keep a failing entry for inspection and mark it consumed (counted, not applied)."""
        try:
            with self.transaction([self.consumer]):
                self.db.execute(
                    "CREATE TABLE IF NOT EXISTS dead_letters "
                    "(at REAL NOT NULL, stage TEXT NOT NULL, body BLOB NOT NULL)"
                )
                self.db.execute(
                    "INSERT INTO dead_letters(at, stage, body) VALUES (?, ?, ?)",
                    (time.time(), entry.stage, entry.to_bytes()),
                )
                self.consumer.record([entry])
                self.count("entries_failed")
                self.count("entries_applied")
        except StorageError as exc:
            log.error("%s: cannot dead-letter: %s", self.name, exc)
            self.count("storage_errors")

    def participants(self) -> list:
        """Extra in-memory state that must follow the transaction's outcome."""
        return []

    def extra_counters(self) -> dict[str, float]:
        s = self.consumer.stats
        return {
            "entries_duplicate": s.duplicates,
            "entries_gap": s.gaps,
            "entries_replayed": s.replayed,
            "catchups": s.catchups,
        }


def _describe(e: LogEntry) -> str:
    return f"{e.stage}/{e.producer}/{e.tile}#{e.seq}"
