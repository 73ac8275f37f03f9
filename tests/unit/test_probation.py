"""Probation end to end through the two services that keep sums: the matcher holds a new
vehicle's passes apart, sends them flagged (``AssocGroup.held``) and, when it settles the
vehicle, the settlement (``AssocGroup.trust``); the solver then holds, releases or drops
exactly what the matcher did. In-process services on real SQLite (scene of
tests/test_merge.py: one sign, passes along a road, 10 rays each)."""

from __future__ import annotations

import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from hdmap.mapping.linking import create, link
from hdmap.mapping.matching import AssocOutput as _Out
from hdmap.mapping.probation import freeze_stale, let_go
from hdmap.mapping.trust import NEW, TrustConfig
from hdmap.runtime.service import ServiceOptions
from schemas import DROP, RELEASE, AssocGroup, LogEntry, ObsGroup
from schemas.ids import hold_key
from services.matcher.service import MatcherConfig, MatcherService, assoc_body
from tests.support.services import CLS, SIGN, Sink, matcher, sign_rays, solver, tile_of, updates

DAY = 86400.0


def held_passes(m: MatcherService, vehicles: list[str], passes: int, t0: float) -> int:
    """Link ``passes`` passes of each vehicle to one new landmark; returns its id."""
    tile = tile_of(m.opts.zoom)
    frame = m.frames(tile)
    m.matching.out = defaultdict(_Out)
    lm = create(
        m.matching,
        tile,
        CLS,
        frame.to_ecef((SIGN + np.array([0.6, -0.4, 0.0]))[None])[0],
        np.eye(3),
    )
    lat, lon, h = frame.to_geodetic(frame.from_ecef(lm.x[None]))
    m.matching.out[lm.home].created.append((lm.id, CLS, float(lat[0]), float(lon[0]), float(h[0])))
    rng = np.random.default_rng(8)
    for k, v in enumerate(vehicles):
        m.state.trust_of(v).last_seen = t0
        for p in range(passes):
            link(m.matching, sign_rays(frame, 100 * k + p, rng), [lm] * 10, v, p, t0)
    return lm.id


def emitted(m: MatcherService) -> list[LogEntry]:
    out = [
        LogEntry("assoc", "matcher-test", home, seq, seq, assoc_body(o))
        for seq, (home, o) in enumerate(sorted(m.matching.out.items()), start=1)
    ]
    m.matching.out = defaultdict(_Out)
    return out


def test_held_then_released_in_the_solver_equals_full_weight_from_the_start(tmp_path: Path):
    t0 = time.time()
    m = matcher(tmp_path / "m")
    lid = held_passes(m, ["veh-1", "veh-2"], 6, t0)
    first = emitted(m)
    g = AssocGroup.from_bytes(first[0].body)
    assert g.held.all() and np.allclose(g.links.weight, 0.05)  # both new: held at 0.05
    s = solver(tmp_path / "s")
    s._apply_in_transaction(first)
    assert s.sums.n_held() == m.sums.n_held() == 12
    updates(s)
    # veh-1 promoted, veh-2 caught: the matcher settles its own sums and tells the solver
    let_go(m.matching, "veh-1", m.state.trust_of("veh-1"), False, 1.0)
    let_go(m.matching, "veh-2", m.state.trust_of("veh-2"), True, 0.0)
    second = emitted(m)
    g2 = AssocGroup.from_bytes(second[0].body)
    assert g2.trust.action.tolist() == [RELEASE, DROP] and len(g2.links) == 0
    s._apply_in_transaction(
        [LogEntry("assoc", "matcher-test", e.tile, 2, 2, e.body) for e in second]
    )
    assert s.sums.n_held() == m.sums.n_held() == 0
    assert s.counters["vehicles_released"] == s.counters["vehicles_dropped"] == 1
    (u,) = updates(s)
    assert u.landmarks.id.tolist() == [lid] and int(u.landmarks.n_obs[0]) == 60
    # the same as a solver given veh-1's rays at full weight and never veh-2's
    m2 = MatcherService(
        ServiceOptions(data_dir=tmp_path / "m2"),
        MatcherConfig(trust=TrustConfig(probation_passes=0)),
    )
    m2.pubs = Sink()  # type: ignore[assignment]
    held_passes(m2, ["veh-1"], 6, t0)
    ref = solver(tmp_path / "ref")
    ref._apply_in_transaction(emitted(m2))
    (r,) = updates(ref)
    np.testing.assert_allclose(u.landmarks.lat, r.landmarks.lat, rtol=0, atol=1e-12)
    np.testing.assert_allclose(u.landmarks.lon, r.landmarks.lon, rtol=0, atol=1e-12)
    np.testing.assert_allclose(u.landmarks.cov, r.landmarks.cov, rtol=1e-6, atol=1e-12)
    # a restart reloads held and settled state alike
    again = solver(tmp_path / "s")
    assert again.sums.n_held() == 0


def test_held_passes_and_the_vehicle_status_survive_a_restart(tmp_path: Path):
    t0 = time.time()
    m = matcher(tmp_path)
    held_passes(m, ["veh-7"], 4, t0)
    with m.transaction([m]):
        m.state.save(m.sums.pack_rows)
    again = matcher(tmp_path)
    t = again.state.trust["veh-7"]
    assert t.status == NEW and t.last_seen == t0 and t.held_homes == {tile_of(m.opts.zoom)}
    assert again.sums.n_held() == 4


def test_a_vehicle_that_never_settles_is_let_go_at_the_probation_weight(tmp_path: Path):
    t0 = time.time()
    m = matcher(tmp_path)
    held_passes(m, ["veh-3"], 4, t0)
    emitted(m)
    freeze_stale(m.matching, t0 + 0.5 * DAY)  # still within its time-out
    assert m.sums.n_held() == 4 and not m.matching.out
    freeze_stale(m.matching, t0 + 1.5 * DAY)
    assert m.sums.n_held() == 0
    (e,) = emitted(m)
    g = AssocGroup.from_bytes(e.body)
    assert g.vehicles == ["veh-3"]
    assert g.trust.action.tolist() == [RELEASE]
    np.testing.assert_allclose(g.trust.weight, [0.05])
    assert m.counters["probation_timed_out"] == 1
    assert m.state.trust["veh-3"].held_homes == set() and m.state.trust["veh-3"].status == NEW
    assert hold_key("veh-3") != 0


def test_a_vehicle_whose_rays_keep_failing_the_gate_weighs_less_in_stats(tmp_path: Path):
    """Its rays are offered to the gate of a landmark of their class and fail it (a loose
    camera: 0.15 rad of direction noise while it reports 0.01): past ``min_gated`` rays its
    weight drops and stats show it."""
    m = matcher(tmp_path)
    tile = tile_of(m.opts.zoom)
    frame = m.frames(tile)
    m.matching.out = defaultdict(_Out)
    create(m.matching, tile, CLS, frame.to_ecef(SIGN[None])[0], np.eye(3) * 0.25)
    rng = np.random.default_rng(2)
    t0 = time.time()
    for p in range(25):  # 250 rays offered, passes a minute apart (gating ticks apart)
        o = sign_rays(frame, p, rng)
        d = o.direction + rng.normal(0.0, 0.15, o.direction.shape)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        at = t0 - 3600.0 + 60.0 * p
        o = type(o)(**{**o.__dict__, "direction": d, "t": np.full(len(d), at)})
        m._unit(tile, ObsGroup("veh-bad", p, p, at + 1.0, o))
    t = m.state.trust["veh-bad"]
    assert t.offered >= 200 and t.passed < 0.5 * t.offered
    m._snapshot_counts()
    stats = m.extra_counters()
    assert 0 < stats["weight.veh-bad"] < 0.05  # probation weight x the gate-failure factor
    assert stats["vehicles_downweighted"] >= 1


def test_a_landmark_only_a_caught_vehicle_saw_leaves_the_map(tmp_path: Path):
    t0 = time.time()
    m = matcher(tmp_path / "m")
    lid = held_passes(m, ["veh-9"], 6, t0)
    s = solver(tmp_path / "s")
    s._apply_in_transaction(emitted(m))
    (u,) = updates(s)
    assert u.landmarks.id.tolist() == [lid] and len(u.removed) == 0  # on the map
    let_go(m.matching, "veh-9", m.state.trust_of("veh-9"), True, 0.0)
    assert lid not in m.state.landmarks and m.counters["emptied"] == 1  # retired, no successor
    (e,) = emitted(m)
    g = AssocGroup.from_bytes(e.body)
    assert g.retired.tolist() == [lid] and g.merged_into.size == 0
    s._apply_in_transaction([LogEntry("assoc", "matcher-test", e.tile, 2, 2, e.body)])
    (u2,) = updates(s)
    assert u2.removed.id.tolist() == [lid] and len(u2.landmarks) == 0  # removed once
    assert int(u2.removed.revision[0]) > int(u.landmarks.revision[0])
    assert lid not in s.state.landmarks
    with m.transaction([m]):
        m.state.save(m.sums.pack_rows)
    assert lid not in matcher(tmp_path / "m").state.landmarks
