"""A producer's checkpoints (issue 20 point 1): the solver's update log truncated by
retention is folded into per-tile checkpoints; a consumer that starts after the
truncation (new, or restored from an old backup) gets the checkpoints and the tail, and
holds exactly the map of a consumer that read the whole log, through later live entries
too. Without checkpoints (the obs and assoc logs) the same query is refused.

Scene: 120 update entries over three tiles, each upserting 1-4 of 30 landmark ids at a
new revision and now and then removing one (ids are never reused), fixed seed.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from hdmap.runtime.log_out import LogWriter, answer
from hdmap.runtime.log_policy import RetentionPolicy
from hdmap.runtime.retention import LogRetention
from hdmap.runtime.store import connect, transaction
from hdmap.runtime.stream import LogConsumer
from schemas import DecodeError, LandmarkUpdates, LogEntry, LogMark, LogQuery
from schemas.tables import Landmarks, Removals
from services.solver.checkpoint import fold_updates

P = "solver-x"
TILES = ("1202", "1203", "1230")


class Wall:
    def __init__(self) -> None:
        self.t = time.time()

    def __call__(self) -> float:
        return self.t


def body(rng: np.random.Generator, tile: int, rev: int, alive: set[int], dead: set[int]) -> bytes:
    """An update of some landmarks of tile ``tile`` (ids ``tile + 1 + 3k``: a landmark
    stays in its tile), now and then removing another of them."""
    ids = [
        3 * int(k) + tile + 1 for k in rng.choice(10, size=int(rng.integers(1, 5)), replace=False)
    ]
    ids = [i for i in ids if i not in dead]
    mine = sorted(i for i in alive if (i - 1) % 3 == tile and i not in ids)
    gone = [int(rng.choice(mine))] if mine and rng.random() < 0.2 else []
    alive |= set(ids)
    alive -= set(gone)
    dead |= set(gone)
    n = len(ids)
    lm = Landmarks(
        np.array(ids, np.uint64), np.zeros(n, np.uint16), 60.0 + rng.random(n) * 1e-3,
        np.full(n, 24.9), np.zeros(n), np.tile([1.0, 0, 0, 1.0, 0, 1.0], (n, 1)),
        np.ones(n, np.uint8), np.full(n, rev, np.uint32), np.ones(n, np.uint32),
        np.full(n, rev, np.uint64), np.full(n, 1.7e9), np.full(n, 1.7e9),
    )  # fmt: skip
    rm = Removals(np.array(gone, np.uint64), np.full(len(gone), rev, np.uint64))
    return LandmarkUpdates(lm, rm).to_bytes()


def write(conn, w: LogWriter, rng, n: int, state: tuple[set, set], rev0: int) -> None:
    with transaction(conn, [w]):
        for k in range(n):
            t = int(rng.integers(0, 3))
            w.append(TILES[t], body(rng, t, rev0 + k, *state))


def apply(held: dict[int, tuple], entries: list[LogEntry]) -> None:
    """A publisher's view: each landmark's last row (lat, revision), removals dropped."""
    for e in entries:
        u = LandmarkUpdates.from_bytes(e.body)
        for k, i in enumerate(u.landmarks.id.tolist()):
            held[i] = (float(u.landmarks.lat[k]), int(u.landmarks.revision[k]))
        for i in u.removed.id.tolist():
            held.pop(i, None)


def catch_up(c: LogConsumer, conn, checkpoints: bool) -> list[LogEntry]:
    out: list[LogEntry] = []
    for _ in range(100):
        conn.execute("BEGIN")
        try:
            entries, head = answer(
                conn, LogQuery.from_bytes(c.query(50).to_bytes()), P, checkpoints
            )
        finally:
            conn.execute("COMMIT")
        got, complete = c.absorb([e.to_bytes() for e in entries] + [head.to_bytes()])
        out += got
        if complete:
            return out
    raise AssertionError("catch-up did not finish")


def commit(conn, c: LogConsumer, entries: list[LogEntry]) -> None:
    with transaction(conn, [c]):
        c.record(entries)


@pytest.fixture
def log(tmp_path):
    """The producer after 120 entries, 80 of them folded and deleted; the whole log's
    entries as written."""
    rng = np.random.default_rng(7)
    wall = Wall()
    conn = connect(tmp_path / "p.sqlite")
    w = LogWriter(conn, "update", P)
    r = LogRetention(conn, "update", P, RetentionPolicy(retain_s=60.0), wall, fold=fold_updates)
    state: tuple[set, set] = (set(), set())
    write(conn, w, rng, 120, state, 1)
    full = [
        LogEntry("update", P, t, s, g, bytes(b))
        for t, s, g, b in conn.execute("SELECT tile, seq, gseq, body FROM log_out ORDER BY gseq")
    ]
    with transaction(conn, []):
        r.on_mark(LogMark("update", P, "publisher-a", 80, w.epoch))
    wall.t += 3600.0
    with transaction(conn, []):
        assert r.truncate() == 80
    return conn, w, r, rng, state, full


@pytest.mark.parametrize("start", [0, 37])
def test_a_consumer_behind_the_deleted_log_gets_the_checkpoints_and_the_tail(
    tmp_path, log, start
) -> None:
    """``start``: how far the consumer had applied (a backup of it); 0: a new one."""
    conn, w, _r, rng, state, full = log
    want: dict[int, tuple] = {}
    apply(want, full)
    cconn = connect(tmp_path / "c.sqlite")
    c = LogConsumer(cconn, "update", [])
    held: dict[int, tuple] = {}
    if start:  # the backup's entries, applied live
        old = [e for e in full if e.gseq <= start]
        for e in old:
            commit(cconn, c, c.offer(e))
        apply(held, old)
    got = catch_up(c, conn, checkpoints=True)
    assert sum(e.checkpoint for e in got) == len(TILES)
    assert all(e.gseq > 80 for e in got if not e.checkpoint)
    commit(cconn, c, got)
    apply(held, got)
    assert held == want and c.stats.checkpoints == len(TILES)
    # the log goes on live: the consumer follows it
    write(conn, w, rng, 30, state, 500)
    live = [
        LogEntry("update", P, t, s, g, bytes(b), w.epoch, 0, 0)
        for t, s, g, b in conn.execute("SELECT tile, seq, gseq, body FROM log_out WHERE gseq > 120")
    ]
    apply(want, live)
    for e in live:
        d = c.offer(e)
        commit(cconn, c, d)
        apply(held, d)
    assert held == want and c.gaps_open == 0


def test_without_checkpoints_the_same_query_is_refused_naming_after_gseq(tmp_path, log) -> None:
    conn = log[0]
    c = LogConsumer(connect(tmp_path / "c.sqlite"), "update", [])
    with pytest.raises(DecodeError) as err:
        answer(conn, LogQuery.from_bytes(c.query(50).to_bytes()), P, checkpoints=False)
    assert err.value.field == "after_gseq"


def lm_update(ids: list[int], gone: list[int], rev: int) -> bytes:
    n = len(ids)
    lm = Landmarks(
        np.array(ids, np.uint64), np.zeros(n, np.uint16), np.full(n, 60.0 + rev * 1e-6),
        np.full(n, 24.9), np.zeros(n), np.tile([1.0, 0, 0, 1.0, 0, 1.0], (n, 1)),
        np.ones(n, np.uint8), np.ones(n, np.uint32), np.ones(n, np.uint32),
        np.full(n, rev, np.uint64), np.full(n, 1.7e9), np.full(n, 1.7e9),
    )  # fmt: skip
    return LandmarkUpdates(
        lm, Removals(np.array(gone, np.uint64), np.full(len(gone), rev, np.uint64))
    ).to_bytes()


def test_a_landmark_that_moves_to_another_tile_and_back_is_where_it_ended(tmp_path) -> None:
    """Its estimate moved: removed from tile A with an upsert in B, later back in A. A
    tile's checkpoint keeps the row when the row came after the removal."""
    wall = Wall()
    conn = connect(tmp_path / "p.sqlite")
    w = LogWriter(conn, "update", P)
    r = LogRetention(conn, "update", P, RetentionPolicy(retain_s=60.0), wall, fold=fold_updates)
    steps = [("1202", [1, 2], []), ("1203", [1], []), ("1202", [2], [1]), ("1202", [1], []),
             ("1203", [], [1])]  # fmt: skip
    with transaction(conn, [w]):
        for k, (tile, ids, gone) in enumerate(steps):
            w.append(tile, lm_update(ids, gone, k + 1))
    full = [
        LogEntry("update", P, t, s, g, bytes(b))
        for t, s, g, b in conn.execute("SELECT tile, seq, gseq, body FROM log_out ORDER BY gseq")
    ]
    with transaction(conn, []):
        r.on_mark(LogMark("update", P, "publisher-a", len(steps), w.epoch))
    wall.t += 3600.0
    with transaction(conn, []):
        assert r.truncate() == len(steps)
    per_tile: dict[str, dict[int, tuple]] = {}
    for e in full:  # the publisher's view: a map per tile
        apply(per_tile.setdefault(e.tile, {}), [e])
    c = LogConsumer(connect(tmp_path / "c.sqlite"), "update", [])
    got: dict[str, dict[int, tuple]] = {}
    for e in catch_up(c, conn, checkpoints=True):
        apply(got.setdefault(e.tile, {}), [e])
    assert got == per_tile and sorted(got["1202"]) == [1, 2] and got["1203"] == {}
