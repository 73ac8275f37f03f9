"""A paused instance whose handover tool went silent resumes by itself
(hdmap/runtime/handover.py, LEASE_S): a region is never left stalled by a tool that died
half-way; while the tool keeps asking, the pause holds."""

from __future__ import annotations

import sqlite3

from hdmap.runtime.handover import LEASE_S, Handover


def test_the_pause_lasts_while_the_tool_asks_and_ends_when_it_goes_silent(tmp_path) -> None:
    now = [1000.0]
    h = Handover("matcher", "m-1", "12", sqlite3.connect(":memory:"), tmp_path, lambda: 7,
                 clock=lambda: now[0])  # fmt: skip
    h.path.write_bytes(b"checkpoint")
    h.paused, h.asked_at = True, now[0]
    now[0] += LEASE_S - 1.0
    assert not h.lease_over() and h.paused
    h.asked_at = now[0]  # the tool asked again (a status poll)
    now[0] += LEASE_S - 1.0
    assert not h.lease_over() and h.paused
    now[0] += 2.0
    assert h.lease_over() and not h.paused and not h.path.exists()
    assert not h.lease_over()  # once
