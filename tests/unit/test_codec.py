"""schemas: a round trip for every message, and every bad input naming its field."""

from __future__ import annotations

import math

import numpy as np
import pytest

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
    NewLandmarks,
    ObservationBatch,
    Observations,
    Removals,
    Stats,
    UploadAck,
)
from schemas.codec import MAX_MESSAGE_BYTES, unpack
from schemas.map import MapLandmarks, updates_from_bytes
from tests.support.messages import (
    ALL,
    CLASSES,
    T0,
    assert_message_equal,
    assert_table_equal,
    batch,
    enc,
    expect,
    make_landmarks,
    make_map_landmarks,
    make_obs,
    make_removals,
    messages,
    raw,
    with_,
    without,
)

# --- round trips -------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ALL)
@pytest.mark.parametrize("n", [0, 1, 257])
def test_round_trip_every_message(name: str, n: int) -> None:
    msg = messages(n)[name]
    data = msg.to_bytes()  # type: ignore[attr-defined]
    assert isinstance(data, bytes)
    d = unpack(data)
    assert d["v"] == 1 and d["type"] == msg.TYPE  # type: ignore[attr-defined]
    assert_message_equal(msg, type(msg).from_bytes(data))  # type: ignore[attr-defined]


def test_round_trip_partial_of_a_clean_batch() -> None:
    msg = messages(300)["ObservationBatch"]
    got, rejected = ObservationBatch.from_bytes_partial(msg.to_bytes())
    assert rejected == []
    assert_message_equal(msg, got)


def test_tables_are_little_endian_row_major_columns() -> None:
    obs = make_obs(4)
    d = raw(batch(obs))
    assert d["n_obs"] == 4
    assert d["obs"]["direction"] == obs.direction.astype("<f8").tobytes()  # row-major (4, 3)
    assert d["obs"]["obs_id"] == obs.obs_id.astype("<u8").tobytes()
    assert len(d["obs"]["score"]) == 4 * 4
    assert set(d["obs"]) == {name for name, _ in Observations.CODEC.cols}


def test_unknown_extra_fields_are_ignored() -> None:
    for name, msg in messages(3).items():
        d = raw(msg)
        d["future_field"] = {"x": [1, 2.5, b"\x00"]}
        if "obs" in d and isinstance(d["obs"], dict):
            d["obs"]["future_column"] = b"\x00" * 7
        assert_message_equal(msg, CLASSES[name].from_bytes(enc(d)))


def test_decode_error_api() -> None:
    e = DecodeError("obs.lat", "out of range", 3)
    assert str(e) == "obs.lat[3]: out of range" and isinstance(e, ValueError)
    assert e.as_dict() == {"field": "obs.lat", "reason": "out of range", "index": 3}
    assert DecodeError("v", "missing").as_dict() == {"field": "v", "reason": "missing"}
    reply = ErrorReply.of(e)
    assert (reply.code, reply.field, reply.reason) == ("bad_request", "obs.lat[3]", "out of range")
    assert_message_equal(reply, ErrorReply.from_bytes(reply.to_bytes()))


# --- envelope and framing -------------------------------------------------------------------


@pytest.mark.parametrize("name", ALL)
def test_framing_errors(name: str) -> None:
    cls = CLASSES[name]
    expect(cls, b"", "message")
    expect(cls, b"\xc1", "message")  # the one byte msgpack never uses
    expect(cls, b"\x93\x01\x02", "message")  # truncated array
    expect(cls, b"hello world", "message")
    expect(cls, enc([1, 2, 3]), "message")  # top level not a map
    expect(cls, enc(7), "message")
    expect(cls, enc({1: 2}), "message")  # non-string map key
    expect(cls, enc({"v": 1}) + b"\x00", "message")  # trailing bytes


@pytest.mark.parametrize("name", ALL)
def test_every_prefix_is_a_decode_error(name: str) -> None:
    data = messages(3)[name].to_bytes()  # type: ignore[attr-defined]
    for i in range(len(data)):
        expect(CLASSES[name], data[:i], "message")


@pytest.mark.parametrize("name", ALL)
def test_envelope_errors(name: str) -> None:
    msg, cls = messages(2)[name], CLASSES[name]
    expect(cls, without(msg, "v"), "v")
    expect(cls, with_(msg, v=2), "v")
    expect(cls, with_(msg, v=0), "v")
    expect(cls, with_(msg, v="1"), "v")
    expect(cls, with_(msg, v=1.0), "v")
    expect(cls, with_(msg, v=True), "v")
    expect(cls, without(msg, "type"), "type")
    expect(cls, with_(msg, type="nope"), "type")
    expect(cls, with_(msg, type=b"obs_batch"), "type")
    other = "Stats" if name != "Stats" else "ErrorReply"
    expect(cls, messages(2)[other].to_bytes(), "type")  # type: ignore[attr-defined]


def test_message_larger_than_byte_limit() -> None:
    big = bytes(MAX_MESSAGE_BYTES + 1)
    for cls in CLASSES.values():
        e = expect(cls, big, "message")
        assert "exceeds" in e.reason
    with pytest.raises(DecodeError, match="exceeds"):
        unpack(messages(2)["MapSnapshot"].to_bytes(), max_bytes=100)  # type: ignore[attr-defined]


def test_unpack_rejects_non_bytes() -> None:
    with pytest.raises(DecodeError) as exc:
        unpack("a string")  # type: ignore[arg-type]
    assert exc.value.field == "message"


# --- header fields ------------------------------------------------------------------------------

INT_FIELDS = [
    ("ObservationBatch", ["pass_id", "batch_id", "n_obs"]),
    ("UploadAck", ["batch_id"]),
    ("LogEntry", ["seq", "gseq"]),
    ("LogQuery", ["limit"]),
    ("ObsGroup", ["pass_id", "batch_id", "n_obs"]),
    ("AssocGroup", ["n_links", "n_obs", "n_created"]),
    ("LandmarkUpdates", ["n_landmarks", "n_removed"]),
    ("MapDelta", ["from_version", "to_version", "n_upserts", "n_removed"]),
    ("MapSnapshot", ["version", "n_landmarks"]),
]
STR_FIELDS = [
    ("ObservationBatch", "vehicle_id", ["", "veh 1", "v/1", "x" * 65, "é"]),
    ("UploadAck", "vehicle_id", ["", "a*b"]),
    ("ObsGroup", "vehicle_id", ["", "a$b"]),
    ("LogEntry", "stage", ["", "map", "obs2"]),
    ("LogEntry", "producer", ["", "a b"]),
    ("LogEntry", "tile", ["", "1204", "0" * 25, "12a"]),
    ("LogQuery", "stage", ["", "OBS"]),
    ("MapDelta", "tile", ["", "4", "0" * 25]),
    ("MapSnapshot", "tile", ["", "12 3"]),
    ("ErrorReply", "code", ["", "bad request"]),
    ("ErrorReply", "field", ["", "x" * 201]),
    ("ErrorReply", "reason", ["", "x" * 201]),
    ("Stats", "service", ["", "a/b"]),
    ("Stats", "instance", [""]),
]
FLOAT_FIELDS = [
    ("ObservationBatch", "sent_at"),
    ("UploadAck", "retry_after_s"),
    ("ObsGroup", "received_at"),
    ("MapDelta", "published_at"),
    ("ErrorReply", "retry_after_s"),
    ("Stats", "started_at"),
]


@pytest.mark.parametrize("name,field", [(n, f) for n, fs in INT_FIELDS for f in fs])
def test_int_header_fields(name: str, field: str) -> None:
    msg, cls = messages(2)[name], CLASSES[name]
    good = raw(msg)[field]
    for bad in (str(good), float(good), True, False, None, -1, b"\x01", [good]):
        expect(cls, with_(msg, **{field: bad}), field)


@pytest.mark.parametrize("name,field,bad_values", STR_FIELDS)
def test_str_header_fields(name: str, field: str, bad_values: list[str]) -> None:
    msg, cls = messages(2)[name], CLASSES[name]
    for bad in [5, 1.5, True, None, b"veh-1", ["veh-1"], *bad_values]:
        expect(cls, with_(msg, **{field: bad}), field)


@pytest.mark.parametrize("name,field", FLOAT_FIELDS)
def test_float_header_fields(name: str, field: str) -> None:
    msg, cls = messages(2)[name], CLASSES[name]
    for bad in ("1.0", True, None, math.nan, math.inf, -math.inf, -1.0, 1e12, b"1"):
        expect(cls, with_(msg, **{field: bad}), field)
    # an integer is a valid number
    assert getattr(cls.from_bytes(with_(msg, **{field: 3})), field) == 3.0


def _optional(name: str, key: str) -> bool:
    return (name, key) in {
        ("UploadAck", "error"),
        ("AssocGroup", "merged_into"),
        ("AssocGroup", "held"),
        ("ErrorReply", "retry_after_s"),
    }


def _missing_cases() -> list:
    cases = []
    for name, msg in messages(2).items():
        for key in raw(msg):
            if key in ("v", "type") or _optional(name, key):
                continue
            cases.append(pytest.param(name, key, id=f"{name}-{key}"))
    return cases


@pytest.mark.parametrize("name,key", _missing_cases())
def test_missing_field_is_named(name: str, key: str) -> None:
    expect(CLASSES[name], without(messages(2)[name], key), key)


def test_error_reply_retry_after_is_optional_and_sent_only_when_set() -> None:
    msg = messages(2)["ErrorReply"]
    assert ErrorReply.from_bytes(msg.to_bytes()).retry_after_s == 2.5
    old = ErrorReply.from_bytes(without(msg, "retry_after_s"))  # an older service's error
    assert (old.code, old.field, old.retry_after_s) == ("rate", "snapshot.client", 0.0)
    plain = ErrorReply("bad_request", "tile", "names no tile")
    assert "retry_after_s" not in raw(plain)  # encoded as an older service did
    assert raw(plain) == {
        "v": 1,
        "type": "error",
        "code": "bad_request",
        "field": "tile",
        "reason": "names no tile",
    }
    assert_message_equal(plain, ErrorReply.from_bytes(plain.to_bytes()))
    assert ErrorReply.from_bytes(with_(msg, retry_after_s=86400.0)).retry_after_s == 86400.0
    expect(ErrorReply, with_(msg, retry_after_s=86400.5), "retry_after_s")


def test_optional_error_in_upload_ack() -> None:
    msg = messages(2)["UploadAck"]
    assert UploadAck.from_bytes(without(msg, "error")).error is None
    assert UploadAck.from_bytes(with_(msg, error=None)).error is None


@pytest.mark.parametrize(
    "name,field,value",
    [
        ("ObservationBatch", "vehicle_id", "veh-1\n"),
        ("MapDelta", "tile", "1202\n"),
        ("LogEntry", "stage", "obs\n"),
    ],
)
def test_trailing_newline_rejected(name: str, field: str, value: str) -> None:
    expect(CLASSES[name], with_(messages(2)[name], **{field: value}), field)


# --- columns --------------------------------------------------------------------------------------

TABLES = [
    ("ObservationBatch", "obs", Observations),
    ("ObsGroup", "obs", Observations),
    ("AssocGroup", "links", Links),
    ("AssocGroup", "obs", Observations),
    ("AssocGroup", "created", NewLandmarks),
    ("LandmarkUpdates", "landmarks", Landmarks),
    ("LandmarkUpdates", "removed", Removals),
    ("MapDelta", "upserts", MapLandmarks),
    ("MapDelta", "removed", Removals),
    ("MapSnapshot", "landmarks", MapLandmarks),
]


@pytest.mark.parametrize("name,tname,tcls", TABLES)
def test_column_structure_errors(name: str, tname: str, tcls: type) -> None:
    msg, cls = messages(3)[name], CLASSES[name]
    expect(cls, with_(msg, **{tname: [1, 2]}), tname)  # table not a map
    expect(cls, without(msg, tname), tname)
    for col, c in tcls.CODEC.cols:
        field = f"{tname}.{col}"
        for bad in (lambda b: b[:-1], lambda b: b + b"\x00", lambda b: b""):
            d = raw(msg)
            d[tname][col] = bad(d[tname][col])
            expect(cls, enc(d), field)
        for bad in ([1.0, 2.0, 3.0], "abc", 7, None):
            d = raw(msg)
            d[tname][col] = bad
            expect(cls, enc(d), field)
        d = raw(msg)
        del d[tname][col]
        if c.optional:  # a column added later: an older sender's message reads as zeros
            got = getattr(cls.from_bytes(enc(d)), tname)
            assert not getattr(got, col).any() and len(got) == len(getattr(msg, tname))
        else:
            expect(cls, enc(d), field)
    # a row count that disagrees with the columns: the first column reports it
    d = raw(msg)
    d[f"n_{tname}"] += 1
    expect(cls, enc(d), f"{tname}.{tcls.CODEC.cols[0][0]}")


def test_oversized_batch() -> None:
    msg = batch(make_obs(5))
    expect(ObservationBatch, msg.to_bytes(), "n_obs", max_obs=4)
    expect(ObservationBatch, msg.to_bytes(), "n_obs", max_obs=0)
    with pytest.raises(DecodeError) as exc:
        ObservationBatch.from_bytes_partial(msg.to_bytes(), max_obs=4)
    assert exc.value.field == "n_obs"
    assert len(ObservationBatch.from_bytes(msg.to_bytes(), max_obs=5).obs) == 5
    # the declared count is checked before the columns are looked at
    expect(ObservationBatch, with_(msg, n_obs=10_001, obs={}), "n_obs")


# --- per-row values of Observations ---------------------------------------------------------

FLOAT_COLS = [name for name, c in Observations.CODEC.cols if c.is_float]


def _set(obs: Observations, col: str, i: int, value) -> Observations:
    a = getattr(obs, col)
    if col == "direction":
        a[i] = value if np.ndim(value) else [value, 0.0, 0.0]
    else:
        a[i] = value
    return obs


def _check_row_rejected(obs: Observations, row: int, field: str) -> None:
    data = batch(obs).to_bytes()
    e = expect(ObservationBatch, data, field)
    assert e.index == row
    good, rejected = ObservationBatch.from_bytes_partial(data)
    assert [(r.obs_id, r.field) for r in rejected] == [(int(obs.obs_id[row]), field)]
    assert rejected[0].reason
    keep = np.ones(len(obs), bool)
    keep[row] = False
    assert_table_equal(obs.take(keep), good.obs)
    assert (good.vehicle_id, good.pass_id, good.batch_id, good.sent_at) == ("veh-1", 1, 2, T0)


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf], ids=["nan", "inf", "-inf"])
@pytest.mark.parametrize("col", FLOAT_COLS)
def test_non_finite_float_rejects_row(col: str, value: float) -> None:
    _check_row_rejected(_set(make_obs(6), col, 3, value), 3, f"obs.{col}")


def _spec(s: str) -> list:
    """'col=value' items; a value with commas is a vector (the direction)."""
    out = []
    for item in s.split():
        col, v = item.split("=")
        value = np.array([float(x) for x in v.split(",")]) if "," in v else float(v)
        out.append(pytest.param(col, value, id=item))
    return out


BAD_VALUES = _spec(
    "lat=90.5 lat=-91 lon=181 lon=-180.5 h=-1001 h=10001 t=-1 t=5e9 direction=1.01,0,0 "
    "direction=0,0,0 direction=0.6,0.8,0.01 sigma_az=0 sigma_az=-0.01 sigma_az=4 sigma_el=0 "
    "sigma_el=-1e-9 sigma_pos_h=0 sigma_pos_h=-2 sigma_pos_h=1001 sigma_pos_v=0 range_m=-0.5 "
    "sigma_range_m=-1 score=1.01 score=-0.01 sign_class=0 sign_class=999"
)
GOOD_EDGES = _spec(
    "lat=90 lat=-90 lon=180 lon=-180 range_m=0 sigma_range_m=0 score=0 score=1 "
    f"sigma_az={math.pi!r} direction={1 + 5e-7!r},0,0 t=0"
)


@pytest.mark.parametrize("col,value", BAD_VALUES)
def test_out_of_range_value_rejects_row(col: str, value) -> None:
    _check_row_rejected(_set(make_obs(6), col, 2, value), 2, f"obs.{col}")


@pytest.mark.parametrize("col,value", GOOD_EDGES)
def test_boundary_values_are_accepted(col: str, value) -> None:
    obs = _set(make_obs(4), col, 1, value)
    assert_table_equal(obs, ObservationBatch.from_bytes(batch(obs).to_bytes()).obs)


def test_duplicate_obs_id_rejects_later_rows() -> None:
    obs = make_obs(6)
    obs.obs_id[4] = obs.obs_id[1]
    obs.obs_id[5] = obs.obs_id[1]
    data = batch(obs).to_bytes()
    e = expect(ObservationBatch, data, "obs.obs_id")
    assert e.index == 4
    good, rejected = ObservationBatch.from_bytes_partial(data)
    assert [(r.obs_id, r.field) for r in rejected] == [(int(obs.obs_id[1]), "obs.obs_id")] * 2
    assert_table_equal(obs.take(np.arange(4)), good.obs)


def test_partial_decode_several_bad_rows() -> None:
    obs = make_obs(12, seed=9)
    obs.lat[1] = math.nan
    obs.sign_class[4] = 77
    obs.obs_id[7] = obs.obs_id[0]
    obs.score[9] = 2.0
    obs.direction[9] = 0.0  # two problems in one row: the first failing column is reported
    obs.sigma_az[11] = 0.0
    good, rejected = ObservationBatch.from_bytes_partial(batch(obs).to_bytes())
    got = {(r.obs_id, r.field) for r in rejected}
    oid = obs.obs_id
    assert got == {
        (int(oid[1]), "obs.lat"),
        (int(oid[4]), "obs.sign_class"),
        (int(oid[7]), "obs.obs_id"),
        (int(oid[9]), "obs.direction"),
        (int(oid[11]), "obs.sigma_az"),
    }
    keep = np.ones(12, bool)
    keep[[1, 4, 7, 9, 11]] = False
    assert_table_equal(obs.take(keep), good.obs)
    expect(ObservationBatch, batch(obs).to_bytes(), "obs.lat").index == 1  # noqa: B015


def test_custom_catalog_in_batch_decode() -> None:
    obs = make_obs(3)
    obs.sign_class[:] = 4
    data = batch(obs).to_bytes()
    from hdmap.geo.signs import SignCatalog, SignClass

    only_stop = SignCatalog([SignClass(1, "stop", 0.75)])
    e = expect(ObservationBatch, data, "obs.sign_class", catalog=only_stop)
    assert e.index == 0


def test_duplicate_of_a_rejected_row_is_also_rejected() -> None:
    obs = make_obs(4)
    obs.lat[0] = math.nan
    obs.obs_id[2] = obs.obs_id[0]
    good, rejected = ObservationBatch.from_bytes_partial(batch(obs).to_bytes())
    oid = int(obs.obs_id[0])
    assert [(r.obs_id, r.field) for r in rejected] == [(oid, "obs.lat"), (oid, "obs.obs_id")]
    assert oid not in good.obs.obs_id.tolist()


# --- other tables and messages -----------------------------------------------------------------


@pytest.mark.parametrize("name,tname", [("ObsGroup", "obs"), ("AssocGroup", "obs")])
def test_observation_rows_are_strict_in_internal_messages(name: str, tname: str) -> None:
    msg = messages(4)[name]
    getattr(msg, tname).lat[2] = math.nan
    e = expect(CLASSES[name], msg.to_bytes(), f"{tname}.lat")  # type: ignore[attr-defined]
    assert e.index == 2


@pytest.mark.parametrize(
    "name,tname",
    [("MapDelta", "upserts"), ("MapSnapshot", "landmarks"), ("LandmarkUpdates", "landmarks")],
)
def test_landmark_rows_are_checked(name: str, tname: str) -> None:
    for col, value in [
        ("status", 3),
        ("lat", 91.0),
        ("lon", math.nan),
        ("h", -2000.0),
        ("updated_at", -1.0),
    ]:
        msg = messages(4)[name]
        getattr(getattr(msg, tname), col)[1] = value
        e = expect(CLASSES[name], msg.to_bytes(), f"{tname}.{col}")  # type: ignore[attr-defined]
        assert e.index == 1
    msg = messages(4)[name]
    getattr(msg, tname).cov[3, 5] = math.inf
    expect(CLASSES[name], msg.to_bytes(), f"{tname}.cov")  # type: ignore[attr-defined]


@pytest.mark.parametrize("name,tname", [("MapDelta", "upserts"), ("MapSnapshot", "landmarks")])
def test_facing_round_trips_and_bad_facings_are_refused(name: str, tname: str) -> None:
    msg = messages(7)[name]
    got = getattr(CLASSES[name].from_bytes(msg.to_bytes()), tname)  # type: ignore[attr-defined]
    sent = getattr(msg, tname)
    np.testing.assert_array_equal(got.facing_deg, sent.facing_deg)
    np.testing.assert_array_equal(got.facing_sigma_deg, sent.facing_sigma_deg)
    az, sigma, known = got.facing()
    assert known.tolist() == (np.arange(7) % 3 != 2).tolist()
    assert np.isnan(az[~known]).all() and np.isnan(sigma[~known]).all()
    for col, value in [
        ("facing_deg", math.nan),
        ("facing_deg", -0.5),
        ("facing_deg", 360.5),
        ("facing_sigma_deg", math.inf),
        ("facing_sigma_deg", -1.0),
        ("facing_sigma_deg", 181.0),
    ]:
        msg = messages(4)[name]
        getattr(getattr(msg, tname), col)[1] = value
        e = expect(CLASSES[name], msg.to_bytes(), f"{tname}.{col}")  # type: ignore[attr-defined]
        assert e.index == 1


@pytest.mark.parametrize("name,tname", [("MapDelta", "upserts"), ("MapSnapshot", "landmarks")])
def test_a_message_without_facing_columns_reads_as_facing_unknown(name: str, tname: str) -> None:
    d = raw(messages(4)[name])  # as an older publisher sends it
    for col in ("facing_deg", "facing_sigma_deg"):
        del d[tname][col]
    got = getattr(CLASSES[name].from_bytes(enc(d)), tname)  # type: ignore[attr-defined]
    assert isinstance(got, MapLandmarks) and not got.facing()[2].any()
    np.testing.assert_array_equal(got.lat, getattr(messages(4)[name], tname).lat)


def test_updates_carry_the_facing_to_the_publisher() -> None:
    upd = LandmarkUpdates(make_map_landmarks(5), make_removals(2))
    data = upd.to_bytes()
    assert not hasattr(LandmarkUpdates.from_bytes(data).landmarks, "facing_deg")  # ignored
    got = updates_from_bytes(data)
    np.testing.assert_array_equal(got.landmarks.facing_sigma_deg, upd.landmarks.facing_sigma_deg)
    old = LandmarkUpdates(make_landmarks(3), make_removals(0)).to_bytes()  # an older solver
    assert not updates_from_bytes(old).landmarks.facing()[2].any()
    d = raw(upd)
    d["landmarks"]["facing_deg"] = np.array([1, 2, 3, 4, np.nan], "<f4").tobytes()
    with pytest.raises(DecodeError) as exc:
        updates_from_bytes(enc(d))
    assert (exc.value.field, exc.value.index) == ("landmarks.facing_deg", 4)


def test_new_landmarks_rows_are_checked() -> None:
    msg = messages(4)["AssocGroup"]
    msg.created.lat[0] = -90.01  # type: ignore[attr-defined]
    expect(AssocGroup, msg.to_bytes(), "created.lat")  # type: ignore[attr-defined]


def test_assoc_group_consistency() -> None:
    msg = messages(4)["AssocGroup"]
    d = raw(msg)
    d["vehicles"] = ["veh-1"]  # links refer to vehicles 0..2
    expect(AssocGroup, enc(d), "links.vehicle")
    expect(AssocGroup, with_(msg, vehicles=["a", 5, "c"]), "vehicles")
    expect(AssocGroup, with_(msg, vehicles="veh-1"), "vehicles")
    other = raw(messages(3)["AssocGroup"])
    d = raw(msg)
    d["links"], d["n_links"] = other["links"], other["n_links"]
    expect(AssocGroup, enc(d), "links")
    for bad in (b"\x00" * 7, [1, 2], None):
        expect(AssocGroup, with_(msg, retired=bad), "retired")
        expect(AssocGroup, with_(msg, merged_into=bad), "merged_into")
    ids = np.array([5, 6], "<u8")
    merged = with_(msg, retired=ids.tobytes(), merged_into=ids[::-1].tobytes())
    assert AssocGroup.from_bytes(merged).merged_into.tolist() == [6, 5]
    expect(
        AssocGroup, with_(msg, retired=ids[:1].tobytes(), merged_into=ids.tobytes()), "merged_into"
    )
    expect(AssocGroup, with_(msg, retired=ids.tobytes(), merged_into=ids.tobytes()), "merged_into")
    d = raw(msg)
    for key in ("merged_into", "held", "trust", "n_trust"):
        del d[key]  # written before the fields existed
    old = AssocGroup.from_bytes(enc(d))
    assert old.merged_into.size == old.held.size == len(old.trust) == 0
    for bad in (b"\x01" * 3, b"\x02" * 4, [1, 0, 1, 0]):
        expect(AssocGroup, with_(msg, held=bad), "held")
    d = raw(msg)
    d["trust"]["action"] = np.array([1, 3], np.uint8).tobytes()
    expect(AssocGroup, enc(d), "trust.action")
    d = raw(msg)
    d["trust"]["vehicle"] = np.array([0, 3], "<u4").tobytes()
    expect(AssocGroup, enc(d), "trust.vehicle")


def test_map_delta_versions() -> None:
    msg = messages(2)["MapDelta"]
    expect(MapDelta, with_(msg, from_version=42, to_version=42), "to_version")
    expect(MapDelta, with_(msg, from_version=43, to_version=42), "to_version")
    assert MapDelta.from_bytes(with_(msg, from_version=0, to_version=2**64 - 1)).to_version > 0


def test_upload_ack_errors() -> None:
    msg = messages(2)["UploadAck"]
    for field in ("accepted", "duplicates"):
        expect(UploadAck, with_(msg, **{field: b"\x00" * 9}), field)
        expect(UploadAck, with_(msg, **{field: [1, 2]}), field)
    for bad_item in (
        [1, "f"],
        [-1, "f", "r"],
        ["1", "f", "r"],
        [True, "f", "r"],
        [1, 2, "r"],
        [1, "f", None],
        "x",
        [1, "f", "r", 4],
    ):
        e = expect(UploadAck, with_(msg, rejected=[[1, "a", "b"], bad_item]), "rejected")
        assert e.index == 1
    expect(UploadAck, with_(msg, rejected={"a": 1}), "rejected")
    expect(UploadAck, with_(msg, error="boom"), "error")
    expect(UploadAck, with_(msg, error={"field": "x"}), "error")
    expect(UploadAck, with_(msg, error={"field": 1, "reason": "r"}), "error")
    expect(UploadAck, with_(msg, retry_after_s=86401.0), "retry_after_s")
    assert UploadAck.from_bytes(with_(msg, error={"field": "f", "reason": "r"})).error.index is None
    expect(UploadAck, with_(msg, rejected=[[1, "a", "b"]] * 11), "rejected", max_rows=10)
    expect(UploadAck, with_(msg, accepted=bytes(88)), "accepted", max_rows=10)


def test_log_entry_and_query_errors() -> None:
    entry = messages(2)["LogEntry"]
    expect(LogEntry, with_(entry, seq=0), "seq")
    expect(LogEntry, with_(entry, gseq=0), "gseq")
    expect(LogEntry, with_(entry, body="text"), "body")
    q = messages(2)["LogQuery"]
    expect(LogQuery, with_(q, offsets=[1]), "offsets")
    expect(LogQuery, with_(q, offsets={"p": [1]}), "offsets")
    expect(LogQuery, with_(q, offsets={"p": {"1201": -1}}), "offsets.p")
    expect(LogQuery, with_(q, offsets={"p": {"1201": "3"}}), "offsets.p")
    expect(LogQuery, with_(q, offsets={"p": {"1201": True}}), "offsets.p")
    expect(LogQuery, with_(q, offsets={b"p": {}}), "offsets")
    for bad in ("120", [1], ["12a"], ["4"], [None]):
        expect(LogQuery, with_(q, prefixes=bad), "prefixes")
    assert LogQuery.from_bytes(with_(q, prefixes=[])).prefixes == []
    expect(LogQuery, with_(q, limit=0), "limit")
    expect(LogQuery, with_(q, limit=100_001), "limit")


def test_stats_errors() -> None:
    s = messages(2)["Stats"]
    expect(Stats, with_(s, counters={"a": "1"}), "counters")
    expect(Stats, with_(s, counters={"a": True}), "counters")
    expect(Stats, with_(s, counters=[1]), "counters")
    expect(Stats, with_(s, rejected={"a": None}), "rejected")
    expect(Stats, with_(s, region=[1]), "region")
    expect(Stats, with_(s, region="120"), "region")
    expect(Stats, with_(s, region=["1"] * 1001), "region")


def test_error_reply_of_any_decode_error_is_decodable() -> None:
    q = LogQuery("obs", {"p" * 300: {"1201": -1}})
    with pytest.raises(DecodeError) as exc:
        LogQuery.from_bytes(q.to_bytes())
    reply = ErrorReply.of(exc.value)
    assert ErrorReply.from_bytes(reply.to_bytes()).code == "bad_request"
