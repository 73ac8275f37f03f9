"""A hostile world: bounded fuzz of the internal stage subscribers.

Inputs are forged log entries on the obs, assoc and update keys, from fresh producers:
random bytes and *mutated valid entries*, hostile in their envelope or in their body
(flipped/truncated bytes, fields of the wrong type or range, NaN/inf/out-of-range
cells, zero-length directions, unknown sign classes, duplicate ids, timestamps far in
the future, huge arrays, wrong message types and versions, content outside the tile an
entry was sent to, sequence gaps and replays).

Properties, over a real stack (router + the four services as processes): every
forged entry is counted by the consuming service in ``Stats.rejected`` by reason, or
as a duplicate, a gap or an applied entry, as a real ``LogConsumer`` (the ``Oracle``)
counts it; afterwards every process is alive, has its liveliness token and answers
stats, every dead-lettered entry is counted and kept, and an honest vehicle uploading
*during* the fuzz had every upload acknowledged and applied by the matcher.

The endpoints a client queries are fuzzed in test_fuzz_endpoints.py; the helpers
shared with it are in fuzz_support.py.

Hypothesis runs derandomized, without a database, with a bounded number of examples.
"""

from __future__ import annotations

import itertools
import math
import sqlite3
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

import msgpack
import pytest
from hypothesis import given
from hypothesis import strategies as st

from hdmap.runtime.bus import Publishers
from hdmap.runtime.stream import LogConsumer
from schemas import (
    AssocGroup,
    DecodeError,
    ErrorReply,
    LandmarkUpdates,
    LogEntry,
    Observations,
    ObsGroup,
    Stats,
    keys,
)
from tests.integration.fuzz_support import (
    assert_all_alive,
    read_db,
    rejected_delta,
    stats_by_service,
)
from tests.support import wait_until
from tests.support.hostile import (
    FUZZ,
    Case,
    _cell,
    _column,
    _with,
    assoc_group,
    hostile,
    landmark_updates,
    obs_group,
)

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
        rej = rejected_delta(before[svc], now[svc])
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
