"""Vehicle <-> ingest: the upload (:class:`ObservationBatch`) and its reply
(:class:`UploadAck`).

>>> ack = UploadAck("veh-1", 7, np.array([1, 2], np.uint64))
>>> UploadAck.from_bytes(ack.to_bytes()).accepted.tolist()
[1, 2]
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from hdmap.geo.signs import CATALOG, SignCatalog
from schemas.codec import DecodeError, get_float, get_int, get_list, get_map, get_str
from schemas.messages import (
    FLOAT_EPOCH_MAX,
    MAX_BATCH,
    MAX_RETRY_AFTER_S,
    MAX_TABLE_ROWS,
    Message,
    as_ids,
    get_ids,
    put_table,
)
from schemas.tables import Absences, Observations


@dataclass(frozen=True)
class Rejection:
    """One observation refused by ingest, and why."""

    obs_id: int
    field: str
    reason: str


@dataclass(frozen=True, eq=False)
class ObservationBatch(Message):
    """Vehicle -> ingest upload (request payload on ``hdmap/v1/upload/<vehicle_id>``)."""

    TYPE: ClassVar[str] = "obs_batch"
    vehicle_id: str
    pass_id: int
    batch_id: int
    sent_at: float
    obs: Observations
    absences: Absences = field(default_factory=Absences.empty)
    """Mapped landmarks this pass had in view and did not detect (a pass sends them once,
    usually with its last upload). Optional on the wire (absent = none)."""

    def _encode(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "vehicle_id": self.vehicle_id,
            "pass_id": int(self.pass_id),
            "batch_id": int(self.batch_id),
            "sent_at": float(self.sent_at),
        }
        put_table(out, "obs", self.obs)
        if len(self.absences):
            put_table(out, "absences", self.absences)
        return out

    @classmethod
    def from_bytes(
        cls, data: bytes, max_obs: int = MAX_BATCH, catalog: SignCatalog = CATALOG
    ) -> ObservationBatch:
        """Strict decode: the first bad row raises."""
        head, obs, bad, fld, why, ab, ab_bad, ab_fld, ab_why = cls._decode(data, max_obs, catalog)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise DecodeError(f"obs.{fld[i]}", str(why[i]), i)
        if ab_bad.any():
            i = int(np.flatnonzero(ab_bad)[0])
            raise DecodeError(f"absences.{ab_fld[i]}", str(ab_why[i]), i)
        return cls(*head, obs, ab)

    @classmethod
    def from_bytes_partial(
        cls, data: bytes, max_obs: int = MAX_BATCH, catalog: SignCatalog = CATALOG
    ) -> tuple[ObservationBatch, list[Rejection]]:
        """Structure errors raise; bad rows come back as rejections, good rows as the batch.
        A refused absence's rejection names the landmark id in ``obs_id`` and a field
        ``absences.<column>``."""
        head, obs, bad, fld, why, ab, ab_bad, ab_fld, ab_why = cls._decode(data, max_obs, catalog)
        rejected = [
            Rejection(int(obs.obs_id[i]), f"obs.{fld[i]}", str(why[i])) for i in np.flatnonzero(bad)
        ]
        rejected += [
            Rejection(int(ab.landmark_id[i]), f"absences.{ab_fld[i]}", str(ab_why[i]))
            for i in np.flatnonzero(ab_bad)
        ]
        obs = obs.take(~bad) if bad.any() else obs
        return cls(*head, obs, ab.take(~ab_bad) if ab_bad.any() else ab), rejected

    @classmethod
    def _decode(cls, data: bytes, max_obs: int, catalog: SignCatalog):
        m = cls._open(data)
        head = (
            get_str(m, "vehicle_id"),
            get_int(m, "pass_id"),
            get_int(m, "batch_id"),
            get_float(m, "sent_at", 0.0, FLOAT_EPOCH_MAX),
        )
        n = get_int(m, "n_obs", 0)
        if n > max_obs:
            raise DecodeError("n_obs", f"batch of {n} observations exceeds the limit of {max_obs}")
        obs: Observations = Observations.CODEC.decode(get_map(m, "obs"), n, "obs", strict=False)
        bad, fld, why = Observations.CODEC.row_errors(obs)
        unknown = ~catalog.known(obs.sign_class) & ~bad
        if unknown.any():
            fld[unknown] = "sign_class"
            codes, which = np.unique(obs.sign_class[unknown], return_inverse=True)
            texts = [
                f"unknown sign class {int(c)} (not in the receiver's sign catalogue)" for c in codes
            ]
            why[unknown] = np.array(texts, dtype=object)[which]  # one text per distinct code
        bad |= unknown
        _, first = np.unique(obs.obs_id, return_index=True)
        dup = np.ones(n, bool)
        dup[first] = False
        dup &= ~bad
        fld[dup], why[dup] = "obs_id", "duplicate id within the batch"
        bad |= dup
        return (head, obs, bad, fld, why, *cls._absences(m, max_obs))

    @staticmethod
    def _absences(m: dict, max_rows: int):
        """The optional absences table and its bad rows (as for the observations)."""
        n = get_int(m, "n_absences", 0) if "absences" in m else 0
        if n > max_rows:
            raise DecodeError("n_absences", f"{n} absences exceed the limit of {max_rows}")
        if n == 0:
            ab = Absences.empty()
            return ab, np.zeros(0, bool), np.zeros(0, object), np.zeros(0, object)
        ab: Absences = Absences.CODEC.decode(get_map(m, "absences"), n, "absences", strict=False)
        bad, fld, why = Absences.CODEC.row_errors(ab)
        _, first = np.unique(ab.landmark_id, return_index=True)
        dup = np.ones(n, bool)
        dup[first] = False
        dup &= ~bad
        fld[dup], why[dup] = "landmark_id", "reported twice in one batch (a pass counts once)"
        return ab, bad | dup, fld, why


@dataclass(frozen=True, eq=False)
class UploadAck(Message):
    """Ingest -> vehicle reply: what is durably recorded, and what was refused.

    ``accepted`` includes ``duplicates`` (ids recorded by an earlier upload).
    ``error`` is set when the whole batch was refused (then nothing is accepted).
    ``permanent`` (only with ``error``): the refusal is not transient, resending soon
    fails the same way (ingest's database is corrupt: it needs an operator); then
    ``retry_after_s`` is the least a vehicle waits before it tries again.
    """

    TYPE: ClassVar[str] = "upload_ack"
    vehicle_id: str
    batch_id: int
    accepted: np.ndarray
    duplicates: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint64))
    rejected: list[Rejection] = field(default_factory=list)
    error: DecodeError | None = None
    retry_after_s: float = 0.0
    permanent: bool = False
    absences: int = 0
    """Absence rows of the upload durably recorded (new or recorded before: a pass's report
    of a landmark counts once). Optional on the wire (absent = 0)."""

    def _encode(self) -> dict[str, Any]:
        out = {
            "vehicle_id": self.vehicle_id,
            "batch_id": int(self.batch_id),
            "accepted": as_ids(self.accepted).tobytes(),
            "duplicates": as_ids(self.duplicates).tobytes(),
            "rejected": [[r.obs_id, r.field, r.reason] for r in self.rejected],
            "error": None if self.error is None else self.error.as_dict(),
            "retry_after_s": float(self.retry_after_s),
        }
        if self.permanent:  # absent means false: an ack reads as an older ingest's otherwise
            out["permanent"] = True
        if self.absences:
            out["absences"] = int(self.absences)
        return out

    @classmethod
    def from_bytes(cls, data: bytes, max_rows: int = MAX_TABLE_ROWS) -> UploadAck:
        m = cls._open(data)
        rejected = []
        for i, r in enumerate(get_list(m, "rejected", max_rows)):
            if (
                not isinstance(r, list)
                or len(r) != 3
                or not isinstance(r[0], int)
                or isinstance(r[0], bool)
                or not 0 <= r[0] < 2**64
                or not isinstance(r[1], str)
                or not isinstance(r[2], str)
                or not 0 < len(r[1]) <= 200
                or not 0 < len(r[2]) <= 200
            ):
                raise DecodeError("rejected", "expected [obs_id, field, reason]", i)
            rejected.append(Rejection(r[0], r[1], r[2]))
        err = m.get("error")
        error = None
        if err is not None:
            if not isinstance(err, dict):
                raise DecodeError("error", "expected a map or nil")
            f, why = err.get("field"), err.get("reason")
            if not isinstance(f, str) or not isinstance(why, str):
                raise DecodeError("error", "expected field and reason strings")
            idx = err.get("index")
            ok_idx = isinstance(idx, int) and not isinstance(idx, bool) and idx >= 0
            error = DecodeError(f, why, idx if ok_idx else None)
        permanent = m.get("permanent", False)  # absent in acks of older ingests
        if not isinstance(permanent, bool):
            raise DecodeError("permanent", "expected a bool")
        if permanent and error is None:
            raise DecodeError("permanent", "set without an error")
        return cls(
            vehicle_id=get_str(m, "vehicle_id"),
            batch_id=get_int(m, "batch_id"),
            accepted=get_ids(m, "accepted", max_rows),
            duplicates=get_ids(m, "duplicates", max_rows),
            rejected=rejected,
            error=error,
            retry_after_s=get_float(m, "retry_after_s", 0.0, MAX_RETRY_AFTER_S),
            permanent=permanent,
            absences=get_int(m, "absences", 0, max_rows) if "absences" in m else 0,
        )
