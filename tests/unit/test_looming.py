"""The looming check (:mod:`hdmap.mapping.looming`, ``SolverConfig.loom_check_k``): how a
landmark's boxes grow as the cars drive up says how far beyond its panel the estimate is,
whatever the panel's size.

Under the model (one panel of any size, passes with a shared origin error of ``TAU`` m per
horizontal axis, 0.5 m white per fix, 3 % white on the boxes) the statistic ``t`` at the
sign is about standard normal: 400 simulated landmarks of 8 head-on passes each (seed 3),
its mean square inside the chi-square 99.9 % interval, the share beyond 3 inside the
binomial bound. A landmark 12 m along the road from its panel is flagged and widened
along the line of sight only; the sums follow a change of frame; the solver on SQLite
makes a candidate of a landmark whose rays loom elsewhere and keeps one whose rays agree;
a pass whose rays come in several assoc entries, and across a restart, gives the sums of
the whole pass.
"""

from __future__ import annotations

import sqlite3
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from hdmap.mapping import box_ranges, looming
from schemas import STATUS_CANDIDATE, STATUS_CONFIRMED
from services.solver.service import SolverConfig
from services.solver.state import SolverLandmark, SolverState
from tests.support.services import (
    SIGN,
    one_sign_solver,
    updates,
)

PANEL = 0.10
TAU = 2.5
PASSES = 8
RAYS = 12


def passes(rng, n_passes: int = PASSES, beyond: float = 0.0, claim: float = 0.03):
    """``n_passes`` head-on passes at a panel at the origin (4 m off the lane), each from
    30-80 m to 10 m, the panel ``exp(N(0, PANEL))`` of its nominal size; per pass an origin
    error of ``TAU`` m per horizontal axis, per fix 0.5 m white, boxes 3 % white. With
    ``beyond``, the boxes are those of a panel that much farther along the road; the
    vehicle claims ``claim`` of relative box noise. Returns
    (origin, direction, range, sigma_range, pass index) of the rays."""
    eps = rng.normal(0.0, PANEL)
    out = []
    for p in range(n_passes):
        y = np.linspace(-rng.uniform(30.0, 80.0), -10.0, RAYS)
        a = np.stack([np.full(RAYS, 4.0), y, np.zeros(RAYS)], axis=1)
        dist = np.linalg.norm(a, axis=1)
        d = -a / dist[:, None]
        far = np.linalg.norm(a - [0.0, beyond, 0.0], axis=1)
        r = far * np.exp(-eps) * (1.0 + rng.normal(0.0, 0.03, RAYS))
        bias = np.r_[rng.normal(0.0, TAU, 2), 0.0]
        a_meas = a + bias + np.c_[rng.normal(0.0, 0.5, (RAYS, 2)), np.zeros(RAYS)]
        out.append((a_meas, d, r, r * np.hypot(PANEL, claim), np.full(RAYS, p)))
    return tuple(np.concatenate([o[i] for o in out]) for i in range(5))


def sums_of(rays) -> np.ndarray:
    a, d, r, sr, p = rays
    h, w = box_ranges.ray_terms(a, d, r, sr, 0.5, PANEL)
    return looming.summed(np.zeros(len(r), np.int64), p, h, w)


@pytest.mark.parametrize("claim", [0.03, 0.12])
def test_t_is_about_standard_normal_at_the_sign(claim):
    """Claims right, and four times the boxes' real noise (measured from the rays'
    scatter about their passes' lines)."""
    rng = np.random.default_rng(3)
    n = 400
    sums = np.concatenate([sums_of(passes(rng, claim=claim)) for _ in range(n)])
    t, g, _ = looming.discrepancy(sums, np.zeros((n, 3)), np.zeros((n, 3, 3)), TAU)
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], n) / n
    assert lo <= float(np.mean(t**2)) <= hi
    # the measured white noise over the claimed (var = c / S; S from the claimed weights)
    c = looming.offset(sums, np.zeros((n, 3)))[1] * sums[:, 4]
    if claim == 0.03:
        assert 0.8 < float(np.median(c)) < 1.25
    else:  # the box's 3 % and the origin's 0.5 m over 12 % and 0.5 m: about 0.1
        assert float(np.median(c)) < 0.2
    flagged = int((np.abs(t) > 3).sum())
    assert flagged <= stats.binom.ppf(0.999, n, 2 * stats.norm.sf(3.0))
    # g runs along the near rays' line of sight (North, toward the panel 4 m East), unit long
    assert np.all(g[:, 1] > 0.9) and np.all(g[:, 0] < 0)
    assert np.all(np.abs(np.linalg.norm(g, axis=1) - 1.0) < 0.05)


@pytest.mark.parametrize("claim", [0.03, 0.12])
def test_the_passes_shared_error_is_measured_from_their_slopes(claim):
    """200 landmarks of 30 passes (seed 5): ``q / a`` pooled estimates ``TAU^2`` within
    four of its standard errors (from the landmarks' own scatter); a landmark of 30 passes
    keeps mostly its measured value over a prior twice too small or large; sums without
    these terms give the prior."""
    rng = np.random.default_rng(5)
    n = 200
    sums = np.concatenate([sums_of(passes(rng, 30, claim=claim)) for _ in range(n)])
    x = np.zeros((n, 3))
    q, a = looming.shared_scatter(sums, x)
    tau2 = q.sum() / a.sum()
    se = np.sqrt(((q - tau2 * a) ** 2).sum()) / a.sum()
    assert abs(tau2 - TAU**2) < 4 * se, (tau2, se)
    assert se < 0.15 * TAU**2
    # a prior twice too small or large weighs as 4 of 34 passes: 0.90 and 1.35 TAU^2
    lo, hi = (np.median(looming.shared_error(sums, x, p)) for p in (TAU / 2, TAU * 2))
    assert 0.7 * TAU**2 < lo < TAU**2 < hi < 1.6 * TAU**2
    # q and a are the passes' own slopes' scatter, as computed pass by pass
    rays = passes(rng, 30, claim=claim)
    a_, d_, r_, sr_, p_ = rays
    h, w = box_ranges.ray_terms(a_, d_, r_, sr_, 0.5, PANEL)
    raw = np.zeros((30, looming.RAW))
    np.add.at(raw, p_.astype(np.int64), looming.raw_terms(h, w))
    per = looming.pass_sums(raw)
    one = looming.summed(np.zeros(len(r_), np.int64), p_, h, w)
    x1 = np.array([[1.0, 3.0, 0.5]])
    d_p = per[:, :4] @ np.append(x1, 1.0) / per[:, 4]
    delta, var, _, _ = looming.offset(one, x1)
    s_all = per[:, 4].sum()
    q1 = (per[:, 4] * (d_p - delta[0]) ** 2).sum() - var[0] * s_all * 29
    a1 = (per[:, 5] / per[:, 4]).sum() - per[:, 5].sum() / s_all
    np.testing.assert_allclose(looming.shared_scatter(one, x1), [[q1], [a1]], rtol=1e-6)
    older = sums.copy()
    older[:, 17:] = np.nan  # sums of an older layout: the prior
    np.testing.assert_allclose(looming.shared_error(older, x, TAU), TAU**2)


def test_a_landmark_along_the_road_from_its_panel_is_widened_there_only():
    rng = np.random.default_rng(4)
    sums = sums_of(passes(rng))
    x = np.array([[0.0, 12.0, 0.0]])  # 12 m beyond the panel, along the road
    cov = np.eye(3)[None] * 0.5**2
    t, g, spread = looming.discrepancy(sums, x, cov, TAU)
    assert t[0] > 3
    delta, _, _, _ = looming.offset(sums, x)
    assert abs(delta[0] - 12.0) < 3 * np.sqrt(spread[0])
    c = box_ranges.widened_along(cov, t, g, spread, 3.0)[0]
    lam, vec = np.linalg.eigh(c)
    u = g[0] / np.linalg.norm(g[0])
    assert abs(float(vec[:, -1] @ u)) > 1 - 1e-9 and np.sqrt(lam[-1]) > 5.0
    np.testing.assert_allclose(lam[:2], 0.25, rtol=1e-9)  # across the line of sight unchanged
    t1, _, _ = looming.discrepancy(sums, x, c[None], TAU)
    np.testing.assert_allclose(np.abs(t1), 1.0, rtol=1e-9)
    # the panel's own place is not flagged
    t0, _, _ = looming.discrepancy(sums, np.zeros((1, 3)), cov, TAU)
    assert abs(t0[0]) < 3


def test_the_sums_follow_a_change_of_frame():
    rng = np.random.default_rng(5)
    a, d, r, sr, p = passes(rng)
    ang = 0.3
    rot = np.array([[np.cos(ang), -np.sin(ang), 0.0], [np.sin(ang), np.cos(ang), 0.0], [0, 0, 1]])
    t = np.array([120.0, -40.0, 2.0])
    half = p < PASSES // 2
    s_f = sums_of((a[half], d[half], r[half], sr[half], p[half]))  # kept in frame F
    s_g = sums_of((a[~half] @ rot.T + t, d[~half] @ rot.T, r[~half], sr[~half], p[~half]))
    both = looming.in_frame(s_f, rot, t) + s_g  # frame G
    whole = sums_of((a @ rot.T + t, d @ rot.T, r, sr, p))
    np.testing.assert_allclose(both, whole, rtol=1e-9, atol=1e-12)
    x_f = np.array([[1.0, 5.0, 0.5]])
    np.testing.assert_allclose(
        looming.offset(s_f, x_f)[0],
        looming.offset(looming.in_frame(s_f, rot, t), x_f @ rot.T + t)[0],
    )


def _run(tmp: Path, cfg: SolverConfig, beyond: float):
    """The sign of tests/support/services.py over 10 passes whose boxes are those of a
    nominal panel ``beyond`` m farther from every camera."""

    def ranged(obs, frame):
        dist = np.linalg.norm(SIGN - frame.from_geodetic(obs.lat, obs.lon, obs.h), axis=1)
        r = dist + beyond
        return replace(obs, range_m=r, sigma_range_m=r * np.hypot(PANEL, 0.03))

    return one_sign_solver(tmp, cfg, 10, edit=ranged)


def test_the_solver_makes_a_candidate_of_a_landmark_its_looming_rules_out(tmp_path: Path):
    # panel_prior off: the ranges' scale says nothing; only how they change does
    base = SolverConfig(panel_prior="off")
    far = _run(tmp_path / "far", base, 15.0)
    right = _run(tmp_path / "right", base, 0.0)
    unchecked = _run(tmp_path / "unchecked", replace(base, loom_check_k=0.0), 15.0)
    a, b, c = (updates(s)[-1].landmarks for s in (far, right, unchecked))
    assert a.status[0] == STATUS_CANDIDATE
    assert b.status[0] == STATUS_CONFIRMED and c.status[0] == STATUS_CONFIRMED
    assert (a.lat[0], a.lon[0], a.h[0]) == (c.lat[0], c.lon[0], c.h[0])  # estimate unchanged
    assert far.counters.get("loom_discrepant", 0) >= 1
    assert right.counters.get("loom_discrepant", 0) == 0
    for s in (far, right, unchecked):
        s.db.close()


def _split_solver(tmp: Path, cuts: int, restart_after: int | None = None):
    """The sign of tests/support/services.py over 6 passes with the box ranges of a
    nominal panel, each pass's rays in ``cuts`` assoc entries (:func:`one_sign_solver`)."""

    def ranged(obs, frame):
        dist = np.linalg.norm(SIGN - frame.from_geodetic(obs.lat, obs.lon, obs.h), axis=1)
        return replace(obs, range_m=dist, sigma_range_m=dist * np.hypot(PANEL, 0.03))

    return one_sign_solver(
        tmp, SolverConfig(), 6, edit=ranged, cuts=cuts, restart_after=restart_after
    )


def test_a_pass_cut_into_entries_gives_the_looming_of_the_whole_pass(tmp_path: Path):
    whole = _split_solver(tmp_path / "whole", 1)
    cut = _split_solver(tmp_path / "cut", 3)
    restarted = _split_solver(tmp_path / "restarted", 3, restart_after=3)
    (a,), (b,), (c,) = (list(s.state.landmarks.values()) for s in (whole, cut, restarted))
    sa, sb, sc = (SolverState.looming_sums([lm]) for lm in (a, b, c))
    np.testing.assert_allclose(sb, sa, rtol=1e-9)
    np.testing.assert_allclose(sc, sa, rtol=1e-9)
    # the passes a minute apart are open (two hours of quiet close them), each one whole
    assert len(a.loom_open) == 6 and len(c.loom_open) == 6
    # once quiet they are closed into the sums with nothing changed
    for s in (whole, cut, restarted):
        s.state.close_loom(s.state.event_time + 1.0)
    assert not a.loom_open and not c.loom_open
    np.testing.assert_allclose(SolverState.looming_sums([a]), sa, rtol=1e-9)
    np.testing.assert_allclose(SolverState.looming_sums([c]), sa, rtol=1e-9)
    for s in (whole, cut, restarted):
        s.db.close()


def test_open_passes_close_by_their_last_ray_and_only_changed_rows_are_written(tmp_path: Path):
    """``SolverState``'s due heap skips an entry whose pass has moved on since; a save
    writes the open passes changed since the last one (a restart reads the same)."""
    conn = sqlite3.connect(tmp_path / "state.sqlite")
    st = SolverState(conn)
    lm = SolverLandmark(7, 0, "t", 0)
    st.put(lm)
    h = np.array([[0.0, 1 / 40, 0.0, 0.0, 1.0], [0.0, 1 / 20, 0.0, 0.0, 1.0]])
    w = np.ones(2)

    def rays(pass_key: int, t: float) -> None:
        st.note_ranges([lm, lm], h, w, np.full(2, pass_key, np.uint64), np.full(2, t))

    rays(1, 10.0)
    rays(2, 10.0)
    st.save(lambda rows: [b""] * len(rows))
    rays(1, 50.0)  # pass 1 goes on: its entry at 10 is stale
    writes = []
    conn.set_trace_callback(writes.append)
    st.save(lambda rows: [b""] * len(rows))
    conn.set_trace_callback(None)
    assert sum("INSERT OR REPLACE INTO loom_open" in q for q in writes) == 1  # pass 1 only
    assert st.close_loom(20.0) == 1 and list(lm.loom_open) == [1]
    assert st.close_loom(50.0) == 0 and st.close_loom(50.5) == 1 and not lm.loom_open
    st.save(lambda rows: [b""] * len(rows))
    assert conn.execute("SELECT count(*) FROM loom_open").fetchone() == (0,)
    conn.close()
