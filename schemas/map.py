"""Publisher -> vehicles: a tile's change (:class:`MapDelta`) and the whole tile
(:class:`MapSnapshot`).

>>> from schemas.tables import Landmarks
>>> s = MapSnapshot("0123", 4, Landmarks.empty())
>>> MapSnapshot.from_bytes(s.to_bytes()).version
4
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from schemas.codec import DecodeError, get_float, get_int, get_str
from schemas.messages import (
    FLOAT_EPOCH_MAX,
    MAX_TABLE_ROWS,
    TILE_RE,
    TILE_TEXT,
    Message,
    get_table,
    put_table,
)
from schemas.tables import Landmarks, Removals


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
        put_table(out, "upserts", self.upserts)
        put_table(out, "removed", self.removed)
        return out

    @classmethod
    def from_bytes(cls, data: bytes) -> MapDelta:
        m = cls._open(data)
        frm = get_int(m, "from_version")
        to = get_int(m, "to_version")
        if to <= frm:
            raise DecodeError("to_version", f"{to} is not after from_version {frm}")
        return cls(
            tile=get_str(m, "tile", TILE_RE, TILE_TEXT),
            from_version=frm,
            to_version=to,
            published_at=get_float(m, "published_at", 0.0, FLOAT_EPOCH_MAX),
            upserts=get_table(m, "upserts", Landmarks, MAX_TABLE_ROWS),
            removed=get_table(m, "removed", Removals, MAX_TABLE_ROWS),
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
        put_table(out, "landmarks", self.landmarks)
        return out

    @classmethod
    def from_bytes(cls, data: bytes) -> MapSnapshot:
        m = cls._open(data)
        return cls(
            tile=get_str(m, "tile", TILE_RE, TILE_TEXT),
            version=get_int(m, "version"),
            landmarks=get_table(m, "landmarks", Landmarks, MAX_TABLE_ROWS),
        )
