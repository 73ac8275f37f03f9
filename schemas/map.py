"""Publisher -> vehicles: a tile's change (:class:`MapDelta`) and the whole tile
(:class:`MapSnapshot`), whose landmark rows are :class:`MapLandmarks` (the ``Landmarks``
columns, the landmark's facing and its existence, optional columns: a message without
them reads as "facing unknown", "existence unknown").

>>> from schemas.tables import Landmarks
>>> s = MapSnapshot("0123", 4, Landmarks.empty())
>>> MapSnapshot.from_bytes(s.to_bytes()).version
4
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from schemas.codec import DecodeError, col, get_float, get_int, get_str, table
from schemas.logs import LandmarkUpdates
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


@table
class MapLandmarks(Landmarks):
    """Published landmark rows: :class:`~schemas.tables.Landmarks` and the facing.

    The facing is the direction the sign is *seen from* (the circular mean of the
    horizontal azimuths from the sign toward the cameras that saw it,
    :mod:`hdmap.mapping.facing`), not the panel normal: cars see a roadside sign 5-70
    degrees off its normal, from the road's side. ``facing_sigma_deg`` 0 = unknown (too
    few rays; an older sender), and then ``facing_deg`` is 0 and means nothing."""

    facing_deg: np.ndarray = col(
        "f4",
        lo=0.0,
        hi=360.0,
        unit_label="deg",
        optional=True,
        doc="azimuth the sign is seen from, clockwise from true North; see facing_sigma_deg",
    )
    facing_sigma_deg: np.ndarray = col(
        "f4",
        lo=0.0,
        hi=180.0,
        unit_label="deg",
        optional=True,
        doc="standard error of facing_deg; 0 = facing unknown",
    )
    exist_state: np.ndarray = col(
        "u1",
        lo=0,
        hi=2,
        optional=True,
        doc="whether the sign still stands: 1 confirmed, 2 doubtful, 0 unknown (revoked: removed)",
    )
    p_exist: np.ndarray = col(
        "f4", lo=0.0, hi=1.0, optional=True, doc="probability that it stands; 0 with state 0"
    )
    first_seen: np.ndarray = col(
        "f8",
        lo=0.0,
        hi=FLOAT_EPOCH_MAX,
        unit_label="s",
        optional=True,
        doc="event time of its first observation; 0 = unknown",
    )
    last_seen: np.ndarray = col(
        "f8",
        lo=0.0,
        hi=FLOAT_EPOCH_MAX,
        unit_label="s",
        optional=True,
        doc="event time of its latest observation; 0 = unknown",
    )

    def facing(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(azimuth deg, sigma deg, known) per row; azimuth and sigma NaN where unknown."""
        known = self.facing_sigma_deg > 0
        az = np.where(known, self.facing_deg.astype(float), np.nan)
        return az, np.where(known, self.facing_sigma_deg.astype(float), np.nan), known


def as_map_landmarks(lm: Landmarks) -> MapLandmarks:
    """``lm`` as :class:`MapLandmarks` (itself if it is one; else facing unknown)."""
    if isinstance(lm, MapLandmarks):
        return lm
    return MapLandmarks(**{name: getattr(lm, name) for name, _ in Landmarks.CODEC.cols})


def updates_from_bytes(data: bytes) -> LandmarkUpdates:
    """:meth:`LandmarkUpdates.from_bytes` with its landmarks read as :class:`MapLandmarks`
    (the solver sends the facing columns in its update log; ``LandmarkUpdates`` itself
    ignores extra columns). Same checks and :class:`DecodeError` fields."""
    m = LandmarkUpdates._open(data)
    return LandmarkUpdates(
        landmarks=get_table(m, "landmarks", MapLandmarks, MAX_TABLE_ROWS),
        removed=get_table(m, "removed", Removals, MAX_TABLE_ROWS),
    )


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
            upserts=get_table(m, "upserts", MapLandmarks, MAX_TABLE_ROWS),
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
            landmarks=get_table(m, "landmarks", MapLandmarks, MAX_TABLE_ROWS),
        )
