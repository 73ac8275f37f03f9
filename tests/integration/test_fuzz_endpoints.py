"""A hostile world: bounded fuzz of every decoder and every service endpoint.

Inputs are random bytes and *mutated valid messages*: flipped/truncated bytes, header
fields of the wrong type or range, NaN/inf/out-of-range cells, zero-length directions,
unknown sign classes, duplicate ids, timestamps far in the future or past, huge
arrays, columns of the wrong length, wrong message types and versions, coordinates
outside the tile a message was sent to.

Properties:

- decoders (every message type): the result is a checked message or a
  ``DecodeError`` whose field is the mutated one; a value that is invalid by
  construction is never accepted;
- service endpoints, over a real stack (router + the four services as processes):
  the upload queryable, the map snapshot queryable, the log replay queryables, the
  stats queryables and the internal stage subscribers (forged log entries on the
  obs, assoc and update keys). Every input gets a clear error naming the field or is
  counted in the service's ``Stats.rejected`` by reason (internal entries: also as a
  duplicate, a gap or an applied entry); afterwards every process is alive, has its
  liveliness token and answers stats, and an honest vehicle uploading *during* the fuzz
  had every upload acknowledged and applied by the matcher.

Hypothesis runs derandomized, without a database, with a bounded number of examples.
"""

from __future__ import annotations

import itertools
import math
import sqlite3
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

import msgpack
import numpy as np
import pytest
import zenoh
from hypothesis import given
from hypothesis import strategies as st

from hdmap.geo.tiles import route_rays
from hdmap.ops.quiesce import totals, wait_quiet
from hdmap.ops.stack import SERVICE_NAMES, Stack, tail
from hdmap.ops.status import collect
from hdmap.runtime.bus import Publishers, open_session, query
from hdmap.runtime.store import connect
from hdmap.runtime.stream import LogConsumer
from schemas import (
    AssocGroup,
    DecodeError,
    ErrorReply,
    HandoverReply,
    HandoverRequest,
    LandmarkUpdates,
    LogEntry,
    LogQuery,
    MapSnapshot,
    ObservationBatch,
    Observations,
    ObsGroup,
    Rejection,
    Stats,
    UploadAck,
    keys,
)
from services.ingest.admission import AdmissionPolicy, admit, check_header
from tests.support import wait_until
from tests.support.hostile import (
    FUZZ,
    Case,
    _cell,
    _column,
    _ids,
    _with,
    assoc_group,
    hostile,
    landmark_updates,
    named_batches,
    obs_group,
    observations,
)

# --- the stack --------------------------------------------------------------------------------


def stats_by_service(session) -> dict[str, Stats]:
    return {s.service: s for s in collect(session)}


def assert_all_alive(stack: Stack, session) -> dict[str, Stats]:
    """Every process runs, has its liveliness token and answers stats."""
    for name, p in stack.procs.items():
        assert p.alive, f"{name} died:\n{tail(p.log_path)}"
    alive = {
        str(r.ok.key_expr).split("/")[3]
        for r in session.liveliness().get(f"{keys.ROOT}/alive/**", timeout=5.0)
        if r.ok
    }
    assert alive == set(SERVICE_NAMES)
    stats = stats_by_service(session)
    assert set(stats) == set(SERVICE_NAMES), stats.keys()
    return stats


def read_db(stack: Stack, service: str, sql: str) -> list[tuple]:
    conn = connect(stack.data_dir / f"{service}-all" / "state.sqlite", readonly=True)
    try:
        return conn.execute(sql).fetchall()
    except sqlite3.OperationalError:  # the table does not exist yet
        return []
    finally:
        conn.close()


class HonestVehicle(threading.Thread):
    """Uploads a small valid batch every ``period`` s while the fuzz runs; keeps every ack
    and, from the obs stage, the log entries its observations went out in."""

    def __init__(self, stack: Stack, vehicle: str = "honest-1", period: float = 0.15):
        super().__init__(name=vehicle, daemon=True)
        self.stack, self.vehicle, self.period = stack, vehicle, period
        self.stop = threading.Event()
        self.acks: list[UploadAck] = []
        self.failures: list[str] = []
        self.sent_ids: set[int] = set()
        self.entries: dict[tuple[str, str], int] = {}
        self._lock = threading.Lock()

    def _on_entry(self, sample: zenoh.Sample) -> None:
        try:
            e = LogEntry.from_bytes(sample.payload.to_bytes())
            g = ObsGroup.from_bytes(e.body)
        except DecodeError:
            return
        if g.vehicle_id == self.vehicle:
            with self._lock:
                k = (e.producer, e.tile)
                self.entries[k] = max(self.entries.get(k, 0), e.seq)

    def run(self) -> None:
        with open_session(self.stack.bus) as s:
            sub = s.declare_subscriber(keys.obs("*"), self._on_entry)
            try:
                for batch_id in range(1, 2000):
                    if self.stop.wait(self.period if batch_id > 1 else 0.0):
                        break
                    obs = observations(8, seed=batch_id, lat=60.2, lon=24.9)
                    now = time.time()
                    batch = ObservationBatch(self.vehicle, batch_id, batch_id, now, obs)
                    payload = batch.to_bytes()
                    replies = query(s, keys.upload(self.vehicle), payload, timeout=20.0)
                    oks = [ok for _k, ok, _e in replies if ok is not None]
                    if len(oks) != 1:
                        self.failures.append(f"batch {batch_id}: replies {replies}")
                        continue
                    self.acks.append(UploadAck.from_bytes(oks[0]))
                    self.sent_ids.update(int(i) for i in obs.obs_id)
            except Exception as exc:  # noqa: BLE001 - reported by check(), not lost in the thread
                self.failures.append(repr(exc))
            finally:
                time.sleep(0.3)  # the last entries' live samples
                sub.undeclare()

    def finish(self) -> None:
        self.stop.set()
        self.join(30)
        assert not self.is_alive()

    def check(self, stack: Stack) -> None:
        """Every upload acknowledged in full, and applied by the matcher."""
        assert not self.failures, self.failures[:5]
        assert len(self.acks) >= 3, f"only {len(self.acks)} honest uploads during the fuzz"
        for a in self.acks:
            assert a.error is None and not a.rejected, a
        accepted = {int(i) for a in self.acks for i in a.accepted}
        assert accepted == self.sent_ids
        assert self.entries, "no obs entry of the honest vehicle was published"

        def applied() -> bool:
            done = dict(
                ((p, t), s)
                for p, t, s in read_db(stack, "matcher", "SELECT producer, tile, seq FROM offsets")
            )
            return all(done.get(k, 0) >= s for k, s in self.entries.items())

        assert wait_until(applied, timeout=60.0), "the matcher did not apply the honest uploads"


@pytest.fixture
def live(stack):
    """The whole stack, a client session and an honest vehicle uploading meanwhile."""
    stack.start_all()
    with open_session(stack.bus) as s:
        honest = HonestVehicle(stack)
        honest.start()
        try:
            yield stack, s, honest
        finally:
            honest.stop.set()
            honest.join(30)


def _rejected_delta(before: Stats, after: Stats) -> Counter:
    d = Counter(after.rejected)
    d.subtract(before.rejected)
    return +d


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
    assert _rejected_delta(before, stats["ingest"]) == +reasons  # every refusal counted by reason
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


# --- internal stage subscribers (forged log entries) ---------------------------------------------

CONSUMER = {"obs": "matcher", "assoc": "solver", "update": "publisher"}
UPSTREAM = {"obs": "ingest", "assoc": "matcher", "update": "solver"}
BODY_DECODER: dict[str, Callable[[bytes], Any]] = {
    "obs": ObsGroup.from_bytes,
    "assoc": AssocGroup.from_bytes,
    "update": LandmarkUpdates.from_bytes,
}
_producers = itertools.count(1)


def valid_body(stage: str, now: float, far: bool = False) -> tuple[str, bytes]:
    """(tile, body) of a valid entry of ``stage``; ``far``: its content lies elsewhere."""
    tile, msg = {"obs": obs_group, "assoc": assoc_group, "update": landmark_updates}[stage](now)
    if far:
        tile = "0" * 16  # sent to a tile in the Pacific, about Helsinki
    return tile, msg.to_bytes()


@st.composite
def forged_entry(draw, stage: str) -> Case:
    """A log entry of a fresh producer, hostile in its envelope or in its body."""
    now = time.time()
    tile, body = valid_body(stage, now, far=draw(st.booleans()))
    if draw(st.booleans()):
        huge = (200, 1000) if stage == "obs" else (2000, 20_000)
        body = draw(hostile(body, now, huge_rows=huge)).data
    entry = LogEntry(stage, f"fz-{next(_producers)}", tile, 1, 1, body).to_bytes()
    if draw(st.booleans()):
        return draw(hostile(entry, now))
    return Case(entry, "hostile body", "log_entry")


class Oracle:
    """What the consumer service must count for forged entries (a real LogConsumer)."""

    def __init__(self, stage: str):
        self.stage = stage
        self.consumer = LogConsumer(sqlite3.connect(":memory:"), stage, [])
        self.rejected: Counter = Counter()
        self.duplicates = self.gaps = self.delivered = 0
        self.reused = 0
        """Entries on a (producer, tile) seen before (a mutated producer name): after a
        poison batch the service's delivery marks lag its offsets (hdmap.runtime.stage drops what is
        re-delivered), so these may be counted nowhere; the checks allow that much slack."""
        self._keys: set[tuple[str, str]] = set()

    def feed(self, data: bytes) -> None:
        try:
            entry = LogEntry.from_bytes(data)
        except DecodeError as e:
            self.rejected[f"bad entry: {e.field}"] += 1
            return
        key = (entry.producer, entry.tile)
        self.reused += key in self._keys
        self._keys.add(key)
        stats = self.consumer.stats
        dup, gaps = stats.duplicates, stats.gaps
        out = self.consumer.offer(entry)
        self.duplicates += stats.duplicates - dup
        self.gaps += stats.gaps - gaps
        self.delivered += len(out)
        for e in out:
            try:
                BODY_DECODER[self.stage](e.body)
            except DecodeError as exc:
                self.rejected[f"{self.stage}.{exc.field}"] += 1


def check_accounted(s, stage: str, before: dict[str, Stats], oracle: Oracle) -> str:
    """'' when the consumer counted every forged entry (bounded wait), else what is missing."""
    svc, up = CONSUMER[stage], UPSTREAM[stage]
    last = ""

    def ok() -> bool:
        nonlocal last
        now = stats_by_service(s)
        if svc not in now or up not in now:
            last = "stats missing"
            return False
        c0, c1 = before[svc].counters, now[svc].counters
        d = {
            k: c1.get(k, 0) - c0.get(k, 0)
            for k in ("entries_applied", "entries_duplicate", "entries_gap")
        }
        real = now[up].counters.get("log_entries", 0) - before[up].counters.get("log_entries", 0)
        rej = _rejected_delta(before[svc], now[svc])
        rej.pop("assoc.unknown_landmark", None)  # depends on the solver's state
        rej.pop(f"{stage}.apply_failed", None)  # dead-lettered forged entries (entries_failed)
        problems = []
        slack = oracle.reused
        if d["entries_applied"] < oracle.delivered + real - slack:
            problems.append(f"applied {d['entries_applied']} < {oracle.delivered} + {real}")
        counted = sum(d.values()) - real
        if counted < oracle.delivered + oracle.duplicates + oracle.gaps - slack:
            want = (oracle.delivered, oracle.duplicates, oracle.gaps, real)
            problems.append(f"counted {d} < delivered/dup/gap/real {want}")
        missing = {k: n - rej[k] for k, n in oracle.rejected.items() if rej[k] < n}
        if any(k.startswith("bad entry") for k in missing) or sum(missing.values()) > slack:
            problems.append(f"rejected {dict(rej)} vs {dict(oracle.rejected)}")
        if set(rej) - set(oracle.rejected):
            problems.append(f"unexpected rejections {dict(rej)} vs {dict(oracle.rejected)}")
        if now[svc].counters.get("backlog", 0):
            problems.append("backlog")
        last = "; ".join(problems)
        return not problems

    wait_until(ok, timeout=90.0, step=0.5)
    return last


def named_entries(stage: str, now: float) -> list[tuple[str, bytes]]:
    """Named forged entries for ``stage`` (fresh producers)."""

    def entry(tile: str, body: bytes, seq: int = 1, producer: str | None = None) -> bytes:
        return LogEntry(
            stage, producer or f"fz-named-{next(_producers)}", tile, seq, 1, body
        ).to_bytes()

    tile, body = valid_body(stage, now)
    m = msgpack.unpackb(body)
    table = {"obs": "obs", "assoc": "obs", "update": "landmarks"}[stage]
    out = [
        ("garbage", b"\x00garbage"),
        ("empty", b"\xc0"),
        ("wrong type", ErrorReply("x", "y", "z").to_bytes()),
        ("seq 0", msgpack.packb({**msgpack.unpackb(entry(tile, body)), "seq": 0})),
        ("tile not a quadkey", msgpack.packb({**msgpack.unpackb(entry(tile, body)), "tile": "9x"})),
        ("far ahead seq (gap)", entry(tile, body, seq=2**64 - 1)),
        ("body garbage", entry(tile, b"\x00garbage")),
        ("body of another stage", entry(tile, ErrorReply("x", "y", "z").to_bytes())),
        ("NaN in body", entry(tile, _cell(m, table, "lat", 0, math.nan))),
        ("lat out of range", entry(tile, _cell(m, table, "lat", 0, 95.0))),
        ("content outside the tile", entry("0" * 16, body)),
        ("tile of another zoom", entry(tile[:5], body)),
        ("valid, then replayed (duplicate)", entry(tile, body, producer="fz-dup")),
        ("the same again", entry(tile, body, producer="fz-dup")),
    ]
    if stage in ("obs", "assoc"):
        n = m["n_obs"]
        ids = _column(m, "obs", "obs_id", dict(Observations.CODEC.cols)["obs_id"])
        out += [
            ("unknown sign class", entry(tile, _cell(m, "obs", "sign_class", 0, 999))),
            ("duplicate obs ids", entry(tile, _cell(m, "obs", "obs_id", n - 1, ids[0]))),
            ("far-future capture time", entry(tile, _cell(m, "obs", "t", 0, 4.0e9))),
            ("zero-length direction", entry(tile, _cell(m, "obs", "direction", 0, [0, 0, 0]))),
        ]
    if stage == "obs":
        out += [
            ("pass_id u64 max", entry(tile, _with(m, pass_id=2**64 - 1))),
            ("vehicle id not an id", entry(tile, _with(m, vehicle_id="veh 1"))),
        ]
    if stage == "assoc":
        out += [
            ("unknown landmark", entry(tile, _cell(m, "links", "landmark_id", 0, 12345))),
            ("vehicle index outside", entry(tile, _cell(m, "links", "vehicle", 0, 7))),
            ("created id u64 max", entry(tile, _cell(m, "created", "id", 0, 2**64 - 1))),
        ]
    if stage == "update":
        out += [
            ("status 3", entry(tile, _cell(m, "landmarks", "status", 0, 3))),
            ("revision u64 max", entry(tile, _cell(m, "landmarks", "revision", 0, 2**64 - 1))),
            ("id u64 max", entry(tile, _cell(m, "landmarks", "id", 0, 2**64 - 1))),
            ("cov inf", entry(tile, _cell(m, "landmarks", "cov", 0, [math.inf] * 6))),
        ]
    return out


@pytest.mark.integration
@pytest.mark.parametrize("stage", ["obs", "assoc", "update"])
def test_fuzz_internal_subscribers(live, stage: str) -> None:
    stack, s, honest = live
    time.sleep(0.5)
    before = stats_by_service(s)
    oracle = Oracle(stage)
    pubs = Publishers(s)
    sent = Counter()
    try:

        def publish(data: bytes, tile_key: str) -> None:
            pubs.put(keys.ROOT + f"/{stage}/{tile_key}", data)
            oracle.feed(data)
            sent["n"] += 1

        @FUZZ
        @given(forged_entry(stage), st.sampled_from(["", "0" * 16, "1" * 16]))
        def run(case: Case, where: str) -> None:
            key_tile = where
            if not key_tile:  # the tile the entry claims, when it is one
                try:
                    key_tile = LogEntry.from_bytes(case.data).tile
                except DecodeError:
                    key_tile = "0123"
            publish(case.data, key_tile)

        run()
        for _name, data in named_entries(stage, time.time()):
            publish(data, "0123")
        problem = check_accounted(s, stage, before, oracle)
        assert not problem, f"{stage}: forged entries not accounted for: {problem}"
    finally:
        pubs.close()

    honest.finish()
    stats = assert_all_alive(stack, s)
    honest.check(stack)
    # a dead-lettered entry is counted (entries_failed) and kept for inspection
    failed = stats[CONSUMER[stage]].counters.get("entries_failed", 0)
    letters = read_db(stack, CONSUMER[stage], "SELECT COUNT(*) FROM dead_letters")
    assert failed == (letters[0][0] if letters else 0)
    assert sent["n"] >= FUZZ.max_examples
