"""The runtime every service shares: one session, one worker, liveliness, stats.

Zenoh callbacks only copy bytes into one bounded inbox; the worker (the thread
that called :meth:`Service.run`) does all the work, in batches, so heavy work
never runs on a Zenoh callback thread (zenoh-python ``z_sub_queued.py`` style).
A full inbox blocks the callback, which with ``CongestionControl.BLOCK`` pushes
back on the producers instead of dropping data; except for input that can be fetched
again (stage log entries, :meth:`Service.subscribe` with ``drop_when_full``): a slow
consumer must not hold up its producer (ingest's acks to vehicles), so such samples are
dropped and the consumer replays them from the producer's log.

Per-key state follows an explicit contract (bytewax ``StatefulLogic``-like):
``handle`` (on items), ``on_timer`` (periodic), and the state lives in SQLite,
committed together with the input offsets it reflects.

Counters follow the transactions too: what :meth:`Service.count` adds inside
:meth:`Service.transaction` is staged, written with the work and shown in stats only once
the transaction commits (dropped if it rolls back), so stats never count uncommitted work;
while a batch is handled or a transaction is open, the gauge ``applying`` is 1. A
transaction that fails on the storage (disk full, read-only) arms :class:`Backoff`: the
service waits before it tries again (the stage loop replays its input then), instead of
failing in a loop.

A corrupt database is a permanent fault: a service whose database fails its check at open
(:func:`hdmap.runtime.store.check_integrity`) or meets corruption later logs one line naming
the file and the cause and ends its process with
:data:`~hdmap.runtime.store.EXIT_CORRUPT` (:class:`PermanentFault`), which ``hdmap up``
does not restart.
"""

from __future__ import annotations

import logging
import os
import queue
import resource
import signal
import sqlite3
import threading
import time
import uuid
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import psutil
import zenoh

from hdmap.geo.tiles import DEFAULT_ZOOM, region_label
from hdmap.runtime.backoff import Backoff
from hdmap.runtime.bus import BusConfig, Publishers, open_session
from hdmap.runtime.config import ConfigError
from hdmap.runtime.heap import TRIM_EVERY_S, trim_heap
from hdmap.runtime.log_policy import GapPolicy, RetentionPolicy
from hdmap.runtime.metrics import MetricsConfig
from hdmap.runtime.metrics_server import ServiceMetrics
from hdmap.runtime.shards import shard_label
from hdmap.runtime.store import (
    EXIT_CORRUPT,
    EXIT_RESTART,
    DatabaseCorrupt,
    Meta,
    StateLost,
    StorageError,
    connect,
    is_corruption,
    transaction,
)
from schemas import Stats, keys

log = logging.getLogger(__name__)


class PermanentFault(SystemExit):
    """A service stopped on a fault no restart repairs (its database is corrupt): as an
    uncaught exception it ends the process with :data:`EXIT_CORRUPT` and prints nothing
    more (the line is logged where it is raised); ``fault`` is the cause."""

    def __init__(self, fault: DatabaseCorrupt):
        super().__init__(EXIT_CORRUPT)
        self.fault = fault

    def __str__(self) -> str:
        return str(self.fault)


def stopped_on(service: str, fault: DatabaseCorrupt) -> PermanentFault:
    """Log the one line that says why ``service`` stops on ``fault``; the exception to raise."""
    log.error(
        "%s: %s; stopping (exit %d, not restarted by hdmap up): restore the file from a "
        "backup, then start it again (docs/operations.md)",
        service,
        fault,
        EXIT_CORRUPT,
    )
    return PermanentFault(fault)


@dataclass(frozen=True)
class Batching:
    """How the worker cuts its inbox into batches (each batch one ``handle`` call: for a
    stage service one transaction, one re-solve and one publish). ``[NAME.batching]`` in a
    services config file (``hdmap service NAME --config FILE``, ``hdmap up --config``).

    What a service computes never depends on these (every stage gives the same state for
    a log however it is batched); its cost does: handed one entry at a time the matcher
    spends 1.5 times and the solver 3 times the CPU per observation they spend on batches
    of 64 (per transaction: the commit, the state save, one call adding the links, the
    re-solve and publish of what the batch touched; BENCHMARKS.md, "Batching"). Lingering
    makes batches of a few entries at moderate load, for a latency of at most
    ``linger_s`` per stage; under saturation the inbox is never empty and nothing
    lingers."""

    max_items: int = 256
    """At most this many items per batch."""
    linger_s: float | None = None
    """After a batch's first item, wait up to this long (wall time, seconds) for more;
    None: the service's own default (:attr:`Service.batch_linger_s`)."""

    def __post_init__(self) -> None:
        if not (isinstance(self.max_items, int) and self.max_items >= 1):
            raise ConfigError("batching.max_items: an integer >= 1")
        if self.linger_s is not None and not (0.0 <= self.linger_s <= 1.0):
            raise ConfigError("batching.linger_s: seconds in [0, 1]")


@dataclass(frozen=True)
class ServiceOptions:
    """What every service takes from the command line or its config file."""

    region: tuple[str, ...] = ()
    """Quadkey prefixes this instance owns (empty = every tile)."""
    data_dir: Path = Path("var")
    bus: BusConfig = field(default_factory=BusConfig)
    instance: str | None = None
    """Stable instance id; default: stored in the data dir on first start."""
    sync: str = "normal"
    """SQLite synchronous mode: 'normal' (survives process crashes) or 'full' (power loss)."""
    zoom: int = DEFAULT_ZOOM
    catchup_interval_s: float = 5.0
    inbox_size: int = 4096
    batching: Batching = field(default_factory=Batching)
    gaps: GapPolicy = field(default_factory=GapPolicy)
    retention: RetentionPolicy = field(default_factory=RetentionPolicy)
    shard: tuple[int, int] = (0, 1)
    """(index, count): this instance serves the keys of its shard only (ingest: vehicles
    by :func:`shard_of` their id); part of the instance's label and data dir when count
    is above 1."""
    metrics: MetricsConfig = field(default_factory=MetricsConfig)
    """Where to serve Prometheus metrics (``[NAME.metrics]``, ``--metrics-port``; off)."""


@dataclass
class Item:
    """One unit of work copied out of a Zenoh callback."""

    kind: str
    key: str
    payload: bytes
    query: zenoh.Query | None = None
    received: float = field(default_factory=time.monotonic)


@dataclass
class _Staged:
    """The counts of the transaction open on ``thread``, shown when it commits."""

    thread: int
    counters: Counter[str] = field(default_factory=Counter)
    rejected: Counter[str] = field(default_factory=Counter)


class _CountsOutcome:
    """Transaction participant that makes the staged counts committed or drops them."""

    def __init__(self, service: Service, staged: _Staged):
        self._service, self._staged = service, staged

    def on_commit(self) -> None:
        self._service._merge(self._staged)

    def on_rollback(self) -> None:
        """Nothing to undo: the staged counts were never shown."""


class Service:
    """Base class: subclasses set ``name`` and implement ``setup``/``handle``/``on_timer``."""

    name: ClassVar[str] = "service"
    batch_linger_s: ClassVar[float] = 0.0
    """Default of :attr:`Batching.linger_s` for this service (the stage services: 0.02 s)."""
    stops_on_corruption: ClassVar[bool] = True
    """Whether corruption met by a transaction while running stops the service like a
    failed check at open (ingest, which refuses uploads instead, sets it False)."""

    def __init__(self, opts: ServiceOptions):
        self.opts = opts
        self.region = list(opts.region)
        self.region_label = region_label(self.region) + shard_label(opts.shard)
        self.data_dir = Path(opts.data_dir) / f"{self.name}-{self.region_label}"
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self.db_path = self.data_dir / "state.sqlite"
        try:
            self.db = connect(self.db_path, sync=opts.sync, check=True)
        except DatabaseCorrupt as exc:
            raise stopped_on(self.name, exc) from exc
        meta = Meta(self.db)
        self.instance = opts.instance or meta.setdefault(
            "instance",
            # '+' (several prefixes) is not allowed in ids: producer names and stats use them
            f"{self.name}-{self.region_label.replace('+', '_')[:40]}-{uuid.uuid4().hex[:8]}",
        )
        stored_zoom = int(meta.setdefault("zoom", str(opts.zoom)))
        if stored_zoom != opts.zoom:
            raise SystemExit(f"{self.db_path}: data dir was built with zoom {stored_zoom}")
        self.counters: Counter[str] = Counter()
        """Committed counts (what stats show); counts of an open transaction are staged."""
        self.rejected: Counter[str] = Counter()
        self._stats_lock = threading.Lock()
        self._staged: _Staged | None = None
        self._busy = False
        self._corrupt_seen: DatabaseCorrupt | None = None
        self._state_lost: StateLost | None = None
        self.clock: Callable[[], float] = time.monotonic
        """The worker's clock (monotonic seconds): timers and the backoff."""
        self.backoff = Backoff()
        self.txn_failures = 0
        """Transactions rolled back on an exception, in this process."""
        self.last_txn_error: tuple[str, float] | None = None
        """The last one's cause (SQLite's error name, or the exception's class) and time."""
        self._load_counters()
        self.inbox: queue.Queue[Item] = queue.Queue(maxsize=opts.inbox_size)
        self.inbox_dropped = threading.Event()
        """Set by a callback that dropped a sample on a full inbox (see :meth:`subscribe`)."""
        self.started_at = time.time()
        self._process = psutil.Process(os.getpid())
        self._declared: list[Any] = []
        self._timers: list[tuple[float, float, Callable[[float], None]]] = []
        self.metrics = ServiceMetrics(self, opts.metrics)  # binds its port, if it has one
        self.session: zenoh.Session
        self.pubs: Publishers

    # -- hooks ----------------------------------------------------------------------------

    def setup(self) -> None:
        """Declare subscribers/queryables (with :meth:`subscribe` / :meth:`serve`)."""

    def handle(self, items: list[Item]) -> None:
        """Process a batch of inbox items (worker thread)."""

    def teardown(self) -> None:
        """Release what setup acquired beyond declarations (threads, connections)."""

    def extra_counters(self) -> dict[str, float]:
        """Gauges and per-process counts of the subclass (read on the stats thread)."""
        return {}

    def retry(self) -> None:
        """Try again what a storage failure left undone, when :attr:`backoff` says so
        (worker thread); by default nothing (the next batch or timer tries)."""

    # -- helpers for subclasses -------------------------------------------------------------

    def count(self, name: str, n: int = 1) -> None:
        """Add ``n`` to a counter: staged until commit inside this thread's transaction,
        at once outside one."""
        with self._stats_lock:
            self._target()[0][name] += n

    def _target(self) -> tuple[Counter[str], Counter[str]]:
        """Where counts go now (the caller holds the stats lock)."""
        st = self._staged
        if st is not None and st.thread == threading.get_ident():
            return st.counters, st.rejected
        return self.counters, self.rejected

    @contextmanager
    def transaction(self, participants: Sequence[Any] = ()) -> Iterator[None]:
        """:func:`hdmap.runtime.store.transaction` that also keeps the counters: what is
        counted inside is written with the work and shown in stats when it commits, never
        if it rolls back, so the counts in stats are committed ones and survive a restart
        (also SIGKILL). A storage failure arms :attr:`backoff` (a commit resets it); a
        corrupt database is remembered so the loop stops the service
        (:attr:`stops_on_corruption`)."""
        staged = _Staged(threading.get_ident())
        with self._stats_lock:
            outer, self._staged = self._staged, staged
        try:
            with transaction(self.db, [_CountsOutcome(self, staged), *participants]):
                yield
                self._save_counters(staged)
        except Exception as exc:
            self._failed(exc)
            raise
        else:
            self.backoff.succeeded()
        finally:
            with self._stats_lock:
                self._staged = outer

    def _merge(self, staged: _Staged) -> None:
        """A commit: its staged counts become committed ones."""
        with self._stats_lock:
            self.counters.update(staged.counters)
            self.rejected.update(staged.rejected)
            staged.counters.clear()
            staged.rejected.clear()

    def _failed(self, exc: Exception) -> None:
        """Account for a rolled-back transaction; a storage failure arms the backoff."""
        cause = exc.__cause__ if isinstance(exc, StorageError) else exc
        name = getattr(cause, "sqlite_errorname", None) or type(cause or exc).__name__
        self.txn_failures += 1
        self.last_txn_error = (str(name), time.time())
        if isinstance(exc, DatabaseCorrupt):
            self._corrupt_seen = exc
        elif isinstance(exc, StateLost):
            self._state_lost = exc
        elif isinstance(exc, StorageError) and exc.transient:
            self.backoff.failed(self.clock())

    def _load_counters(self) -> None:
        self.db.execute(
            "CREATE TABLE IF NOT EXISTS counters (kind TEXT NOT NULL, name TEXT NOT NULL, "
            "value REAL NOT NULL, PRIMARY KEY (kind, name)) WITHOUT ROWID"
        )
        for kind, name, value in self.db.execute("SELECT kind, name, value FROM counters"):
            target = self.counters if kind == "c" else self.rejected
            target[name] = int(value) if float(value).is_integer() else value

    def _save_counters(self, staged: _Staged) -> None:
        """Write the counters as they are once ``staged`` commits (inside the transaction)."""
        with self._stats_lock:
            counters = Counter(self.counters)
            counters.update(staged.counters)
            rejected = Counter(self.rejected)
            rejected.update(staged.rejected)
        rows = [("c", k, float(v)) for k, v in counters.items()]
        rows += [("r", k, float(v)) for k, v in rejected.items()]
        self.db.executemany(
            "INSERT OR REPLACE INTO counters(kind, name, value) VALUES (?,?,?)", rows
        )

    def reject(self, reason: str, n: int = 1) -> None:
        """Count refused input by reason (staged inside a transaction, like :meth:`count`)."""
        with self._stats_lock:
            counters, rejected = self._target()
            rejected[reason] += n
            counters["rejected"] += n

    def subscribe(self, key: str, kind: str, drop_when_full: bool = False) -> None:
        """Samples on ``key`` into the inbox as items of ``kind``. A full inbox blocks the
        callback (pushing back on the publisher), or with ``drop_when_full`` drops the
        sample and sets :attr:`inbox_dropped` (for input that can be fetched again, such
        as stage log entries: the producer's log still has them)."""

        def cb(sample: zenoh.Sample) -> None:
            item = Item(kind, str(sample.key_expr), sample.payload.to_bytes())
            if not drop_when_full:
                self.inbox.put(item)
                return
            try:
                self.inbox.put_nowait(item)
            except queue.Full:
                self.inbox_dropped.set()

        self._declared.append(self.session.declare_subscriber(key, cb))

    def serve(self, key: str, kind: str, mine: Callable[[str], bool] | None = None) -> None:
        """A queryable whose queries the worker answers (then drops) later; with ``mine``,
        a query whose key it refuses is dropped unanswered at once (another instance's:
        the querier gets that one's answer alone)."""

        def cb(q: zenoh.Query) -> None:
            if mine is not None and not mine(str(q.key_expr)):
                q.drop()
                return
            payload = q.payload.to_bytes() if q.payload is not None else b""
            self.inbox.put(Item(kind, str(q.key_expr), payload, q))

        self._declared.append(self.session.declare_queryable(key, cb))

    def every(self, period_s: float, fn: Callable[[float], None]) -> None:
        self._timers.append((period_s, self.clock() + period_s, fn))

    def declare(self, entity: Any) -> Any:
        """Keep a declared entity so it is undeclared before the session closes."""
        self._declared.append(entity)
        return entity

    # -- stats ----------------------------------------------------------------------------

    def stats(self) -> Stats:
        cpu = self._process.cpu_times()
        with self._stats_lock:
            counters: dict[str, float] = dict(self.counters)
            rejected = dict(self.rejected)
            applying = self._busy or self._staged is not None
        counters.update(self.extra_counters())
        counters["backlog"] = self.inbox.qsize()
        counters["applying"] = int(applying)
        counters["txn_failures"] = self.txn_failures
        counters["txn_failing"] = self.backoff.failures
        counters["retry_in_s"] = self.backoff.wait_s(self.clock())
        if (last := self.last_txn_error) is not None:
            counters[f"last_txn_error.{last[0]}"] = last[1]
        counters["cpu_s"] = cpu.user + cpu.system
        mem = self._process.memory_info()
        counters["rss_bytes"] = mem.rss
        # Anonymous memory (RssAnon: heap, stacks, caches): RSS less the shared mappings
        # (files, /dev/shm: Zenoh's shared-memory segment counts in RSS once touched).
        counters["rss_anon_bytes"] = mem.rss - getattr(mem, "shared", 0)
        counters["rss_peak_bytes"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
        counters["uptime_s"] = time.time() - self.started_at
        counters = {k: _wire_number(v) for k, v in counters.items()}
        rejected = {k: _wire_number(v) for k, v in rejected.items()}
        return Stats(self.name, self.instance, self.region, self.started_at, counters, rejected)

    def _answer_stats(self, q: zenoh.Query) -> None:
        try:
            q.reply(q.key_expr, self.stats().to_bytes())
        finally:
            q.drop()

    # -- main loop --------------------------------------------------------------------------

    def run(self, stop: threading.Event) -> None:
        with open_session(self.opts.bus) as session:
            self.session = session
            self.pubs = Publishers(session)
            try:
                self.setup()
                self.declare(
                    session.declare_queryable(
                        keys.stats(self.name, self.region_label, self.instance), self._answer_stats
                    )
                )
                self.declare(
                    session.liveliness().declare_token(
                        keys.alive(self.name, self.region_label, self.instance)
                    )
                )
                self.every(TRIM_EVERY_S, lambda _now: trim_heap())  # RSS follows what is held
                log.info("%s %s ready (region %s)", self.name, self.instance, self.region_label)
                self.metrics.start()
                self._loop(stop)
            finally:
                self.metrics.close()
                for d in reversed(self._declared):
                    try:
                        d.undeclare()
                    except zenoh.ZError:
                        pass
                self.pubs.close()
                self.teardown()
                self.db.close()

    def _loop(self, stop: threading.Event) -> None:
        while not stop.is_set():
            now = self.clock()
            due = [t[1] for t in self._timers]
            if self.backoff.retry_at is not None:
                due.append(self.backoff.retry_at)
            timeout = max(0.0, min([0.2, *(d - now for d in due)]))
            items: list[Item] = []
            try:
                items.append(self.inbox.get(timeout=timeout))
                until = time.monotonic() + self.linger_s
                while len(items) < self.opts.batching.max_items:
                    left = until - time.monotonic()
                    it = self.inbox.get(timeout=left) if left > 0 else self.inbox.get_nowait()
                    items.append(it)
            except queue.Empty:
                pass
            self.step(items)

    @property
    def linger_s(self) -> float:
        """How long a batch waits for more items after its first (:class:`Batching`)."""
        own = self.opts.batching.linger_s
        return self.batch_linger_s if own is None else own

    def step(self, items: list[Item]) -> None:
        """One turn of the worker: handle ``items``, retry what the backoff lets, run the
        timers that are due; raise a :class:`DatabaseCorrupt` a transaction met (when
        :attr:`stops_on_corruption`), which stops the service (exit 65)."""
        if items:
            with self._stats_lock:
                self._busy = True
            began = time.monotonic()
            try:
                self.handle(items)
            finally:
                with self._stats_lock:
                    self._busy = False
                self.metrics.batch_done(items, began)
            self._stop_if_corrupt()
        if self.backoff.fire(self.clock()):
            self.retry()
            self._stop_if_corrupt()
        now = self.clock()
        for i, (period, due, fn) in enumerate(self._timers):
            if now >= due:
                self._run_timer(fn, now)
                self._timers[i] = (period, self.clock() + period, fn)
        self._stop_if_corrupt()

    def _run_timer(self, fn: Callable[[float], None], now: float) -> None:
        """A timer; one whose transaction fails on the storage is tried at its next period."""
        try:
            fn(now)
        except DatabaseCorrupt:
            raise
        except StorageError as exc:
            if not exc.transient:
                raise
            log.error("%s: %s; the timer runs again at its next period", self.name, exc)
            self.count("storage_errors")
        self._stop_if_corrupt()

    def _stop_if_corrupt(self) -> None:
        """Stop on a corrupt database (:attr:`stops_on_corruption`), and on state that could
        not be reloaded after a rollback (every service: a restart reloads it)."""
        if self.stops_on_corruption and (fault := self._corrupt_seen) is not None:
            raise fault
        if (lost := self._state_lost) is not None:
            log.error("%s: %s; exiting to be restarted (exit %d)", self.name, lost, EXIT_RESTART)
            raise SystemExit(EXIT_RESTART)


def _wire_number(v: float) -> float:
    """A counter as msgpack can carry it (ints beyond 64 bits become floats).

    >>> _wire_number(2**70) == float(2**70), _wire_number(3)
    (True, 3)
    """
    if isinstance(v, int) and not -(2**63) <= v < 2**64:
        return float(v)
    return v


def run_until_signalled(service: Service) -> int:
    """Run a service in this process until SIGTERM/SIGINT, then close cleanly; the exit
    code: 0, or :data:`EXIT_CORRUPT` when it stopped on a corrupt database."""
    stop = threading.Event()

    def on_signal(signum: int, _frame: object) -> None:
        log.info("%s: signal %d, stopping", service.name, signum)
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    try:
        service.run(stop)
    except DatabaseCorrupt as exc:  # met after the check at open, and not handled below
        stopped_on(service.name, exc)
        return EXIT_CORRUPT
    except sqlite3.DatabaseError as exc:
        if not is_corruption(exc):
            raise
        stopped_on(service.name, DatabaseCorrupt(service.db_path, str(exc)))
        return EXIT_CORRUPT
    return 0
