"""Store-and-forward uploads: nothing leaves the vehicle's queue until ingest acks it.

Observations go into a local SQLite queue first (it survives a restart of the
vehicle process); ``flush`` sends the oldest ones as :class:`schemas.ObservationBatch`
requests (one pass per batch) and deletes exactly what the ack says was recorded
(accepted, including duplicates of an earlier upload) or refused for good
(rejected rows). Timeouts, transport errors and "retry later" answers keep them
queued; ``flush`` is retried with backoff by the caller's loop. An ack with
``retry_after_s > 0`` (rate limit, storage trouble) also holds back the next upload:
``flush`` sends nothing until that delay has passed.

A refusal marked ``permanent`` (ingest's database is corrupt: a server fault that needs an
operator, nothing wrong with the observations) keeps them queued too, but the vehicle
backs off: it waits ``retry_after_s``, at least :data:`PERMANENT_BACKOFF_MIN_S`, doubling
with each permanent refusal in a row up to :data:`PERMANENT_BACKOFF_MAX_S`, then probes
with one batch; :attr:`Uploader.fault` (and ``UploadResult.permanent_fault``) says why it
waits, and the first refusal of a series is logged as an error. The first accepted
upload ends the series. The queue is bounded only by the vehicle's disk: a long server
outage is an operations matter (docs/operations.md).
"""

from __future__ import annotations

import itertools
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zenoh

from hdmap.runtime.bus import query
from hdmap.runtime.store import connect, i64_to_u64, transaction, u64_to_i64
from schemas import DecodeError, ObservationBatch, Observations, Rejection, UploadAck, keys

log = logging.getLogger(__name__)

_REC = Observations.CODEC.record_dtype
_REC_V1 = Observations.CODEC.base_record_dtype


PERMANENT_BACKOFF_MIN_S = 60.0
"""The least wait after a permanent refusal (whatever its ``retry_after_s``)."""

PERMANENT_BACKOFF_MAX_S = 3600.0
"""The longest wait between probes while ingest keeps refusing permanently."""


@dataclass
class UploadResult:
    sent: int = 0
    accepted: int = 0
    """Observations ingest holds durably after this flush, duplicates included (as in
    :class:`schemas.UploadAck`): all of them leave the queue."""
    duplicates: int = 0
    """Of ``accepted``, those an earlier upload had already recorded (a retried batch)."""
    rejected: int = 0
    """Observations ingest refused one by one (they leave the queue, see ``rejected_by``)."""
    rejected_by: dict[str, int] = field(default_factory=dict)
    """``rejected`` by the field ingest named (``obs.lat``, ``obs.t``, ...); each reason is
    also logged once per batch, and every refused row is kept in :meth:`Uploader.rejected`."""
    refused: str = ""
    """The last batch refused whole in this flush: ``<field>: <reason>`` (``rate``,
    ``vehicle.new``, ``storage``, ...); its observations stay queued."""
    failed_batches: int = 0
    """Batches with no usable answer (timeout, transport, retry-later); still queued."""
    retry_after_s: float = 0.0
    """> 0: ingest asked to wait; nothing more is sent for this long."""
    permanent_fault: str = ""
    """Set when ingest refused permanently (or still does: the uploader waits): why."""


class Uploader:
    """One vehicle's upload stream with its durable local queue."""

    SCHEMA = """
    CREATE TABLE IF NOT EXISTS outbox (
        obs_id INTEGER PRIMARY KEY, pass_id INTEGER NOT NULL, rec BLOB NOT NULL);
    CREATE TABLE IF NOT EXISTS rejected (
        obs_id INTEGER PRIMARY KEY, field TEXT NOT NULL, reason TEXT NOT NULL, at REAL);
    CREATE TABLE IF NOT EXISTS counters (name TEXT PRIMARY KEY, value INTEGER NOT NULL);
    """

    def __init__(
        self,
        vehicle_id: str,
        queue_path: str | Path,
        batch_size: int = 500,
        clock: Callable[[], float] = time.monotonic,
    ):
        self.vehicle_id = vehicle_id
        self.batch_size = batch_size
        self._clock = clock
        self._retry_at = -float("inf")  # nothing is sent before this (last retry_after_s)
        self._backoff = 0.0  # the last wait after a permanent refusal (0: none in a row)
        self._refusals = 0  # batches refused for now (retry later) since the last accepted one
        self.fault: str = ""
        """Why ingest refuses for good (a permanent refusal, until an upload is accepted)."""
        self._db = connect(queue_path)
        self._db.executescript(self.SCHEMA)
        self._next_batch = self._counter("batch_id")

    def close(self) -> None:
        self._db.close()

    def _counter(self, name: str) -> int:
        row = self._db.execute("SELECT value FROM counters WHERE name=?", (name,)).fetchone()
        return 0 if row is None else int(row[0])

    @property
    def last_obs_id(self) -> int:
        """The last observation id handed out (0 before the first)."""
        return int(self._counter("obs_id"))

    def next_obs_ids(self, n: int) -> np.ndarray:
        """Fresh observation ids, unique for this vehicle across restarts."""
        with transaction(self._db):
            start = self._counter("obs_id")
            self._db.execute(
                "INSERT OR REPLACE INTO counters(name, value) VALUES ('obs_id', ?)", (start + n,)
            )
        return np.arange(start + 1, start + n + 1, dtype=np.uint64)

    def enqueue(self, pass_id: int, obs: Observations) -> None:
        """Store observations durably before any upload is attempted."""
        rec = Observations.CODEC.to_records(obs)
        ids = u64_to_i64(obs.obs_id).tolist()
        with transaction(self._db):
            self._db.executemany(
                "INSERT OR IGNORE INTO outbox(obs_id, pass_id, rec) VALUES (?, ?, ?)",
                [(ids[i], int(pass_id), rec[i].tobytes()) for i in range(len(ids))],
            )

    @property
    def retry_in(self) -> float:
        """Seconds until ``flush`` sends again (0: now)."""
        return max(0.0, self._retry_at - self._clock())

    @property
    def pending(self) -> int:
        return int(self._db.execute("SELECT COUNT(*) FROM outbox").fetchone()[0])

    def _oldest_batch(self) -> tuple[int, Observations] | None:
        row = self._db.execute("SELECT pass_id FROM outbox ORDER BY obs_id LIMIT 1").fetchone()
        if row is None:
            return None
        pass_id = int(row[0])
        recs = self._db.execute(
            "SELECT rec FROM outbox WHERE pass_id=? ORDER BY obs_id LIMIT ?",
            (pass_id, self.batch_size),
        ).fetchall()
        parts = []
        for old, rows in itertools.groupby(
            (r[0] for r in recs), key=lambda b: len(b) != _REC.itemsize
        ):
            dt = _REC_V1 if old else _REC  # rows queued before the optional columns
            parts.append(Observations.CODEC.from_records(np.frombuffer(b"".join(rows), dtype=dt)))
        return pass_id, Observations.concat(parts)

    def flush(
        self, session: zenoh.Session, timeout: float = 5.0, max_batches: int = 1000
    ) -> UploadResult:
        """Send queued observations until the queue is empty or a batch fails (bounded)."""
        res = UploadResult()
        for _ in range(max_batches):
            wait = self._retry_at - self._clock()
            if wait > 0:
                res.retry_after_s = wait
                res.permanent_fault = self.fault
                break
            nxt = self._oldest_batch()
            if nxt is None:
                break
            pass_id, obs = nxt
            self._next_batch += 1
            batch = ObservationBatch(self.vehicle_id, pass_id, self._next_batch, time.time(), obs)
            res.sent += len(obs)
            ack = self._send(session, batch, timeout)
            if ack is None or ack.error is not None:
                res.failed_batches += 1
                if ack is not None and ack.permanent:
                    self._hold_after_permanent(ack, res)
                elif ack is not None:
                    # one warning per streak: a bulk upload paced by the rate limit is
                    # refused once per batch, and each retry would say the same thing
                    self._refusals += 1
                    level = logging.WARNING if self._refusals == 1 else logging.DEBUG
                    log.log(level, "%s: batch refused: %s", self.vehicle_id, ack.error)
                    res.refused = f"{ack.error.field}: {ack.error.reason}"
                    if ack.retry_after_s > 0:
                        self._retry_at = self._clock() + ack.retry_after_s
                        res.retry_after_s = ack.retry_after_s
                break
            self._backoff, self.fault = 0.0, ""
            if self._refusals > 1:
                log.info(
                    "%s: uploads accepted again after %d refused batch(es)",
                    self.vehicle_id,
                    self._refusals,
                )
            self._refusals = 0
            self._settle(ack)
            res.accepted += len(ack.accepted)
            res.duplicates += len(ack.duplicates)
            res.rejected += len(ack.rejected)
            if ack.rejected:
                self._report_rejected(ack, res)
        return res

    def _report_rejected(self, ack: UploadAck, res: UploadResult) -> None:
        """Count one batch's refused rows by field and say so in one log line per field."""
        by_field: dict[str, list[Rejection]] = {}
        for r in ack.rejected:
            by_field.setdefault(r.field, []).append(r)
        for f, rows in sorted(by_field.items()):
            res.rejected_by[f] = res.rejected_by.get(f, 0) + len(rows)
            log.warning(
                "%s: ingest refused %d observation(s) of batch %d on %s: %s",
                self.vehicle_id,
                len(rows),
                ack.batch_id,
                f,
                rows[0].reason,
            )

    def _hold_after_permanent(self, ack: UploadAck, res: UploadResult) -> None:
        """Back off after a permanent refusal (module docstring); the batch stays queued."""
        if not self._backoff:
            log.error(
                "%s: ingest refuses uploads for good: %s; observations stay queued, "
                "probing with backoff",
                self.vehicle_id,
                ack.error,
            )
        wait = max(ack.retry_after_s, PERMANENT_BACKOFF_MIN_S, 2 * self._backoff)
        self._backoff = min(wait, PERMANENT_BACKOFF_MAX_S)
        self._retry_at = self._clock() + self._backoff
        self.fault = str(ack.error)
        res.retry_after_s, res.permanent_fault = self._backoff, self.fault

    def _send(self, session: zenoh.Session, batch: ObservationBatch, timeout: float):
        try:
            replies = query(
                session,
                keys.upload(self.vehicle_id),
                batch.to_bytes(),
                timeout=timeout,
                target=zenoh.QueryTarget.ALL,  # every ingest shard; its vehicle's answers
            )
        except zenoh.ZError as exc:
            log.warning("%s: upload failed: %s", self.vehicle_id, exc)
            return None
        for _key, ok, _err in replies:
            if ok is not None:
                try:
                    return UploadAck.from_bytes(ok)
                except DecodeError as exc:
                    log.warning("%s: bad ack: %s", self.vehicle_id, exc)
        return None

    def _settle(self, ack: UploadAck) -> None:
        done = u64_to_i64(np.concatenate([ack.accepted, ack.duplicates])).tolist()
        refused: list[Rejection] = ack.rejected
        with transaction(self._db):
            self._db.executemany("DELETE FROM outbox WHERE obs_id=?", [(i,) for i in done])
            self._db.executemany(
                "DELETE FROM outbox WHERE obs_id=?",
                [(int(u64_to_i64(np.array([r.obs_id], np.uint64))[0]),) for r in refused],
            )
            self._db.executemany(
                "INSERT OR REPLACE INTO rejected(obs_id, field, reason, at) VALUES (?, ?, ?, ?)",
                [
                    (
                        int(u64_to_i64(np.array([r.obs_id], np.uint64))[0]),
                        r.field,
                        r.reason,
                        time.time(),
                    )
                    for r in refused
                ],
            )
            self._db.execute(
                "INSERT OR REPLACE INTO counters(name, value) VALUES ('batch_id', ?)",
                (self._next_batch,),
            )

    def rejected(self) -> list[Rejection]:
        rows = self._db.execute("SELECT obs_id, field, reason FROM rejected").fetchall()
        ids = i64_to_u64(np.array([r[0] for r in rows], np.int64))
        return [Rejection(int(i), r[1], r[2]) for i, r in zip(ids, rows, strict=True)]
