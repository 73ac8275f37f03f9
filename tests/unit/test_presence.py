"""The map follows the world in the matcher (issue 21, :mod:`hdmap.mapping.presence`): passes
that detect a landmark keep it, vehicles' "not seen" reports take it down, and no single
vehicle (blind, or reporting "not seen" everywhere) can. In-process matcher and solver on
real SQLite, fed a simulated town's passes (fixed seed) as obs entries, then absences.

The arithmetic (a miss of a full look: log((1 - 0.9) / (1 - 0.02)) = -2.28; a landmark at
the cap 6.9 falls to revoked, -2.9, at the fifth) is :mod:`hdmap.mapping.existence`'s; here
the wiring: counting once per pass, the per-vehicle cap, two vehicles to revoke, the
tombstone, persistence and what the solver publishes.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from fleetsim.loadgen import LoadConfig, build_pool
from hdmap.geo.tiles import quadkeys_of
from hdmap.mapping.evidence import EvidencePolicy
from hdmap.mapping.existence import ExistenceConfig
from hdmap.mapping.presence import PresenceConfig
from hdmap.mapping.trust import TRUSTED
from hdmap.runtime.service import ServiceOptions
from schemas import Absences, AssocGroup, LandmarkUpdates, LogEntry, Observations, ObsGroup
from schemas.ids import COUNTER_BITS, home_tile
from schemas.map import updates_from_bytes
from services.matcher.replay import Sink, open_matcher
from services.matcher.service import MatcherConfig
from services.solver.service import SolverService

EX = ExistenceConfig()
T0 = time.time() - 2 * 86_400.0


class Feed:
    """Obs entries for a matcher (one producer, numbered per tile), its assoc entries to a
    solver, the solver's updates kept."""

    def __init__(self, tmp: Path):
        self.tmp = tmp
        self.seq: dict[str, int] = {}
        self.gseq = 0
        self.open()

    def open(self) -> None:
        # a report alone (no rays of its pass) would make its pass blind: off here, but
        # for the blind test, which turns it on
        lenient = PresenceConfig(evidence=EvidencePolicy(min_seen=0))
        self.m = open_matcher(self.tmp / "matcher", MatcherConfig(presence=lenient))
        self.m.pubs = Sink(keep=True)
        self.s = SolverService(ServiceOptions(data_dir=self.tmp / "solver"))
        self.s.pubs = Sink(keep=True)
        self.assoc: list[AssocGroup] = []
        self.updates: list[LandmarkUpdates] = []

    def close(self) -> None:
        self.m.db.close()
        self.s.db.close()

    def entry(self, tile: str, g: ObsGroup) -> LogEntry:
        self.gseq += 1
        self.seq[tile] = self.seq.get(tile, 0) + 1
        return LogEntry("obs", "ingest-t", tile, self.seq[tile], self.gseq, g.to_bytes())

    def apply(self, entries: list[LogEntry]) -> None:
        self.m._apply_in_transaction(entries)
        out = [LogEntry.from_bytes(p) for _k, p in self.m.pubs.sent]
        self.m.pubs.sent.clear()
        self.assoc += [AssocGroup.from_bytes(e.body) for e in out]
        if out:
            self.s._apply_in_transaction(out)
        ups = [LogEntry.from_bytes(p) for _k, p in self.s.pubs.sent]
        self.s.pubs.sent.clear()
        self.updates += [updates_from_bytes(e.body) for e in ups if e.stage == "update"]

    def passes(self, pool, vehicle: str, first: int, n: int, t: float) -> float:
        """``n`` pool passes of ``vehicle`` from pass id ``first``, one a minute from ``t``."""
        for k in range(n):
            for part in pool[(first + k) % len(pool)]:
                obs = Observations(**{**part.__dict__, "t": t + (part.t - part.t[0])})
                tiles = quadkeys_of(obs.lat, obs.lon, self.m.opts.zoom)
                self.apply(
                    [
                        self.entry(
                            str(tile),
                            ObsGroup(vehicle, first + k, first + k, t + 1, obs.take(tiles == tile)),
                        )
                        for tile in np.unique(tiles)
                    ]
                )
            t += 60.0
        return t

    def absent(
        self, vehicle: str, pass_id: int, ids: list[int], t: float, frames: int = 12
    ) -> None:
        n = len(ids)
        ab = Absences(
            landmark_id=np.array(ids, np.uint64),
            t=np.full(n, t),
            frames=np.full(n, frames, np.uint32),
            share=np.full(n, 0.2, np.float32),
            range_m=np.full(n, 15.0, np.float32),
            bearing_deg=np.zeros(n, np.float32),
        )
        by_tile: dict[str, list[int]] = {}
        for k, i in enumerate(ids):
            by_tile.setdefault(home_tile(i, self.m.opts.zoom), []).append(k)
        self.apply(
            [
                self.entry(
                    tile,
                    ObsGroup(
                        vehicle, pass_id, 1, t + 1, Observations.empty(), ab.take(np.array(ks))
                    ),
                )
                for tile, ks in sorted(by_tile.items())
            ]
        )


@pytest.fixture(scope="module")
def pool():
    return build_pool(LoadConfig(pool_passes=24, n_signs=30, n_blocks=3, seed=4))[1]


@pytest.fixture
def feed(tmp_path, pool):
    f = Feed(tmp_path)
    f.t = f.passes(pool, "veh-a", 0, 24, T0)
    f.t = f.passes(pool, "veh-b", 100, 24, f.t)
    yield f
    f.close()


def busiest(feed: Feed) -> int:
    lms = feed.m.state.landmarks
    return max(lms, key=lambda i: (feed.m.sums.n_passes(np.array([lms[i].row]))[0], -i))


def test_passes_that_detect_it_raise_a_landmark_to_the_cap_and_say_when(feed):
    lid = busiest(feed)
    lm = feed.m.state.landmarks[lid]
    assert lm.exist == pytest.approx(EX.l_max)
    assert T0 < lm.created_at <= lm.last_seen <= feed.t
    row = next(u.landmarks for u in reversed(feed.updates) if lid in u.landmarks.id.tolist())
    k = row.id.tolist().index(lid)
    assert row.exist_state[k] == 1 and row.p_exist[k] == pytest.approx(0.999, abs=1e-3)
    assert row.first_seen[k] == lm.created_at and row.last_seen[k] == lm.last_seen


def test_misses_of_two_vehicles_revoke_and_leave_a_tombstone(feed):
    lid = busiest(feed)
    t = feed.t
    for k, v in enumerate(["veh-a", "veh-a", "veh-a", "veh-b", "veh-b"]):
        feed.absent(v, 500 + k, [lid], t + 60 * k)
    assert feed.m.counters["absences_capped"] == 1  # veh-a's third within a day
    lm = feed.m.state.landmarks[lid]
    assert EX.l_revoked < lm.exist < EX.l_confirmed  # four counted: doubtful, not yet gone
    rows = [u.landmarks for u in feed.updates if lid in u.landmarks.id.tolist()]
    assert rows[-1].exist_state[rows[-1].id.tolist().index(lid)] == 2
    feed.absent("veh-a", 600, [lid], t + 86_400.0)  # a day later: veh-a counts again
    assert lid not in feed.m.state.landmarks and feed.m.counters["revoked"] == 1
    last = feed.assoc[-1]
    assert lid in last.retired.tolist() and last.merged_into.size == 0
    assert lid in feed.updates[-1].removed.id.tolist()  # the vehicles' maps drop it
    assert lid not in feed.s.state.landmarks
    home = home_tile(lid, feed.m.opts.zoom)  # its tile's id counter is past it: never again
    assert feed.m.state.counters[home] >= lid & ((1 << COUNTER_BITS) - 1)


def test_one_vehicle_alone_cannot_revoke_whatever_it_reports(feed):
    lid = busiest(feed)
    for day in range(6):
        for k in range(5):
            feed.absent("veh-a", 1000 + 10 * day + k, [lid], feed.t + day * 86_400 + 60 * k)
    lm = feed.m.state.landmarks[lid]
    assert lm.exist > EX.l_revoked and feed.m.counters.get("revoked", 0) == 0
    assert feed.m.counters["absences_capped"] == 6 * 3
    assert feed.m.counters["revocations_deferred"] >= 1
    feed.absent("new-car", 1, [lid], feed.t)  # on probation: held, not counted
    assert feed.m.counters["absences_held"] == 1


def test_a_blind_pass_and_a_contradicted_report_count_nothing(feed, pool):
    ids = sorted(feed.m.state.landmarks)[:4]
    before = {i: feed.m.state.landmarks[i].exist for i in ids}
    feed.absent("veh-b", 700, ids, feed.t)  # in view four, saw none: blind
    assert feed.m.counters["absences_blind"] == 4
    strict = PresenceConfig(evidence=EvidencePolicy(min_seen=1))  # one report blind too
    feed.m.config = replace(feed.m.config, presence=strict)
    feed.m.matching.config = feed.m.config
    feed.absent("veh-b", 701, ids[:1], feed.t + 60.0)
    assert feed.m.counters["absences_blind"] == 5
    feed.m.config = replace(
        feed.m.config, presence=PresenceConfig(evidence=EvidencePolicy(min_seen=0))
    )
    feed.m.matching.config = feed.m.config
    assert {i: feed.m.state.landmarks[i].exist for i in ids} == before
    n = len(feed.assoc)
    t = feed.passes(pool, "veh-a", 300, 1, feed.t + 60)  # pass 300 links rays ...
    linked = {int(i) for g in feed.assoc[n:] for i in g.links.landmark_id.tolist()}
    lid = sorted(linked)[0]
    feed.absent("veh-a", 300, [lid], t)  # ... and says it did not see one of them
    assert feed.m.counters["absences_contradicted"] == 1


def test_existence_and_counted_misses_survive_a_restart(feed):
    lid = busiest(feed)
    feed.absent("veh-a", 900, [lid], feed.t)
    feed.absent("veh-b", 901, [lid], feed.t + 60)
    lm = feed.m.state.landmarks[lid]
    exist, records = lm.exist, feed.m.state.misses.records(lid)
    solver_row = feed.s.state.landmarks[lid].existence
    feed.close()
    feed.open()
    assert feed.m.state.landmarks[lid].exist == exist
    assert feed.m.state.misses.records(lid) == records and feed.m.state.misses.revocable(lid)
    assert feed.s.state.landmarks[lid].existence == solver_row


def test_a_vehicle_on_probation_has_its_reports_held_until_promoted(feed, pool):
    lid = busiest(feed)
    feed.absent("veh-n", 1, [lid], feed.t)
    assert feed.m.counters["absences_held"] == 1
    assert feed.m.state.landmarks[lid].exist == pytest.approx(EX.l_max)  # not weighed yet
    feed.close()
    feed.open()  # held reports are kept with the table
    assert [r[:2] for r in feed.m.state.held_absences["veh-n"]] == [(1, lid)]
    t = feed.t + 60.0
    trust = feed.m.config.trust

    def on_probation() -> bool:
        return feed.m.state.trust["veh-n"].held(trust)

    for k in range(24):
        t = feed.passes(pool, "veh-n", 2 + k, 1, t)
        if not on_probation():
            break
    assert not on_probation() and feed.m.state.trust["veh-n"].status == TRUSTED
    assert "veh-n" not in feed.m.state.held_absences
    assert feed.m.counters["absences_counted"] == 1  # weighed once promoted


def test_the_published_states_are_the_wires():
    from hdmap.mapping import presence
    from schemas import tables

    assert (presence.EXIST_CONFIRMED, presence.EXIST_DOUBTFUL) == (
        tables.EXIST_CONFIRMED,
        tables.EXIST_DOUBTFUL,
    )
