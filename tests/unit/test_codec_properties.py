"""Property tests of the wire codec: nothing but DecodeError ever escapes a decoder."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from hdmap.geo.signs import CATALOG
from schemas import (
    AssocGroup,
    DecodeError,
    ErrorReply,
    Landmarks,
    LandmarkUpdates,
    Links,
    LogEntry,
    LogHead,
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

PROFILE = settings(
    max_examples=250,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


def _decoders():
    """Every decoder, as (name, callable)."""
    out = [
        (c.__name__, c.from_bytes)
        for c in (
            ObservationBatch,
            UploadAck,
            LogEntry,
            LogQuery,
            LogHead,
            ObsGroup,
            AssocGroup,
            LandmarkUpdates,
            MapDelta,
            MapSnapshot,
            ErrorReply,
            Stats,
        )
    ]
    out.append(("ObservationBatch.partial", ObservationBatch.from_bytes_partial))
    return out


DECODERS = _decoders()


def _obs(n: int, seed: int) -> Observations:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return Observations(
        obs_id=np.arange(n, dtype=np.uint64) + 100,
        t=1.7e9 + rng.uniform(0, 60, n),
        image=np.arange(n, dtype=np.uint32),
        sign_class=np.full(n, 4, np.uint16),
        lat=60.17 + rng.normal(0, 1e-3, n),
        lon=24.94 + rng.normal(0, 1e-3, n),
        h=np.full(n, 20.0),
        direction=d,
        sigma_az=np.full(n, 0.01),
        sigma_el=np.full(n, 0.005),
        sigma_pos_h=np.full(n, 3.0),
        sigma_pos_v=np.full(n, 5.0),
        range_m=rng.uniform(0, 50, n),
        sigma_range_m=np.full(n, 2.0),
        score=np.full(n, 0.8, np.float32),
    )


def _landmarks(n: int) -> Landmarks:
    return Landmarks(
        id=np.arange(n, dtype=np.uint64),
        sign_class=np.full(n, 1, np.uint16),
        lat=np.full(n, 60.17),
        lon=np.full(n, 24.94),
        h=np.full(n, 20.0),
        cov=np.tile([1.0, 0.1, 0.0, 1.0, 0.0, 4.0], (n, 1)),
        status=np.ones(n, np.uint8),
        n_obs=np.full(n, 7, np.uint32),
        n_passes=np.full(n, 3, np.uint32),
        revision=np.arange(n, dtype=np.uint64) + 1,
        updated_at=np.full(n, 1.7e9),
        source_time=np.full(n, 1.7e9),
    )


def _valid_messages() -> list[bytes]:
    ids = np.array([1, 2, 3], np.uint64)
    rem = Removals(id=ids[:2], revision=ids[:2])
    lm = _landmarks(3)
    new = NewLandmarks(id=lm.id, sign_class=lm.sign_class, lat=lm.lat, lon=lm.lon, h=lm.h)
    links = Links(
        landmark_id=ids,
        vehicle=np.array([0, 1, 0], np.uint32),
        pass_id=ids,
        received_at=np.full(3, 1.7e9),
        weight=np.ones(3, np.float32),
    )
    msgs = [
        ObservationBatch("veh-1", 1, 2, 1.7e9, _obs(3, 0)),
        UploadAck(
            "veh-1",
            2,
            ids,
            ids[:1],
            [Rejection(9, "obs.lat", "bad")],
            DecodeError("n_obs", "too many"),
            1.0,
        ),
        LogEntry("obs", "ingest-1", "1201", 1, 1, b"payload"),
        LogQuery("obs", {"ingest-1": {"1201": 4}}, limit=10),
        LogQuery("obs", {"ingest-1": {"1201": 4}}, ["12"], 10, {"ingest-1": 7}),
        LogHead("obs", "ingest-1", 5, 9),
        UploadAck("veh-1", 3, ids[:0], error=DecodeError("storage", "corrupt"), permanent=True),
        ObsGroup("veh-1", 1, 2, 1.7e9, _obs(3, 1)),
        AssocGroup(["a", "b"], links, _obs(3, 2), new, ids[:1]),
        AssocGroup(
            ["a", "b"],
            links,
            _obs(3, 2),
            new,
            ids[:2],
            merged_into=ids[2:],
            held=np.array([True, False, True]),
            trust=TrustChanges(
                np.array([1, 0], np.uint32), np.array([1, 2], np.uint8), np.ones(2, np.float32)
            ),
        ),
        LandmarkUpdates(lm, rem),
        MapDelta("1201", 1, 2, 1.7e9, lm, rem),
        MapSnapshot("1201", 2, lm),
        ErrorReply("bad_request", "obs.lat[1]", "out of range"),
        ErrorReply("rate", "snapshot.client", "too many", 0.25),
        Stats("ingest", "i-1", ["12"], 1.7e9, {"n": 1.5}, {"obs.lat": 2}),
    ]
    return [m.to_bytes() for m in msgs]


VALID = _valid_messages()


def _only_decode_errors(data: bytes) -> int:
    """Run every decoder; return how many accepted the input. Anything else propagates."""
    accepted = 0
    for _, dec in DECODERS:
        try:
            dec(data)
            accepted += 1
        except DecodeError as e:
            assert isinstance(e.field, str) and e.field and isinstance(e.reason, str)
    return accepted


def test_every_valid_message_decodes_with_exactly_its_own_decoders() -> None:
    for data in VALID:
        n = _only_decode_errors(data)
        assert n == (2 if data == VALID[0] else 1)


# --- (a) arbitrary bytes ------------------------------------------------------------------------


@PROFILE
@given(st.binary(max_size=512))
def test_arbitrary_bytes_only_raise_decode_error(data: bytes) -> None:
    _only_decode_errors(data)


@PROFILE
@given(st.binary(max_size=64))
def test_arbitrary_bytes_after_a_map_header(data: bytes) -> None:
    # start like a real message so the msgpack parser gets further in
    for head in (b"\x82\xa1v\x01\xa4type", b"\xde\x00\x03", b"\x81\xa3obs"):
        _only_decode_errors(head + data)


# --- (b) mutations of valid messages -----------------------------------------------------------


@st.composite
def mutated(draw) -> bytes:
    data = bytearray(draw(st.sampled_from(VALID)))
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["flip", "set", "insert", "delete", "truncate"]))
        if not data:
            break
        i = draw(st.integers(0, len(data) - 1))
        if op == "flip":
            data[i] ^= 1 << draw(st.integers(0, 7))
        elif op == "set":
            data[i] = draw(st.integers(0, 255))
        elif op == "insert":
            data[i:i] = draw(st.binary(min_size=1, max_size=8))
        elif op == "delete":
            del data[i : i + draw(st.integers(1, 8))]
        else:
            del data[i:]
    return bytes(data)


@PROFILE
@given(mutated())
def test_mutated_messages_only_raise_decode_error(data: bytes) -> None:
    _only_decode_errors(data)


# --- (c) arbitrary msgpack maps ------------------------------------------------------------------

FIELD_NAMES = sorted({k for data in VALID for k in msgpack.unpackb(data)} | {"n", "index"})
TYPES = sorted({msgpack.unpackb(data)["type"] for data in VALID})

scalars = (
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=20)
    | st.binary(max_size=48)
)
keys = st.sampled_from(FIELD_NAMES) | st.text(max_size=8)
values = st.recursive(
    scalars,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(keys, inner, max_size=4),
    max_leaves=20,
)


@st.composite
def message_maps(draw) -> dict:
    m = draw(st.dictionaries(keys, values, max_size=10))
    if draw(st.booleans()):
        m["v"] = 1
        m["type"] = draw(st.sampled_from(TYPES))
    return m


@PROFILE
@given(message_maps())
def test_arbitrary_maps_only_raise_decode_error(m: dict) -> None:
    _only_decode_errors(msgpack.packb(m, use_bin_type=True))


@PROFILE
@given(st.sampled_from(VALID), st.data())
def test_replacing_one_field_only_raises_decode_error(data: bytes, draw) -> None:
    m = msgpack.unpackb(data)
    key = draw.draw(st.sampled_from(sorted(m)))
    m[key] = draw.draw(values)
    if isinstance(m.get("obs"), dict) and m["obs"] and draw.draw(st.booleans()):
        col = draw.draw(st.sampled_from(sorted(m["obs"])))
        m["obs"][col] = draw.draw(values)
    _only_decode_errors(msgpack.packb(m, use_bin_type=True))


# --- (d) round trip of generated Observations ---------------------------------------------------

finite = {"allow_nan": False, "allow_infinity": False}


@st.composite
def observations(draw) -> Observations:
    n = draw(st.integers(0, 40))

    def f8(lo: float, hi: float, **kw):
        return draw(hnp.arrays(np.float64, n, elements=st.floats(lo, hi, **finite, **kw)))

    raw_dir = draw(hnp.arrays(np.float64, (n, 3), elements=st.floats(-1, 1, **finite)))
    raw_dir[np.linalg.norm(raw_dir, axis=1) < 1e-3] = [0.0, 1.0, 0.0]
    direction = raw_dir / np.linalg.norm(raw_dir, axis=1, keepdims=True)
    return Observations(
        obs_id=draw(hnp.arrays(np.uint64, n, elements=st.integers(0, 2**64 - 1), unique=True)),
        t=f8(0.0, 4.1e9),
        image=draw(hnp.arrays(np.uint32, n)),
        sign_class=draw(hnp.arrays(np.uint16, n, elements=st.sampled_from(CATALOG.codes.tolist()))),
        lat=f8(-90.0, 90.0),
        lon=f8(-180.0, 180.0),
        h=f8(-1000.0, 10000.0),
        direction=direction,
        sigma_az=f8(0.0, math.pi, exclude_min=True),
        sigma_el=f8(0.0, math.pi, exclude_min=True),
        sigma_pos_h=f8(0.0, 1000.0, exclude_min=True),
        sigma_pos_v=f8(0.0, 1000.0, exclude_min=True),
        range_m=f8(0.0, 10000.0),
        sigma_range_m=f8(0.0, 10000.0),
        score=draw(hnp.arrays(np.float32, n, elements=st.floats(0.0, 1.0, width=32))),
    )


@PROFILE
@given(observations(), st.integers(0, 2**64 - 1), st.floats(0.0, 4.1e9))
def test_generated_observations_round_trip_exactly(obs: Observations, pass_id: int, sent: float):
    msg = ObservationBatch("veh_1.a-B", pass_id, 0, sent, obs)
    data = msg.to_bytes()
    for got in (ObservationBatch.from_bytes(data), ObservationBatch.from_bytes_partial(data)[0]):
        assert (got.vehicle_id, got.pass_id, got.batch_id, got.sent_at) == (
            "veh_1.a-B",
            pass_id,
            0,
            sent,
        )
        for name, c in Observations.CODEC.cols:
            a, b = getattr(obs, name), getattr(got.obs, name)
            assert b.dtype == np.dtype(c.dtype) and b.shape == a.shape
            assert a.tobytes() == b.tobytes(), name  # bit-exact, including -0.0
    assert ObservationBatch.from_bytes_partial(data)[1] == []


@pytest.mark.parametrize("name,decode", DECODERS, ids=[n for n, _ in DECODERS])
def test_deeply_nested_input_is_a_decode_error(name: str, decode) -> None:
    deep = b"\x91" * 100_000 + b"\xc0"  # 100k nested arrays
    with pytest.raises(DecodeError):
        decode(deep)
    deep_map = b"\x81\xa1a" * 100_000 + b"\xc0"
    with pytest.raises(DecodeError):
        decode(deep_map)
