"""Ingest: vehicles upload by request/reply; the ack means "durably recorded".

Per upload (``hdmap/v1/upload/<vehicle_id>`` queryable):

1. decode and validate (:class:`schemas.ObservationBatch`); a broken batch is
   answered with an :class:`schemas.UploadAck` carrying the error, bad rows are
   rejected one by one with field and reason; admission policy (timestamps,
   vehicle id matching the key) rejects more rows;
2. drop duplicates by (vehicle, observation id): a retried batch is acknowledged
   again but recorded once;
3. route each new observation to the tile of its expected target point and
   append one :class:`schemas.ObsGroup` entry per tile to the obs log, in the same
   SQLite transaction as the dedup rows;
4. commit, then reply the ack, then publish the entries on ``hdmap/v1/obs/<tile>``.

Uploads that arrive together are committed in one transaction (one fsync for many).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from hdmap import keys
from hdmap.service import Item, Service, ServiceOptions
from hdmap.store import StorageError, u64_to_i64
from hdmap.stream import STAGE_KEYS, LogServer, LogWriter
from hdmap.tiles import DEFAULT_TARGET_RANGE_M, route_rays
from schemas import DecodeError, ObservationBatch, ObsGroup, UploadAck
from schemas.messages import MAX_BATCH
from services.ingest.admission import AdmissionPolicy, admit

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class IngestConfig:
    max_batch: int = MAX_BATCH
    default_range_m: float = DEFAULT_TARGET_RANGE_M
    policy: AdmissionPolicy = field(default_factory=AdmissionPolicy)


@dataclass
class _Pending:
    """An upload decoded and staged in the current transaction, waiting for its ack."""

    item: Item
    ack: UploadAck


class IngestService(Service):
    name = "ingest"

    SCHEMA = """
    CREATE TABLE IF NOT EXISTS seen (
        vehicle TEXT NOT NULL, obs_id INTEGER NOT NULL, PRIMARY KEY (vehicle, obs_id))
        WITHOUT ROWID;
    """

    def __init__(self, opts: ServiceOptions, config: IngestConfig | None = None):
        super().__init__(opts)
        self.config = config or IngestConfig()
        self.db.executescript(self.SCHEMA)
        self.writer = LogWriter(self.db, "obs", self.instance)
        self._log_server: LogServer | None = None

    def setup(self) -> None:
        self.serve(keys.upload(keys.ANY), "upload")
        self._log_server = LogServer(self.session, self.db_path, "obs", self.instance)

    def teardown(self) -> None:
        if self._log_server is not None:
            self._log_server.close()

    def handle(self, items: list[Item]) -> None:
        uploads = [it for it in items if it.kind == "upload" and it.query is not None]
        staged: list[_Pending] = []
        entries = []
        try:
            with self.transaction([self.writer]):
                for it in uploads:
                    ack, new_entries = self._stage(it)
                    staged.append(_Pending(it, ack))
                    entries += new_entries
                self.count("log_entries", len(entries))
        except StorageError as exc:
            log.error("ingest: %s", exc)
            self.count("storage_errors")
            err = DecodeError("storage", f"not recorded, retry later ({exc})")
            for it in uploads:
                self._reply(
                    it,
                    UploadAck("unknown", 0, np.zeros(0, np.uint64), error=err, retry_after_s=5.0),
                )
            return
        for p in staged:
            self._reply(p.item, p.ack)
        for e in entries:
            self.pubs.put(STAGE_KEYS["obs"](e.tile), e.to_bytes())

    def _reply(self, it: Item, ack: UploadAck) -> None:
        assert it.query is not None
        try:
            it.query.reply(it.query.key_expr, ack.to_bytes())
        finally:
            it.query.drop()

    def _stage(self, it: Item):
        """Decode, validate, dedupe and append one upload (inside the transaction)."""
        self.count("uploads")
        key_vehicle = keys.last_chunk(it.key)
        try:
            batch, rejected = ObservationBatch.from_bytes_partial(it.payload, self.config.max_batch)
            if batch.vehicle_id != key_vehicle:
                raise DecodeError(
                    "vehicle_id",
                    f"{batch.vehicle_id!r} does not match the upload key {key_vehicle!r}",
                )
        except DecodeError as exc:
            self.reject(f"batch.{exc.field}")
            return UploadAck(key_vehicle, 0, np.zeros(0, np.uint64), error=exc), []
        self.count("received", len(batch.obs) + len(rejected))
        obs, more = admit(batch.obs, self.config.policy, time.time())
        rejected += more
        for r in rejected:
            self.reject(r.field)

        ids = obs.obs_id
        dup = self._seen(batch.vehicle_id, ids)
        new = obs.take(~dup) if dup.any() else obs
        self.db.executemany(
            "INSERT INTO seen(vehicle, obs_id) VALUES (?, ?)",
            [(batch.vehicle_id, int(i)) for i in u64_to_i64(new.obs_id)],
        )
        self.count("accepted", len(new))
        self.count("duplicates", int(dup.sum()))
        entries = []
        if len(new):
            tiles = route_rays(
                new.lat,
                new.lon,
                new.h,
                new.direction,
                new.range_m,
                self.opts.zoom,
                self.config.default_range_m,
            )
            for tile in np.unique(tiles):
                group = ObsGroup(
                    batch.vehicle_id,
                    batch.pass_id,
                    batch.batch_id,
                    time.time(),
                    new.take(tiles == tile),
                )
                entries.append(self.writer.append(str(tile), group.to_bytes()))
        ack = UploadAck(
            batch.vehicle_id, batch.batch_id, ids, duplicates=ids[dup], rejected=rejected
        )
        return ack, entries

    def _seen(self, vehicle: str, ids: np.ndarray) -> np.ndarray:
        if ids.size == 0:
            return np.zeros(0, bool)
        signed = u64_to_i64(ids)
        found: set[int] = set()
        chunk = 900
        for s in range(0, signed.size, chunk):
            part = [int(x) for x in signed[s : s + chunk]]
            marks = ",".join("?" * len(part))
            found.update(
                r[0]
                for r in self.db.execute(
                    f"SELECT obs_id FROM seen WHERE vehicle=? AND obs_id IN ({marks})",
                    [vehicle, *part],
                )
            )
        return np.fromiter((int(x) in found for x in signed), bool, signed.size)

    def extra_counters(self) -> dict[str, float]:
        return {"log_head_gseq": self.writer.gseq}
