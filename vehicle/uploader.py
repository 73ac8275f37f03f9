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

A pass's absences (:class:`schemas.Absences`, issue 21) are queued with its observations
(table ``absences``, one row per pass and landmark) and sent once: with the batch that
takes the pass's last queued observations, or, when none is left (all uploaded, or none
recorded), in a batch of their own with no observations (after the passes that still have
observations queued); at most ``batch_size`` of them per batch, the rest in the next. Any
ack of the batch takes them off the queue: ``UploadAck.absences`` counts those recorded,
a refused one comes back as a :class:`schemas.Rejection` with the landmark id in
``obs_id`` and a field ``absences.<column>`` (kept in :meth:`Uploader.rejected_absences`),
and those neither recorded nor refused (an ingest that does not know absences) are counted
and logged, not sent again.
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
from schemas import (
    Absences,
    DecodeError,
    ObservationBatch,
    Observations,
    Rejection,
    UploadAck,
    keys,
)

log = logging.getLogger(__name__)

_REC = Observations.CODEC.record_dtype
_REC_V1 = Observations.CODEC.base_record_dtype
_ABSENCE_REC = Absences.CODEC.record_dtype
ABSENCE_FIELD = "absences."
"""The prefix of a refused absence's field in :attr:`schemas.UploadAck.rejected`."""


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
    absences_sent: int = 0
    """Absence rows sent (in batches with an answer or without)."""
    absences_recorded: int = 0
    """Absence rows ingest recorded (``UploadAck.absences``); they leave the queue."""
    absences_rejected: int = 0
    """Absence rows ingest refused one by one (they leave the queue, see
    ``absences_rejected_by``)."""
    absences_rejected_by: dict[str, int] = field(default_factory=dict)
    """``absences_rejected`` by the field ingest named (``absences.range_m``, ...); logged
    once per field and batch, every refused row kept in :meth:`Uploader.rejected_absences`."""
    absences_unrecorded: int = 0
    """Absence rows of answered batches that ingest neither recorded nor refused (an ingest
    that ignores them); they leave the queue, logged."""


class Uploader:
    """One vehicle's upload stream with its durable local queue."""

    SCHEMA = """
    CREATE TABLE IF NOT EXISTS outbox (
        obs_id INTEGER PRIMARY KEY, pass_id INTEGER NOT NULL, rec BLOB NOT NULL);
    CREATE TABLE IF NOT EXISTS rejected (
        obs_id INTEGER PRIMARY KEY, field TEXT NOT NULL, reason TEXT NOT NULL, at REAL);
    CREATE TABLE IF NOT EXISTS counters (name TEXT PRIMARY KEY, value INTEGER NOT NULL);
    CREATE TABLE IF NOT EXISTS absences (
        seq INTEGER PRIMARY KEY, pass_id INTEGER NOT NULL, landmark_id INTEGER NOT NULL,
        rec BLOB NOT NULL, UNIQUE (pass_id, landmark_id));
    CREATE TABLE IF NOT EXISTS rejected_absences (
        pass_id INTEGER NOT NULL, landmark_id INTEGER NOT NULL, field TEXT NOT NULL,
        reason TEXT NOT NULL, at REAL, PRIMARY KEY (pass_id, landmark_id));
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
        self._refusal_warned_at = -float("inf")  # clock of the last refusal warning
        self._refused_since_warning = 0
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

    def enqueue(self, pass_id: int, obs: Observations, absences: Absences | None = None) -> None:
        """Store a pass's observations and its absences durably (one transaction) before
        any upload is attempted. A landmark already queued for the pass keeps its row."""
        rec = Observations.CODEC.to_records(obs)
        ids = u64_to_i64(obs.obs_id).tolist()
        ab = Absences.empty() if absences is None else absences
        ab_rec = Absences.CODEC.to_records(ab)
        ab_ids = u64_to_i64(ab.landmark_id).tolist()
        with transaction(self._db):
            self._db.executemany(
                "INSERT OR IGNORE INTO outbox(obs_id, pass_id, rec) VALUES (?, ?, ?)",
                [(ids[i], int(pass_id), rec[i].tobytes()) for i in range(len(ids))],
            )
            self._db.executemany(
                "INSERT OR IGNORE INTO absences(pass_id, landmark_id, rec) VALUES (?, ?, ?)",
                [(int(pass_id), ab_ids[i], ab_rec[i].tobytes()) for i in range(len(ab_ids))],
            )

    @property
    def retry_in(self) -> float:
        """Seconds until ``flush`` sends again (0: now)."""
        return max(0.0, self._retry_at - self._clock())

    @property
    def pending(self) -> int:
        return int(self._db.execute("SELECT COUNT(*) FROM outbox").fetchone()[0])

    @property
    def pending_absences(self) -> int:
        return int(self._db.execute("SELECT COUNT(*) FROM absences").fetchone()[0])

    def _oldest_batch(self) -> tuple[int, Observations] | None:
        """The pass of the oldest queued observation and its oldest observations (at most
        ``batch_size``); with none queued, the pass of the oldest queued absence and no
        observations; None: nothing queued."""
        row = self._db.execute("SELECT pass_id FROM outbox ORDER BY obs_id LIMIT 1").fetchone()
        if row is None:
            row = self._db.execute("SELECT pass_id FROM absences ORDER BY seq LIMIT 1").fetchone()
            return None if row is None else (int(row[0]), Observations.empty())
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

    def _batch_absences(self, pass_id: int, n_obs: int) -> Absences:
        """The absences that go with a batch of ``n_obs`` of the pass's oldest observations:
        the pass's oldest (at most ``batch_size``) if the batch takes all it has queued,
        else none (they go with its last batch)."""
        left = self._db.execute("SELECT COUNT(*) FROM outbox WHERE pass_id=?", (pass_id,))
        if int(left.fetchone()[0]) > n_obs:
            return Absences.empty()
        recs = self._db.execute(
            "SELECT rec FROM absences WHERE pass_id=? ORDER BY seq LIMIT ?",
            (pass_id, self.batch_size),
        ).fetchall()
        if not recs:
            return Absences.empty()
        rows = np.frombuffer(b"".join(r[0] for r in recs), dtype=_ABSENCE_REC)
        return Absences.CODEC.from_records(rows)

    REFUSAL_WARN_EVERY_S = 60.0
    """At most one warning a minute for refusals to retry later: a bulk upload paced by
    the rate limit is refused every other batch, and each line would say the same."""

    def _note_refusal(self, ack: UploadAck) -> None:
        """Log a refusal to retry later: a warning for the first of a streak unless one
        was given within ``REFUSAL_WARN_EVERY_S`` (it then counts those refused since),
        the others at debug level."""
        self._refused_since_warning += 1
        now = self._clock()
        if self._refusals == 1 and now - self._refusal_warned_at >= self.REFUSAL_WARN_EVERY_S:
            more = self._refused_since_warning - 1
            since = f" ({more} more batch(es) refused since the last warning)" if more else ""
            log.warning("%s: batch refused: %s%s", self.vehicle_id, ack.error, since)
            self._refusal_warned_at, self._refused_since_warning = now, 0
        else:
            log.debug("%s: batch refused: %s", self.vehicle_id, ack.error)

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
            ab = self._batch_absences(pass_id, len(obs))
            self._next_batch += 1
            batch = ObservationBatch(
                self.vehicle_id, pass_id, self._next_batch, time.time(), obs, absences=ab
            )
            res.sent += len(obs)
            res.absences_sent += len(ab)
            ack = self._send(session, batch, timeout)
            if ack is None or ack.error is not None:
                res.failed_batches += 1
                if ack is not None and ack.permanent:
                    self._hold_after_permanent(ack, res)
                elif ack is not None:
                    self._refusals += 1
                    self._note_refusal(ack)
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
            obs_rej = [r for r in ack.rejected if not r.field.startswith(ABSENCE_FIELD)]
            ab_rej = [r for r in ack.rejected if r.field.startswith(ABSENCE_FIELD)]
            self._settle(ack, obs_rej, pass_id, ab, ab_rej)
            res.accepted += len(ack.accepted)
            res.duplicates += len(ack.duplicates)
            res.rejected += len(obs_rej)
            self._report_rejected(ack.batch_id, obs_rej, res.rejected_by, "observation(s)")
            res.absences_recorded += ack.absences
            res.absences_rejected += len(ab_rej)
            self._report_rejected(ack.batch_id, ab_rej, res.absences_rejected_by, "absence(s)")
            unrecorded = len(ab) - ack.absences - len(ab_rej)
            if unrecorded > 0:
                res.absences_unrecorded += unrecorded
                log.warning(
                    "%s: ingest neither recorded nor refused %d of the %d absence(s) of "
                    "batch %d (it does not know them?); not sent again",
                    self.vehicle_id,
                    unrecorded,
                    len(ab),
                    ack.batch_id,
                )
        return res

    def _report_rejected(
        self, batch_id: int, refused: list[Rejection], by: dict[str, int], what: str
    ) -> None:
        """Count one batch's refused rows by field into ``by`` and say so in one log line
        per field."""
        by_field: dict[str, list[Rejection]] = {}
        for r in refused:
            by_field.setdefault(r.field, []).append(r)
        for f, rows in sorted(by_field.items()):
            by[f] = by.get(f, 0) + len(rows)
            log.warning(
                "%s: ingest refused %d %s of batch %d on %s: %s",
                self.vehicle_id,
                len(rows),
                what,
                batch_id,
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

    def _settle(
        self,
        ack: UploadAck,
        refused: list[Rejection],
        pass_id: int,
        absences: Absences,
        refused_absences: list[Rejection],
    ) -> None:
        """Take off the queue what an ack answered: its accepted and ``refused``
        observations, and the batch's ``absences`` (all of them: sent once), keeping the
        refused rows of both."""
        done = u64_to_i64(np.concatenate([ack.accepted, ack.duplicates])).tolist()
        sent = u64_to_i64(absences.landmark_id).tolist()
        with transaction(self._db):
            self._db.executemany("DELETE FROM outbox WHERE obs_id=?", [(i,) for i in done])
            self._db.executemany(
                "DELETE FROM outbox WHERE obs_id=?", [(_as_i64(r.obs_id),) for r in refused]
            )
            self._db.executemany(
                "INSERT OR REPLACE INTO rejected(obs_id, field, reason, at) VALUES (?, ?, ?, ?)",
                [(_as_i64(r.obs_id), r.field, r.reason, time.time()) for r in refused],
            )
            self._db.executemany(
                "DELETE FROM absences WHERE pass_id=? AND landmark_id=?",
                [(int(pass_id), i) for i in sent],
            )
            self._db.executemany(
                "INSERT OR REPLACE INTO rejected_absences(pass_id, landmark_id, field, reason, at)"
                " VALUES (?, ?, ?, ?, ?)",
                [
                    (int(pass_id), _as_i64(r.obs_id), r.field, r.reason, time.time())
                    for r in refused_absences
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

    def rejected_absences(self) -> list[tuple[int, Rejection]]:
        """Every absence ingest refused: (pass id, the rejection, ``obs_id`` the landmark)."""
        rows = self._db.execute(
            "SELECT pass_id, landmark_id, field, reason FROM rejected_absences"
        ).fetchall()
        ids = i64_to_u64(np.array([r[1] for r in rows], np.int64))
        return [(int(r[0]), Rejection(int(i), r[2], r[3])) for i, r in zip(ids, rows, strict=True)]


def _as_i64(u: int) -> int:
    """A u64 id as SQLite's signed integer (:func:`hdmap.runtime.store.u64_to_i64`)."""
    return int(u64_to_i64(np.array([u], np.uint64))[0])
