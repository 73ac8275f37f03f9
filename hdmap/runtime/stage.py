"""A service that consumes one stage log and (optionally) produces the next.

The exactly-once loop of :mod:`hdmap.runtime.stream`, wired once for matcher, solver and
publisher:

1. live entries arrive on the input stage key for the region; the consumer puts
   them in order, drops duplicates and notices gaps;
2. on start, on a gap, when an upstream producer appears, and every
   ``catchup_interval_s``, the consumer replays what it is missing; the producers'
   answers are waited for on a thread of their own (:mod:`hdmap.runtime.catchup`), so
   live entries keep flowing meanwhile, and a gap nobody fills is retried with backoff
   and given up after a while (:class:`~hdmap.runtime.stream.GapPolicy`);
3. ``apply(entries)`` runs inside one SQLite transaction together with the
   offsets of those entries and the output entries it appends;
4. after the commit, the output entries are published live.

Entries are applied in each producer's ``gseq`` order (live entries released from
behind a gap are merged with the replay), never twice (an entry at or below the
committed offset is dropped even if it is delivered again), and an entry whose apply
raises, or breaks an SQLite constraint, is set aside (dead-lettered) alone; a failing
storage (full, read-only) leaves the entries unapplied, to be replayed: the service's
:class:`~hdmap.runtime.service.Backoff` spaces the tries (at once, then 0.1 s doubling up
to 5 s), and live entries that arrive meanwhile are not taken (they stay in the producer's
log, which the retry replays). Corruption met while applying
(:class:`~hdmap.runtime.store.DatabaseCorrupt`) stops the service, as the check at open
does (exit 65).
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from itertools import pairwise

import zenoh

from hdmap.runtime.catchup import BackgroundCatchUp, Fetch, bus_fetch
from hdmap.runtime.handover import Handover
from hdmap.runtime.log_checkpoint import Fold
from hdmap.runtime.log_out import LogServer, LogWriter
from hdmap.runtime.retention import LogRetention
from hdmap.runtime.service import Item, Service, ServiceOptions
from hdmap.runtime.store import DatabaseCorrupt, StorageError
from hdmap.runtime.stream import STAGE_KEYS, LogConsumer
from schemas import DecodeError, LogEntry, LogMark, keys

log = logging.getLogger(__name__)


class StageService(Service):
    """Subclasses set ``input_stage``/``upstream`` and, if they produce, ``output_stage``."""

    batch_linger_s = 0.02
    input_stage: str = ""
    upstream: str = ""
    """Name of the service producing ``input_stage`` (its liveliness triggers catch-up)."""
    output_stage: str | None = None
    hands_over: bool = False
    """Owns its region's state and hands it over on request (matcher, solver:
    :mod:`hdmap.runtime.handover`)."""
    output_fold: Fold | None = None
    """Set when the output log's entries are states: retention folds what it deletes into
    per-tile checkpoints that answer catch-ups from below (:mod:`hdmap.runtime.log_checkpoint`)."""

    def __init__(self, opts: ServiceOptions):
        super().__init__(opts)
        self.consumer = LogConsumer(
            self.db, self.input_stage, self.region, opts.gaps, lambda: self.clock()
        )
        self.catchups: BackgroundCatchUp | None = None
        """Set up with the session (:meth:`setup`), or by a test with its own fetch."""
        self.writer = (
            LogWriter(self.db, self.output_stage, self.instance) if self.output_stage else None
        )
        self._log_server: LogServer | None = None
        self.retention = (
            LogRetention(
                self.db, self.output_stage, self.instance, opts.retention, fold=self.output_fold
            )
            if self.output_stage
            else None
        )
        self.handover = Handover(
            self.name,
            self.instance,
            self.region_label,
            self.db,
            self.data_dir,
            lambda: self.writer.gseq if self.writer else 0,
            inputs=self.consumer.positions,
            hold=self.consumer.hold_at,
        )
        self._paused_dropped = 0
        """Live entries dropped while paused for a handover (the producers' logs keep them)."""
        self._outbox: list[LogEntry] = []
        self._deferred = 0
        """Live entries not taken while a storage failure is waited out (replayed later)."""
        self._dropped_batches = 0
        """Times live entries were dropped on a full inbox (each time a catch-up follows)."""
        self.db.execute(
            "CREATE TABLE IF NOT EXISTS dead_letters "
            "(at REAL NOT NULL, stage TEXT NOT NULL, body BLOB NOT NULL)"
        )

    # -- hooks for subclasses ----------------------------------------------------------------

    def apply(self, entries: list[LogEntry]) -> None:
        """Apply in-order input entries; append outputs with :meth:`emit` (in a transaction)."""
        raise NotImplementedError

    def after_commit(self) -> None:
        """Publish derived state after a successful apply (beyond the output log)."""

    def before_handover(self) -> None:
        """Make the database the whole state before a handover's checkpoint (inside a
        transaction; :mod:`hdmap.runtime.handover`)."""

    def first_output(self) -> None:
        """What a service whose output log is new but whose state is not (a part of a split
        or a merge: :mod:`hdmap.runtime.partition` starts each part as a new producer)
        writes as its log's first entries with :meth:`emit` (inside a transaction): by
        default nothing. A consumer reads a new producer's log from its start."""

    def handle_other(self, items: list[Item]) -> None:
        """Items that are not stage entries (queries of this service)."""
        for it in items:
            if it.query is not None:
                it.query.drop()

    # -- wiring -------------------------------------------------------------------------------

    def setup(self) -> None:
        for prefix in self.region or [""]:
            key = STAGE_KEYS[self.input_stage](keys.region(prefix))
            self.subscribe(key, "entry", drop_when_full=True)
        if self.output_stage:
            self._log_server = LogServer(
                self.session,
                self.db_path,
                self.output_stage,
                self.instance,
                checkpoints=self.output_fold is not None,
            )
        if self.retention is not None:
            self.retention.wire(self)
        if self.upstream:

            def on_alive(sample: zenoh.Sample) -> None:
                if sample.kind == zenoh.SampleKind.PUT:
                    self.inbox.put(Item("producer_up", str(sample.key_expr), b""))

            self.declare(
                self.session.liveliness().declare_subscriber(
                    keys.alive(self.upstream, "*", "*"), on_alive
                )
            )
        if self.hands_over:
            self.serve(self.handover.key(), "handover")
        self.start_log()
        self.every(self.opts.catchup_interval_s, lambda _now: self._mark_catchup())
        self.every(self.opts.catchup_interval_s, lambda _now: self.publish_marks())
        self.use_fetch(bus_fetch(self.session))
        self.inbox.put(Item("kick", "", b""))

    def use_fetch(self, fetch_round: Fetch, executor=None) -> None:
        """Catch up with ``fetch_round`` (the bus, or a test's log) on ``executor``."""
        if self.catchups is not None:
            self.catchups.close()
        self.catchups = BackgroundCatchUp(self.consumer, fetch_round, self._kick, executor=executor)

    def publish_marks(self) -> None:
        """Tell each producer how far this consumer has applied its log (its retention);
        not while paused for a handover (the mark stays; a stopped one has left)."""
        if self.handover.paused:
            return
        for m in self.consumer.marks(self.instance):
            self.pubs.put(keys.mark(m.stage, m.producer, m.consumer), m.to_bytes())

    def _kick(self) -> None:
        """Wake the worker (a catch-up round's answers are in); a full inbox wakes it too."""
        with contextlib.suppress(queue.Full):
            self.inbox.put_nowait(Item("kick", "", b""))

    def run(self, stop: threading.Event) -> None:
        self.handover.stop = stop  # a handover's last request stops the process
        super().run(stop)

    def _handover(self, it: Item, deliver: list[LogEntry]) -> None:
        """Apply what came before a handover request, then serve it."""
        if self.handover.applying and not self.backoff.waiting(self.clock()):
            self._deliver(deliver)
        deliver.clear()
        was_paused = self.handover.paused
        self.handover.answer(it, self._prepare_handover, self.reject)
        if was_paused and not self.handover.paused:  # resumed: fetch what was dropped
            self.consumer.need_catchup = True
        if self.handover.stop is not None and self.handover.stop.is_set():
            for producer in sorted(self.consumer.watermarks):  # no longer hold their logs
                leave = LogMark(self.input_stage, producer, self.instance, 0, 0)
                self.pubs.put(
                    keys.mark(self.input_stage, producer, self.instance), leave.to_bytes()
                )

    def _prepare_handover(self) -> None:
        with self.transaction(self.participants()):
            self.before_handover()

    def teardown(self) -> None:
        if self.catchups is not None:
            self.catchups.close()
        if self._log_server is not None:
            self._log_server.close()

    def _mark_catchup(self) -> None:
        if self.handover.lease_over():  # the handover tool is gone: apply again
            self.count("handover_expired")
        # on the worker thread: a blocking put into its own full inbox would never return
        self.consumer.need_catchup = True
        with contextlib.suppress(queue.Full):
            self.inbox.put_nowait(Item("kick", "", b""))

    def emit(self, tile: str, body: bytes) -> LogEntry:
        """Append an output entry (inside apply's transaction); published after commit."""
        assert self.writer is not None
        e = self.writer.append(tile, body)
        self._outbox.append(e)
        return e

    def handle(self, items: list[Item]) -> None:
        """Live entries, kicks and producers appearing: deliver in order and apply; while a
        storage failure is waited out (:attr:`backoff`), nothing is applied and live
        entries are left to the replay that follows."""
        waiting = self.backoff.waiting(self.clock())
        if self.inbox_dropped.is_set():  # live entries lost on a full inbox: replay them
            self.inbox_dropped.clear()
            self.consumer.need_catchup = True
            self._dropped_batches += 1
        deliver: list[LogEntry] = []
        others: list[Item] = []
        for it in items:
            if it.kind == "entry":
                try:
                    entry = LogEntry.from_bytes(it.payload)
                except DecodeError as exc:
                    self.reject(f"bad entry: {exc.field}")
                    continue
                if waiting:  # the rollback rewound the consumer: the retry replays it
                    self._deferred += 1
                    continue
                if not self.handover.applying or self.consumer.past_cut(entry):
                    self._paused_dropped += 1  # handed over: the producer's log keeps it
                    continue
                deliver += self.consumer.offer(entry)
            elif it.kind == "handover":
                self._handover(it, deliver)
            elif it.kind == "producer_up":
                self.consumer.need_catchup = True
            elif it.kind == "mark" and self.retention is not None:
                self.retention.take(self, [it])
            elif it.kind != "kick":
                others.append(it)
        if not waiting and self.handover.applying:
            self._deliver(deliver)
            if self.handover.advancing and self.consumer.at_cut():
                self.handover.reach_cut(self._prepare_handover)
        if others:
            self.handle_other(others)

    def retry(self) -> None:
        """The backoff after a storage failure is over: replay and apply what is missing."""
        self.handle([])

    def _deliver(self, deliver: list[LogEntry]) -> None:
        """Take in the catch-up rounds that are done (and start the next that is due),
        give up gaps open too long, then apply what is not applied yet."""
        now = self.clock()
        if self.catchups is not None:
            deliver += self.catchups.poll(now)
        for producer, tile, last, first in self.consumer.expire_gaps(now):
            log.warning(
                "%s: gap in %s/%s not filled in %g s (applied up to %d, waiting from %d); "
                "the waiting entries are dropped and the log asked again later",
                self.name,
                producer,
                tile,
                self.consumer.policy.timeout_s,
                last,
                first,
            )
        deliver = self._unapplied(in_producer_order(deliver))
        if deliver:
            self._apply_and_publish(deliver)
        elif self.consumer.marks_behind:  # a quiet producer's head: its marks reach it
            with self.transaction([self.consumer]):
                self.consumer.record([])

    def _unapplied(self, entries: list[LogEntry]) -> list[LogEntry]:
        """Entries above the committed offsets. A batch that failed and was applied entry
        by entry leaves the consumer's delivery marks behind its offsets, so the next
        replay delivers those entries again: they must not be applied twice."""
        done = self.consumer.committed
        return [e for e in entries if e.seq > done(e.producer, e.tile)]

    def _apply_and_publish(self, entries: list[LogEntry]) -> bool:
        """Apply a batch in one transaction; a batch that raises is retried entry by entry,
        and an entry that still raises is set aside (dead-lettered, counted, logged) so one
        poisonous entry cannot stop the stage. Storage failures are not set aside: the
        entries stay unapplied and are replayed once :attr:`backoff` allows; corruption
        is raised (it stops the service). Whether the storage kept up (False: it failed
        and the rest of the work waits)."""
        try:
            self._apply_in_transaction(entries)
        except DatabaseCorrupt:
            raise
        except StorageError as exc:
            if not exc.transient:  # SQLite refused the statement: a poison, not the disk
                return self._isolate(entries)
            log.error(
                "%s: %s; entries will be replayed (failure %d in a row, next try in %.3g s)",
                self.name,
                exc,
                self.backoff.failures,
                self.backoff.wait_s(self.clock()),
            )
            self.count("storage_errors")
            self._outbox = []
            return False
        except Exception:  # noqa: BLE001 - any bug in apply: isolate the entry that causes it
            return self._isolate(entries)
        return True

    def _isolate(self, entries: list[LogEntry]) -> bool:
        """Each entry in its own transaction, dead-lettering one that fails alone; stops at
        a storage failure (the rest is replayed later). Whether the storage kept up."""
        if len(entries) > 1:
            return all(self._apply_and_publish([e]) for e in entries)  # stops at a False
        log.exception("%s: entry %s failed; dead-lettered", self.name, _describe(entries[0]))
        return self._dead_letter(entries[0])

    def start_log(self) -> None:
        """:meth:`first_output` in one transaction when the output log is new (nothing
        written yet, ``gseq`` 0), its entries published after the commit."""
        if self.writer is None or self.writer.gseq > 0:
            return
        self._in_transaction(self.first_output)

    def _apply_in_transaction(self, entries: list[LogEntry]) -> None:
        def work() -> None:
            self.apply(entries)
            self.consumer.record(entries)
            self.count("entries_applied", len(entries))

        self._in_transaction(work)

    def _in_transaction(self, work: Callable[[], None]) -> None:
        """``work`` in one transaction with the consumer, the log writer and the
        subclass's participants; the output entries it appended published after the
        commit (none if it raises)."""
        participants = [self.consumer] + ([self.writer] if self.writer else [])
        participants += self.participants()
        self._outbox = []
        try:
            with self.transaction(participants):
                work()
                self.count("log_entries", len(self._outbox))
        except BaseException:
            self._outbox = []
            raise
        for e in self._outbox:
            self.pubs.put(STAGE_KEYS[e.stage](e.tile), e.to_bytes())
        self._outbox = []
        self.after_commit()

    def _dead_letter(self, entry: LogEntry) -> bool:
        """Keep a failing entry for inspection and mark it consumed (counted, not applied);
        whether the storage kept it (corruption is raised)."""
        try:
            with self.transaction([self.consumer]):
                self.db.execute(
                    "INSERT INTO dead_letters(at, stage, body) VALUES (?, ?, ?)",
                    (time.time(), entry.stage, entry.to_bytes()),
                )
                self.consumer.record([entry])
                self.count("entries_failed")
                self.count("entries_applied")
                self.reject(f"{entry.stage}.apply_failed")  # in Stats.rejected, by reason
        except DatabaseCorrupt:
            raise
        except StorageError as exc:
            log.error("%s: cannot dead-letter: %s", self.name, exc)
            self.count("storage_errors")
            return False
        return True

    def participants(self) -> list:
        """Extra in-memory state that must follow the transaction's outcome."""
        return []

    def extra_counters(self) -> dict[str, float]:
        s = self.consumer.stats
        return {
            "lag_entries": float(self.consumer.lag),
            "entries_duplicate": s.duplicates,
            "entries_gap": s.gaps,
            "entries_replayed": s.replayed,
            "catchups": s.catchups,
            "resyncs": s.resyncs,
            "replay_refused": s.replay_refused,
            "checkpoints_taken": s.checkpoints,
            "gaps_open": self.consumer.gaps_open,
            "gap_oldest_s": self.consumer.oldest_gap_s(),
            "gaps_expired": s.gaps_expired,
            "entries_ahead": self.consumer.ahead_entries,
            "entries_ahead_dropped": s.ahead_dropped,
            "entries_deferred": self._deferred,
            "inbox_overflows": self._dropped_batches,
            "handover_paused": float(self.handover.paused),
            "entries_paused_dropped": self._paused_dropped,
        }


def in_producer_order(entries: list[LogEntry]) -> list[LogEntry]:
    """Each producer's entries in the order it wrote them (``LogEntry.order``: its runs in
    turn, each in ``gseq`` order), at the places its entries take.

    The consumer releases a live entry that waited behind a gap as soon as the gap is
    filled, ahead of replayed entries of other tiles the producer wrote before it; this
    puts them back in the order the producer wrote them (the order of a run without the
    gap, which the matcher's results depend on). Per (producer, tile) the order is
    unchanged: ``seq`` grows with ``gseq``.
    """
    mine: dict[str, list[LogEntry]] = defaultdict(list)
    for e in entries:
        mine[e.producer].append(e)
    if all(all(a.order < b.order for a, b in pairwise(v)) for v in mine.values()):
        return entries
    queues = {p: iter(sorted(v, key=lambda e: e.order)) for p, v in mine.items()}
    return [next(queues[e.producer]) for e in entries]


def _describe(e: LogEntry) -> str:
    return f"{e.stage}/{e.producer}/{e.tile}#{e.seq}"
