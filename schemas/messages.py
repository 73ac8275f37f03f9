"""What every wire message (version 1) shares: the :class:`Message` base with the common
envelope, the size limits, the bounds of times and tiles, and the helpers that put tables
and id arrays into a message's map and take them out.

The messages, by concern: :mod:`schemas.upload` (vehicle <-> ingest), :mod:`schemas.logs`
(the services' durable stage logs), :mod:`schemas.map` (publisher -> vehicles),
:mod:`schemas.control` (errors and stats); the tables they carry: :mod:`schemas.tables`.
Field-by-field documentation with units and frames: ``schemas/README.md``. Every
``from_bytes`` raises :class:`schemas.codec.DecodeError` naming the field.

>>> as_ids([1, 2]).dtype.str
'<u8'
"""

from __future__ import annotations

import re
from typing import Any, ClassVar

import numpy as np

from schemas.codec import (
    VERSION,
    DecodeError,
    Table,
    check_envelope,
    get_bytes,
    get_int,
    get_map,
    pack,
    unpack,
)

MAX_BATCH = 10_000
"""Default upper bound on rows in one upload batch (configurable per ingest)."""
MAX_TABLE_ROWS = 1_000_000
"""Upper bound on rows in internal tables (log entries, snapshots)."""

TILE_RE = re.compile(r"[0-3]{1,24}")
"""A tile: its quadkey."""
TILE_TEXT = "a quadkey (1-24 digits 0-3)"
"""What :data:`TILE_RE` accepts, for error messages."""
FLOAT_EPOCH_MAX = 4.1e9
"""Upper bound on Unix times, s (the year 2100)."""
MAX_RETRY_AFTER_S = 86400.0
"""Upper bound of every ``retry_after_s`` (``UploadAck``, ``ErrorReply``), s (a day)."""


def get_table(m: dict, name: str, cls: type, max_rows: int, strict: bool = True) -> Any:
    """The table ``name`` of class ``cls`` in ``m`` (its columns and ``n_<name>`` rows)."""
    n = get_int(m, f"n_{name}", 0, max_rows)
    return cls.CODEC.decode(get_map(m, name), n, name, strict=strict)


def put_table(out: dict, name: str, t: Table) -> None:
    """Put table ``t`` into ``out`` as ``name`` (its columns) and ``n_<name>`` (its rows)."""
    out[name] = type(t).CODEC.encode(t)
    out[f"n_{name}"] = len(t)


def as_ids(a: Any) -> np.ndarray:
    """Ids as little-endian u64 (``.tobytes()`` is their wire form)."""
    return np.ascontiguousarray(a, dtype="<u8")


def get_ids(m: dict, name: str, max_rows: int) -> np.ndarray:
    """The u64 ids of the ``bin`` field ``name``, at most ``max_rows``."""
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
