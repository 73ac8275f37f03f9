"""The services' durable stage logs: the envelope of an entry (:class:`LogEntry`), a
consumer's query (:class:`LogQuery`) and the entry bodies of the three stages:
:class:`ObsGroup` (obs, ingest -> matcher), :class:`AssocGroup` (assoc, matcher ->
solver) and :class:`LandmarkUpdates` (update, solver -> publisher).

>>> e = LogEntry("obs", "ingest-1", "0123", 1, 1, b"body")
>>> LogEntry.from_bytes(e.to_bytes()).tile
'0123'
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from schemas.codec import (
    DecodeError,
    get_bytes,
    get_float,
    get_int,
    get_list,
    get_map,
    get_str,
    valid_id,
)
from schemas.messages import (
    FLOAT_EPOCH_MAX,
    MAX_TABLE_ROWS,
    TILE_RE,
    TILE_TEXT,
    Message,
    as_ids,
    get_ids,
    get_table,
    put_table,
)
from schemas.tables import (
    Absences,
    ExistenceRows,
    Landmarks,
    Links,
    NewLandmarks,
    Observations,
    Removals,
    TrustChanges,
)

_STAGE_RE = re.compile(r"obs|assoc|update")
_STAGE = "one of obs, assoc, update"


@dataclass(frozen=True, eq=False)
class LogEntry(Message):
    """Envelope of one entry of a producer's durable log (obs, assoc or update stage).

    ``seq`` counts this producer's entries for this tile (1, 2, ...: a consumer
    seeing a gap catches up); ``gseq`` counts all of this producer's entries, so
    replayed entries can be applied in their original order.

    ``epoch`` names the producer's run that wrote the entry (a new one at every start,
    larger than any before it in the producer's database), ``base`` is the tile's last
    ``seq`` and ``gbase`` the producer's last ``gseq`` when that run began. A producer
    restored from an old backup numbers its new entries with ``seq`` values its consumers
    already applied (from the lost run): a consumer that meets a newer epoch whose
    ``base`` is below what it applied of the tile resynchronises the tile to ``base``, and
    one whose last entry of the producer is past ``gbase`` asks again from there
    (:class:`hdmap.runtime.stream.LogConsumer`).
    Optional on the wire (absent = 0: a producer from before epochs).

    ``checkpoint``: the entry is the producer's state of the tile as of ``seq`` (its
    entries up to ``seq`` folded into one), standing for all of them: what a producer
    sends a consumer that asks for entries it has deleted, on a log whose entries are
    states (the update log: the latest row of each landmark and every removal). Optional
    on the wire (absent: an ordinary entry).
    """

    TYPE: ClassVar[str] = "log_entry"
    stage: str
    producer: str
    tile: str
    seq: int
    gseq: int
    body: bytes
    epoch: int = 0
    base: int = 0
    gbase: int = 0
    """The producer's ``gseq`` when the entry's run began."""
    checkpoint: bool = False

    def _encode(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "stage": self.stage,
            "producer": self.producer,
            "tile": self.tile,
            "seq": int(self.seq),
            "gseq": int(self.gseq),
            "body": self.body,
        }
        if self.epoch:
            out["epoch"], out["base"] = int(self.epoch), int(self.base)
            out["gbase"] = int(self.gbase)
        if self.checkpoint:
            out["checkpoint"] = 1
        return out

    @classmethod
    def from_bytes(cls, data: bytes) -> LogEntry:
        m = cls._open(data)
        seq = get_int(m, "seq", 1)
        epoch = get_int(m, "epoch", 0, 2**63 - 1) if "epoch" in m else 0
        base = get_int(m, "base", 0, seq - 1) if "base" in m else 0
        gseq = get_int(m, "gseq", 1)
        gbase = get_int(m, "gbase", 0, gseq - 1) if "gbase" in m else 0
        return cls(
            stage=get_str(m, "stage", _STAGE_RE, _STAGE),
            producer=get_str(m, "producer"),
            tile=get_str(m, "tile", TILE_RE, TILE_TEXT),
            seq=seq,
            gseq=gseq,
            body=get_bytes(m, "body"),
            epoch=epoch,
            base=base,
            gbase=gbase,
            checkpoint=bool(get_int(m, "checkpoint", 0, 1)) if "checkpoint" in m else False,
        )

    @property
    def order(self) -> tuple[int, int]:
        """Where the entry stands in its producer's writing: ``(epoch, gseq)`` (a restored
        producer's ``gseq`` restarts below its lost run's; its epoch is newer)."""
        return (self.epoch, self.gseq)


MAX_EPOCHS = 64
"""A producer's latest runs a :class:`LogHead` lists."""

MAX_LISTED_TILES = 100_000
"""Tiles a :class:`LogQuery` may list over all producers."""


def _get_offsets(m: dict) -> dict[str, dict[str, int]]:
    offsets = get_map(m, "offsets")
    if len(offsets) > 10_000:
        raise DecodeError("offsets", f"{len(offsets)} producers exceeds the limit of 10000")
    listed = 0
    for p, tiles in offsets.items():
        if not valid_id(p) or not isinstance(tiles, dict):
            raise DecodeError("offsets", "expected producer id -> {tile: seq}")
        listed += len(tiles)
        if listed > MAX_LISTED_TILES:
            raise DecodeError("offsets", f"more than {MAX_LISTED_TILES} tiles listed")
        for t, s in tiles.items():
            if (
                not isinstance(t, str)
                or not TILE_RE.fullmatch(t)
                or not isinstance(s, int)
                or isinstance(s, bool)
                or not 0 <= s < 2**63
            ):
                raise DecodeError(f"offsets.{p}", "expected quadkey -> non-negative seq")
    return offsets


@dataclass(frozen=True, eq=False)
class LogQuery(Message):
    """Consumer -> producers: the entries of a region that the consumer has not applied.

    Two forms. With ``after_gseq`` (what consumers send): for a tile listed in
    ``offsets``, its entries with ``seq`` above the listed one; for every other tile of
    the region, its entries with ``gseq`` above the producer's watermark (absent = 0).
    The answer ends with a :class:`LogHead` saying how far it goes, so the query stays
    as small as the tiles active since the watermark, whatever the region ever held.
    Without ``after_gseq`` (older consumers): every tile with entries after its listed
    ``seq`` (absent = 0), and no :class:`LogHead`.
    """

    TYPE: ClassVar[str] = "log_query"
    stage: str
    offsets: dict[str, dict[str, int]]
    """producer -> tile -> last applied seq."""
    prefixes: list[str] = field(default_factory=list)
    """Quadkey prefixes of the consumer's region (empty = every tile)."""
    limit: int = 1000
    """At most this many entries per producer in one answer."""
    after_gseq: dict[str, int] | None = None
    """producer -> watermark: every entry of the region up to this ``gseq`` is applied,
    except in the listed tiles. Optional on the wire (absent = the per-tile form)."""

    def _encode(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "stage": self.stage,
            "offsets": self.offsets,
            "prefixes": list(self.prefixes),
            "limit": int(self.limit),
        }
        if self.after_gseq is not None:
            out["after_gseq"] = {p: int(g) for p, g in self.after_gseq.items()}
        return out

    @classmethod
    def from_bytes(cls, data: bytes) -> LogQuery:
        m = cls._open(data)
        offsets = _get_offsets(m)
        prefixes = get_list(m, "prefixes", 10_000)
        for i, p in enumerate(prefixes):
            if not isinstance(p, str) or (p and not TILE_RE.fullmatch(p)):
                raise DecodeError("prefixes", "expected quadkey prefixes", i)
        after: dict[str, int] | None = None
        if "after_gseq" in m:
            after = get_map(m, "after_gseq")
            if len(after) > 10_000:
                raise DecodeError("after_gseq", f"{len(after)} producers exceeds the limit")
            for p, g in after.items():
                if not valid_id(p) or not isinstance(g, int) or isinstance(g, bool):
                    raise DecodeError("after_gseq", "expected producer id -> gseq")
                if not 0 <= g < 2**63:
                    raise DecodeError(f"after_gseq.{p}", "expected a non-negative gseq")
        return cls(
            stage=get_str(m, "stage", _STAGE_RE, _STAGE),
            offsets=offsets,
            prefixes=prefixes,
            limit=get_int(m, "limit", 1, 100_000),
            after_gseq=after,
        )


@dataclass(frozen=True, eq=False)
class LogHead(Message):
    """Producer -> consumer: the last reply to a :class:`LogQuery` with ``after_gseq``.

    Every entry the query asked for with ``gseq <= through`` is in this answer; ``head``
    is the producer's last ``gseq`` when it read (``through >= head``: nothing more).
    A producer that sent no head did not answer: the consumer learns nothing from it.
    """

    TYPE: ClassVar[str] = "log_head"
    stage: str
    producer: str
    through: int
    head: int
    epochs: list[tuple[int, int]] = field(default_factory=list)
    """The producer's latest runs, oldest first: (epoch, ``gseq`` when it began). A
    consumer whose watermark is past the start of the first epoch newer than any it has
    seen met a restored producer (see :class:`LogEntry`). Optional (absent: none)."""

    def _encode(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "stage": self.stage,
            "producer": self.producer,
            "through": int(self.through),
            "head": int(self.head),
        }
        if self.epochs:
            out["epochs"] = [[int(e), int(g)] for e, g in self.epochs]
        return out

    @classmethod
    def from_bytes(cls, data: bytes) -> LogHead:
        m = cls._open(data)
        epochs = []
        for i, pair in enumerate(get_list(m, "epochs", MAX_EPOCHS) if "epochs" in m else []):
            if (
                not isinstance(pair, list)
                or len(pair) != 2
                or not all(isinstance(v, int) and not isinstance(v, bool) for v in pair)
                or not all(0 <= v < 2**63 for v in pair)
            ):
                raise DecodeError("epochs", "expected [epoch, gseq] pairs of non-negative ints", i)
            epochs.append((pair[0], pair[1]))
        return cls(
            stage=get_str(m, "stage", _STAGE_RE, _STAGE),
            producer=get_str(m, "producer"),
            through=get_int(m, "through", 0, 2**63 - 1),
            head=get_int(m, "head", 0, 2**63 - 1),
            epochs=epochs,
        )

    @property
    def complete(self) -> bool:
        return self.through >= self.head


@dataclass(frozen=True, eq=False)
class LogMark(Message):
    """Consumer -> producer (``hdmap/v1/mark/<stage>/<producer>/<consumer>``): how far the
    consumer has applied the producer's log. Every entry of the consumer's region with
    ``gseq`` up to ``gseq`` is applied and committed, in the producer's run ``epoch``
    (the run of the last entry it applied). A producer keeps its log above the smallest
    mark of its consumers (and a retention floor) and deletes the rest; a mark in a run
    the producer does not have (it was restored) is ignored.
    """

    TYPE: ClassVar[str] = "log_mark"
    stage: str
    producer: str
    consumer: str
    gseq: int
    epoch: int

    def _encode(self) -> dict[str, Any]:
        return {
            "stage": self.stage,
            "producer": self.producer,
            "consumer": self.consumer,
            "gseq": int(self.gseq),
            "epoch": int(self.epoch),
        }

    @classmethod
    def from_bytes(cls, data: bytes) -> LogMark:
        m = cls._open(data)
        return cls(
            stage=get_str(m, "stage", _STAGE_RE, _STAGE),
            producer=get_str(m, "producer"),
            consumer=get_str(m, "consumer"),
            gseq=get_int(m, "gseq", 0, 2**63 - 1),
            epoch=get_int(m, "epoch", 0, 2**63 - 1),
        )


def decode_replay(data: bytes) -> LogEntry | LogHead:
    """A reply to a :class:`LogQuery`: an entry, or the answer's closing head."""
    try:
        return LogEntry.from_bytes(data)
    except DecodeError as exc:
        if exc.field != "type":
            raise
    return LogHead.from_bytes(data)


@dataclass(frozen=True, eq=False)
class ObsGroup(Message):
    """Ingest -> matcher log body: one upload batch's accepted observations for one tile."""

    TYPE: ClassVar[str] = "obs_group"
    vehicle_id: str
    pass_id: int
    batch_id: int
    received_at: float
    obs: Observations
    absences: Absences = field(default_factory=Absences.empty)
    """The upload's absences of landmarks whose home tile is this entry's tile (new to
    ingest: a pass's report of a landmark is logged once). Optional on the wire."""

    def _encode(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "vehicle_id": self.vehicle_id,
            "pass_id": int(self.pass_id),
            "batch_id": int(self.batch_id),
            "received_at": float(self.received_at),
        }
        put_table(out, "obs", self.obs)
        if len(self.absences):
            put_table(out, "absences", self.absences)
        return out

    @classmethod
    def from_bytes(cls, data: bytes) -> ObsGroup:
        m = cls._open(data)
        absences = Absences.empty()
        if "absences" in m:
            absences = get_table(m, "absences", Absences, MAX_TABLE_ROWS)
        return cls(
            vehicle_id=get_str(m, "vehicle_id"),
            pass_id=get_int(m, "pass_id"),
            batch_id=get_int(m, "batch_id"),
            received_at=get_float(m, "received_at", 0.0, FLOAT_EPOCH_MAX),
            obs=get_table(m, "obs", Observations, MAX_TABLE_ROWS),
            absences=absences,
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
    existence: ExistenceRows = field(default_factory=lambda: ExistenceRows.empty())
    """Landmarks whose existence changed (a pass closed on them, or absences counted),
    applied after this entry's links; a revoked landmark is in ``retired`` instead.
    Optional on the wire."""

    def _encode(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "vehicles": list(self.vehicles),
            "retired": as_ids(self.retired).tobytes(),
            "merged_into": as_ids(self.merged_into).tobytes(),
        }
        put_table(out, "links", self.links)
        put_table(out, "obs", self.obs)
        put_table(out, "created", self.created)
        if np.any(self.held):
            out["held"] = np.ascontiguousarray(self.held, np.uint8).tobytes()
        if len(self.trust):
            put_table(out, "trust", self.trust)
        if len(self.existence):
            put_table(out, "existence", self.existence)
        return out

    @classmethod
    def from_bytes(cls, data: bytes) -> AssocGroup:
        m = cls._open(data)
        vehicles = get_list(m, "vehicles", MAX_TABLE_ROWS)
        for i, v in enumerate(vehicles):
            if not isinstance(v, str):
                raise DecodeError("vehicles", "expected a string", i)
        links = get_table(m, "links", Links, MAX_TABLE_ROWS)
        obs = get_table(m, "obs", Observations, MAX_TABLE_ROWS)
        if len(links) != len(obs):
            raise DecodeError("links", f"{len(links)} rows but obs has {len(obs)}")
        if len(links) and int(links.vehicle.max()) >= len(vehicles):
            raise DecodeError("links.vehicle", "index outside vehicles")
        retired = get_ids(m, "retired", MAX_TABLE_ROWS)
        merged = np.zeros(0, np.uint64)
        if "merged_into" in m:
            merged = get_ids(m, "merged_into", MAX_TABLE_ROWS)
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
            trust = get_table(m, "trust", TrustChanges, MAX_TABLE_ROWS)
            if len(trust) and int(trust.vehicle.max()) >= len(vehicles):
                raise DecodeError("trust.vehicle", "index outside vehicles")
        existence = ExistenceRows.empty()
        if "existence" in m:
            existence = get_table(m, "existence", ExistenceRows, MAX_TABLE_ROWS)
        return cls(
            vehicles=vehicles,
            links=links,
            obs=obs,
            created=get_table(m, "created", NewLandmarks, MAX_TABLE_ROWS),
            retired=retired,
            merged_into=merged,
            held=held,
            trust=trust,
            existence=existence,
        )


@dataclass(frozen=True, eq=False)
class LandmarkUpdates(Message):
    """Solver -> publisher log body: new estimates for landmarks of one tile, and removals."""

    TYPE: ClassVar[str] = "landmark_updates"
    landmarks: Landmarks
    removed: Removals

    def _encode(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        put_table(out, "landmarks", self.landmarks)
        put_table(out, "removed", self.removed)
        return out

    @classmethod
    def from_bytes(cls, data: bytes) -> LandmarkUpdates:
        m = cls._open(data)
        return cls(
            landmarks=get_table(m, "landmarks", Landmarks, MAX_TABLE_ROWS),
            removed=get_table(m, "removed", Removals, MAX_TABLE_ROWS),
        )
