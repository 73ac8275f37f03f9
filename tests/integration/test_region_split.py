"""Rescaling a live region (issue 20 point 4): ``hdmap region split`` and ``merge`` under
load, with a router, ingest, matcher, solver and publisher as processes on 127.0.0.1.

Two towns on one region (``all``): the demo town's passes near Helsinki (quadkey 1...)
and the same passes 60 degrees of longitude west (0..., a rotation about the Earth's
axis: the same streets and signs in every local frame), uploaded alternately by one
vehicle per town with fixed capture times, each upload sent again until acknowledged.

Under that load the region is split into ``1`` and ``0+2+3`` (the command as an operator
runs it, then a matcher and a solver started per sub-region); in the merge test the two
are then merged back into ``all``. Acknowledged == applied: ingest's accepted count
equals what the matchers received, summed; and the final map (the publisher's
snapshots) is the one a run of the same uploads without a split publishes: the same
landmarks, ids and positions.
"""

from __future__ import annotations

import re
import sqlite3
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from fleetsim.loadgen import LoadConfig, build_pool, town_tiles_with_halo
from hdmap.geo.tiles import neighbours, quadkeys_of
from hdmap.ops.quiesce import totals, wait_quiet
from hdmap.ops.region import HandoverError, ask
from hdmap.ops.stack import Stack
from hdmap.ops.status import collect
from hdmap.runtime.bus import open_session, query
from schemas import (
    ErrorReply,
    HandoverRequest,
    Landmarks,
    MapSnapshot,
    ObservationBatch,
    UploadAck,
    keys,
)
from tests.support import wait_until
from tests.support.uploads import upload

pytestmark = pytest.mark.integration

SHIFT_DEG = -60.0
"""Town B's longitude offset (into quadrant 0)."""
PARTS = (("1",), ("0", "2", "3"))


def payloads(n_uploads: int) -> tuple[list[tuple[str, bytes, int]], list[str]]:
    """(vehicle, upload, observations) in sending order, and the towns' tiles."""
    cfg = LoadConfig(pool_passes=30, n_signs=60, n_blocks=4, seed=3)
    world, pool = build_pool(cfg)
    tiles_a = town_tiles_with_halo(world)
    t0 = time.time() - 3600.0
    out: list[tuple[str, bytes, int]] = []
    next_id = {"veh-a": 1, "veh-b": 1}
    batch = {"veh-a": 0, "veh-b": 0}
    k = 0
    while len(out) < n_uploads:
        for v in ("veh-a", "veh-b"):
            parts = pool[(k // 2) % len(pool)]
            for part in parts:
                n = len(part)
                batch[v] += 1
                ids = np.arange(next_id[v], next_id[v] + n, dtype=np.uint64)
                next_id[v] += n
                lon = part.lon + (SHIFT_DEG if v == "veh-b" else 0.0)
                t = np.full(n, t0 + 2.0 * len(out))
                obs = type(part)(**{**part.__dict__, "obs_id": ids, "t": t, "lon": lon})
                body = ObservationBatch(v, k // 2 + 1, batch[v], time.time(), obs).to_bytes()
                out.append((v, body, n))
            k += 1
    lat, lon, _ = world.signs_geodetic()
    b = set(quadkeys_of(lat, lon + SHIFT_DEG).tolist())
    tiles_b = sorted(b | {n for t in b for n in neighbours(t)})
    return out[:n_uploads], tiles_a + tiles_b


class Uploader(threading.Thread):
    """Sends the uploads in order, each until acknowledged, ``pace_s`` apart, and holds
    once ``limit`` are sent (a rescale keeps some for after its command: on a busy machine
    the uploads can otherwise all be sent before it)."""

    def __init__(self, session, uploads, pace_s: float) -> None:
        super().__init__(daemon=True)
        self.s, self.uploads, self.pace_s = session, uploads, pace_s
        self.acked = 0
        self.sent = 0
        self.resent = 0
        self.refused = 0  # acknowledged with an error (not a timeout)
        self.limit = len(uploads)
        self.last_failure = None  # the last refusal or reply of a failed try (for messages)
        self.stop = threading.Event()

    def run(self) -> None:
        for v, body, _n in self.uploads:
            while self.sent >= self.limit and not self.stop.is_set():
                time.sleep(0.05)
            while not self.stop.is_set():
                replies = query(self.s, keys.upload(v), body, 10.0)
                got = [ok for _k, ok, _e in replies if ok]
                ack = UploadAck.from_bytes(got[0]) if got else None
                if ack is not None and ack.error is None:
                    self.acked += len(ack.accepted) + len(ack.duplicates)
                    break
                self.refused += ack is not None
                self.last_failure = replies[:1] if ack is None else ack.error
                self.resent += 1
                time.sleep(0.2)
            self.sent += 1
            time.sleep(self.pace_s)


def final_map(session, tiles: list[str]) -> dict[int, tuple]:
    rows = []
    for t in tiles:
        for _k, ok, _e in query(session, keys.map_snapshot(t), timeout=5.0):
            if ok is not None:
                rows.append(MapSnapshot.from_bytes(ok).landmarks)
    lm = Landmarks.concat(rows) if rows else None
    if lm is None:
        return {}
    return {
        int(i): (float(lm.lat[k]), float(lm.lon[k]), float(lm.h[k]), int(lm.n_obs[k]))
        for k, i in enumerate(lm.id.tolist())
    }


def region_cmd(stack, *args: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "hdmap.cli", "region", *args, "--data-dir",
           str(stack.data_dir), "--connect", stack.listen]  # fmt: skip
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300)


def start_parts(stack, parts) -> None:
    for part in parts:
        stack.start_service("matcher", part)
        stack.start_service("solver", part)
    names = [stack.service_key(s, p) for p in parts for s in ("matcher", "solver")]
    stack.wait_ready(names, 60.0)


def run(stack, uploads, tiles, rescale=None) -> tuple[dict, dict, float]:
    """The uploads through a fresh stack (``rescale(stack, uploader)`` meanwhile); the
    final map, the summed counters and how many were acknowledged."""
    stack.start_all()
    with open_session(stack.bus) as s:
        up = Uploader(s, uploads, 0.12 if rescale else 0.0)
        up.start()
        try:
            if rescale is not None:
                rescale(stack, up)
            up.join(300)
            assert not up.is_alive()
            assert wait_quiet(s, 120.0)
            t = totals(collect(s, 2.0))
            return final_map(s, tiles), t, up.acked
        finally:
            up.stop.set()
            up.join(30)
            stack.stop_all()


def split_midway(stack, up, then_hold_at: int | None = None) -> None:
    """Split at a quarter of the uploads (then let them go on, up to ``then_hold_at``)."""
    assert wait_until(lambda: up.sent >= len(up.uploads) // 4, 120.0)
    at, refused = up.sent, up.refused
    up.limit = at + 20  # uploads go on during the command, some are left after it
    r = region_cmd(stack, "split", "all", "--into", "1", "--into", "0+2+3")
    assert r.returncode == 0, r.stderr + r.stdout
    assert "paused" in r.stdout and "stopped" in r.stdout
    print(next(line for line in r.stdout.splitlines() if line.startswith("paused for")))
    went_on(up, at, refused)
    up.limit = len(up.uploads) if then_hold_at is None else then_hold_at
    stack.procs["matcher-all"].popen.wait(30)  # the handover stopped them
    stack.procs["solver-all"].popen.wait(30)
    start_parts(stack, PARTS)
    # the stopped matcher no longer holds ingest's log (its leaving mark)
    old = re.search(r"matcher all \((matcher-all-[0-9a-f]+)\) paused", r.stdout).group(1)
    assert wait_until(lambda: old not in marks_on(stack.data_dir / "ingest-all"), 30.0)


def went_on(up, at: int, refused: int) -> None:
    """Ingest refused no upload while a region command ran (``refused``: the uploader's
    count before it) and they go on after it (not a race against the command's own speed:
    on a busy machine one upload can outlast it)."""
    assert wait_until(lambda: up.sent > at, 60.0), (
        f"sent {up.sent} of {len(up.uploads)} (at {at}), refused {up.refused}, "
        f"retried {up.resent}, last failure {up.last_failure}"
    )
    assert up.refused == refused, f"{up.refused - refused} uploads refused during the command"


def marks_on(data_dir) -> set[str]:
    """The consumers a producer keeps marks of (its SQLite file, read only)."""
    conn = sqlite3.connect(f"file:{data_dir / 'state.sqlite'}?mode=ro", uri=True)
    try:
        return {c for (c,) in conn.execute("SELECT consumer FROM log_marks")}
    finally:
        conn.close()


def merge_back(stack, up) -> None:
    """Split at a quarter of the uploads, merge back into one region at half of them, with
    one part behind the other: its matcher paused from its start until the merge. The
    merge brings both to one position of ingest's log first (``cut``: the paused part
    applies its backlog, then both hold), so the joined matcher goes on from a state the
    unsplit one had (tests/unit/test_partition.py shows what a join apart changes)."""
    split_midway(stack, up, then_hold_at=len(up.uploads) // 2)
    with open_session(stack.bus) as s:
        assert ask(s, "matcher", "1", "pause").paused
    assert wait_until(lambda: up.sent >= len(up.uploads) // 2, 120.0)
    at, refused = up.sent, up.refused
    up.limit = at + 20
    r = region_cmd(stack, "merge", "--from", "1", "--from", "0+2+3", "--into", "all")
    assert r.returncode == 0, r.stderr + r.stdout
    print(r.stdout)
    held = re.findall(r"matcher (\S+): holds at the cut", r.stdout)
    assert sorted(held) == ["0+2+3", "1"]
    went_on(up, at, refused)
    up.limit = len(up.uploads)
    for part in PARTS:
        for svc in ("matcher", "solver"):
            stack.procs[stack.service_key(svc, part)].popen.wait(30)
    stack.start_service("matcher")
    stack.start_service("solver")
    stack.wait_ready(["matcher-all", "solver-all"], 60.0)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The uploads, the towns' tiles, and the map and acknowledged count of a run of the
    uploads without a split."""
    uploads, tiles = payloads(360)
    with Stack(tmp_path_factory.mktemp("unsplit") / "stack") as st:
        want, _, acked = run(st, uploads, tiles)
    assert len(want) >= 40
    return uploads, tiles, want, acked


@pytest.mark.parametrize("rescale", [split_midway, merge_back], ids=["split", "split_merge"])
def test_a_region_rescaled_under_load_loses_nothing_and_maps_as_unsplit(
    tmp_path, reference, rescale
) -> None:
    uploads, tiles, want, acked0 = reference
    with Stack(tmp_path / "stack") as st:
        got, t, acked = run(st, uploads, tiles, rescale)
    assert acked == acked0 == t["ingest"]["accepted"]
    assert t["matcher"]["received"] == t["ingest"]["accepted"]  # acknowledged == applied
    assert t["matcher"].get("entries_failed", 0) == 0
    assert sorted(got) == sorted(want)
    worst = max(
        max(abs(got[i][0] - want[i][0]), abs(got[i][1] - want[i][1])) * 111_000 for i in want
    )
    print(f"{len(want)} landmarks; largest difference from the unsplit map {worst:.2e} m")
    assert got == want, f"positions differ by up to {worst:.2e} m"


def test_a_paused_region_refuses_bad_requests_and_resumes_without_loss(stack) -> None:
    """Pause the matcher, upload (acknowledged, not applied), refuse malformed and
    out-of-order requests by field, resume: the matcher receives every observation."""
    stack.start_all()
    with open_session(stack.bus) as s:
        for b in range(3):
            assert upload(s, "veh-1", b + 1, 100 * b, 20).error is None
        assert wait_until(lambda: totals(collect(s, 2.0))["matcher"].get("received") == 60)
        r = ask(s, "matcher", "all", "pause")
        assert r.paused and r.size > 0 and r.instance.startswith("matcher-all")
        for b in range(3, 6):
            assert upload(s, "veh-1", b + 1, 100 * b, 20).error is None
        time.sleep(1.0)
        m = totals(collect(s, 2.0))["matcher"]
        assert m["received"] == 60 and m["handover_paused"] == 1
        assert m["entries_paused_dropped"] >= 1
        bad = [
            (b"\x00garbage", "message"),
            (HandoverRequest("pause").to_bytes().replace(b"pause", b"pouse"), "op"),
        ]
        for payload, field in bad:
            ((_k, ok, err),) = query(s, keys.handover("matcher", "all"), payload, 5.0)
            assert ok is None and ErrorReply.from_bytes(err).field == field
        with pytest.raises(HandoverError, match="offset"):
            ask(s, "matcher", "all", "state", offset=r.size + 1)
        chunk = ask(s, "matcher", "all", "state")
        assert chunk.data[:15] == b"SQLite format 3"
        assert not ask(s, "matcher", "all", "resume").paused
        with pytest.raises(HandoverError, match="not paused"):
            ask(s, "matcher", "all", "stop")
        assert wait_until(lambda: totals(collect(s, 2.0))["matcher"].get("received") == 120)
        stats = next(x for x in collect(s, 2.0) if x.service == "matcher")
        want = {"handover.message": 1, "handover.op": 2, "handover.offset": 1}
        assert {k: v for k, v in stats.rejected.items() if k.startswith("handover")} == want
