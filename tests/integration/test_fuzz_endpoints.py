"""A hostile world: bounded fuzz of the service endpoints a client queries.

Inputs are random bytes and *mutated valid messages*: flipped/truncated bytes, header
fields of the wrong type or range, NaN/inf/out-of-range cells, zero-length directions,
unknown sign classes, duplicate ids, timestamps far in the future or past, huge
arrays, columns of the wrong length, wrong message types and versions, coordinates
outside the tile a message was sent to.

Properties, over a real stack (router + the four services as processes): the upload
queryable, the map snapshot queryable, the log replay queryables, the stats
queryables and the handover queryables. Every input gets a clear error naming the
field or is counted in the service's ``Stats.rejected`` by reason; afterwards every
process is alive, has its liveliness token and answers stats, and an honest vehicle
uploading *during* the fuzz had every upload acknowledged and applied by the matcher.

The decoders are fuzzed in tests/unit/test_fuzz_decoders.py, the internal stage
subscribers in test_fuzz_internal.py; the helpers shared with the latter are in
fuzz_support.py.

Hypothesis runs derandomized, without a database, with a bounded number of examples.
"""

from __future__ import annotations

import math
import time
from collections import Counter
from typing import Any

import msgpack
import numpy as np
import pytest
import zenoh
from hypothesis import given
from hypothesis import strategies as st

from hdmap.geo.tiles import route_rays
from hdmap.ops.quiesce import totals, wait_quiet
from hdmap.ops.stack import SERVICE_NAMES
from hdmap.ops.status import collect
from hdmap.runtime.bus import query
from schemas import (
    DecodeError,
    ErrorReply,
    HandoverReply,
    HandoverRequest,
    LogEntry,
    LogQuery,
    MapSnapshot,
    ObservationBatch,
    Observations,
    Rejection,
    Stats,
    UploadAck,
    keys,
)
from services.ingest.admission import AdmissionPolicy, admit, check_header
from tests.integration.fuzz_support import (
    assert_all_alive,
    rejected_delta,
    stats_by_service,
)
from tests.support.hostile import (
    FUZZ,
    Case,
    _cell,
    _ids,
    _with,
    hostile,
    named_batches,
    observations,
)

# --- the upload queryable -----------------------------------------------------------------------


def boundary_uploads() -> list[tuple[str, dict, Observations]]:
    """(name, header overrides, observations) of uploads at the edges of the valid ranges."""
    out: list[tuple[str, dict, Observations]] = []

    def obs(**cols: Any) -> Observations:
        o = observations(6, seed=len(out))
        for k, v in cols.items():
            getattr(o, k)[:] = v
        return o

    base = obs()
    out += [
        ("pass_id 2^64-1 (refused: signed 64-bit downstream)", {"pass_id": 2**64 - 1}, base),
        ("pass_id 2^63 (refused)", {"pass_id": 2**63}, base),
        ("pass_id 2^63-1", {"pass_id": 2**63 - 1}, obs()),
        ("batch_id 2^64-1", {"batch_id": 2**64 - 1}, obs()),
        ("obs_id near 2^64", {}, obs(obs_id=np.arange(2**64 - 7, 2**64 - 1, dtype=np.uint64))),
        ("image 2^32-1", {}, obs(image=2**32 - 1)),
        ("north pole", {}, obs(lat=90.0)),
        ("south pole", {}, obs(lat=-90.0)),
        ("mercator edge", {}, obs(lat=85.06)),
        ("antimeridian east", {}, obs(lon=180.0)),
        ("antimeridian west", {}, obs(lon=-180.0)),
        ("straight up, 10 km", {}, obs(direction=[0.0, 0.0, 1.0], range_m=10_000.0)),
        ("straight down from -1000 m", {}, obs(direction=[0.0, 0.0, -1.0], h=-1000.0)),
        (
            "sigmas at their maximum",
            {},
            obs(sigma_az=math.pi, sigma_el=math.pi, sigma_pos_h=1000.0, sigma_pos_v=1000.0),
        ),
        (
            "sigmas denormal",
            {},
            obs(sigma_az=5e-324, sigma_el=5e-324, sigma_pos_h=5e-324, sigma_pos_v=5e-324),
        ),
        ("range 10 km, sigma 0", {}, obs(range_m=10_000.0, sigma_range_m=0.0)),
        ("score 0", {}, obs(score=0.0)),
    ]
    return out


# --- the upload queryable -----------------------------------------------------------------------

FUZZ_VEHICLES = [f"fz-{k}" for k in range(16)]


@st.composite
def upload_case(draw) -> tuple[str, Case]:
    """(key vehicle, hostile batch) with fresh ids; mostly sent on the batch's own key."""
    now = time.time()
    vehicle = draw(st.sampled_from(FUZZ_VEHICLES))
    obs = observations(draw(st.integers(1, 12)), seed=draw(st.integers(0, 3)))
    base = ObservationBatch(vehicle, draw(st.integers(0, 9)), next(_ids), now, obs).to_bytes()
    case = draw(hostile(base, now, huge_rows=(500, 10_001)))
    key = draw(st.sampled_from([vehicle] * 6 + ["fz-other", "a" * 65, "veh 1", "*", "**"]))
    return key, case


def expected_ack(key: str, case: Case, now: float) -> tuple[str | None, list[Rejection]]:
    """(error field, rejected rows) ingest must answer, from the reference decoder."""
    if key in ("*", "**", "veh 1") or len(key) > 64:
        return "key", []
    try:
        batch, rejected = ObservationBatch.from_bytes_partial(case.data)
    except DecodeError as e:
        return e.field, []
    if batch.vehicle_id != key:
        return "vehicle_id", []
    try:
        check_header(batch)
    except DecodeError as e:
        return e.field, []
    tiles = route_rays(
        batch.obs.lat, batch.obs.lon, batch.obs.h, batch.obs.direction, batch.obs.range_m
    )
    _, more = admit(batch.obs, AdmissionPolicy(), now, tiles)
    return None, rejected + more


def check_ack(key: str, case: Case, replies, sent_at: float) -> Counter:
    """Check ingest's answer to one hostile upload; the stats reasons it implies."""
    assert len(replies) == 1, f"{case}: {len(replies)} replies"
    _k, ok, err = replies[0]
    assert ok is not None, f"{case}: error reply {err!r}"
    ack = UploadAck.from_bytes(ok)  # every answer decodes, also for hostile keys
    want_field, want_rows = expected_ack(key, case, sent_at)
    if ack.error is not None:
        if ack.error.field == "rate":
            assert ack.retry_after_s > 0
            return Counter({"rate_limited": 1})
        if ack.error.field == "vehicle.new" and want_field is None:  # a well-formed batch
            assert ack.retry_after_s > 0 and len(ack.accepted) == 0
            return Counter({"vehicle.new": 1})
        assert ack.error.field == want_field, f"{case} on {key!r}: {ack.error}"
        assert case.explains(want_field) or want_field in ("key", "vehicle_id"), case
        assert len(ack.accepted) == 0 and ack.retry_after_s == 0
        return Counter({f"batch.{want_field}": 1})
    assert want_field is None, f"{case} on {key!r}: accepted, expected error {want_field}"
    got = sorted((r.obs_id, r.field) for r in ack.rejected)
    assert got == sorted((r.obs_id, r.field) for r in want_rows), case
    if case.must_fail or case.admission:  # the mutated row is among the rejected
        assert any(r.field == case.field for r in ack.rejected), (case, ack.rejected)
    return Counter(r.field for r in ack.rejected)


@pytest.mark.integration
def test_fuzz_upload_endpoint(live) -> None:
    stack, s, honest = live
    before = stats_by_service(s)["ingest"]
    reasons: Counter = Counter()

    @FUZZ
    @given(upload_case())
    def run(kc: tuple[str, Case]) -> None:
        key, case = kc
        sent_at = time.time()
        replies = query(s, keys.upload(key), case.data or None, timeout=20.0)
        reasons.update(check_ack(key, case, replies, sent_at))

    run()

    now = time.time()
    for name, payload, field, row in named_batches(now):
        m = msgpack.unpackb(payload) if field != "message" else None
        key = m["vehicle_id"] if isinstance(m, dict) and field != "vehicle_id" else "fz-0"
        case = Case(payload, name, "obs_batch", field, row, True)
        got = check_ack(key, case, query(s, keys.upload(key), payload or None, timeout=20.0), now)
        assert got == Counter({f"batch.{field}" if row is None else field: 1}), (name, got)
        reasons.update(got)
    for key, field in [("fz-other", "vehicle_id"), ("a" * 65, "key"), ("*", "key")]:
        payload = ObservationBatch("fz-0", 1, 1, now, observations(2)).to_bytes()
        case = Case(payload, f"sent on {key}", "obs_batch")
        got = check_ack(key, case, query(s, keys.upload(key), payload), now)
        assert got == Counter({f"batch.{field}": 1}), (key, got)
        reasons.update(got)
    future = ObservationBatch("fz-0", 1, 1, now, observations(2)).to_bytes()
    for value in (now + 3600.0, now - 40 * 86400.0, 1.0):
        payload = _cell(msgpack.unpackb(future), "obs", "t", 1, value)
        case = Case(payload, f"t={value}", "obs_batch", "obs.t", 1, False, True)
        got = check_ack("fz-0", case, query(s, keys.upload("fz-0"), payload), now)
        assert got == Counter({"obs.t": 1}), got
        reasons.update(got)

    for name, header, obs in boundary_uploads():  # valid extremes: accepted, and no stage chokes
        kw = {"pass_id": 1, "batch_id": 1, **header}
        batch = ObservationBatch("fz-edge", kw["pass_id"], kw["batch_id"], time.time(), obs)
        ack = UploadAck.from_bytes(query(s, keys.upload("fz-edge"), batch.to_bytes())[0][1])
        if header.get("pass_id", 0) > 2**63 - 1:
            assert ack.error is not None and ack.error.field == "pass_id", (name, ack)
            reasons["batch.pass_id"] += 1
        else:
            assert ack.error is None and len(ack.accepted) == len(obs) and not ack.rejected, name

    honest.finish()
    stats = assert_all_alive(stack, s)
    assert rejected_delta(before, stats["ingest"]) == +reasons  # every refusal counted by reason
    honest.check(stack)
    # everything ingest accepted reaches the matcher, and no stage choked on it
    assert wait_quiet(s, timeout=120.0), totals(collect(s))
    t = totals(collect(s))
    assert t["matcher"]["received"] == t["ingest"]["accepted"]
    for svc in ("matcher", "solver", "publisher"):
        assert t[svc].get("entries_failed", 0) == 0, (svc, t[svc])


# --- snapshot, log replay and stats queryables ----------------------------------------------------

CHUNK = st.text("abcXYZ0123456789_.-", min_size=1, max_size=30)
QUADKEY = st.text("0123", min_size=1, max_size=24)


def _replies(s, selector: str, payload: bytes | None):
    try:
        return query(s, selector, payload, timeout=10.0)
    except zenoh.ZError:  # a selector Zenoh itself refuses never reaches a service
        return None


@st.composite
def log_query_payload(draw, producers: list[str]) -> tuple[bytes | None, str]:
    now = time.time()
    stage = draw(st.sampled_from(["obs", "assoc", "update", "nope"]))
    offsets = draw(
        st.dictionaries(
            st.sampled_from([*producers, "fz-producer"]),
            st.dictionaries(QUADKEY, st.sampled_from([0, 1, 2, 2**63 - 1]), max_size=3),
            max_size=2,
        )
    )
    prefixes = draw(st.lists(st.sampled_from(["", "1", "12", "1201", "0", "3"]), max_size=3))
    limit = draw(st.integers(1, 50))
    base = msgpack.packb(
        {
            "v": 1,
            "type": "log_query",
            "stage": stage,
            "offsets": offsets,
            "prefixes": prefixes,
            "limit": limit,
        }
    )
    how = draw(st.sampled_from(["valid", "valid", "hostile", "hostile", "none"]))
    if how == "valid":
        return base, "valid"
    if how == "none":
        return None, "no payload"
    return draw(hostile(base, now)).data, "hostile"


def check_log_replies(replies, payload: bytes | None) -> None:
    """Replay answers: entries of the serving stage, or errors naming the field."""
    try:
        req = LogQuery.from_bytes(payload or b"")
        want_err = None
    except DecodeError as e:
        req, want_err = None, ErrorReply.of(e).field
    for key, ok, err in replies:
        if ok is not None:
            e = LogEntry.from_bytes(ok)
            assert req is not None and e.stage == req.stage, (req, e)
            assert key == keys.log(e.stage, e.producer, e.tile)
        else:
            er = ErrorReply.from_bytes(err)
            assert er.field, er
            assert er.field == (want_err or "stage"), (er, want_err, req)
    if req is not None:
        per_producer = Counter(LogEntry.from_bytes(ok).producer for _k, ok, _ in replies if ok)
        assert all(v <= req.limit for v in per_producer.values())


@pytest.mark.integration
def test_fuzz_query_endpoints(live) -> None:
    stack, s, honest = live
    time.sleep(1.0)  # some honest entries in the logs to replay
    stats0 = stats_by_service(s)
    producers = {st_.service: st_.instance for st_ in stats0.values()}
    stages = {"ingest": "obs", "matcher": "assoc", "solver": "update"}
    served = {producers[svc]: stage for svc, stage in stages.items()}

    @FUZZ
    @given(
        st.one_of(QUADKEY, CHUNK, st.sampled_from(["*", "**", "12$*", "0123456701234567"])),
        st.one_of(st.none(), st.binary(max_size=64)),
    )
    def snapshots(chunk: str, payload: bytes | None) -> None:
        replies = _replies(s, keys.map_snapshot(chunk), payload)
        if replies is None:
            return
        concrete = "*" not in chunk
        if concrete:
            assert len(replies) == 1, (chunk, replies)
        for _k, ok, err in replies:
            if ok is not None:
                snap = MapSnapshot.from_bytes(ok)
                assert snap.tile == chunk, (chunk, snap.tile)
            else:
                assert ErrorReply.from_bytes(err).field == "tile", chunk

    @FUZZ
    @given(
        st.sampled_from(["obs", "assoc", "update", "*", "*", "nope"]),
        st.sampled_from(["*", "*", *served, "fz-producer"]),
        st.sampled_from(["*", "**", "1$*", "12$*"]) | QUADKEY | CHUNK,
        log_query_payload(sorted(served)),
    )
    def replays(stage: str, producer: str, tile: str, pq: tuple[bytes | None, str]) -> None:
        payload, _how = pq
        replies = _replies(s, keys.log(stage, producer, tile), payload)
        if replies is not None:
            check_log_replies(replies, payload)

    @FUZZ
    @given(
        st.sampled_from(["*", "**", *SERVICE_NAMES, "nope"]),
        st.one_of(st.none(), st.binary(max_size=64), st.just(b"\xc1" * 1000)),
    )
    def stats(service: str, payload: bytes | None) -> None:
        sel = f"{keys.ROOT}/stats/{service}" + ("" if service == "**" else "/*/*")
        replies = _replies(s, sel, payload)
        assert replies is not None
        for _k, ok, _err in replies:
            assert ok is not None
            Stats.from_bytes(ok)
        if service in SERVICE_NAMES:
            assert len(replies) == 1

    @FUZZ
    @given(
        st.sampled_from(["matcher", "solver", "*"]),
        st.sampled_from(["all", "*", "12", "0+1"]),
        st.one_of(
            st.none(),
            st.binary(max_size=64),
            st.just(HandoverRequest("status").to_bytes().replace(b"status", b"stotus")),
            st.just(HandoverRequest("status", 2**51).to_bytes()),
        ),
    )
    def handovers(service: str, region: str, payload: bytes | None) -> None:
        """Never a valid pause or stop (the stack must go on): each answer names a field."""
        replies = _replies(s, keys.handover(service, region), payload)
        for _k, ok, err in replies or []:
            assert ok is None, (service, region, payload)
            assert ErrorReply.from_bytes(err).field in ("message", "v", "type", "op", "offset")

    snapshots()
    replays()
    stats()
    handovers()
    for svc in ("matcher", "solver"):  # still applying: the fuzz paused nothing
        ((_k, ok, _e),) = query(s, keys.handover(svc, "all"), HandoverRequest("status").to_bytes())
        assert not HandoverReply.from_bytes(ok).paused

    # named cases, each with the error it must get
    ingest = producers["ingest"]
    for sel, payload, field in [
        (keys.map_snapshot("abc"), None, "tile"),
        (keys.map_snapshot("0" * 25), None, "tile"),
        (keys.map_snapshot("0124"), None, "tile"),
        (keys.log("obs", ingest, "*"), None, "message"),
        (keys.log("obs", ingest, "*"), b"\xc1", "message"),
        (keys.log("obs", ingest, "*"), LogQuery("assoc", {}, [], 10).to_bytes(), "stage"),
        (keys.log("obs", ingest, "*"), _with(_lq(), limit=0), "limit"),
        (keys.log("obs", ingest, "*"), _with(_lq(), limit=10**6), "limit"),
        (keys.log("obs", ingest, "*"), _with(_lq(), offsets={"veh 1": {}}), "offsets"),
        (keys.log("obs", ingest, "*"), _with(_lq(), offsets={"p": {"12": -1}}), "offsets.p"),
        (keys.log("obs", ingest, "*"), _with(_lq(), offsets={"p": {"x": 1}}), "offsets.p"),
        (keys.log("obs", ingest, "*"), _with(_lq(), prefixes=["9"]), "prefixes[0]"),
        (keys.log("obs", ingest, "*"), _with(_lq(), prefixes=["0"] * 10_001), "prefixes"),
        (keys.log("obs", ingest, "*"), _with(_lq(), v=2), "v"),
    ]:
        replies = query(s, sel, payload, timeout=10.0)
        assert len(replies) == 1 and replies[0][2] is not None, (sel, replies)
        assert ErrorReply.from_bytes(replies[0][2]).field == field, (sel, field)

    honest.finish()
    assert_all_alive(stack, s)
    honest.check(stack)


def _lq() -> dict:
    return msgpack.unpackb(LogQuery("obs", {}, [], 10).to_bytes())
