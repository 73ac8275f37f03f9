"""The matcher's timers run on event time (:mod:`hdmap.mapping.event_time`): pending rays
wait from their own capture time, expire when an entry moves the clock ``pending_ttl_s``
past it (at the sweep of that entry, whatever the wall clock or the batching says).
In-process matcher on real SQLite (scene of tests/support/services.py)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from hdmap.runtime.service import ServiceOptions
from schemas import LogEntry, ObsGroup
from services.matcher.service import MatcherConfig, MatcherService
from tests.support.services import SIGN, Sink, sign_rays, tile_of

T0 = 1.7e9
DAY = 86400.0


def service(path: Path) -> MatcherService:
    svc = MatcherService(ServiceOptions(data_dir=path), MatcherConfig())
    svc.pubs = Sink()  # type: ignore[assignment]
    return svc


def entry(
    m: MatcherService, seq: int, captured: float, received: float, east_m: float, n: int
) -> LogEntry:
    """``n`` rays of one pass at a sign ``east_m`` east of the scene's, captured at
    ``captured`` and stamped by ingest at ``received``."""
    tile = tile_of(m.opts.zoom)
    at = SIGN + np.array([east_m, 0.0, 0.0])
    obs = sign_rays(m.frames(tile), seq, np.random.default_rng(seq), n=n, at=at)
    obs = replace(obs, t=np.full(len(obs), captured))
    body = ObsGroup(f"veh-{seq}", seq, seq, received, obs).to_bytes()
    return LogEntry("obs", "ingest-t", tile, seq, seq, body)


def test_rays_wait_from_their_capture_time_and_expire_on_event_time(tmp_path: Path) -> None:
    m = service(tmp_path)
    ttl = m.config.pending_ttl_s
    # two rays (too few to start a landmark) uploaded a day after they were captured
    m._apply_in_transaction([entry(m, 1, T0, T0 + DAY, 0.0, 2)])
    p = m.state.pending[tile_of(m.opts.zoom)]
    assert len(p) == 2 and (p.added_at == T0).all()
    assert m.matching.now == T0
    # data captured just inside the TTL, elsewhere: they still wait
    m._apply_in_transaction([entry(m, 2, T0 + ttl - 1.0, T0 + DAY, 200.0, 2)])
    assert m.state.pending_count() == 4 and "expired" not in m.counters
    # an entry that moves the clock past the TTL (into the next sweep period): gone, at
    # that entry, though the wall clock is years later throughout
    m._apply_in_transaction([entry(m, 3, T0 + ttl + 61.0, T0 + DAY, 400.0, 2)])
    assert m.counters["expired"] == 2
    assert m.state.pending_count() == 4  # the second pair and the third
    again = service(tmp_path)  # and in storage
    assert again.state.pending_count() == 4 and again.matching.now == T0 + ttl + 61.0


def test_the_batching_does_not_change_what_expires(tmp_path: Path) -> None:
    ttl = MatcherConfig().pending_ttl_s
    plan = [(k, T0 + k * ttl / 3.0, 100.0 * k) for k in range(1, 10)]
    one = service(tmp_path / "one")
    for k, t, east in plan:  # one entry a batch, stamped as they come
        one._apply_in_transaction([entry(one, k, t, t + 5.0, east, 2)])
    bulk = service(tmp_path / "bulk")  # all in one batch, a day late
    bulk._apply_in_transaction(
        [entry(bulk, k, t, T0 + 10 * ttl + DAY, east, 2) for k, t, east in plan]
    )
    assert one.counters["expired"] == bulk.counters["expired"] > 0
    a, b = one.state.pending[tile_of(one.opts.zoom)], bulk.state.pending[tile_of(bulk.opts.zoom)]
    assert a.added_at.tolist() == b.added_at.tolist()
    assert one.matching.now == bulk.matching.now
