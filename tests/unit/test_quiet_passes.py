"""The solver and the matcher close passes quiet for ``close_passes_after_s`` of event
time (the rays' capture times, each no later than its ingest stamp): the estimate and
covariance are those of the open passes, the stored state shrinks. In-process services on
real SQLite, through their transactions (scene of tests/test_merge.py).
"""

from __future__ import annotations

import time
from collections import defaultdict
from dataclasses import replace
from pathlib import Path

import numpy as np

from hdmap.mapping.estimator.packing import OPEN_DTYPE_V4
from hdmap.mapping.event_time import advance
from hdmap.mapping.linking import create, link, refresh
from hdmap.mapping.matching import AssocOutput as _Out
from hdmap.mapping.quiet import QuietPasses
from hdmap.mapping.trust import TrustConfig
from hdmap.runtime.service import ServiceOptions
from schemas import Links, NewLandmarks, Observations
from services.matcher.service import MatcherConfig, MatcherService
from services.solver.service import SolverConfig, SolverService
from tests.support import Clock
from tests.support.services import (
    CLS,
    SIGN,
    Sink,
    assoc_entry,
    matcher,
    sign_rays,
    tile_of,
    updates,
)


def solver(path: Path, close: bool) -> SolverService:
    cfg = SolverConfig(close_passes_after_s=7200.0 if close else 0.0)
    svc = SolverService(ServiceOptions(data_dir=path), cfg)
    svc.pubs = Sink()  # type: ignore[assignment]
    return svc


T0 = 1.7e9
"""Event time of the scenes' start (capture times; ingest stamps 5 s after)."""


def at(obs: Observations, t: float) -> Observations:
    """``obs`` captured at ``t``."""
    return replace(obs, t=np.full(len(obs), t))


def open_on(svc, row: int) -> int:
    """Passes open on sums row ``row``."""
    return sum(1 for r, _c in svc.sums.open_passes() if r == row)


def test_quiet_passes_close_and_the_map_is_the_same(tmp_path: Path):
    tile = tile_of(ServiceOptions().zoom)
    m = matcher(tmp_path / "m")  # for an id and the frame only
    frame = m.frames(tile)
    rng = np.random.default_rng(11)
    lid = m.state.next_id(tile)
    lat, lon, h = frame.to_geodetic((SIGN + np.array([0.5, 0.5, 0.0]))[None])
    created = NewLandmarks(
        np.array([lid], np.uint64), np.full(1, CLS, np.uint16), lat, lon, h
    )  # fmt: skip
    # two vehicles, 12 passes each; every pass uploaded in two groups (its halves), one
    # group every 10 minutes of event time: group seq captured at T0 + 600 seq
    groups = []
    for p in range(12):
        for v in ("veh-a", "veh-b"):
            o = sign_rays(frame, p, rng)
            for half in (slice(0, 5), slice(5, 10)):
                sel = np.arange(10)[half]
                obs = o.take(sel)
                obs = replace(obs, obs_id=obs.obs_id + (0 if v == "veh-a" else 500_000))
                groups.append((v, p, obs))
    # three hours later a third vehicle passes: every earlier pass has been quiet 2 h
    late = sign_rays(frame, 12, rng)
    groups.append(("veh-c", 0, replace(late, obs_id=late.obs_id + 900_000)))

    def entry(seq: int, v: str, p: int, obs: Observations, t: float):
        n = len(obs)
        links = Links(
            np.full(n, lid, np.uint64),
            np.zeros(n, np.uint32),
            np.full(n, p, np.uint64),
            np.full(n, t + 5.0),  # ingest's stamp, after the capture
            np.ones(n, np.float32),
        )
        kw = {"created": created} if seq == 1 else {}
        return assoc_entry(seq, tile, vehicles=[v], obs=at(obs, t), links=links, **kw)

    svcs = {c: solver(tmp_path / f"s{c}", c) for c in (False, True)}
    for seq, (v, p, obs) in enumerate(groups, start=1):
        t = T0 + 600.0 * seq + (3 * 3600.0 if v == "veh-c" else 0.0)
        for s in svcs.values():
            s._apply_in_transaction([entry(seq, v, p, obs, t)])
    last = {c: updates(s)[-1].landmarks for c, s in svcs.items()}
    kept, closed = last[False], last[True]
    np.testing.assert_allclose(closed.lat, kept.lat, rtol=0, atol=1e-12)
    np.testing.assert_allclose(closed.lon, kept.lon, rtol=0, atol=1e-12)
    np.testing.assert_allclose(closed.cov, kept.cov, rtol=1e-9, atol=1e-15)
    assert int(closed.n_passes[0]) == int(kept.n_passes[0]) == 25
    row = {c: s.state.landmarks[lid].row for c, s in svcs.items()}
    # pass p's groups are seq 4p+1..4p+4 (veh-a's two halves, then veh-b's), 10 min apart;
    # at seq 48 the passes quiet for 2 hours were closed (17), the 7 of the last two hours
    # when the late vehicle came; its own pass is open
    assert svcs[True].sums.n_open_passes == 1
    assert svcs[False].sums.n_open_passes == 8  # max_open_passes, by eviction
    assert svcs[True].counters["passes_closed"] == 24
    blob = {
        c: s.db.execute("SELECT length(sums) FROM landmarks").fetchone()[0] for c, s in svcs.items()
    }
    assert blob[False] - blob[True] == 7 * OPEN_DTYPE_V4.itemsize  # no pull: v4 rows
    # restart: the stored (closed) state and clock give the same map
    again = solver(tmp_path / "sTrue", True)
    assert again.state.event_time == svcs[True].state.event_time
    sol = again.sums.solve(np.array([again.state.landmarks[lid].row]), update_reference=False)
    ref = svcs[True].sums.solve(np.array([row[True]]), update_reference=False)
    np.testing.assert_allclose(sol.x, ref.x, rtol=0, atol=1e-12)
    # the pass open at the restart is quiet from the restored clock on: it closes when
    # data two hours later moves the clock (a pass elsewhere), not before
    assert again.sums.n_open_passes == 1 and len(again._quiet) == 1
    t_last = again.state.event_time
    lid2 = lid + 1
    lat2, lon2, h2 = frame.to_geodetic((SIGN + np.array([40.0, 0.0, 0.0]))[None])
    other = NewLandmarks(np.array([lid2], np.uint64), np.full(1, CLS, np.uint16), lat2, lon2, h2)
    far = sign_rays(frame, 20, rng, at=SIGN + np.array([40.0, 0.0, 0.0]))
    n = len(far)
    for k, dt in enumerate((3600.0, 7200.0 + 61.0)):
        links = Links(
            np.full(n, lid2, np.uint64), np.zeros(n, np.uint32), np.full(n, 20 + k, np.uint64),
            np.full(n, t_last + dt + 5.0), np.ones(n, np.float32),
        )  # fmt: skip
        obs = at(replace(far, obs_id=far.obs_id + 10_000 * (k + 1)), t_last + dt)
        kw = {"created": other} if k == 0 else {}
        seq = len(groups) + 1 + k
        again._apply_in_transaction(
            [assoc_entry(seq, tile, vehicles=["veh-d"], obs=obs, links=links, **kw)]
        )
        assert open_on(again, again.state.landmarks[lid].row) == (1 if k == 0 else 0)
    sol = again.sums.solve(np.array([again.state.landmarks[lid].row]), update_reference=False)
    np.testing.assert_allclose(sol.x, ref.x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(sol.cov, ref.cov, rtol=1e-9, atol=1e-15)


def tick(svc: MatcherService, t: float) -> None:
    """The matcher's clock moved to ``t`` by an entry (what :meth:`apply` runs after it)."""
    svc.state.event_time = max(svc.state.event_time, t)
    advance(svc.matching)


def test_the_matcher_closes_quiet_passes_in_its_gating_sums(tmp_path: Path) -> None:
    svcs = {}
    for close in (False, True):
        cfg = MatcherConfig(  # no probation: held passes are never closed (nor evicted)
            close_passes_after_s=7200.0 if close else 0.0,
            trust=TrustConfig(probation_passes=0),
        )
        svc = MatcherService(ServiceOptions(data_dir=tmp_path / f"m{close}"), cfg)
        svc.pubs = Sink()  # type: ignore[assignment]
        svcs[close] = svc
    rng = np.random.default_rng(4)
    tile = tile_of(ServiceOptions().zoom)
    frame = svcs[True].frames(tile)
    passes = [sign_rays(frame, p, rng) for p in range(12)]
    lms = {}
    for close, svc in svcs.items():
        svc.matching.out = defaultdict(_Out)
        lms[close] = create(svc.matching, tile, CLS, frame.to_ecef(SIGN[None])[0], np.eye(3) * 4.0)
    for p, obs in enumerate(passes):  # one pass every 20 minutes of event time
        for close, svc in svcs.items():
            tick(svc, T0 + 1200.0 * p)  # its entry moved the clock: due passes close
            svc._apply_in_transaction([])  # saved
            svc.matching.out = defaultdict(_Out)
            link(svc.matching, obs, [lms[close]] * len(obs), "veh-1", p, time.time())
            # as a unit does: re-solved, saved with the batch
            refresh(svc.matching, [lms[close].id])
    # the closing service saves its last pass and restarts: its open passes are quiet from
    # the restart on
    svcs[True]._apply_in_transaction([])
    restarted = MatcherService(ServiceOptions(data_dir=tmp_path / "mTrue"), svcs[True].config)
    restarted.pubs = Sink()  # type: ignore[assignment]
    n_open = svcs[True].sums.n_open_passes
    assert restarted.state.event_time == svcs[True].state.event_time == T0 + 1200.0 * 11
    assert len(restarted.matching.quiet) == restarted.sums.n_open_passes == n_open
    svcs[True].db.close()
    svcs[True] = restarted
    for svc in svcs.values():  # an entry two hours after the last pass
        tick(svc, T0 + 1200.0 * 11 + 7200.0 + 61.0)
        svc._apply_in_transaction([])
    assert svcs[True].sums.n_open_passes == 0
    assert svcs[False].sums.n_open_passes == 8
    assert svcs[True].counters["passes_closed"] == 12
    sol = {c: s.sums.solve([lms[c].row], update_reference=False) for c, s in svcs.items()}
    np.testing.assert_allclose(sol[True].x, sol[False].x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(sol[True].cov, sol[False].cov, rtol=1e-9, atol=1e-15)
    blob = {
        c: s.db.execute("SELECT length(sums) FROM landmarks").fetchone()[0] for c, s in svcs.items()
    }
    assert blob[False] - blob[True] == 8 * OPEN_DTYPE_V4.itemsize


def test_a_merged_landmarks_open_pass_closes_with_its_pass():
    """Pass 5 is open on landmark 2 only; landmark 2 is merged into landmark 1: the moved
    pass closes when pass 5 is quiet (it was noted for landmark 2, now gone)."""
    from types import SimpleNamespace

    from hdmap.mapping.estimator import EstimatorConfig, LandmarkSums, Rays
    from hdmap.mapping.quiet import close_quiet, merge_rows

    class State:
        def __init__(self) -> None:
            self.landmarks = {1: SimpleNamespace(id=1, row=0), 2: SimpleNamespace(id=2, row=1)}
            self.put_ids: list[int] = []

        def put(self, lm) -> None:
            self.put_ids.append(lm.row)

    sums = LandmarkSums(EstimatorConfig(), capacity=2)
    rows = sums.new_rows(2, np.array([[0.0, 20.0, 2.0], [0.5, 20.0, 2.0]]))
    rays = Rays.from_angles(np.zeros((3, 3)), [0.0, 0.01, 0.02], [0.1] * 3, 0.01, 0.01, 1.0, 1.0)
    sums.accumulate([rows[1]] * 3, [5] * 3, rays)
    clock, state = Clock(0.0), State()
    quiet = QuietPasses(7200.0, clock)
    quiet.note(5, [(2, int(rows[1]))])
    assert sums.open_clusters(int(rows[1])) == [5]
    merge_rows(quiet, sums, state.landmarks[1], state.landmarks.pop(2), None, None)
    assert sums.open_passes() == [(int(rows[0]), 5)]
    clock.t = 7201.0
    assert close_quiet(quiet, sums, state) == 1
    assert sums.n_open_passes == 0 and state.put_ids == [int(rows[0])]
