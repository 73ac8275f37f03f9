"""Bringing regions to be joined to one position of their input (``hdmap region merge``):
the consumer held at a cut delivers the region's entries up to it and none past it, live
or replayed, and knows when it is there (hdmap/runtime/stream.py ``hold_at``); the
instance's side refuses a cut it is past, and holds ``state``/``stop`` until it reached
the cut (hdmap/runtime/handover.py).

The producer's answers come from its SQLite log by :func:`rows_since`, as its queryable
gives them (tests/unit/test_stream_watermark.py)."""

from __future__ import annotations

import sqlite3

import pytest

from hdmap.runtime.handover import Handover
from hdmap.runtime.store import connect
from hdmap.runtime.stream import LogConsumer
from schemas import DecodeError, HandoverRequest
from tests.unit.test_stream_watermark import PRODUCER, Producer, apply, catch_up


@pytest.fixture
def prod(tmp_path):
    p = Producer(tmp_path / "p.sqlite")
    yield p
    p.conn.close()


def test_a_consumer_held_at_a_cut_takes_the_region_up_to_it_and_nothing_past(tmp_path, prod):
    conn = connect(tmp_path / "c.sqlite")
    c = LogConsumer(conn, "obs", ["1"])
    first = prod.write(["10", "20", "11"])
    apply(conn, c, catch_up(c, prod))
    assert c.positions() == {PRODUCER: first[-1].gseq}
    behind = prod.write(["10", "21", "12", "11"])  # the region's: 10, 12, 11
    cut = {PRODUCER: behind[2].gseq}  # up to tile 12's entry
    c.hold_at(cut)
    assert not c.at_cut() and c.need_catchup
    assert c.offer(behind[3]) == []  # live, past the cut: not delivered, not held
    got = catch_up(c, prod)
    assert [(e.tile, e.seq) for e in got] == [("10", 2), ("12", 1)]
    assert not c.at_cut()  # delivered, not yet committed
    apply(conn, c, got)
    assert c.at_cut() and c.positions() == cut
    assert catch_up(c, prod) == []  # what is past the cut stays in the producer's log
    c.hold_at(None)  # the handover called off: the rest comes
    assert [(e.tile, e.seq) for e in catch_up(c, prod)] == [("11", 2)]
    conn.close()


def test_a_consumer_furthest_in_a_log_is_at_a_cut_there_without_a_catch_up(tmp_path, prod):
    """The part that applied the cut's own entry needs nothing more of that producer (its
    producer may even be gone); one that applied nothing of a producer the cut does not
    name is there too."""
    conn = connect(tmp_path / "c.sqlite")
    c = LogConsumer(conn, "obs", ["1"])
    written = prod.write(["10", "11"])
    for e in written:
        assert c.offer(e) == [e]
    apply(conn, c, written)
    c.hold_at({PRODUCER: written[-1].gseq})
    assert c.at_cut()
    c.hold_at({})
    assert c.at_cut()
    conn.close()


def handover(tmp_path, inputs: dict[str, int]) -> tuple[Handover, list]:
    held: list = []
    h = Handover("matcher", "m-1", "1", sqlite3.connect(":memory:"), tmp_path, lambda: 0,
                 inputs=lambda: inputs, hold=held.append)  # fmt: skip
    return h, held


def ask(h: Handover, op: str, cut: dict[str, int] | None = None):
    return h._serve(HandoverRequest(op, 0, tuple(sorted((cut or {}).items()))), lambda: None)


def test_an_instance_takes_a_cut_only_paused_and_not_below_what_it_applied(tmp_path) -> None:
    h, held = handover(tmp_path, {"ingest-a": 40, "ingest-b": 7})
    with pytest.raises(DecodeError, match="not paused") as e:
        ask(h, "cut", {"ingest-a": 50, "ingest-b": 7})
    assert e.value.field == "op"
    ask(h, "pause")
    with pytest.raises(DecodeError, match="ingest-b: applied up to gseq 7") as e:
        ask(h, "cut", {"ingest-a": 50})
    assert e.value.field == "cut" and held == []
    r = ask(h, "cut", {"ingest-a": 50, "ingest-b": 7})
    assert held == [{"ingest-a": 50, "ingest-b": 7}] and h.advancing and not r.at_cut
    assert r.inputs == (("ingest-a", 40), ("ingest-b", 7))
    for op in ("state", "stop"):
        with pytest.raises(DecodeError, match="still applying up to the cut"):
            ask(h, op)
    h.reach_cut(lambda: None)
    assert ask(h, "status").at_cut and not h.applying and h.path.exists()
    assert ask(h, "state").size == h.path.stat().st_size
    ask(h, "resume")
    assert held[-1] is None and h.cut is None and not h.at_cut and h.applying
