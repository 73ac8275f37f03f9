"""The matcher's clock: event time (an entry's latest capture time, no later than its
ingest stamp), monotone, and not moved by an entry stamped far ahead of the wall clock
(``Matching.entry_time``); the probation time-out and forgetting
look at the vehicles due only (``SeenIndex``). In-process matcher on real SQLite (scene of
tests/support/services.py: one sign, passes along a road, 10 rays each)."""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hdmap.mapping.landmarks import LandmarkTable
from hdmap.mapping.linking import create, link
from hdmap.mapping.matching import AssocOutput, Matching, MatchingConfig
from hdmap.mapping.probation import follow_time, forget_quiet, freeze_stale
from hdmap.mapping.trust import NEW, TrustConfig
from hdmap.runtime.config import ConfigError
from hdmap.runtime.service import ServiceOptions
from schemas import LogEntry, Observations, ObsGroup
from services.matcher.service import MatcherConfig, MatcherService
from tests.support.services import CLS, SIGN, Sink, matcher, sign_rays, tile_of

DAY = 86400.0
FORGED = 3_976_214_400.0  # 2096-01-01 00:00 UTC


def held_passes(m: MatcherService, vehicles: list[str], passes: int, seen: float) -> None:
    """Link ``passes`` held passes of each vehicle (last seen at ``seen``) to a new
    landmark at the sign, and save."""
    tile = tile_of(m.opts.zoom)
    frame = m.frames(tile)
    m.matching.out = defaultdict(AssocOutput)
    x = frame.to_ecef((SIGN + np.array([0.6, -0.4, 0.0]))[None])[0]
    lm = create(m.matching, tile, CLS, x, np.eye(3))
    rng = np.random.default_rng(8)
    for k, v in enumerate(vehicles):
        m.state.seen(v, seen)
        for p in range(passes):
            link(m.matching, sign_rays(frame, 100 * k + p, rng), [lm] * 10, v, p, seen)
    with m.transaction([m]):
        m.state.save(m.sums.pack_rows)


def entry(
    m: MatcherService, vehicle: str, received_at: float, seq: int, captured: float | None = None
) -> LogEntry:
    """An obs entry of one pass of ``vehicle`` at the sign, stamped ``received_at``, its
    rays captured over the 10 s before ``captured`` (default: the stamp)."""
    tile = tile_of(m.opts.zoom)
    obs = sign_rays(m.frames(tile), 500 + seq, np.random.default_rng(seq))
    end = received_at if captured is None else captured
    obs = replace(obs, t=end - np.linspace(10.0, 0.0, len(obs)))
    body = ObsGroup(vehicle, 500 + seq, seq, received_at, obs).to_bytes()
    return LogEntry("obs", "ingest-t", tile, seq, seq, body)


def on_probation(m: MatcherService, v: str) -> bool:
    t = m.state.trust[v]
    return t.status == NEW and bool(t.held_homes) and v in m.state.held_by_seen


def test_a_forged_entry_dated_2096_releases_no_one_and_is_counted(tmp_path: Path) -> None:
    now = time.time()
    m = matcher(tmp_path)
    held_passes(m, ["veh-1", "veh-2"], 3, now - 0.5 * DAY)  # half their time-out to go
    m._apply_in_transaction([entry(m, "veh-h", now, 1), entry(m, "veh-f", FORGED, 2)])
    assert m.counters["time_clamped"] == 1
    assert m.counters.get("probation_timed_out", 0) == 0
    assert on_probation(m, "veh-1") and on_probation(m, "veh-2")
    assert m.matching.now == now  # the honest entry's time, not the forged one's
    assert m.state.trust["veh-f"].last_seen == now  # its unit is at the clock's time
    again = matcher(tmp_path)  # and so is what was saved
    assert again.matching.now == now and again.state.trust["veh-f"].last_seen == now
    assert on_probation(again, "veh-1") and on_probation(again, "veh-2")
    # what the largest time of the batch would have done
    assert freeze_stale(again.matching, FORGED) == 4  # all four on probation


def test_an_honest_entry_still_lets_stale_vehicles_go(tmp_path: Path) -> None:
    now = time.time()
    m = matcher(tmp_path)
    held_passes(m, ["veh-1"], 3, now - 1.5 * DAY)
    held_passes(m, ["veh-2"], 3, now - 0.5 * DAY)
    m._apply_in_transaction([entry(m, "veh-h", now, 1)])
    assert m.counters["probation_timed_out"] == 1 and "time_clamped" not in m.counters
    assert not m.state.trust["veh-1"].held_homes and on_probation(m, "veh-2")


def test_the_clock_is_capture_time_clamped_by_the_ingest_stamp(tmp_path: Path) -> None:
    now = time.time()
    m = matcher(tmp_path)
    m._apply_in_transaction([entry(m, "veh-a", now - 50.0, 1, captured=now - 60.0)])
    assert m.matching.now == now - 60.0  # its latest capture, not its stamp
    # a vehicle whose clock runs ahead of ingest's: no later than the stamp
    m._apply_in_transaction([entry(m, "veh-b", now - 40.0, 2, captured=now + 200.0)])
    assert m.matching.now == now - 40.0
    # a day's drive uploaded now: the clock does not go back; the vehicle was seen then
    m._apply_in_transaction([entry(m, "veh-c", now - 30.0, 3, captured=now - DAY)])
    assert m.matching.now == now - 40.0
    assert m.state.trust["veh-c"].last_seen == now - DAY
    again = matcher(tmp_path)  # saved with the state, under its new name
    assert again.matching.now == now - 40.0
    names = {n for (n,) in again.db.execute("SELECT name FROM clock")}
    assert "event" in names and "ingest" not in names


def test_time_is_monotone_across_batches_and_restarts(tmp_path: Path) -> None:
    t1 = time.time() - 1000.0
    m = matcher(tmp_path)
    m._apply_in_transaction([entry(m, "veh-a", t1, 1)])
    assert m.matching.now == t1
    m._apply_in_transaction([entry(m, "veh-b", t1 - 100.0, 2)])  # an older stamp
    assert m.matching.now == t1 and m.state.trust["veh-b"].last_seen == t1 - 100.0
    m._apply_in_transaction([entry(m, "veh-a", t1 + 10.0, 3), entry(m, "veh-b", t1 + 5.0, 4)])
    assert m.matching.now == t1 + 10.0
    m = matcher(tmp_path)  # a restart does not take the clock back
    assert m.matching.now == t1 + 10.0
    m._apply_in_transaction([entry(m, "veh-c", t1, 5), entry(m, "veh-c", FORGED, 6)])
    assert m.matching.now == t1 + 10.0 and m.counters["time_clamped"] == 1
    m = matcher(tmp_path)
    assert m.matching.now == t1 + 10.0
    m._apply_in_transaction([entry(m, "veh-a", t1 + 20.0, 7)])
    assert m.matching.now == t1 + 20.0


def test_the_outcome_does_not_depend_on_the_batching(tmp_path: Path) -> None:
    """An entry that moves the clock past a vehicle's time-out lets it go before that
    vehicle's next unit in the same batch, as it does when the two come one by one."""
    now = time.time()
    runs = {}
    for name, batches in (("one by one", [[1], [2]]), ("together", [[1, 2]])):
        m = matcher(tmp_path / name)
        held_passes(m, ["veh-1"], 3, now - 1.5 * DAY)
        e = {1: entry(m, "veh-h", now, 1), 2: entry(m, "veh-1", now, 2)}
        for b in batches:
            m._apply_in_transaction([e[k] for k in b])
        t = m.state.trust["veh-1"]
        runs[name] = (m.counters["probation_timed_out"], t.last_seen, sorted(t.held_homes))
    assert runs["one by one"] == runs["together"]
    assert runs["together"][0] == 1 and runs["together"][2]  # let go, then held again


class CountingDict(dict):
    """A dict that counts the look-ups and walks made on it."""

    def __init__(self, *a: Any) -> None:
        super().__init__(*a)
        self.touched = 0

    def __getitem__(self, k: Any) -> Any:
        self.touched += 1
        return super().__getitem__(k)

    def get(self, k: Any, default: Any = None) -> Any:
        self.touched += 1
        return super().get(k, default)

    def __iter__(self) -> Iterator[Any]:
        self.touched += len(self)
        return super().__iter__()

    def items(self) -> Any:
        self.touched += len(self)
        return super().items()

    def values(self) -> Any:
        self.touched += len(self)
        return super().values()

    def keys(self) -> Any:
        self.touched += len(self)
        return super().keys()


def fleet(n: int, t0: float, trust: TrustConfig) -> Matching:
    """A matcher domain with ``n`` vehicles on probation with held passes in one tile,
    vehicle ``i`` last seen at ``t0 + i``."""
    tile = tile_of(17)
    m = Matching(
        MatchingConfig(trust=trust), LandmarkTable(Observations.empty), 17, [], lambda *_: None,
        time.time,
    )  # fmt: skip
    for i in range(n):
        v = f"v{i:05d}"
        m.state.seen(v, t0 + i)
        m.state.hold_home(v, tile)
    m.state.trust = CountingDict(m.state.trust)
    return m


def test_freeze_stale_looks_at_the_vehicles_due_only() -> None:
    t0 = 1.0e9
    cfg = TrustConfig()
    m = fleet(10_000, t0, cfg)
    ix, trust = m.state.held_by_seen, m.state.trust
    assert isinstance(trust, CountingDict)
    assert freeze_stale(m, t0 + cfg.probation_ttl_s - 1.0) == 0  # no one due
    assert ix.visited == 0 and trust.touched == 0
    assert freeze_stale(m, t0 + cfg.probation_ttl_s + 4.5) == 5  # v00000 .. v00004
    assert ix.visited == 5 and trust.touched <= 3 * 5
    assert len(ix) == 9_995 and not trust["v00003"].held_homes
    trust["v00007"].last_seen = t0 + 50_000.0  # drove again (key 7 is a lower bound)
    ix.visited = trust.touched = 0
    assert freeze_stale(m, t0 + cfg.probation_ttl_s + 9.5) == 4  # v00005, 6, 8, 9
    assert ix.visited == 5 and trust.touched <= 3 * 5  # and v00007, filed again
    assert trust["v00007"].held_homes and "v00007" in ix
    ix.visited = 0
    assert freeze_stale(m, t0 + cfg.probation_ttl_s + 9.5) == 0 and ix.visited == 0


def test_records_of_vehicles_gone_for_long_are_forgotten_only_without_held_passes() -> None:
    t0 = 1.0e9
    cfg = TrustConfig(probation_ttl_s=10 * DAY, forget_after_s=DAY)
    m = fleet(1_000, t0, cfg)
    m.state.seen("gone", t0 - 5.0)  # no held passes
    m.state.seen("back", t0 - 5.0)
    m.state.trust["back"].last_seen = t0 + 5 * DAY  # seen since it was filed
    ix, trust = m.state.all_by_seen, m.state.trust
    assert isinstance(trust, CountingDict)
    trust.touched = 0
    assert forget_quiet(m, t0 + DAY + 9.5) == 1  # v00000 .. v00009 hold passes: kept
    assert "gone" not in trust and "back" in trust and "v00003" in trust
    assert ix.visited == 12 and trust.touched <= 3 * 12
    assert "gone" in m.state._trust_gone  # deleted at the next save
    ix.visited = 0
    assert forget_quiet(m, t0 + DAY + 9.5) == 0 and ix.visited == 0  # looked at later
    follow_time(m)  # the clock is at 0: nothing is due
    assert ix.visited == 0


def test_a_forgotten_vehicle_is_gone_from_storage_and_new_when_it_returns(tmp_path: Path) -> None:
    now = time.time()
    cfg = MatcherConfig(trust=TrustConfig(forget_after_s=2 * DAY))
    m = MatcherService(ServiceOptions(data_dir=tmp_path), cfg)
    m.pubs = Sink()  # type: ignore[assignment]
    held_passes(m, ["veh-old"], 3, now - 3 * DAY)  # let go after a day, then forgotten
    with m.transaction([m]):
        m.state.seen("veh-quiet", now - 3 * DAY)
        m.state.seen("veh-recent", now - DAY)
        m.state.save(m.sums.pack_rows)
    m._apply_in_transaction([entry(m, "veh-h", now, 1)])
    assert m.counters["probation_timed_out"] == 1 and m.counters["trust_forgotten"] == 2
    assert set(m.state.trust) == {"veh-recent", "veh-h"}
    again = MatcherService(ServiceOptions(data_dir=tmp_path), cfg)
    assert set(again.state.trust) == {"veh-recent", "veh-h"}
    n = again.db.execute("SELECT count(*) FROM trust_status WHERE vehicle='veh-quiet'")
    assert n.fetchone()[0] == 0


def test_config_checks() -> None:
    with pytest.raises(ConfigError, match="forget_after_s"):
        MatcherConfig(trust=TrustConfig(forget_after_s=3600.0))
    with pytest.raises(ConfigError, match="time_tolerance_s"):
        MatcherConfig(time_tolerance_s=0.0)
    MatcherConfig(trust=TrustConfig(forget_after_s=0.0))  # kept for ever
