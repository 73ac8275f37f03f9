"""The runtime every service shares: one session, one worker, liveliness, stats.

Zenoh callbacks only copy bytes into one bounded inbox; the worker (the thread
that called :meth:`Service.run`) does all the work, in batches, so heavy work
never runs on a Zenoh callback thread (zenoh-python ``z_sub_queued.py`` style).
A full inbox blocks the callback, which with ``CongestionControl.BLOCK`` pushes
back on the producers instead of dropping data.

Per-key state follows an explicit contract (bytewax ``StatefulLogic``-like):
``handle`` (on items), ``on_timer`` (periodic), and the state lives in SQLite,
committed together with the input offsets it reflects.

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
from hdmap.runtime.bus import BusConfig, Publishers, open_session
from hdmap.runtime.store import (
    EXIT_CORRUPT,
    DatabaseCorrupt,
    Meta,
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
    max_batch_items: int = 256


@dataclass
class Item:
    """One unit of work copied out of a Zenoh callback."""

    kind: str
    key: str
    payload: bytes
    query: zenoh.Query | None = None
    received: float = field(default_factory=time.monotonic)


class Service:
    """Base class: subclasses set ``name`` and implement ``setup``/``handle``/``on_timer``."""

    name: ClassVar[str] = "service"

    def __init__(self, opts: ServiceOptions):
        self.opts = opts
        self.region = list(opts.region)
        self.region_label = region_label(self.region)
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
        self.rejected: Counter[str] = Counter()
        self._stats_lock = threading.Lock()
        self._load_counters()
        self.inbox: queue.Queue[Item] = queue.Queue(maxsize=opts.inbox_size)
        self.started_at = time.time()
        self._process = psutil.Process(os.getpid())
        self._declared: list[Any] = []
        self._timers: list[tuple[float, float, Callable[[float], None]]] = []
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
        return {}

    # -- helpers for subclasses -------------------------------------------------------------

    def count(self, name: str, n: int = 1) -> None:
        with self._stats_lock:
            self.counters[name] += n

    @contextmanager
    def transaction(self, participants: Sequence[Any] = ()) -> Iterator[None]:
        """:func:`hdmap.runtime.store.transaction` that also keeps the counters: they are written
        with the work they count and restored if it rolls back, so the counts in stats
        survive a restart (also SIGKILL) and never count work that was not kept."""
        with self._stats_lock:
            saved = (self.counters.copy(), self.rejected.copy())
        try:
            with transaction(self.db, participants):
                yield
                self._save_counters()
        except BaseException:
            with self._stats_lock:
                self.counters, self.rejected = saved
            raise

    def _load_counters(self) -> None:
        self.db.execute(
            "CREATE TABLE IF NOT EXISTS counters (kind TEXT NOT NULL, name TEXT NOT NULL, "
            "value REAL NOT NULL, PRIMARY KEY (kind, name)) WITHOUT ROWID"
        )
        for kind, name, value in self.db.execute("SELECT kind, name, value FROM counters"):
            target = self.counters if kind == "c" else self.rejected
            target[name] = int(value) if float(value).is_integer() else value

    def _save_counters(self) -> None:
        with self._stats_lock:
            rows = [("c", k, float(v)) for k, v in self.counters.items()]
            rows += [("r", k, float(v)) for k, v in self.rejected.items()]
        self.db.executemany(
            "INSERT OR REPLACE INTO counters(kind, name, value) VALUES (?,?,?)", rows
        )

    def reject(self, reason: str, n: int = 1) -> None:
        with self._stats_lock:
            self.rejected[reason] += n
            self.counters["rejected"] += n

    def subscribe(self, key: str, kind: str) -> None:
        def cb(sample: zenoh.Sample) -> None:
            self.inbox.put(Item(kind, str(sample.key_expr), sample.payload.to_bytes()))

        self._declared.append(self.session.declare_subscriber(key, cb))

    def serve(self, key: str, kind: str) -> None:
        """A queryable whose queries the worker answers (then drops) later."""

        def cb(q: zenoh.Query) -> None:
            payload = q.payload.to_bytes() if q.payload is not None else b""
            self.inbox.put(Item(kind, str(q.key_expr), payload, q))

        self._declared.append(self.session.declare_queryable(key, cb))

    def every(self, period_s: float, fn: Callable[[float], None]) -> None:
        self._timers.append((period_s, time.monotonic() + period_s, fn))

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
        counters.update(self.extra_counters())
        counters["backlog"] = self.inbox.qsize()
        counters["cpu_s"] = cpu.user + cpu.system
        counters["rss_bytes"] = self._process.memory_info().rss
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
                log.info("%s %s ready (region %s)", self.name, self.instance, self.region_label)
                self._loop(stop)
            finally:
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
            timeout = 0.2
            if self._timers:
                timeout = max(0.0, min(0.2, min(t[1] for t in self._timers) - time.monotonic()))
            items: list[Item] = []
            try:
                items.append(self.inbox.get(timeout=timeout))
                while len(items) < self.opts.max_batch_items:
                    items.append(self.inbox.get_nowait())
            except queue.Empty:
                pass
            if items:
                self.handle(items)
            now = time.monotonic()
            for i, (period, due, fn) in enumerate(self._timers):
                if now >= due:
                    fn(now)
                    self._timers[i] = (period, time.monotonic() + period, fn)


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
