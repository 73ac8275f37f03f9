"""Hostile inputs for the fuzz tests: valid messages of every type to start from, and
mutations of them (flipped bytes, truncation, wrong types, NaN/inf, huge arrays, duplicate
ids, far timestamps, unknown classes, zero directions, coordinates outside their tile).

Shared by tests/unit/test_fuzz_decoders.py, tests/integration/test_fuzz_endpoints.py and
tests/integration/test_fuzz_internal.py; the observation
builder is the attack generators' (:mod:`fleetsim.attacks`).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

from fleetsim.attacks import HELSINKI, fresh_observations
from hdmap.geo.tiles import quadkeys_of, route_rays
from schemas import (
    AssocGroup,
    ErrorReply,
    Landmarks,
    LandmarkUpdates,
    Links,
    LogEntry,
    LogHead,
    LogMark,
    LogQuery,
    MapDelta,
    MapSnapshot,
    NewLandmarks,
    ObservationBatch,
    Observations,
    ObsGroup,
    Rejection,
    Removals,
    Stats,
    UploadAck,
)
from schemas.codec import Col

FUZZ = settings(
    max_examples=150,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=list(HealthCheck),
)

_ids = itertools.count(1_000_000)
"""Fresh observation / landmark numbers across every example of the module."""


# --- valid messages to start from -----------------------------------------------------------


def observations(n: int, seed: int = 0, lat: float = HELSINKI[0], lon: float = HELSINKI[1]):
    """Valid observations with fresh ids (:func:`fleetsim.attacks.fresh_observations`)."""
    return fresh_observations(n, next(_ids) * 1000, seed, lat, lon)


def landmarks(n: int, now: float, seed: int = 0) -> Landmarks:
    rng = np.random.default_rng(seed)
    return Landmarks(
        id=np.arange(n, dtype=np.uint64) + next(_ids),
        sign_class=np.full(n, 4, np.uint16),
        lat=HELSINKI[0] + rng.normal(0, 1e-4, n),
        lon=HELSINKI[1] + rng.normal(0, 1e-4, n),
        h=np.full(n, 20.0),
        cov=np.tile([1.0, 0.1, 0.0, 1.0, 0.0, 4.0], (n, 1)),
        status=np.ones(n, np.uint8),
        n_obs=np.full(n, 7, np.uint32),
        n_passes=np.full(n, 3, np.uint32),
        revision=np.arange(n, dtype=np.uint64) + 1,
        updated_at=np.full(n, now),
        source_time=np.full(n, now),
    )


def tile_of_obs(obs: Observations) -> str:
    return str(route_rays(obs.lat, obs.lon, obs.h, obs.direction, obs.range_m)[0])


def obs_group(now: float, n: int = 6) -> tuple[str, ObsGroup]:
    obs = observations(n)
    tile = tile_of_obs(obs)
    return tile, ObsGroup(f"fz-veh-{next(_ids)}", 1, 1, now, obs)


def assoc_group(now: float, n: int = 6) -> tuple[str, AssocGroup]:
    obs = observations(n)
    lm = landmarks(2, now)
    created = NewLandmarks(id=lm.id, sign_class=lm.sign_class, lat=lm.lat, lon=lm.lon, h=lm.h)
    links = Links(
        landmark_id=np.resize(lm.id, n).astype(np.uint64),
        vehicle=(np.arange(n) % 2).astype(np.uint32),
        pass_id=np.ones(n, np.uint64),
        received_at=np.full(n, now),
        weight=np.ones(n, np.float32),
    )
    tile = str(quadkeys_of(lm.lat[:1], lm.lon[:1])[0])
    return tile, AssocGroup(["fz-a", "fz-b"], links, obs, created, np.zeros(0, np.uint64))


def landmark_updates(now: float, n: int = 3) -> tuple[str, LandmarkUpdates]:
    lm = landmarks(n, now)
    rem = Removals(id=lm.id[:1] + np.uint64(10**6), revision=lm.revision[:1])
    return str(quadkeys_of(lm.lat[:1], lm.lon[:1])[0]), LandmarkUpdates(lm, rem)


def valid_messages(now: float) -> dict[str, bytes]:
    """One valid encoding of every message type, by wire type."""
    ids = np.array([1, 2, 3], np.uint64)
    lm = landmarks(3, now)
    rem = Removals(id=ids[:2], revision=ids[:2])
    tile, group = obs_group(now, 4)
    msgs = [
        ObservationBatch("fz-0", 1, 2, now, observations(4)),
        UploadAck("fz-0", 2, ids, ids[:1], [Rejection(9, "obs.lat", "bad")], None, 0.0),
        LogEntry("obs", "fz-producer", tile, 2, 5, group.to_bytes(), 7, 1, 3),
        LogQuery("obs", {"fz-producer": {tile: 4}}, ["12"], 10, {"fz-producer": 3}),
        LogHead("obs", "fz-producer", 3, 8, [(5, 0), (7, 3)]),
        LogMark("obs", "fz-producer", "fz-consumer", 5, 7),
        group,
        assoc_group(now, 4)[1],
        LandmarkUpdates(lm, rem),
        MapDelta(tile, 1, 2, now, lm, rem),
        MapSnapshot(tile, 2, lm),
        ErrorReply("busy", "snapshot.total", "too many", 0.5),
        Stats("ingest", "i-1", ["12"], now, {"n": 1.5}, {"obs.lat": 2}),
    ]
    return {m.TYPE: m.to_bytes() for m in msgs}


# --- hostile variants -----------------------------------------------------------------------

TABLES: dict[str, type] = {
    "obs": Observations,
    "links": Links,
    "created": NewLandmarks,
    "landmarks": Landmarks,
    "upserts": Landmarks,
    "removed": Removals,
}

HEADER_VALUES: list[Any] = [
    None,
    True,
    False,
    math.nan,
    math.inf,
    -math.inf,
    -1,
    0,
    2**64 - 1,
    -(2**63),
    1.5,
    4.1e9 + 1,
    1e300,
    "",
    "x" * 300,
    "veh 1",
    "0123",
    b"\x00" * 9,
    [],
    [1, "a"],
    {},
    {"a": 1},
]

RELATED: dict[tuple[str, str], tuple[str, ...]] = {
    ("map_delta", "from_version"): ("to_version",),
    ("assoc_group", "vehicles"): ("links.vehicle",),
    ("assoc_group", "n_links"): ("links",),
    ("assoc_group", "n_obs"): ("links",),
    ("assoc_group", "links"): ("links",),
    ("assoc_group", "obs"): ("links",),
    ("log_entry", "seq"): ("base",),  # base < seq
    ("log_entry", "gseq"): ("gbase",),  # gbase < gseq
}
OPTIONAL = {
    ("upload_ack", "error"),
    ("assoc_group", "merged_into"),
    ("error", "retry_after_s"),
    ("log_query", "after_gseq"),
    ("log_entry", "epoch"),  # producers from before epochs
    ("log_entry", "base"),
    ("log_entry", "gbase"),
    ("log_head", "epochs"),
}
"""Fields a message may lack (absent reads as a default)."""


def always_invalid(value: Any, mtype: str, key: str) -> bool:
    """A header value no field of any message accepts (bool, NaN/inf, nil where required)."""
    if isinstance(value, bool) or (isinstance(value, float) and not math.isfinite(value)):
        return True
    return value is None and (mtype, key) not in OPTIONAL


@dataclass
class Case:
    """One hostile input and what its mutation implies."""

    data: bytes
    what: str
    mtype: str = ""
    field: str | None = None
    """The mutated field ('obs.lat', 'pass_id'); None: no oracle on the error's field."""
    row: int | None = None
    must_fail: bool = False
    """Invalid by the schema, whatever else: a decoder must not accept it."""
    admission: bool = False
    """Valid by the schema but refused by ingest's admission policy (a row of ``field``)."""
    related: tuple[str, ...] = ()
    must_pass: bool = False
    """Valid by the schema (boundary values): a decoder must accept it."""

    def explains(self, err_field: str) -> bool:
        if self.field is None:
            return True
        return any(
            err_field == f or err_field.startswith(f + ".") for f in (self.field, *self.related)
        )

    def __repr__(self) -> str:
        return (
            f"Case({self.what!r}, field={self.field!r}, row={self.row}, must_fail={self.must_fail})"
        )


def _tables(m: dict) -> list[str]:
    return sorted(t for t in TABLES if isinstance(m.get(t), dict) and f"n_{t}" in m)


def _column(m: dict, table: str, name: str, c: Col) -> np.ndarray:
    a = np.frombuffer(m[table][name], dtype=np.dtype(c.dtype).newbyteorder("<")).copy()
    return a.reshape(-1, c.width) if c.width > 1 else a


def bad_cells(
    c: Col, mtype: str, table: str, name: str, now: float
) -> list[tuple[Any, bool, bool]]:
    """(value, invalid by the schema, refused by admission) for one cell of column ``c``."""
    out: list[tuple[Any, bool, bool]] = []
    if c.is_float:
        if c.unit:
            bad = [[0.0, 0.0, 0.0], [math.nan, 0.0, 0.0], [1.0, 1.0, 0.0], [math.inf, 0, 0]]
            return [(v, True, False) for v in bad]
        if c.width > 1:
            return [([math.nan] + [1.0] * (c.width - 1), True, False)]
        out += [(math.nan, True, False), (math.inf, True, False), (-math.inf, True, False)]
        if c.lo is not None:
            out.append((c.lo if c.lo_open else c.lo - 1.0, True, False))
        if c.hi is not None:
            out.append((c.hi * 2 + 1.0, True, False))
        if name == "t" and mtype == "obs_batch":  # schema-valid, but not now
            out += [(now + 3600.0, False, True), (1.0, False, True), (4.0e9, False, True)]
        return out
    info = np.iinfo(np.dtype(c.dtype))
    if c.hi is not None:
        out.append((int(c.hi) + 1, True, False))
    if name == "sign_class" and mtype == "obs_batch":
        out += [(0, True, False), (21, True, False), (info.max, True, False)]
    out += [(0, False, False), (int(info.max), False, False)]
    return out


def extreme_cells(c: Col, table: str, name: str) -> list[tuple[Any, bool]]:
    """(value, valid by the schema) at the boundaries of column ``c``."""
    if c.unit:
        return [([1.0, 0.0, 0.0], True), ([0.0, 0.0, -1.0], True), ([0.0, -1.0, 0.0], True)]
    if c.is_float:
        if c.width > 1:
            return [([1e308] * c.width, True), ([-1e308] * c.width, True), ([-0.0] * c.width, True)]
        lo = -1e308 if c.lo is None else (np.nextafter(c.lo, np.inf) if c.lo_open else c.lo)
        hi = 1e308 if c.hi is None else c.hi
        if c.dtype == "f4":
            lo, hi = (
                (float(np.nextafter(np.float32(c.lo), np.float32(np.inf))) if c.lo_open else lo),
                hi,
            )
        return [(float(lo), True), (float(hi), True)]
    info = np.iinfo(np.dtype(c.dtype))
    valid = not (table == "links" and name == "vehicle")  # an index into another field
    lo = int(c.lo) if c.lo is not None else 0
    hi = int(c.hi) if c.hi is not None else int(info.max)
    return [(lo, valid), (hi, valid)] + ([(2**63, valid)] if hi >= 2**63 else [])


def _set_cell(m: dict, table: str, name: str, c: Col, row: int, value: Any) -> None:
    a = _column(m, table, name, c)
    a[row] = value
    m[table][name] = a.astype(np.dtype(c.dtype).newbyteorder("<")).tobytes()


@st.composite
def byte_mutation(draw, data: bytes) -> bytes:
    buf = bytearray(data)
    for _ in range(draw(st.integers(1, 4))):
        if not buf:
            break
        op = draw(st.sampled_from(["flip", "set", "insert", "delete", "truncate"]))
        i = draw(st.integers(0, len(buf) - 1))
        if op == "flip":
            buf[i] ^= 1 << draw(st.integers(0, 7))
        elif op == "set":
            buf[i] = draw(st.integers(0, 255))
        elif op == "insert":
            buf[i:i] = draw(st.binary(min_size=1, max_size=8))
        elif op == "delete":
            del buf[i : i + draw(st.integers(1, 8))]
        else:
            del buf[i:]
    return bytes(buf)


@st.composite
def hostile(draw, base: bytes, now: float, huge_rows: tuple[int, ...] = (2000, 10001)) -> Case:
    """A hostile variant of the valid message ``base`` (one mutation, or random bytes)."""
    m = msgpack.unpackb(base, raw=False)
    mtype = m["type"]
    tables = _tables(m)
    kinds = ["random", "bytes", "header", "delete", "envelope", "extreme_header"]
    if tables:
        kinds += ["cell", "cell", "cell", "structure", "huge", "extreme", "extreme"]
    if mtype == "obs_batch":
        kinds += ["duplicate_id"]
    kind = draw(st.sampled_from(kinds))
    pack = msgpack.packb
    if kind == "random":
        return Case(draw(st.binary(max_size=300)), "random bytes", mtype)
    if kind == "bytes":
        return Case(draw(byte_mutation(base)), "mutated bytes", mtype)
    if kind == "envelope":
        key = draw(st.sampled_from(["v", "type"]))
        other = ["obs_batch", "log_entry", "stats", "error", "", None, 1]
        value = draw(st.sampled_from([2, 0, "1", 1.0, None, True] if key == "v" else other))
        if value == mtype:
            value = "nope"
        m[key] = value
        return Case(pack(m), f"envelope {key}={value!r}", mtype, key, must_fail=True)
    headers = sorted(k for k in m if k not in ("v", "type"))
    if kind == "extreme_header":  # boundary values of integer and float header fields
        numeric = [
            k for k in headers if isinstance(m[k], int | float) and not isinstance(m[k], bool)
        ]
        if not numeric:
            return Case(base, "unchanged (no numeric header)", mtype)
        key = draw(st.sampled_from(numeric))
        m[key] = draw(st.sampled_from([0, 1, 2**63 - 1, 2**63, 2**64 - 1, 0.0, 4.1e9, 86400.0]))
        related = RELATED.get((mtype, key), ()) + ((key[2:],) if key.startswith("n_") else ())
        return Case(pack(m), f"{key}={m[key]!r}", mtype, key, related=related)
    if kind == "header":
        key = draw(st.sampled_from(headers))
        value = draw(st.sampled_from(HEADER_VALUES))
        m[key] = value
        related = RELATED.get((mtype, key), ()) + ((key[2:],) if key.startswith("n_") else ())
        bad = always_invalid(value, mtype, key)
        return Case(pack(m), f"{key}={value!r:.40}", mtype, key, None, bad, related=related)
    if kind == "delete":
        key = draw(st.sampled_from(headers))
        del m[key]
        must = (mtype, key) not in OPTIONAL
        related = RELATED.get((mtype, key), ()) + ((key[2:],) if key.startswith("n_") else ())
        return Case(pack(m), f"without {key}", mtype, key, None, must, related=related)
    table = draw(st.sampled_from(tables))
    cols = TABLES[table].CODEC.cols
    n = m[f"n_{table}"]
    if kind == "huge":
        rows = draw(st.sampled_from(huge_rows))
        for t in tables:
            for name, c in TABLES[t].CODEC.cols:
                a = _column(m, t, name, c)
                if len(a):
                    a = np.resize(a, (rows, *a.shape[1:]))  # tiled: obs ids repeat
                m[t][name] = a.astype(np.dtype(c.dtype).newbyteorder("<")).tobytes()
            if m[f"n_{t}"]:
                m[f"n_{t}"] = rows
        must = mtype == "obs_batch" and rows > 10_000
        return Case(pack(m), f"huge {rows} rows", mtype, "n_obs" if must else None, None, must)
    if kind == "structure":
        name, c = draw(st.sampled_from(cols))
        op = draw(st.sampled_from(["short", "long", "missing", "type", "count", "count_huge"]))
        fname = f"{table}.{name}"
        if op == "short" and m[table][name]:
            m[table][name] = m[table][name][: -draw(st.integers(1, 8))]
        elif op == "long":
            m[table][name] = m[table][name] + b"\x00" * draw(st.integers(1, 8))
        elif op == "missing":
            del m[table][name]
        elif op == "type":
            m[table][name] = draw(st.sampled_from([None, 1, "abc", [1, 2], {"a": b"x"}]))
        elif op in ("count", "count_huge"):
            m[f"n_{table}"] = n + 1 if op == "count" else 10**6
            return Case(
                pack(m),
                f"n_{table}={m[f'n_{table}']}",
                mtype,
                f"n_{table}",
                None,
                True,
                related=(table,),
            )
        else:
            return Case(pack(m), "empty column unchanged", mtype)
        return Case(pack(m), f"{fname} {op}", mtype, fname, None, True)
    if n == 0:
        return Case(base, "unchanged (empty table)", mtype)
    row = draw(st.integers(0, n - 1))
    if kind == "duplicate_id":
        c = dict(cols)["obs_id"]
        ids = _column(m, "obs", "obs_id", c)
        other = draw(st.integers(0, n - 1).filter(lambda j: j != row)) if n > 1 else row
        if other == row:
            return Case(base, "unchanged (one row)", mtype)
        _set_cell(m, "obs", "obs_id", c, max(row, other), ids[min(row, other)])
        return Case(pack(m), "duplicate obs_id", mtype, "obs.obs_id", max(row, other), True)
    name, c = draw(st.sampled_from(cols))
    if kind == "extreme":
        value, valid = draw(st.sampled_from(extreme_cells(c, table, name)))
        if name == "obs_id" and value in _column(m, table, name, c).tolist():
            valid = valid and mtype != "obs_batch"  # now a duplicate id
        if name == "sign_class" and mtype == "obs_batch":
            valid = False  # 0 and 65535 are no known class
        _set_cell(m, table, name, c, row, value)
        what = f"{table}.{name}[{row}]={value!r:.40} (boundary)"
        return Case(pack(m), what, mtype, f"{table}.{name}", row, must_pass=valid)
    value, must, adm = draw(st.sampled_from(bad_cells(c, mtype, table, name, now)))
    _set_cell(m, table, name, c, row, value)
    return Case(
        pack(m), f"{table}.{name}[{row}]={value!r:.40}", mtype, f"{table}.{name}", row, must, adm
    )


def _with(m: dict, **kw: Any) -> bytes:
    return msgpack.packb({**m, **kw})


def _cell(m: dict, table: str, name: str, row: int, value: Any) -> bytes:
    m = msgpack.unpackb(msgpack.packb(m))
    _set_cell(m, table, name, dict(TABLES[table].CODEC.cols)[name], row, value)
    return msgpack.packb(m)


def _batch_map(now: float, n: int = 4) -> dict:
    return msgpack.unpackb(ObservationBatch("fz-0", 1, 1, now, observations(n)).to_bytes())


def named_batches(now: float) -> list[tuple[str, bytes, str, int | None]]:
    """(name, payload, field named by the strict decoder's error, row) of classic bad batches."""
    m = _batch_map(now)
    ids = _column(m, "obs", "obs_id", dict(Observations.CODEC.cols)["obs_id"])
    big = ObservationBatch("fz-0", 1, 1, now, observations(10_001)).to_bytes()
    return [
        ("garbage", b"\x00\x01garbage", "message", None),
        ("empty", b"", "message", None),
        ("truncated", msgpack.packb(m)[:-7], "message", None),
        ("not a map", msgpack.packb([1, 2, 3]), "message", None),
        ("version 2", _with(m, v=2), "v", None),
        ("version as float", _with(m, v=1.0), "v", None),
        ("other type", _with(m, type="log_entry"), "type", None),
        ("negative pass_id", _with(m, pass_id=-1), "pass_id", None),
        ("pass_id as str", _with(m, pass_id="7"), "pass_id", None),
        ("sent_at NaN", _with(m, sent_at=math.nan), "sent_at", None),
        ("sent_at far future", _with(m, sent_at=1e12), "sent_at", None),
        ("vehicle id with space", _with(m, vehicle_id="veh 1"), "vehicle_id", None),
        ("n_obs over max_obs", big, "n_obs", None),
        ("n_obs huge, columns short", _with(m, n_obs=10**9), "n_obs", None),
        ("n_obs one too many", _with(m, n_obs=5), "obs.obs_id", None),
        (
            "column missing",
            _with(m, obs={k: v for k, v in m["obs"].items() if k != "lat"}),
            "obs.lat",
            None,
        ),
        ("column truncated", _with(m, obs={**m["obs"], "h": m["obs"]["h"][:-1]}), "obs.h", None),
        ("column as list", _with(m, obs={**m["obs"], "t": [1.0, 2.0, 3.0, 4.0]}), "obs.t", None),
        ("lat NaN", _cell(m, "obs", "lat", 1, math.nan), "obs.lat", 1),
        ("lon 200", _cell(m, "obs", "lon", 2, 200.0), "obs.lon", 2),
        ("h inf", _cell(m, "obs", "h", 0, math.inf), "obs.h", 0),
        ("sigma_az zero", _cell(m, "obs", "sigma_az", 3, 0.0), "obs.sigma_az", 3),
        ("score NaN", _cell(m, "obs", "score", 1, math.nan), "obs.score", 1),
        ("t beyond 2100", _cell(m, "obs", "t", 2, 5e9), "obs.t", 2),
        (
            "zero-length direction",
            _cell(m, "obs", "direction", 1, [0.0, 0.0, 0.0]),
            "obs.direction",
            1,
        ),
        (
            "direction not unit",
            _cell(m, "obs", "direction", 2, [1.0, 1.0, 0.0]),
            "obs.direction",
            2,
        ),
        ("unknown sign class", _cell(m, "obs", "sign_class", 3, 999), "obs.sign_class", 3),
        ("duplicate ids", _cell(m, "obs", "obs_id", 2, ids[0]), "obs.obs_id", 2),
    ]
