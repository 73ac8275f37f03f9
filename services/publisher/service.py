"""Publisher: owns the tile maps, pushes deltas, answers snapshots.

Consumes the solver's update log for its region (exactly once, see
:mod:`hdmap.runtime.stage`), coalesces changes, and every ``interval_s`` publishes one
:class:`schemas.MapDelta` per changed tile on ``hdmap/v1/map/<tile>/delta``
(version + 1 per change set). The snapshot queryables answer
:class:`schemas.MapSnapshot` for any tile of the region, also empty ones, on the
anonymous key ``hdmap/v1/map/<tile>`` and on the client's own
``hdmap/v1/map/<tile>/by/<client>`` (the reply has the query's key). Each query is
charged to its client's budget and to the total one on the callback thread before it is
queued (:mod:`services.publisher.limits`, ``[publisher.snapshots]``); a refused one is
answered at once with ``rate`` or ``busy`` and a ``retry_after_s``, and counted in
``Stats.rejected`` under the error's field (``snapshot.client``, ``snapshot.total``,
``snapshot.queue``; ``snapshot.tile`` for a key naming no one tile of the region).

The flush commits the new version before publishing it: after a crash between
the two, vehicles see the next delta's ``from_version`` ahead of theirs and
fetch the snapshot, which already holds the lost change set.
"""

from __future__ import annotations

import logging
import sqlite3
from dataclasses import dataclass, field

import zenoh

from hdmap.geo.tiles import in_region, valid_quadkey
from hdmap.runtime.queries import QueryServer
from hdmap.runtime.stage import StageService
from hdmap.runtime.store import StorageError
from schemas import DecodeError, ErrorReply, LogEntry, keys
from schemas.map import updates_from_bytes
from services.publisher.limits import SnapshotLimiter, SnapshotLimits
from services.publisher.tilemap import TileMaps, read_snapshot

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PublisherConfig:
    interval_s: float = 0.1
    """Changes are coalesced into one delta per tile at this interval. It adds up to its
    length to every change's latency (upload to vehicle): at 0.5 s the load test's p50
    was 0.35-0.45 s and its p99 reached 1 s at 4,000 obs/s with the matcher at 55-75 % of a
    core; at 0.1 s p50 0.17 s, p99 0.81 s (``benchmarks/bench_e2e.py
    --publish-interval-s``, BENCHMARKS.md). Longer: fewer, larger deltas (a landmark that
    changes often is sent once per interval)."""
    snapshots: SnapshotLimits = field(default_factory=SnapshotLimits)
    """Per-client and total limits on snapshot queries (``[publisher.snapshots]``)."""


class PublisherService(StageService):
    name = "publisher"
    input_stage = "update"
    upstream = "solver"

    def __init__(self, opts, config: PublisherConfig | None = None):
        super().__init__(opts)
        self.config = config or PublisherConfig()
        self.maps = TileMaps(self.db)
        self._snapshots: list[QueryServer] = []
        self._counts = self.maps.counts()
        self.limiter = SnapshotLimiter(self.config.snapshots)
        """Charged on the Zenoh callback threads (thread-safe)."""

    def setup(self) -> None:
        super().setup()
        lim = self.config.snapshots
        for prefix in self.region or [""]:
            tiles = keys.region(prefix)
            self._snapshots.append(
                QueryServer(
                    self.session,
                    [keys.map_snapshot(tiles), keys.map_snapshot_for(keys.ANY, tiles)],
                    self.db_path,
                    self._answer_snapshot,
                    "snapshots",
                    admit=self._admit_snapshot,
                    on_refused=self._refused_snapshot,
                    max_queued=lim.max_queued,
                    busy=lim.queue_busy(),
                )
            )
        self.every(self.config.interval_s, lambda _now: self.flush())

    def teardown(self) -> None:
        for s in self._snapshots:
            s.close()
        super().teardown()

    def apply(self, entries: list[LogEntry]) -> None:
        for e in entries:
            try:
                upd = updates_from_bytes(e.body)
            except DecodeError as exc:
                self.reject(f"update.{exc.field}")
                continue
            self.metrics.ages(upd.landmarks.source_time)
            self.count("changes", self.maps.apply(e.tile, upd))

    def flush(self) -> None:
        try:
            with self.transaction():
                deltas = self.maps.flush()
                self.count("deltas", len(deltas))
                self.count("quarantined", self.maps.quarantined)
                self.count("delta_upserts", sum(len(d.upserts) for d in deltas))
        except StorageError as exc:
            log.error("publisher flush: %s", exc)
            self.count("storage_errors")
            return
        self._counts = self.maps.counts()  # worker thread: the stats thread reads the copy
        for d in deltas:
            self.pubs.put(keys.map_delta(d.tile), d.to_bytes())

    def _admit_snapshot(self, q: zenoh.Query) -> ErrorReply | None:
        """Zenoh callback thread: charge the query to its client (anonymous and odd keys
        to ``anonymous``) and to the total; the refusal, or None to queue it."""
        _tile, client = keys.snapshot_request(str(q.key_expr))
        return self.limiter.check(client)

    def _refused_snapshot(self, err: ErrorReply) -> None:
        """Zenoh callback thread: count a query answered ``rate`` or ``busy`` unserved
        (:meth:`reject` takes the stats lock; outside the worker's transaction it counts
        at once, and the worker's next commit persists it)."""
        self.reject(err.field)

    def _answer_snapshot(self, conn: sqlite3.Connection, q: zenoh.Query) -> None:
        key = str(q.key_expr)
        tile = keys.snapshot_tile(key)
        if not valid_quadkey(tile) or not in_region(tile, self.region):
            err = DecodeError("tile", f"{key!r} names no one quadkey of this region")
            q.reply_err(ErrorReply.of(err).to_bytes())
            self.reject("snapshot.tile")
            return
        snap, withheld = read_snapshot(conn, tile)
        q.reply(key, snap.to_bytes())  # a concrete key (it names one tile and one client)
        self.count("snapshots")
        if withheld:
            self.count("snapshot_rows_withheld", withheld)

    def extra_counters(self) -> dict[str, float]:
        out = super().extra_counters()
        out.update(self._counts)
        out["snapshot_clients"] = len(self.limiter)
        return out
