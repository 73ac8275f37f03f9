"""Publisher: owns the tile maps, pushes deltas, answers snapshots.

Consumes the solver's update log for its region (exactly once, see
:mod:`hdmap.runtime.stage`), coalesces changes, and every ``interval_s`` publishes one
:class:`schemas.MapDelta` per changed tile on ``hdmap/v1/map/<tile>/delta``
(version + 1 per change set). The ``hdmap/v1/map/<tile>`` queryable answers
:class:`schemas.MapSnapshot` for any tile of the region, also empty ones.

The flush commits the new version before publishing it: after a crash between
the two, vehicles see the next delta's ``from_version`` ahead of theirs and
fetch the snapshot, which already holds the lost change set.
"""

from __future__ import annotations

import logging
import sqlite3
from dataclasses import dataclass

import zenoh

from hdmap.geo.tiles import in_region, valid_quadkey
from hdmap.runtime.stage import StageService
from hdmap.runtime.store import StorageError
from hdmap.runtime.stream import QueryServer
from schemas import DecodeError, ErrorReply, LandmarkUpdates, LogEntry, keys
from services.publisher.tilemap import TileMaps, read_snapshot

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PublisherConfig:
    interval_s: float = 0.5
    """Changes are coalesced into one delta per tile at this interval."""


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

    def setup(self) -> None:
        super().setup()
        for prefix in self.region or [""]:
            self._snapshots.append(
                QueryServer(
                    self.session,
                    keys.map_snapshot(keys.region(prefix)),
                    self.db_path,
                    self._answer_snapshot,
                    "snapshots",
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
                upd = LandmarkUpdates.from_bytes(e.body)
            except DecodeError as exc:
                self.reject(f"update.{exc.field}")
                continue
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

    def _answer_snapshot(self, conn: sqlite3.Connection, q: zenoh.Query) -> None:
        tile = keys.snapshot_tile(str(q.key_expr))
        if not valid_quadkey(tile) or not in_region(tile, self.region):
            err = DecodeError("tile", f"{str(q.key_expr)!r} names no one quadkey of this region")
            q.reply_err(ErrorReply.of(err).to_bytes())
            self.reject("snapshot.tile")
            return
        snap, withheld = read_snapshot(conn, tile)
        q.reply(keys.map_snapshot(tile), snap.to_bytes())
        self.count("snapshots")
        if withheld:
            self.count("snapshot_rows_withheld", withheld)

    def extra_counters(self) -> dict[str, float]:
        out = super().extra_counters()
        out.update(self._counts)
        return out
