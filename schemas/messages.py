"""Wire messages, version 1: one type per message, msgpack on the wire.

Field-by-field documentation with units and frames: ``schemas/README.md``.
Every ``from_bytes`` raises :class:`schemas.codec.DecodeError` naming the field.

>>> ack = UploadAck("veh-1", 7, np.array([1, 2], np.uint64))
>>> UploadAck.from_bytes(ack.to_bytes()).accepted.tolist()
[1, 2]
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from hdmap.geo.signs import CATALOG, SignCatalog
from schemas.codec import (
    VERSION,
    DecodeError,
    Table,
    check_envelope,
    col,
    get_bytes,
    get_float,
    get_int,
    get_list,
    get_map,
    get_str,
    pack,
    table,
    unpack,
    valid_id,
)

MAX_BATCH = 10_000
"""Default upper bound on rows in one upload batch (configurable per ingest)."""
MAX_TABLE_ROWS = 1_000_000
"""Upper bound on rows in internal tables (log entries, snapshots)."""

_TILE_RE = re.compile(r"[0-3]{1,24}")
_STAGE_RE = re.compile(r"obs|assoc|update")
_REASON_RE = re.compile(r".{1,200}", re.S)
_TILE = "a quadkey (1-24 digits 0-3)"
_STAGE = "one of obs, assoc, update"
_TEXT = "1-200 characters"
_FLOAT_EPOCH_MAX = 4.1e9  # year 2100


# --- tables ---------------------------------------------------------------------------


@table
class Observations(Table):
    """Projection lines, one row per detection (see geoloc.ProjectionLines)."""

    obs_id: np.ndarray = col("u8", doc="unique per vehicle")
    t: np.ndarray = col("f8", lo=0.0, hi=_FLOAT_EPOCH_MAX, unit_label="s", doc="capture time, Unix")
    image: np.ndarray = col("u4", doc="image index within the pass; same value = same image")
    sign_class: np.ndarray = col("u2", doc="sign class code (hdmap.geo.signs)")
    lat: np.ndarray = col("f8", lo=-90.0, hi=90.0, unit_label="deg", doc="camera centre A")
    lon: np.ndarray = col("f8", lo=-180.0, hi=180.0, unit_label="deg")
    h: np.ndarray = col("f8", lo=-1000.0, hi=10000.0, unit_label="m", doc="ellipsoidal height")
    direction: np.ndarray = col("f8", 3, unit=True, doc="unit vector, ENU at A")
    sigma_az: np.ndarray = col("f8", lo=0.0, lo_open=True, hi=math.pi, unit_label="rad")
    sigma_el: np.ndarray = col("f8", lo=0.0, lo_open=True, hi=math.pi, unit_label="rad")
    sigma_pos_h: np.ndarray = col("f8", lo=0.0, lo_open=True, hi=1000.0, unit_label="m")
    sigma_pos_v: np.ndarray = col("f8", lo=0.0, lo_open=True, hi=1000.0, unit_label="m")
    range_m: np.ndarray = col("f8", lo=0.0, hi=10000.0, unit_label="m", doc="0 = no estimate")
    sigma_range_m: np.ndarray = col("f8", lo=0.0, hi=10000.0, unit_label="m")
    score: np.ndarray = col("f4", lo=0.0, hi=1.0)
    track: np.ndarray = col(
        "u4",
        optional=True,
        doc="detections of one sign followed from image to image within the pass; 0 = none",
    )


@table
class Links(Table):
    """Per associated observation: its landmark and where it came from."""

    landmark_id: np.ndarray = col("u8")
    vehicle: np.ndarray = col("u4", doc="index into AssocGroup.vehicles")
    pass_id: np.ndarray = col("u8")
    received_at: np.ndarray = col(
        "f8", lo=0.0, hi=_FLOAT_EPOCH_MAX, unit_label="s", doc="ingest receipt time, Unix"
    )
    weight: np.ndarray = col(
        "f4", lo=0.0, hi=1.0, doc="relative weight of the observation (trust in its vehicle)"
    )


@table
class TrustChanges(Table):
    """A vehicle leaves probation: its held passes (links with ``held``) are let go at a new
    weight (``action`` 1: promoted) or taken out (``action`` 2: caught shifting its data)."""

    vehicle: np.ndarray = col("u4", doc="index into AssocGroup.vehicles")
    action: np.ndarray = col("u1", lo=1, hi=2, doc="1 = release (promoted), 2 = drop (caught)")
    weight: np.ndarray = col("f4", lo=0.0, hi=1.0, doc="weight of the released rays")


RELEASE, DROP = 1, 2
"""``TrustChanges.action`` values."""


@table
class NewLandmarks(Table):
    """Landmarks created by the matcher, with the triangulated initial position."""

    id: np.ndarray = col("u8")
    sign_class: np.ndarray = col("u2")
    lat: np.ndarray = col("f8", lo=-90.0, hi=90.0, unit_label="deg")
    lon: np.ndarray = col("f8", lo=-180.0, hi=180.0, unit_label="deg")
    h: np.ndarray = col("f8", lo=-1000.0, hi=10000.0, unit_label="m")


@table
class Landmarks(Table):
    """Landmark estimates as published (update, delta, snapshot)."""

    id: np.ndarray = col("u8")
    sign_class: np.ndarray = col("u2")
    lat: np.ndarray = col("f8", lo=-90.0, hi=90.0, unit_label="deg")
    lon: np.ndarray = col("f8", lo=-180.0, hi=180.0, unit_label="deg")
    h: np.ndarray = col("f8", lo=-1000.0, hi=10000.0, unit_label="m")
    cov: np.ndarray = col("f8", 6, unit_label="m^2", doc="ENU at the landmark: ee en eu nn nu uu")
    status: np.ndarray = col("u1", lo=0, hi=2, doc="0 candidate, 1 confirmed, 2 retired")
    n_obs: np.ndarray = col("u4")
    n_passes: np.ndarray = col("u4")
    revision: np.ndarray = col("u8", doc="grows with every change of this landmark")
    updated_at: np.ndarray = col("f8", lo=0.0, hi=_FLOAT_EPOCH_MAX, unit_label="s")
    source_time: np.ndarray = col(
        "f8",
        lo=0.0,
        hi=_FLOAT_EPOCH_MAX,
        unit_label="s",
        doc="ingest receipt time of the newest observation in this revision (latency tracing)",
    )


@table
class Removals(Table):
    id: np.ndarray = col("u8")
    revision: np.ndarray = col("u8")


STATUS_CANDIDATE, STATUS_CONFIRMED, STATUS_RETIRED = 0, 1, 2


def _table(m: dict, name: str, cls: type, max_rows: int, strict: bool = True) -> Any:
    n = get_int(m, f"n_{name}", 0, max_rows)
    return cls.CODEC.decode(get_map(m, name), n, name, strict=strict)


def _put_table(out: dict, name: str, t: Table) -> None:
    out[name] = type(t).CODEC.encode(t)
    out[f"n_{name}"] = len(t)


def _ids(a: Any) -> np.ndarray:
    return np.ascontiguousarray(a, dtype="<u8")


def _get_ids(m: dict, name: str, max_rows: int) -> np.ndarray:
    raw = get_bytes(m, name)
    if len(raw) % 8:
        raise DecodeError(name, f"{len(raw)} bytes is not a whole number of u64")
    if len(raw) // 8 > max_rows:
        raise DecodeError(name, f"{len(raw) // 8} ids exceeds the limit of {max_rows}")
    return np.frombuffer(raw, dtype="<u8").astype(np.uint64)


class Message:
    """Base: ``to_bytes`` / ``from_bytes`` with the common envelope."""

    TYPE: ClassVar[str]

    def to_bytes(self) -> bytes:
        body = self._encode()
        body["v"] = VERSION
        body["type"] = self.TYPE
        return pack(body)

    def _encode(self) -> dict[str, Any]:
        raise NotImplementedError

    @classmethod
    def _open(cls, data: bytes) -> dict:
        m = unpack(data)
        check_envelope(m, cls.TYPE)
        return m


# --- vehicle <-> ingest -----------------------------------------------------------------


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

    def _encode(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "vehicle_id": self.vehicle_id,
            "pass_id": int(self.pass_id),
            "batch_id": int(self.batch_id),
            "sent_at": float(self.sent_at),
        }
        _put_table(out, "obs", self.obs)
        return out

    @classmethod
    def from_bytes(
        cls, data: bytes, max_obs: int = MAX_BATCH, catalog: SignCatalog = CATALOG
    ) -> ObservationBatch:
        """Strict decode: the first bad row raises."""
        head, obs, bad, fld, why = cls._decode(data, max_obs, catalog)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise DecodeError(f"obs.{fld[i]}", str(why[i]), i)
        return cls(*head, obs)

    @classmethod
    def from_bytes_partial(
        cls, data: bytes, max_obs: int = MAX_BATCH, catalog: SignCatalog = CATALOG
    ) -> tuple[ObservationBatch, list[Rejection]]:
        """Structure errors raise; bad rows come back as rejections, good rows as the batch."""
        head, obs, bad, fld, why = cls._decode(data, max_obs, catalog)
        rejected = [
            Rejection(int(obs.obs_id[i]), f"obs.{fld[i]}", str(why[i])) for i in np.flatnonzero(bad)
        ]
        return cls(*head, obs.take(~bad) if bad.any() else obs), rejected

    @classmethod
    def _decode(cls, data: bytes, max_obs: int, catalog: SignCatalog):
        m = cls._open(data)
        head = (
            get_str(m, "vehicle_id"),
            get_int(m, "pass_id"),
            get_int(m, "batch_id"),
            get_float(m, "sent_at", 0.0, _FLOAT_EPOCH_MAX),
        )
        n = get_int(m, "n_obs", 0)
        if n > max_obs:
            raise DecodeError("n_obs", f"batch of {n} observations exceeds the limit of {max_obs}")
        obs: Observations = Observations.CODEC.decode(get_map(m, "obs"), n, "obs", strict=False)
        bad, fld, why = Observations.CODEC.row_errors(obs)
        unknown = ~catalog.known(obs.sign_class) & ~bad
        fld[unknown], why[unknown] = "sign_class", "unknown sign class"
        bad |= unknown
        _, first = np.unique(obs.obs_id, return_index=True)
        dup = np.ones(n, bool)
        dup[first] = False
        dup &= ~bad
        fld[dup], why[dup] = "obs_id", "duplicate id within the batch"
        bad |= dup
        return head, obs, bad, fld, why


@dataclass(frozen=True, eq=False)
class UploadAck(Message):
    """Ingest -> vehicle reply: what is durably recorded, and what was refused.

    ``accepted`` includes ``duplicates`` (ids recorded by an earlier upload).
    ``error`` is set when the whole batch was refused (then nothing is accepted).
    """

    TYPE: ClassVar[str] = "upload_ack"
    vehicle_id: str
    batch_id: int
    accepted: np.ndarray
    duplicates: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint64))
    rejected: list[Rejection] = field(default_factory=list)
    error: DecodeError | None = None
    retry_after_s: float = 0.0

    def _encode(self) -> dict[str, Any]:
        return {
            "vehicle_id": self.vehicle_id,
            "batch_id": int(self.batch_id),
            "accepted": _ids(self.accepted).tobytes(),
            "duplicates": _ids(self.duplicates).tobytes(),
            "rejected": [[r.obs_id, r.field, r.reason] for r in self.rejected],
            "error": None if self.error is None else self.error.as_dict(),
            "retry_after_s": float(self.retry_after_s),
        }

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
        return cls(
            vehicle_id=get_str(m, "vehicle_id"),
            batch_id=get_int(m, "batch_id"),
            accepted=_get_ids(m, "accepted", max_rows),
            duplicates=_get_ids(m, "duplicates", max_rows),
            rejected=rejected,
            error=error,
            retry_after_s=get_float(m, "retry_after_s", 0.0, 86400.0),
        )


# --- internal streams -------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class LogEntry(Message):
    """Envelope of one entry of a producer's durable log (obs, assoc or update stage).

    ``seq`` counts this producer's entries for this tile (1, 2, ...: a consumer
    seeing a gap catches up); ``gseq`` counts all of this producer's entries, so
    replayed entries can be applied in their original order.
    """

    TYPE: ClassVar[str] = "log_entry"
    stage: str
    producer: str
    tile: str
    seq: int
    gseq: int
    body: bytes

    def _encode(self) -> dict[str, Any]:
        return {
            "stage": self.stage,
            "producer": self.producer,
            "tile": self.tile,
            "seq": int(self.seq),
            "gseq": int(self.gseq),
            "body": self.body,
        }

    @classmethod
    def from_bytes(cls, data: bytes) -> LogEntry:
        m = cls._open(data)
        return cls(
            stage=get_str(m, "stage", _STAGE_RE, _STAGE),
            producer=get_str(m, "producer"),
            tile=get_str(m, "tile", _TILE_RE, _TILE),
            seq=get_int(m, "seq", 1),
            gseq=get_int(m, "gseq", 1),
            body=get_bytes(m, "body"),
        )


@dataclass(frozen=True, eq=False)
class LogQuery(Message):
    """Consumer -> producers: entries after these offsets for tiles of these prefixes."""

    TYPE: ClassVar[str] = "log_query"
    stage: str
    offsets: dict[str, dict[str, int]]
    """producer -> tile -> last applied seq (absent = 0)."""
    prefixes: list[str] = field(default_factory=list)
    """Quadkey prefixes of the consumer's region (empty = every tile)."""
    limit: int = 1000
    """At most this many entries per producer in one answer."""

    def _encode(self) -> dict[str, Any]:
        return {
            "stage": self.stage,
            "offsets": self.offsets,
            "prefixes": list(self.prefixes),
            "limit": int(self.limit),
        }

    @classmethod
    def from_bytes(cls, data: bytes) -> LogQuery:
        m = cls._open(data)
        offsets = get_map(m, "offsets")
        if len(offsets) > 10_000:
            raise DecodeError("offsets", f"{len(offsets)} producers exceeds the limit of 10000")
        for p, tiles in offsets.items():
            if not valid_id(p) or not isinstance(tiles, dict):
                raise DecodeError("offsets", "expected producer id -> {tile: seq}")
            for t, s in tiles.items():
                if (
                    not isinstance(t, str)
                    or not _TILE_RE.fullmatch(t)
                    or not isinstance(s, int)
                    or isinstance(s, bool)
                    or not 0 <= s < 2**63
                ):
                    raise DecodeError(f"offsets.{p}", "expected quadkey -> non-negative seq")
        prefixes = get_list(m, "prefixes", 10_000)
        for i, p in enumerate(prefixes):
            if not isinstance(p, str) or (p and not _TILE_RE.fullmatch(p)):
                raise DecodeError("prefixes", "expected quadkey prefixes", i)
        return cls(
            stage=get_str(m, "stage", _STAGE_RE, _STAGE),
            offsets=offsets,
            prefixes=prefixes,
            limit=get_int(m, "limit", 1, 100_000),
        )


@dataclass(frozen=True, eq=False)
class ObsGroup(Message):
    """Ingest -> matcher log body: one upload batch's accepted observations for one tile."""

    TYPE: ClassVar[str] = "obs_group"
    vehicle_id: str
    pass_id: int
    batch_id: int
    received_at: float
    obs: Observations

    def _encode(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "vehicle_id": self.vehicle_id,
            "pass_id": int(self.pass_id),
            "batch_id": int(self.batch_id),
            "received_at": float(self.received_at),
        }
        _put_table(out, "obs", self.obs)
        return out

    @classmethod
    def from_bytes(cls, data: bytes) -> ObsGroup:
        m = cls._open(data)
        return cls(
            vehicle_id=get_str(m, "vehicle_id"),
            pass_id=get_int(m, "pass_id"),
            batch_id=get_int(m, "batch_id"),
            received_at=get_float(m, "received_at", 0.0, _FLOAT_EPOCH_MAX),
            obs=_table(m, "obs", Observations, MAX_TABLE_ROWS),
        )


@dataclass(frozen=True, eq=False)
class AssocGroup(Message):
    """Matcher -> solver log body: associations and landmark lifecycle for one tile."""

    TYPE: ClassVar[str] = "assoc_group"
    vehicles: list[str]
    links: Links
    obs: Observations
    created: NewLandmarks
    retired: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint64))
    """Landmarks that end here, after this entry's links (their rays stay in the map)."""
    merged_into: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint64))
    """Per retired landmark, the landmark that takes over its rays (``retired[i]`` was the
    same sign as ``merged_into[i]``); may be shorter than ``retired`` (the rest end
    without a successor). Optional on the wire (absent = empty)."""
    held: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    """Per link, whether its vehicle is on probation (its pass is held apart until a
    ``trust`` change settles it); empty = none held. Optional on the wire."""
    trust: TrustChanges = field(default_factory=lambda: TrustChanges.empty())
    """Vehicles leaving probation, applied after this entry's links. Optional on the wire."""

    def _encode(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "vehicles": list(self.vehicles),
            "retired": _ids(self.retired).tobytes(),
            "merged_into": _ids(self.merged_into).tobytes(),
        }
        _put_table(out, "links", self.links)
        _put_table(out, "obs", self.obs)
        _put_table(out, "created", self.created)
        if np.any(self.held):
            out["held"] = np.ascontiguousarray(self.held, np.uint8).tobytes()
        if len(self.trust):
            _put_table(out, "trust", self.trust)
        return out

    @classmethod
    def from_bytes(cls, data: bytes) -> AssocGroup:
        m = cls._open(data)
        vehicles = get_list(m, "vehicles", MAX_TABLE_ROWS)
        for i, v in enumerate(vehicles):
            if not isinstance(v, str):
                raise DecodeError("vehicles", "expected a string", i)
        links = _table(m, "links", Links, MAX_TABLE_ROWS)
        obs = _table(m, "obs", Observations, MAX_TABLE_ROWS)
        if len(links) != len(obs):
            raise DecodeError("links", f"{len(links)} rows but obs has {len(obs)}")
        if len(links) and int(links.vehicle.max()) >= len(vehicles):
            raise DecodeError("links.vehicle", "index outside vehicles")
        retired = _get_ids(m, "retired", MAX_TABLE_ROWS)
        merged = np.zeros(0, np.uint64)
        if "merged_into" in m:
            merged = _get_ids(m, "merged_into", MAX_TABLE_ROWS)
        if merged.size > retired.size:
            raise DecodeError("merged_into", f"{merged.size} ids for {retired.size} retired")
        if np.any(merged == retired[: merged.size]):
            raise DecodeError("merged_into", "a landmark merged into itself")
        held = np.zeros(0, bool)
        if "held" in m:
            raw = np.frombuffer(get_bytes(m, "held"), np.uint8)
            if raw.size != len(links):
                raise DecodeError("held", f"{raw.size} flags for {len(links)} links")
            if np.any(raw > 1):
                raise DecodeError("held", "flags must be 0 or 1")
            held = raw.astype(bool)
        trust = TrustChanges.empty()
        if "trust" in m or "n_trust" in m:
            trust = _table(m, "trust", TrustChanges, MAX_TABLE_ROWS)
            if len(trust) and int(trust.vehicle.max()) >= len(vehicles):
                raise DecodeError("trust.vehicle", "index outside vehicles")
        return cls(
            vehicles=vehicles,
            links=links,
            obs=obs,
            created=_table(m, "created", NewLandmarks, MAX_TABLE_ROWS),
            retired=retired,
            merged_into=merged,
            held=held,
            trust=trust,
        )


@dataclass(frozen=True, eq=False)
class LandmarkUpdates(Message):
    """Solver -> publisher log body: new estimates for landmarks of one tile, and removals."""

    TYPE: ClassVar[str] = "landmark_updates"
    landmarks: Landmarks
    removed: Removals

    def _encode(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        _put_table(out, "landmarks", self.landmarks)
        _put_table(out, "removed", self.removed)
        return out

    @classmethod
    def from_bytes(cls, data: bytes) -> LandmarkUpdates:
        m = cls._open(data)
        return cls(
            landmarks=_table(m, "landmarks", Landmarks, MAX_TABLE_ROWS),
            removed=_table(m, "removed", Removals, MAX_TABLE_ROWS),
        )


# --- publisher -> vehicles ----------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class MapDelta(Message):
    """Published on ``hdmap/v1/map/<tile>/delta``: applies on top of ``from_version``."""

    TYPE: ClassVar[str] = "map_delta"
    tile: str
    from_version: int
    to_version: int
    published_at: float
    upserts: Landmarks
    removed: Removals

    def _encode(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "tile": self.tile,
            "from_version": int(self.from_version),
            "to_version": int(self.to_version),
            "published_at": float(self.published_at),
        }
        _put_table(out, "upserts", self.upserts)
        _put_table(out, "removed", self.removed)
        return out

    @classmethod
    def from_bytes(cls, data: bytes) -> MapDelta:
        m = cls._open(data)
        frm = get_int(m, "from_version")
        to = get_int(m, "to_version")
        if to <= frm:
            raise DecodeError("to_version", f"{to} is not after from_version {frm}")
        return cls(
            tile=get_str(m, "tile", _TILE_RE, _TILE),
            from_version=frm,
            to_version=to,
            published_at=get_float(m, "published_at", 0.0, _FLOAT_EPOCH_MAX),
            upserts=_table(m, "upserts", Landmarks, MAX_TABLE_ROWS),
            removed=_table(m, "removed", Removals, MAX_TABLE_ROWS),
        )


@dataclass(frozen=True, eq=False)
class MapSnapshot(Message):
    """Reply of the ``hdmap/v1/map/<tile>`` queryable: the whole tile at ``version``."""

    TYPE: ClassVar[str] = "map_snapshot"
    tile: str
    version: int
    landmarks: Landmarks

    def _encode(self) -> dict[str, Any]:
        out: dict[str, Any] = {"tile": self.tile, "version": int(self.version)}
        _put_table(out, "landmarks", self.landmarks)
        return out

    @classmethod
    def from_bytes(cls, data: bytes) -> MapSnapshot:
        m = cls._open(data)
        return cls(
            tile=get_str(m, "tile", _TILE_RE, _TILE),
            version=get_int(m, "version"),
            landmarks=_table(m, "landmarks", Landmarks, MAX_TABLE_ROWS),
        )


# --- service plumbing -----------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ErrorReply(Message):
    """Any queryable's answer to a request it cannot serve."""

    TYPE: ClassVar[str] = "error"
    code: str
    field: str
    reason: str

    def _encode(self) -> dict[str, Any]:
        return {"code": self.code, "field": self.field, "reason": self.reason}

    @classmethod
    def from_bytes(cls, data: bytes) -> ErrorReply:
        m = cls._open(data)
        return cls(
            get_str(m, "code"), get_str(m, "field", _REASON_RE), get_str(m, "reason", _REASON_RE)
        )

    @classmethod
    def of(cls, exc: DecodeError, code: str = "bad_request") -> ErrorReply:
        where = exc.field if exc.index is None else f"{exc.field}[{exc.index}]"
        return cls(code, where[:200] or "message", exc.reason[:200] or "invalid")


@dataclass(frozen=True, eq=False)
class Stats(Message):
    """Reply of ``hdmap/v1/stats/<service>/<region>/<id>``: counters of one instance."""

    TYPE: ClassVar[str] = "stats"
    service: str
    instance: str
    region: list[str]
    started_at: float
    counters: dict[str, float]
    rejected: dict[str, int] = field(default_factory=dict)

    def _encode(self) -> dict[str, Any]:
        return {
            "service": self.service,
            "instance": self.instance,
            "region": list(self.region),
            "started_at": float(self.started_at),
            "counters": dict(self.counters),
            "rejected": dict(self.rejected),
        }

    @classmethod
    def from_bytes(cls, data: bytes) -> Stats:
        m = cls._open(data)
        region = get_list(m, "region", 1000)
        counters = get_map(m, "counters")
        rejected = get_map(m, "rejected")
        for k, v in counters.items():
            if (
                not isinstance(k, str)
                or not isinstance(v, int | float)
                or isinstance(v, bool)
                or not math.isfinite(v)
            ):
                raise DecodeError("counters", f"expected name -> finite number, got {k!r}")
        for k, v in rejected.items():
            if not isinstance(k, str) or not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise DecodeError("rejected", f"expected reason -> count, got {k!r}")
        if not all(isinstance(r, str) for r in region):
            raise DecodeError("region", "expected quadkey prefixes")
        return cls(
            service=get_str(m, "service"),
            instance=get_str(m, "instance"),
            region=region,
            started_at=get_float(m, "started_at", 0.0, _FLOAT_EPOCH_MAX),
            counters=counters,
            rejected=rejected,
        )
