"""Per-pass and per-vehicle budgets in the matcher (issue #17, point 1): a pass whose
pending rays never make a landmark costs each upload what the upload brings, not what the
pass accumulated. In-process matcher on real SQLite, uploads applied as batches.

Scene (tests/support/services.py): one sign 30 m north of a road origin. The hostile pass
is a parked car that sees the sign from one spot with no range: its rays meet, but never
with the parallax a candidate needs. Structural checks only (counters, sizes; no timing).
"""

from __future__ import annotations

import itertools
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from fleetsim.synthetic import ray_observations
from hdmap.mapping.initiation import InitConfig
from hdmap.mapping.pending import NO_LANDMARK, forget_budgets
from hdmap.runtime.config import ConfigError, from_mapping
from hdmap.runtime.service import ServiceOptions
from schemas import LogEntry, Observations, ObsGroup
from schemas.ids import pass_key
from services.matcher.replay import landmark_digest
from services.matcher.service import MatcherConfig, MatcherService
from tests.support.services import CLS, SIGN, Sink, sign_rays, tile_of

PARKED = 10
"""Rays per upload of the parked car."""


def service(path: Path, **knobs) -> MatcherService:
    """A matcher whose uploads are each their own gating tick (``tick_s`` 0, unless given):
    each upload's rays are tried as seeds as it comes, which the counts here follow (with
    ticks, a pass's rays wait for its tick's end unless over a budget:
    :func:`test_in_one_tick_a_parked_car_is_held_to_its_budget_by_upload`)."""
    knobs.setdefault("tick_s", 0.0)
    svc = MatcherService(ServiceOptions(data_dir=path), MatcherConfig(**knobs))
    svc.pubs = Sink()  # type: ignore[assignment]
    return svc


def parked_rays(frame, k: int, rng: np.random.Generator, n: int = PARKED) -> Observations:
    """Upload ``k`` of a car parked at (12, 0): rays at the sign from one spot, no range."""
    a = np.array([12.0, 0.0, 1.5]) + rng.normal(0, 0.01, (n, 3))
    v = SIGN - a + rng.normal(0, 0.005, (n, 3)) * np.linalg.norm(SIGN - a, axis=1)[:, None]
    d = v / np.linalg.norm(v, axis=1, keepdims=True)
    lat, lon, h = frame.to_geodetic(a)
    return ray_observations(lat, lon, h, d, np.arange(n) + n * k, np.arange(n) + 100 * k, CLS)


class Feed:
    """Uploads into one tile of a matcher, one batch each; the counters' change per upload."""

    def __init__(self, svc: MatcherService) -> None:
        self.svc = svc
        self.tile = tile_of(svc.opts.zoom)
        self.frame = svc.frames(self.tile)
        self.seq = itertools.count(1)

    def upload(
        self, vehicle: str, pass_id: int, obs: Observations, at: float | None = None
    ) -> dict[str, float]:
        """Apply one upload stamped by ingest at ``at`` (None: now; its event time when its
        rays carry none)."""
        before = dict(self.svc.counters)
        s = next(self.seq)
        g = ObsGroup(vehicle, pass_id, s, time.time() if at is None else at, obs)
        self.svc._apply_in_transaction([LogEntry("obs", "ingest-t", self.tile, s, s, g.to_bytes())])
        return {k: v - before.get(k, 0) for k, v in self.svc.counters.items()}

    def waiting(self, vehicle: str, pass_id: int | None = None) -> int:
        p = self.svc.state.pending.get(self.tile)
        if p is None:
            return 0
        if pass_id is None:
            return p.per_vehicle[vehicle]
        return int((p.key == pass_key(vehicle, pass_id)).sum())


def test_a_parked_car_is_held_to_its_budget_then_quarantined(tmp_path: Path) -> None:
    cap, after = 40, 3
    svc = service(
        tmp_path, pending_max_per_pass=cap, quarantine_after=after, init_reseed_max=PARKED
    )
    f = Feed(svc)
    rng = np.random.default_rng(0)
    seen = []
    for k in range(20):
        d = f.upload("veh-parked", 1, parked_rays(f.frame, k, rng))
        seen.append(d)
        # what initiation looked at: at most the pass's budget and the upload, grown from
        # the upload only
        assert d.get("init_rays", 0) <= cap + PARKED
        assert d.get("init_seeds", 0) <= PARKED
        assert f.waiting("veh-parked", 1) <= cap
    assert svc.counters["created"] == 0
    sent = 20 * PARKED
    assert svc.counters["pending_evicted"] == svc.counters["pending_evicted.pass"] == sent - cap
    # the cap is reached at upload 3 (40 rays), upload 4 evicts (after its attempt); then
    # uploads 5-7 fail, and from upload 8 on the pass is quarantined
    reached = next(k for k, d in enumerate(seen) if d.get("pending_evicted", 0))
    assert reached == cap // PARKED
    assert svc.counters["passes_quarantined"] == 1
    assert svc.counters[f"passes_quarantined.{NO_LANDMARK}"] == 1
    b = svc.state.passes[pass_key("veh-parked", 1)]
    assert b.quarantined == NO_LANDMARK and b.failed == after and b.evicted == sent - cap
    # quarantined: no more initiation work, the uploads are still pooled (in the budget)
    for d in seen[reached + after + 1 :]:
        assert d.get("init_rays", 0) == 0 and d.get("init_skipped_quarantined", 0) == 1
    assert f.waiting("veh-parked", 1) == cap
    svc._snapshot_counts()
    assert svc.extra_counters()["passes_in_quarantine"] == 1
    assert svc.extra_counters()["quarantine.veh-parked"] == 1
    # every ray received is linked, waiting or evicted
    c = svc.counters
    assert c["received"] == c.get("linked", 0) + svc.state.pending_count() + c["pending_evicted"]


def test_in_one_tick_a_parked_car_is_held_to_its_budget_by_upload(tmp_path: Path) -> None:
    """With gating ticks, a pass's rays are tried when the tick ends; a pass (or vehicle)
    over its budget is tried and evicted at its upload, so what it pools inside one tick
    (twenty uploads stamped within a second) stays bounded all the same."""
    cap, after = 40, 3
    svc = service(
        tmp_path,
        tick_s=1.0,
        pending_max_per_pass=cap,
        quarantine_after=after,
        init_reseed_max=PARKED,
    )
    f = Feed(svc)
    rng = np.random.default_rng(0)
    t0 = float(int(time.time()) - 3600)  # a tick starts here
    for k in range(20):
        d = f.upload("veh-parked", 1, parked_rays(f.frame, k, rng), t0 + 0.04 * k)
        assert d.get("init_rays", 0) <= cap + PARKED and f.waiting("veh-parked", 1) <= cap
        # tried from the first upload over the budget (which evicts and makes the pass's
        # budget record) until ``after`` more attempts failed (quarantined)
        assert (d.get("init_rays", 0) > 0) == (cap // PARKED <= k <= cap // PARKED + after)
        # each attempt ends the tick there (every waiting ray tried); quarantined: no more
        assert d.get("tick_split", 0) == (d.get("init_rays", 0) > 0)
    assert svc.counters["pending_evicted"] == 20 * PARKED - cap
    assert svc.counters["passes_quarantined"] == 1


def test_without_the_budgets_the_work_grows_with_the_pass(tmp_path: Path) -> None:
    """The old way (every waiting ray seeds again): seeds per upload = the pass's rays."""
    svc = service(
        tmp_path,
        pending_max_per_pass=0,
        pending_max_per_vehicle=0,
        quarantine_after=0,
        init_reseed_max=0,
    )
    f = Feed(svc)
    rng = np.random.default_rng(1)
    seeds = [
        f.upload("veh-parked", 1, parked_rays(f.frame, k, rng)).get("init_seeds", 0)
        for k in range(6)
    ]
    assert seeds == [PARKED * (k + 1) for k in range(6)]
    assert svc.counters.get("pending_evicted", 0) == 0 and f.waiting("veh-parked", 1) == 60
    assert svc.counters.get("init_new_seeds_only", 0) == 0
    # new seeds only above init_reseed_max: the upload's rays, whatever the pass holds
    svc2 = service(
        tmp_path / "new", pending_max_per_pass=0, quarantine_after=0, init_reseed_max=PARKED
    )
    f2 = Feed(svc2)
    seeds = [
        f2.upload("veh-parked", 1, parked_rays(f2.frame, k, rng)).get("init_seeds", 0)
        for k in range(6)
    ]
    assert seeds == [PARKED] * 6
    assert svc2.counters["init_new_seeds_only"] == 5


@pytest.mark.parametrize("reseed", [64, 1])
def test_an_honest_pass_split_over_uploads_still_makes_its_landmark(tmp_path, reseed) -> None:
    """In full (the default at this size) or from the second upload's rays only."""
    svc = service(tmp_path, init_reseed_max=reseed)
    f = Feed(svc)
    rng = np.random.default_rng(2)
    obs = sign_rays(f.frame, 0, rng)
    first = f.upload("veh-a", 0, obs.take(np.arange(3)))  # too few rays to start anything
    assert first.get("created", 0) == 0 and f.waiting("veh-a", 0) == 3
    second = f.upload("veh-a", 0, obs.take(np.arange(3, 10)))  # grown from the new rays
    assert second["created"] == 1 and second["init_seeds"] == (10 if reseed > 10 else 7)
    assert f.waiting("veh-a", 0) == 0 and svc.counters["linked"] == 10
    lm = next(iter(svc.state.landmarks.values()))
    assert np.linalg.norm(f.frame.from_ecef(lm.x[None])[0] - SIGN) < 3.0
    assert svc.counters.get("pending_evicted", 0) == 0 and not svc.state.passes


def test_a_quarantined_pass_is_adopted_by_another_pass_landmark(tmp_path: Path) -> None:
    svc = service(tmp_path, pending_max_per_pass=20, quarantine_after=1)
    f = Feed(svc)
    rng = np.random.default_rng(3)
    for k in range(4):
        f.upload("veh-parked", 1, parked_rays(f.frame, k, rng))
    assert svc.counters["passes_quarantined"] == 1
    d = f.upload("veh-b", 0, sign_rays(f.frame, 0, rng))
    assert d["created"] == 1 and d["adopted"] > 0
    assert f.waiting("veh-parked", 1) == 20 - d["adopted"]


def test_a_vehicle_opening_a_pass_per_upload_is_held_to_its_budget(tmp_path: Path) -> None:
    svc = service(tmp_path, pending_max_per_pass=40, pending_max_per_vehicle=50)
    f = Feed(svc)
    rng = np.random.default_rng(4)
    for k in range(12):
        f.upload("veh-churn", k, parked_rays(f.frame, k, rng))
        assert f.waiting("veh-churn") <= 50
    assert svc.counters["pending_evicted"] == svc.counters["pending_evicted.vehicle"] == 70
    # the oldest passes went first
    p = svc.state.pending[f.tile]
    assert sorted(set(p.pass_id.tolist())) == list(range(7, 12))


def test_budgets_and_the_pool_survive_a_restart_and_records_are_forgotten(tmp_path) -> None:
    svc = service(tmp_path, pending_max_per_pass=20, quarantine_after=1)
    f = Feed(svc)
    rng = np.random.default_rng(5)
    for k in range(4):
        f.upload("veh-parked", 1, parked_rays(f.frame, k, rng))
    stored = svc.db.execute("SELECT COUNT(*) FROM pending").fetchone()[0]
    assert stored == svc.state.pending_count() == 20
    svc.db.close()
    again = service(tmp_path, pending_max_per_pass=20, quarantine_after=1)
    b = again.state.passes[pass_key("veh-parked", 1)]
    assert b.quarantined == NO_LANDMARK and b.evicted == 20
    p = again.state.pending[f.tile]
    assert len(p) == 20 and p.tried.all() and p.saved.all()
    # silent for the pending TTL of event time: the record goes, in storage too
    again.state.event_time = b.last_at + again.config.pending_ttl_s + 1.0
    assert forget_budgets(again.matching) == 1
    with again.transaction([again]):
        again.state.save(again.sums.pack_rows)
    assert again.db.execute("SELECT COUNT(*) FROM pass_budget").fetchone()[0] == 0


def test_budget_knobs_are_checked() -> None:
    with pytest.raises(ConfigError, match=r"matcher\.pending_max_per_pass: below"):
        from_mapping(MatcherConfig, {"pending_max_per_pass": 2}, "matcher")
    with pytest.raises(ConfigError, match=r"matcher\.quarantine_after: must be >= 0"):
        from_mapping(MatcherConfig, {"quarantine_after": -1}, "matcher")
    cfg = from_mapping(MatcherConfig, {"pending_max_per_pass": 0}, "matcher")
    assert cfg.pending_max_per_pass == 0
    low = replace(cfg, init=InitConfig(min_rays=2), pending_max_per_pass=2)  # no raise
    assert low.pending_max_per_pass == 2


def test_a_pass_over_its_budget_ends_the_tick_and_the_units_after_it_see_its_landmark(
    tmp_path: Path,
) -> None:
    """An honest pass whose one upload passes the budget inside a tick (a pass uploaded at
    its end, a tile without landmarks) starts its landmark at that upload, and the tick
    ends there: the next pass's upload, stamped in the same tick, links to the landmark
    instead of waiting beside it. Uploads applied one by one and in one batch (associated
    ahead, then redone after the split) give the same map."""
    t0 = float(int(time.time()) - 3600)  # a tick starts here
    digests = set()
    for batched in (False, True):
        svc = service(tmp_path / str(batched), tick_s=1.0, pending_max_per_pass=8)
        f = Feed(svc)
        rng = np.random.default_rng(3)
        ups = [
            ("veh-a", 1, sign_rays(f.frame, 1, rng, n=12), t0),
            ("veh-b", 2, sign_rays(f.frame, 2, rng), t0 + 0.2),
        ]
        if batched:
            entries = []
            for v, pid, obs, at in ups:
                s = next(f.seq)
                body = ObsGroup(v, pid, s, at, obs).to_bytes()
                entries.append(LogEntry("obs", "ingest-t", f.tile, s, s, body))
            svc._apply_in_transaction(entries)
            assert svc.counters["assoc_redone"] == 1  # associated ahead with no landmark
        else:
            first = f.upload(*ups[0][:3], ups[0][3])
            assert first["tick_split"] == 1 and first["created"] == 1
            second = f.upload(*ups[1][:3], ups[1][3])
            assert second["associated"] == 10 and second.get("tick_split", 0) == 0
        assert len(svc.state.landmarks) == 1 and f.waiting("veh-b") == 0
        digests.add(landmark_digest(svc))
    assert len(digests) == 1
