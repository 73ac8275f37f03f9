"""Limits on snapshot queries (``[publisher.snapshots]``): per client, and in all.

A snapshot costs the publisher a read of the tile's rows and an encoding; thousands of
queries a second fill its query queue and delay every other snapshot (issue 17: 3,000
queries/s took the map latency p99 from 0.83 s to 42 s). So every query is charged,
on the Zenoh callback thread before it is queued, to

- its client's token bucket (``per_client_per_s``, ``per_client_burst``): the client is
  the id in ``hdmap/v1/map/<tile>/by/<client>`` (:func:`schemas.keys.map_snapshot_for`;
  the vehicle's authenticated id in secured mode), and every anonymous
  ``hdmap/v1/map/<tile>`` query is the one client ``anonymous``. Over it the query is
  answered at once with ``ErrorReply(code="rate", field="snapshot.client",
  retry_after_s=...)``;
- then the bucket of all clients together (``total_per_s``, ``total_burst``), which bounds
  the work when many ids ask at once (a Sybil client making up ids, where the router does
  not authenticate them). Over it: ``code="busy"``, ``field="snapshot.total"`` (the
  client's token is given back: the refusal is not its fault).

A vehicle starting in a dense area fetches tens of tiles at once, hence the client burst
of 200 and a sustained 20/s. Buckets of at most ``max_clients`` clients are kept; the
least recently seen is forgotten first (an idle client's bucket is full, so forgetting it
gives nothing away). A rate of 0 disables that limit. Time comes from an injected clock.

>>> t = [0.0]
>>> lim = SnapshotLimiter(SnapshotLimits(per_client_per_s=1, per_client_burst=2), lambda: t[0])
>>> [lim.check("veh-1") is None for _ in range(3)], lim.check("veh-2") is None
([True, True, False], True)
>>> err = lim.check("veh-1")
>>> err.code, err.field, err.retry_after_s
('rate', 'snapshot.client', 1.0)
"""

from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

from hdmap.runtime.config import ConfigError
from hdmap.runtime.ratelimit import MAX_RETRY_AFTER_S, TokenBucket
from schemas import ErrorReply

MIN_RETRY_S = 0.001
"""Least ``retry_after_s`` of a refusal (0 would read as "no advice")."""


@dataclass(frozen=True)
class SnapshotLimits:
    """``[publisher.snapshots]``: limits on snapshot queries; a rate of 0 disables it."""

    per_client_per_s: float = 20.0
    """Sustained snapshot queries per second of one client."""
    per_client_burst: float = 200.0
    """Queries one client may make at once after being idle (a vehicle starting in a
    dense area fetches every tile around it)."""
    total_per_s: float = 300.0
    """Sustained snapshot queries per second of all clients together."""
    total_burst: float = 1000.0
    """Queries all clients together may make at once."""
    max_clients: int = 100_000
    """Client buckets kept in memory (least recently seen forgotten first)."""
    max_queued: int = 1024
    """Admitted queries waiting for the answering thread (per region prefix); beyond,
    a query is answered ``busy`` (``snapshot.queue``) at once."""

    def __post_init__(self) -> None:
        for name in ("per_client_per_s", "per_client_burst", "total_per_s", "total_burst"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ConfigError(f"snapshots.{name}: must be a finite number >= 0, got {v}")
        if self.per_client_per_s > 0 and self.per_client_burst < 1:
            raise ConfigError("snapshots.per_client_burst: must be >= 1")
        if self.total_per_s > 0 and self.total_burst < 1:
            raise ConfigError("snapshots.total_burst: must be >= 1")
        if self.max_clients < 1:
            raise ConfigError("snapshots.max_clients: must be >= 1")
        if self.max_queued < 1:
            raise ConfigError("snapshots.max_queued: must be >= 1")

    @property
    def queue_retry_s(self) -> float:
        """``retry_after_s`` of a query refused on a full queue: about the time the queue
        takes to drain at ``total_per_s`` (1 s when that is unlimited), at least 0.1 s."""
        if self.total_per_s <= 0:
            return 1.0
        return min(MAX_RETRY_AFTER_S, max(0.1, self.max_queued / self.total_per_s))

    def queue_busy(self) -> ErrorReply:
        """The answer to a query that finds ``max_queued`` queries waiting."""
        return ErrorReply(
            "busy",
            "snapshot.queue",
            f"{self.max_queued} snapshot queries are waiting; retry later",
            self.queue_retry_s,
        )


class SnapshotLimiter:
    """The per-client buckets and the total bucket of snapshot queries.

    Thread-safe (one lock): :meth:`check` runs on the Zenoh callback threads, ``len`` on
    the stats thread. Invariant: at most ``limits.max_clients`` client buckets, in least
    recently seen order.
    """

    def __init__(self, limits: SnapshotLimits, clock: Callable[[], float] = time.monotonic):
        self.limits = limits
        self.clock = clock
        self._lock = threading.Lock()
        self._clients: OrderedDict[str, TokenBucket] = OrderedDict()
        self._total = (
            TokenBucket(limits.total_per_s, limits.total_burst, clock())
            if limits.total_per_s > 0
            else None
        )

    def check(self, client: str) -> ErrorReply | None:
        """Charge one query of ``client``: None if it may be served, else the refusal to
        answer (``rate``: this client is over its rate; ``busy``: all clients are)."""
        lim = self.limits
        with self._lock:
            now = self.clock()
            bucket = None
            if lim.per_client_per_s > 0:
                bucket = self._bucket(client, now)
                wait = bucket.take(1.0, now)
                if wait > 0:
                    return ErrorReply(
                        "rate",
                        "snapshot.client",
                        f"client {client!r} asks for more than {lim.per_client_per_s:g} "
                        f"snapshots/s; retry after {wait:.3g} s",
                        _retry(wait),
                    )
            if self._total is not None:
                wait = self._total.take(1.0, now)
                if wait > 0:
                    if bucket is not None:
                        bucket.refund(1.0)
                    return ErrorReply(
                        "busy",
                        "snapshot.total",
                        f"more than {lim.total_per_s:g} snapshots/s asked for in all; "
                        f"retry after {wait:.3g} s",
                        _retry(wait),
                    )
        return None

    def _bucket(self, client: str, now: float) -> TokenBucket:
        """The bucket of ``client`` (the caller holds the lock), now the most recent."""
        b = self._clients.get(client)
        if b is None:
            lim = self.limits
            b = self._clients[client] = TokenBucket(lim.per_client_per_s, lim.per_client_burst, now)
            while len(self._clients) > lim.max_clients:
                self._clients.popitem(last=False)
        else:
            self._clients.move_to_end(client)
        return b

    def __len__(self) -> int:
        """Clients with a bucket."""
        with self._lock:
            return len(self._clients)


def _retry(wait: float) -> float:
    return min(max(wait, MIN_RETRY_S), MAX_RETRY_AFTER_S)
