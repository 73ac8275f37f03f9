"""Codec machinery: msgpack envelopes with columnar numpy tables, validated at the edge.

Every message is a msgpack map with ``v`` (schema version) and ``type``. Tables
(one row per observation or landmark) travel as one msgpack ``bin`` per column,
little-endian, row-major for vector columns: decoding a 1,000-row batch is a
dozen ``np.frombuffer`` calls and vectorised checks, not 1,000 dicts.

Anything wrong raises :class:`DecodeError` naming the field; nothing else escapes
:func:`unpack` or a table decoder.

>>> import msgpack
>>> unpack(b"\\xc1")
Traceback (most recent call last):
...
schemas.codec.DecodeError: message: not valid msgpack (...)
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar, TypeVar

import msgpack
import numpy as np

VERSION = 1
"""Wire schema version this code writes and reads."""

MAX_MESSAGE_BYTES = 64 * 1024 * 1024


class DecodeError(ValueError):
    """Bad input: which field, why, and for a table row, which row.

    >>> str(DecodeError("lat", "out of range [-90, 90]", index=3))
    'lat[3]: out of range [-90, 90]'
    """

    def __init__(self, field: str, reason: str, index: int | None = None):
        self.field = field
        self.reason = reason
        self.index = index
        where = field if index is None else f"{field}[{index}]"
        super().__init__(f"{where}: {reason}")

    def as_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"field": self.field, "reason": self.reason}
        if self.index is not None:
            d["index"] = self.index
        return d


def pack(obj: Mapping[str, Any]) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def unpack(data: bytes | bytearray | memoryview, max_bytes: int = MAX_MESSAGE_BYTES) -> dict:
    """Bytes -> top-level map, or :class:`DecodeError`."""
    if not isinstance(data, bytes | bytearray | memoryview):
        raise DecodeError("message", f"expected bytes, got {type(data).__name__}")
    if len(data) > max_bytes:
        raise DecodeError("message", f"{len(data)} bytes exceeds the limit of {max_bytes}")
    if len(data) == 0:
        raise DecodeError("message", "empty")
    try:
        obj = msgpack.unpackb(bytes(data), raw=False, strict_map_key=True, use_list=True)
    except (ValueError, TypeError, msgpack.UnpackException, RecursionError) as exc:
        raise DecodeError("message", f"not valid msgpack ({type(exc).__name__})") from None
    if not isinstance(obj, dict):
        raise DecodeError("message", f"expected a map, got {type(obj).__name__}")
    return obj


def check_envelope(m: Mapping[str, Any], expected_type: str) -> None:
    v = m.get("v")
    if v is None:
        raise DecodeError("v", "missing schema version")
    if not isinstance(v, int) or isinstance(v, bool):
        raise DecodeError("v", f"expected an integer, got {type(v).__name__}")
    if v != VERSION:
        raise DecodeError("v", f"unknown schema version {v} (this service reads {VERSION})")
    t = m.get("type")
    if t != expected_type:
        raise DecodeError("type", f"expected {expected_type!r}, got {t!r}")


# --- scalar header fields -----------------------------------------------------------

_ID_RE = re.compile(r"[A-Za-z0-9_.\-]{1,64}")
U64_MAX = (1 << 64) - 1


def get_int(m: Mapping[str, Any], name: str, lo: int = 0, hi: int = U64_MAX) -> int:
    if name not in m:
        raise DecodeError(name, "missing")
    v = m[name]
    if not isinstance(v, int) or isinstance(v, bool):
        raise DecodeError(name, f"expected an integer, got {type(v).__name__}")
    if not lo <= v <= hi:
        raise DecodeError(name, f"{v} out of range [{lo}, {hi}]")
    return v


def get_float(
    m: Mapping[str, Any], name: str, lo: float = -math.inf, hi: float = math.inf
) -> float:
    if name not in m:
        raise DecodeError(name, "missing")
    v = m[name]
    if not isinstance(v, int | float) or isinstance(v, bool):
        raise DecodeError(name, f"expected a number, got {type(v).__name__}")
    try:
        v = float(v)
    except OverflowError:
        raise DecodeError(name, "out of range") from None
    if not math.isfinite(v):
        raise DecodeError(name, "not finite")
    if not lo <= v <= hi:
        raise DecodeError(name, f"{v} out of range [{lo}, {hi}]")
    return v


def get_str(
    m: Mapping[str, Any],
    name: str,
    pattern: re.Pattern[str] = _ID_RE,
    expected: str = "1-64 characters of [A-Za-z0-9_.-]",
) -> str:
    if name not in m:
        raise DecodeError(name, "missing")
    v = m[name]
    if not isinstance(v, str):
        raise DecodeError(name, f"expected a string, got {type(v).__name__}")
    if not pattern.fullmatch(v):
        raise DecodeError(name, f"{v[:80]!r} is not {expected}")
    return v


def valid_id(v: object) -> bool:
    """Whether ``v`` is an identifier as vehicle ids and producer names must be."""
    return isinstance(v, str) and _ID_RE.fullmatch(v) is not None


def get_bytes(m: Mapping[str, Any], name: str) -> bytes:
    if name not in m:
        raise DecodeError(name, "missing")
    v = m[name]
    if not isinstance(v, bytes):
        raise DecodeError(name, f"expected bin, got {type(v).__name__}")
    return v


def get_map(m: Mapping[str, Any], name: str) -> dict:
    if name not in m:
        raise DecodeError(name, "missing")
    v = m[name]
    if not isinstance(v, dict):
        raise DecodeError(name, f"expected a map, got {type(v).__name__}")
    return v


def get_list(m: Mapping[str, Any], name: str, max_len: int) -> list:
    if name not in m:
        raise DecodeError(name, "missing")
    v = m[name]
    if not isinstance(v, list):
        raise DecodeError(name, f"expected an array, got {type(v).__name__}")
    if len(v) > max_len:
        raise DecodeError(name, f"{len(v)} items exceeds the limit of {max_len}")
    return v


# --- columnar tables ----------------------------------------------------------------


@dataclass(frozen=True)
class Col:
    """One column of a table: dtype, vector width and per-row value constraints."""

    dtype: str
    width: int = 1
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    unit: bool = False
    """Rows are unit vectors (norm within ``UNIT_TOL`` of 1)."""
    unit_label: str = ""
    doc: str = ""
    optional: bool = False
    """A column added in a later release: absent on the wire (an older sender) reads as
    zeros, and a constructor may leave it out (zeros)."""

    @property
    def is_float(self) -> bool:
        return np.dtype(self.dtype).kind == "f"

    def zeros(self, n: int) -> np.ndarray:
        """``n`` rows of zeros (what an absent optional column reads as)."""
        return np.zeros((n, self.width) if self.width > 1 else n, dtype=self.dtype)


UNIT_TOL = 1e-6
"""Allowed |norm - 1| of unit-vector columns (checked as |norm^2 - 1| <= 2 UNIT_TOL)."""


def col(dtype: str, width: int = 1, **kw: Any) -> Any:
    """Declare a dataclass field as a table column (``optional=True``: defaults to zeros)."""
    c = Col(dtype, width, **kw)
    if c.optional:
        return field(default=None, metadata={"col": c})
    return field(metadata={"col": c})


T = TypeVar("T")


_MIN, _MAX = np.minimum.reduce, np.maximum.reduce
"""Whole-array reductions without ``ndarray.min``'s wrapper (NaN propagates as there)."""


@dataclass(frozen=True)
class _ColPlan:
    """What decoding and checking one column needs, worked out once per table."""

    name: str
    col: Col
    wire: np.dtype
    """The column's dtype on the wire (little-endian)."""
    native: np.dtype | None
    """The host's dtype when it is not the wire's (None: a copy of the wire bytes)."""
    row_nbytes: int
    finite_check: bool
    """A float column without both bounds (the bounds' comparisons catch NaN otherwise)."""
    ranged: bool

    @classmethod
    def of(cls, name: str, c: Col) -> _ColPlan:
        wire = np.dtype(c.dtype).newbyteorder("<")
        host = wire.newbyteorder("=")
        return cls(
            name,
            c,
            wire,
            None if host == wire else host,
            c.width * wire.itemsize,
            c.is_float and (c.lo is None or c.hi is None),
            c.lo is not None or c.hi is not None,
        )


class TableCodec:
    """Encoder/decoder for one table dataclass, built once.

    ``decode`` checks structure (every column present, bin, right length) and
    raises; ``row_errors`` returns the first failing field per row so callers
    can reject single rows; ``decode(strict=True)`` raises on the first bad row.
    """

    def __init__(self, cls: type[T]):
        self.cls = cls
        self.cols: list[tuple[str, Col]] = [(f.name, f.metadata["col"]) for f in fields(cls)]  # type: ignore[arg-type]
        self.row_bytes = sum(np.dtype(c.dtype).itemsize * c.width for _, c in self.cols)
        self._plan = [_ColPlan.of(name, c) for name, c in self.cols]

    def encode(self, obj: Any) -> dict[str, bytes]:
        out: dict[str, bytes] = {}
        n = None
        for name, c in self.cols:
            a = np.ascontiguousarray(getattr(obj, name), dtype=np.dtype(c.dtype).newbyteorder("<"))
            rows = a.shape[0] if a.ndim else 1
            if n is None:
                n = rows
            elif rows != n:
                raise ValueError(f"column {name} has {rows} rows, expected {n}")
            out[name] = a.tobytes()
        return out

    def decode(self, m: Any, n: int, path: str, strict: bool = True) -> Any:
        if not isinstance(m, dict):
            raise DecodeError(path, f"expected a map of columns, got {type(m).__name__}")
        arrays: dict[str, np.ndarray] = {}
        for p in self._plan:
            name, c = p.name, p.col
            raw = m.get(name)
            if not isinstance(raw, bytes):
                fname = f"{path}.{name}" if path else name
                if c.optional and name not in m:
                    arrays[name] = c.zeros(n)
                    continue
                if raw is None:
                    raise DecodeError(fname, "missing column")
                raise DecodeError(fname, f"expected bin, got {type(raw).__name__}")
            expected = n * p.row_nbytes
            if len(raw) != expected:
                fname = f"{path}.{name}" if path else name
                raise DecodeError(fname, f"{len(raw)} bytes, expected {expected} for {n} rows")
            a = np.frombuffer(raw, dtype=p.wire)
            a = a.copy() if p.native is None else a.astype(p.native)
            arrays[name] = a.reshape(n, c.width) if c.width > 1 else a
        obj = self.cls(**arrays)
        if strict:
            bad, fld, reason = self.row_errors(obj)
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                raise DecodeError(f"{path}.{fld[i]}" if path else str(fld[i]), str(reason[i]), i)
        return obj

    def all_rows_ok(self, obj: Any) -> bool:
        """Fast path: one min/max reduction per column (NaN fails every comparison)."""
        for p in self._plan:
            a = getattr(obj, p.name)
            if a.size == 0:
                continue
            c = p.col
            if p.finite_check and not np.isfinite(a).all():
                return False
            if p.ranged:
                mn, mx = _MIN(a, axis=None), _MAX(a, axis=None)
                if c.lo is not None and not (mn > c.lo if c.lo_open else mn >= c.lo):
                    return False
                if c.hi is not None and not mx <= c.hi:
                    return False
            if c.unit:
                sq = np.einsum("ij,ij->i", a, a)
                if not np.abs(sq - 1.0).max() <= 2 * UNIT_TOL:
                    return False
        return True

    def row_errors(self, obj: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(bad mask, field name, reason) per row; first failing check wins."""
        n = len(getattr(obj, self.cols[0][0]))
        bad = np.zeros(n, bool)
        if self.all_rows_ok(obj):
            return bad, np.zeros(n, object), np.zeros(n, object)
        fld = np.full(n, "", dtype=object)
        why = np.full(n, "", dtype=object)

        def flag(mask: np.ndarray, name: str, reason: str) -> None:
            new = mask & ~bad
            if new.any():
                fld[new] = name
                why[new] = reason
                bad[:] |= new

        for name, c in self.cols:
            a = getattr(obj, name)
            if c.is_float:
                fin = np.isfinite(a) if a.ndim == 1 else np.isfinite(a).all(axis=1)
                flag(~fin, name, "not finite (NaN or inf)")
            if c.unit:
                fa = np.where(np.isfinite(a), a, 0.0)
                sq = np.einsum("ij,ij->i", fa, fa)
                flag(~(np.abs(sq - 1.0) <= 2 * UNIT_TOL), name, "not a unit vector")
            if c.lo is not None or c.hi is not None:
                with np.errstate(invalid="ignore"):
                    v = a if a.ndim == 1 else a.min(axis=1)
                    w = a if a.ndim == 1 else a.max(axis=1)
                    lo = -np.inf if c.lo is None else c.lo
                    hi = np.inf if c.hi is None else c.hi
                    below = (v <= lo) if c.lo_open else (v < lo)
                    lb = "(" if c.lo_open else "["
                    flag(below | (w > hi), name, f"out of range {lb}{_fmt(lo)}, {_fmt(hi)}]")
        return bad, fld, why

    @property
    def record_dtype(self) -> np.dtype:
        """A packed numpy structured dtype with one field per column (for row storage)."""
        return self._records(optional=True)

    @property
    def base_record_dtype(self) -> np.dtype:
        """:attr:`record_dtype` without the optional columns (rows stored before them)."""
        return self._records(optional=False)

    def _records(self, optional: bool) -> np.dtype:
        return np.dtype(
            [
                (n, np.dtype(c.dtype).newbyteorder("<"), (c.width,) if c.width > 1 else ())
                for n, c in self.cols
                if optional or not c.optional
            ]
        )

    def to_records(self, obj: Any) -> np.ndarray:
        rec = np.empty(len(getattr(obj, self.cols[0][0])), dtype=self.record_dtype)
        for name, _ in self.cols:
            rec[name] = getattr(obj, name)
        return rec

    def from_records(self, rec: np.ndarray) -> Any:
        """Rows of :attr:`record_dtype` (or an older dtype without optional columns)."""
        have = rec.dtype.names or ()
        return self.cls(
            **{
                name: np.ascontiguousarray(rec[name]).astype(np.dtype(c.dtype), copy=True)
                for name, c in self.cols
                if name in have
            }
        )

    def take(self, obj: Any, idx: np.ndarray) -> Any:
        """Rows ``idx`` (mask or indices) of a table."""
        return self.cls(**{name: getattr(obj, name)[idx] for name, _ in self.cols})

    def concat(self, parts: list[Any]) -> Any:
        return self.cls(
            **{name: np.concatenate([getattr(p, name) for p in parts]) for name, _ in self.cols}
        )

    def empty(self) -> Any:
        return self.cls(
            **{
                name: np.zeros((0, c.width) if c.width > 1 else 0, dtype=c.dtype)
                for name, c in self.cols
            }
        )


def _fmt(x: float) -> str:
    return f"{x:g}"


class Table:
    """Base of table dataclasses; :func:`table` attaches the codec built once per class."""

    CODEC: ClassVar[TableCodec]

    def __post_init__(self) -> None:
        for name, c in self.CODEC.cols:
            if c.optional and getattr(self, name) is None:
                object.__setattr__(self, name, c.zeros(len(self)))

    def __len__(self) -> int:
        # the first column's rows (the codec's columns are the fields, in order: looking
        # them up with dataclasses.fields cost more than the rest of a small table's use)
        return int(np.shape(getattr(self, self.CODEC.cols[0][0]))[0])

    def take(self, idx: np.ndarray) -> Any:
        return self.CODEC.take(self, idx)

    @classmethod
    def concat(cls, parts: list[Any]) -> Any:
        return cls.CODEC.concat(parts) if parts else cls.CODEC.empty()

    @classmethod
    def empty(cls) -> Any:
        return cls.CODEC.empty()


TableT = TypeVar("TableT", bound=type)


def table(cls: TableT) -> TableT:
    """Class decorator: a frozen dataclass whose fields are :func:`col` columns."""
    cls = dataclass(frozen=True, eq=False)(cls)
    cls.CODEC = TableCodec(cls)  # type: ignore[attr-defined]
    return cls
