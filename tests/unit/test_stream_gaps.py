"""Bounded gaps (issue 20): a consumer holds at most ``GapPolicy.max_ahead`` live entries
behind gaps, retries a gap the catch-up did not fill with a doubling delay (not at every
batch), gives a gap up after ``timeout_s`` (reported, its waiting entries dropped), and
waits for the producers' answers off the worker thread. Fake clock, real SQLite, no bus
(the producers' answers come from a list, or from a fetch the test holds back)."""

from __future__ import annotations

import sqlite3
import threading
from pathlib import Path

import pytest

from hdmap.runtime.catchup import BackgroundCatchUp, InlineExecutor
from hdmap.runtime.config import ConfigError
from hdmap.runtime.log_policy import GapPolicy
from hdmap.runtime.stream import LogConsumer
from schemas import LogEntry

TILE = "0123"
FAR = 10**12


class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def entry(seq: int, tile: str = TILE, gseq: int | None = None) -> LogEntry:
    return LogEntry("obs", "ingest-x", tile, seq, seq if gseq is None else gseq, b"e%d" % seq)


def consumer(tmp_path: Path, clock: Clock, **policy) -> LogConsumer:
    conn = sqlite3.connect(tmp_path / "c.sqlite", isolation_level=None)
    return LogConsumer(conn, "obs", [], GapPolicy(**policy), clock)


def test_the_buffer_behind_gaps_is_bounded_and_what_it_drops_comes_again(tmp_path):
    c = consumer(tmp_path, Clock(), max_ahead=5)
    for seq in range(3, 13):  # 1 and 2 are missing
        assert c.offer(entry(seq)) == []
    assert c.ahead_entries == 5 and c.stats.ahead_dropped == 5 and c.stats.gaps == 10
    got = c.offer(entry(1)) + c.offer(entry(2))
    assert [e.seq for e in got] == [1, 2, 3, 4, 5, 6, 7]  # the five held, released in order
    assert c.ahead_entries == 0 and c.oldest_gap_s() == 0.0
    assert [e.seq for e in c.offer(entry(8))] == [8]  # a dropped one, replayed, fits on


def test_a_gap_nobody_fills_is_retried_with_a_doubling_delay_then_given_up(tmp_path):
    clock = Clock()
    c = consumer(tmp_path, clock, retry_s=0.5, retry_max_s=2.0, timeout_s=10.0)
    c.need_catchup = False
    assert [e.seq for e in c.offer(entry(1))] == [1]
    assert c.offer(entry(FAR)) == []  # forged: no producer has the entries before it
    assert c.wants_catchup(clock.t)  # a new gap asks at once
    tries, nxt = [], 2
    while clock.t < 1000.0 + 9.9:
        if c.wants_catchup(clock.t):
            tries.append(round(clock.t - 1000.0, 3))
            c.begin_catchup()
            delivered, complete = c.absorb([])  # the producers have nothing more
            assert delivered == [] and complete
            c.end_round(complete, clock.t)
        # good traffic on the same tile is delivered as it comes, past the waiting entry
        assert [e.seq for e in c.offer(entry(nxt))] == [nxt]
        nxt += 1
        clock.t += 0.1
    assert tries == [0.0, 0.5, 1.5, 3.5, 5.5, 7.5, 9.5]  # 0.5, 1, 2, then the 2 s cap
    assert c.stats.catchups == len(tries)
    assert c.expire_gaps(clock.t) == [] and c.oldest_gap_s() == pytest.approx(9.9)
    clock.t = 1010.0
    assert c.expire_gaps(clock.t) == [("ingest-x", TILE, nxt - 1, FAR)]
    assert c.stats.gaps_expired == 1 and c.ahead_entries == 0
    assert not c.wants_catchup(clock.t + 100.0)
    c.record(c.offer(entry(nxt)) and [entry(s) for s in range(1, nxt + 1)])
    c.on_commit()
    assert c.lag == 0  # the forged seq claims no lag once given up


def test_live_entries_of_the_tile_flow_past_an_entry_waiting_far_ahead(tmp_path):
    c = consumer(tmp_path, Clock())
    assert c.offer(entry(FAR)) == []
    got = [e.seq for s in range(1, 6) for e in c.offer(entry(s))]
    assert got == [1, 2, 3, 4, 5] and c.ahead_entries == 1


def test_rounds_are_waited_for_off_the_worker_and_a_stale_one_is_dropped(tmp_path):
    """A producer that answers slowly holds up nothing: ``poll`` returns at once while the
    round is in flight, live entries are delivered meanwhile, and the round's entries are
    absorbed at the poll after it is done (duplicates of what came live dropped). A round
    asked before a rollback is dropped, and a new one asked."""
    clock = Clock()
    c = consumer(tmp_path, clock)
    log = [entry(s) for s in range(1, 7)]
    release = threading.Event()
    asked: list[bytes] = []

    def slow(_selectors, request):
        asked.append(request)
        assert release.wait(30)
        return [e.to_bytes() for e in log]

    woken = threading.Event()
    bg = BackgroundCatchUp(c, slow, woken.set)
    try:
        assert bg.poll(clock.t) == [] and bg.busy  # start: a catch-up is due
        assert c.offer(log[0]) == [log[0]]  # live traffic does not wait for it
        assert bg.poll(clock.t) == [] and len(asked) == 1  # still one round in flight
        release.set()
        assert woken.wait(30)
        got = bg.poll(clock.t)
        assert [e.seq for e in got] == [2, 3, 4, 5, 6] and not bg.busy
        assert c.stats.duplicates == 1 and c.stats.catchups == 1

        release.clear()
        woken.clear()
        c.need_catchup = True
        assert bg.poll(clock.t) == [] and bg.busy
        c.on_rollback()  # the batch being applied rolled back: the consumer rewinds
        release.set()
        assert woken.wait(30)
        for _ in range(100):  # the stale round is dropped, a new one asked and absorbed
            got = bg.poll(clock.t)
            if got or not bg.busy:
                break
            woken.clear()
            assert woken.wait(30)
        assert [e.seq for e in got] == [1, 2, 3, 4, 5, 6] and len(asked) == 3
    finally:
        release.set()
        bg.close()


def test_an_inline_executor_completes_a_catch_up_within_one_poll(tmp_path):
    c = consumer(tmp_path, Clock())
    log = [entry(s) for s in range(1, 4)]
    bg = BackgroundCatchUp(
        c, lambda _s, _r: [e.to_bytes() for e in log], lambda: None, executor=InlineExecutor()
    )
    assert [e.seq for e in bg.poll(0.0)] == [1, 2, 3] and not bg.busy


@pytest.mark.parametrize(
    "bad", [{"max_ahead": -1}, {"timeout_s": 0.0}, {"retry_s": float("nan")}, {"retry_max_s": "1"}]
)
def test_a_bad_gap_policy_is_refused_naming_the_key(bad):
    with pytest.raises(ConfigError, match=f"gaps.{next(iter(bad))}"):
        GapPolicy(**bad)
