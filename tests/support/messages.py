"""Message builders and assertions for the codec tests (tests/unit/test_codec.py and the
fuzz tests): realistic random content for every message, the raw msgpack form, and the
expected ``DecodeError``."""

from __future__ import annotations

import dataclasses

import msgpack
import numpy as np
import pytest

from hdmap.geo.signs import CATALOG
from schemas import (
    AssocGroup,
    DecodeError,
    ErrorReply,
    Landmarks,
    LandmarkUpdates,
    Links,
    LogEntry,
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
    TrustChanges,
    UploadAck,
)
from schemas.codec import Table
from schemas.map import MapLandmarks

T0 = 1.7e9

# --- realistic random content -------------------------------------------------------------


def make_obs(n: int, seed: int = 0) -> Observations:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3)) * [1.0, 1.0, 0.1]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rng_m = np.where(rng.random(n) < 0.3, 0.0, rng.uniform(5.0, 80.0, n))
    return Observations(
        obs_id=rng.permutation(
            np.arange(n, dtype=np.uint64) * np.uint64(2**53 - 1) + np.uint64(2**63)
        ),
        t=T0 + np.sort(rng.uniform(0, 600, n)),
        image=np.sort(rng.integers(0, 2**32, n, dtype=np.uint64)).astype(np.uint32),
        sign_class=rng.choice(CATALOG.codes, n).astype(np.uint16),
        lat=60.17 + rng.normal(0, 0.01, n),
        lon=24.94 + rng.normal(0, 0.01, n),
        h=rng.uniform(10, 40, n),
        direction=d,
        sigma_az=rng.uniform(0.002, 0.05, n),
        sigma_el=rng.uniform(0.002, 0.02, n),
        sigma_pos_h=rng.uniform(0.5, 10, n),
        sigma_pos_v=rng.uniform(1, 15, n),
        range_m=rng_m,
        sigma_range_m=rng_m * 0.12,
        score=rng.uniform(0, 1, n).astype(np.float32),
    )


def make_landmarks(n: int, seed: int = 1) -> Landmarks:
    rng = np.random.default_rng(seed)
    return Landmarks(
        id=rng.integers(0, 2**63, n, dtype=np.uint64) | np.uint64(2**63),
        sign_class=rng.choice(CATALOG.codes, n).astype(np.uint16),
        lat=60.17 + rng.normal(0, 0.01, n),
        lon=24.94 + rng.normal(0, 0.01, n),
        h=rng.uniform(10, 40, n),
        cov=np.column_stack(
            [
                rng.uniform(0.1, 4, n),
                rng.normal(0, 0.1, (n, 2)),
                rng.uniform(0.1, 4, n),
                rng.normal(0, 0.1, n),
                rng.uniform(1, 9, n),
            ]
        ),
        status=rng.integers(0, 3, n).astype(np.uint8),
        n_obs=rng.integers(1, 10_000, n).astype(np.uint32),
        n_passes=rng.integers(1, 500, n).astype(np.uint32),
        revision=rng.integers(1, 2**40, n).astype(np.uint64),
        updated_at=T0 + rng.uniform(0, 1e5, n),
        source_time=T0 + rng.uniform(0, 1e5, n),
    )


def make_removals(n: int, seed: int = 2) -> Removals:
    rng = np.random.default_rng(seed)
    return Removals(
        id=rng.integers(0, 2**64 - 1, n, dtype=np.uint64),
        revision=rng.integers(1, 1000, n).astype(np.uint64),
    )


def make_links(n: int, n_vehicles: int, seed: int = 3) -> Links:
    rng = np.random.default_rng(seed)
    return Links(
        landmark_id=rng.integers(0, 2**64 - 1, n, dtype=np.uint64),
        vehicle=rng.integers(0, n_vehicles, n).astype(np.uint32),
        pass_id=rng.integers(0, 2**64 - 1, n, dtype=np.uint64),
        received_at=T0 + rng.uniform(0, 1e5, n),
        weight=rng.uniform(0, 1, n).astype(np.float32),
    )


def make_map_landmarks(n: int, seed: int = 1) -> MapLandmarks:
    """:func:`make_landmarks` with facings (every third unknown: sigma 0)."""
    lm = make_landmarks(n, seed)
    rng = np.random.default_rng(seed + 100)
    known = np.arange(n) % 3 != 2
    return MapLandmarks(
        **{name: getattr(lm, name) for name, _ in Landmarks.CODEC.cols},
        facing_deg=np.where(known, rng.uniform(0, 360, n), 0.0).astype(np.float32),
        facing_sigma_deg=np.where(known, rng.uniform(0.01, 40, n), 0.0).astype(np.float32),
    )


def make_new(n: int, seed: int = 4) -> NewLandmarks:
    lm = make_landmarks(n, seed)
    return NewLandmarks(id=lm.id, sign_class=lm.sign_class, lat=lm.lat, lon=lm.lon, h=lm.h)


def ids(*v: int) -> np.ndarray:
    return np.array(v, np.uint64)


def messages(n: int = 5) -> dict[str, object]:
    """One realistic instance of every message type."""
    return {
        "ObservationBatch": ObservationBatch("veh-0042", 2**40 + 3, 17, T0 + 1.5, make_obs(n)),
        "UploadAck": UploadAck(
            "veh-0042",
            17,
            ids(1, 3, 2**64 - 1),
            ids(3),
            [Rejection(7, "obs.lat", "out of range [-90, 90]")],
            DecodeError("obs.lat", "out of range", 4),
            2.5,
        ),
        "LogEntry": LogEntry("obs", "ingest-1", "1201202110133102", 5, 99, b"\x00\x01body"),
        "LogQuery": LogQuery(
            "assoc",
            {"matcher-1": {"1201": 3, "1202": 0}, "m.2": {}},
            prefixes=["120", "1213"],
            limit=250,
        ),
        "ObsGroup": ObsGroup("veh-1", 4, 5, T0 + 2, make_obs(n, 7)),
        "AssocGroup": AssocGroup(
            ["veh-1", "veh-2", "veh-3"],
            make_links(n, 3),
            make_obs(n, 8),
            make_new(3),
            ids(11, 12),
            held=np.arange(n) % 2 == 0,
            trust=TrustChanges(
                np.array([0, 2], np.uint32), np.array([1, 2], np.uint8), np.array([1.0, 0.0])
            ),
        ),
        "LandmarkUpdates": LandmarkUpdates(make_landmarks(n), make_removals(2)),
        "MapDelta": MapDelta(
            "1201202110133102", 41, 42, T0 + 3, make_map_landmarks(n), make_removals(3)
        ),
        "MapSnapshot": MapSnapshot("1201202110133102", 42, make_map_landmarks(n)),
        "ErrorReply": ErrorReply("rate", "snapshot.client", "client 'veh-1' asks too often", 2.5),
        "Stats": Stats(
            "matcher", "m-1", ["120", "121"], T0, {"obs_in": 1234, "lag_s": 0.25}, {"obs.lat": 3}
        ),
    }


CLASSES = {name: type(m) for name, m in messages().items()}
ALL = list(CLASSES)

# --- helpers -------------------------------------------------------------------------------


def assert_table_equal(a: Table, b: Table) -> None:
    assert type(a) is type(b)
    for name, c in type(a).CODEC.cols:
        x, y = getattr(a, name), getattr(b, name)
        assert y.dtype == np.dtype(c.dtype), name
        assert y.shape == x.shape, name
        np.testing.assert_array_equal(y, np.asarray(x, c.dtype), err_msg=name)


def assert_message_equal(a: object, b: object) -> None:
    assert type(a) is type(b)
    for f in dataclasses.fields(a):  # type: ignore[arg-type]
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, Table):
            assert_table_equal(x, y)
        elif isinstance(x, np.ndarray):
            assert y.dtype == x.dtype and np.array_equal(x, y), f.name
        elif isinstance(x, DecodeError):
            assert y.as_dict() == x.as_dict()
        else:
            assert y == x, f.name


def raw(msg: object) -> dict:
    return msgpack.unpackb(msg.to_bytes(), raw=False)  # type: ignore[attr-defined]


def enc(d: object) -> bytes:
    return msgpack.packb(d, use_bin_type=True)


def expect(cls: type, data: bytes, field: str, **kw) -> DecodeError:
    with pytest.raises(DecodeError) as exc:
        cls.from_bytes(data, **kw)  # type: ignore[attr-defined]
    assert exc.value.field == field, str(exc.value)
    assert exc.value.reason
    return exc.value


def with_(msg: object, **changes) -> bytes:
    d = raw(msg)
    d.update(changes)
    return enc(d)


def without(msg: object, key: str) -> bytes:
    d = raw(msg)
    del d[key]
    return enc(d)


def batch(obs: Observations) -> ObservationBatch:
    return ObservationBatch("veh-1", 1, 2, T0, obs)
