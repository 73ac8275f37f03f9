"""The solver's check of a landmark's position against its panel (``SolverConfig.
range_check_k``, :func:`hdmap.mapping.box_ranges.panel_discrepancy`): the rays' box
ranges at the estimate against the catalogue's nominal panel size.

Under the catalogue's model (one panel, its size log-normal with 10 %, the estimate where
its covariance says) ``z`` is standard normal: 400 simulated head-on approaches, seed 3,
its variance inside the chi-square 99.9 % interval. A landmark whose ranges put its panel
elsewhere is published with its covariance widened along the line of sight (a
candidate), its estimate unchanged; the sums survive a restart and follow a merge."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy import stats

from hdmap.mapping import box_ranges
from hdmap.runtime.service import ServiceOptions
from schemas import STATUS_CANDIDATE, STATUS_CONFIRMED, Links, NewLandmarks, Observations
from services.solver.service import SolverConfig, SolverService
from services.solver.state import SolverState
from tests.support.services import (
    CLS,
    SIGN,
    Sink,
    assoc_entry,
    matcher,
    one_sign_solver,
    sign_rays,
    tile_of,
    updates,
)

PANEL = 0.10


def approach(rng, eps: float, n: int = 12):
    """One head-on pass at a panel at the origin (4 m off the lane), 60 -> 10 m, its size
    ``exp(eps)`` times nominal: origins with 0.5 m white noise, boxes with 3 % noise."""
    y = np.linspace(-60.0, -10.0, n)
    a = np.stack([np.full(n, 4.0), y, np.zeros(n)], axis=1)
    dist = np.linalg.norm(a, axis=1)
    d = -a / dist[:, None]
    r = dist * np.exp(-eps) * (1.0 + rng.normal(0.0, 0.03, n))
    a_meas = a + np.c_[rng.normal(0.0, 0.5, (n, 2)), np.zeros(n)]
    return a_meas, d, r, r * np.hypot(PANEL, 0.03)


def test_z_is_standard_normal_for_panels_of_the_catalogues_spread():
    rng = np.random.default_rng(3)
    n = 400
    sums = np.zeros((n, box_ranges.N_SUMS))
    for k in range(n):
        eps = rng.normal(0.0, PANEL)
        for _ in range(5):  # passes
            a, d, r, sr = approach(rng, eps)
            h, w = box_ranges.ray_terms(a, d, r, sr, 0.5, PANEL)
            sums[k] += box_ranges.summed(np.zeros(len(r), np.int64), h, w)[0]
    cov = np.tile(np.eye(3) * 0.3**2, (n, 1, 1))
    z, g, s = box_ranges.panel_discrepancy(sums, np.zeros((n, 3)), cov, PANEL)
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], n) / n
    assert lo <= float(np.mean(z**2)) <= hi
    assert abs(float(np.mean(z))) <= stats.norm.ppf(0.9995) / np.sqrt(n)
    # g runs along the line of sight, about 1 / (typical range) long
    assert np.all(g[:, 1] > 0) and np.all((1 / 60 < g[:, 1]) & (g[:, 1] < 1 / 10))
    # the check changes none of them beyond k = 3 in more than the binomial share
    flagged = int((np.abs(z) > 3).sum())
    assert flagged <= stats.binom.ppf(0.999, n, 2 * stats.norm.sf(3.0))
    widened = box_ranges.widened_along_sight(cov, z, g, s, 3.0, PANEL)
    assert int((np.abs(widened - cov) > 0).any(axis=(1, 2)).sum()) == flagged


def test_a_landmark_off_its_panel_along_the_line_of_sight_is_widened_there_only():
    rng = np.random.default_rng(4)
    a, d, r, sr = approach(rng, 0.0)
    s = box_ranges.summed(
        np.zeros(len(r), np.int64), *box_ranges.ray_terms(a, d, r, sr, 0.5, PANEL)
    )
    x = np.array([[0.0, 15.0, 0.0]])  # 15 m beyond the panel, along the road
    cov = np.eye(3)[None] * 0.5**2
    z, g, sc = box_ranges.panel_discrepancy(s, x, cov, PANEL)
    assert z[0] > 3
    c = box_ranges.widened_along_sight(cov, z, g, sc, 3.0, PANEL)[0]
    lam, vec = np.linalg.eigh(c)
    assert np.sqrt(lam[-1]) > 5.0  # metres: the panel's place is within reach now
    u = g[0] / np.linalg.norm(g[0])  # the mean line of sight, about North
    assert abs(u[1]) > 0.98 and abs(float(vec[:, -1] @ u)) > 1 - 1e-9
    np.testing.assert_allclose(lam[:2], 0.25, rtol=1e-9)  # across it unchanged
    # the widened covariance puts the discrepancy at one standard deviation
    z1, _, _ = box_ranges.panel_discrepancy(s, x, c[None], PANEL)
    np.testing.assert_allclose(z1, 1.0, rtol=1e-9)


def _run(tmp: Path, cfg: SolverConfig, range_factor: float, passes: int = 10) -> SolverService:
    """The sign of tests/support/services.py seen over ``passes`` passes whose box ranges
    are ``range_factor`` times the cameras' distance to it."""

    def ranged(obs, frame):
        dist = np.linalg.norm(SIGN - frame.from_geodetic(obs.lat, obs.lon, obs.h), axis=1)
        rel = np.hypot(PANEL, 0.03)
        return replace(obs, range_m=range_factor * dist, sigma_range_m=range_factor * dist * rel)

    return one_sign_solver(tmp, cfg, passes, edit=ranged)


def test_the_solver_widens_only_what_its_panel_rules_out(tmp_path: Path):
    off = _run(tmp_path / "off", SolverConfig(panel_prior="off"), 1.6)
    on = _run(tmp_path / "on", SolverConfig(), 1.6)
    right = _run(tmp_path / "right", SolverConfig(), 1.0)
    a, b, c = (updates(s)[-1].landmarks for s in (off, on, right))
    assert a.status[0] == STATUS_CONFIRMED and c.status[0] == STATUS_CONFIRMED
    assert b.status[0] == STATUS_CANDIDATE  # its ranges put the panel 60 % farther
    assert (b.lat[0], b.lon[0], b.h[0]) == (a.lat[0], a.lon[0], a.h[0])  # estimate unchanged
    assert on.counters.get("range_discrepant", 0) >= 1
    assert right.counters.get("range_discrepant", 0) == 0
    # the sums are kept with the landmark and come back after a restart
    before = {i: lm.ranges.copy() for i, lm in on.state.landmarks.items()}
    assert all(r[4] > 0 for r in before.values())
    for s in (off, on, right):
        s.db.close()
    again = SolverService(ServiceOptions(data_dir=tmp_path / "on" / "s"), SolverConfig())
    assert {i: lm.ranges.tolist() for i, lm in again.state.landmarks.items()} == {
        i: r.tolist() for i, r in before.items()
    }
    again.db.close()


def test_the_box_range_sums_follow_a_merge(tmp_path: Path):
    """Two landmarks of one sign, each with half the passes, merged: the kept one's sums
    (box ranges and looming, its open passes too) are those of one landmark given every
    ray from the start."""
    tile = tile_of(ServiceOptions().zoom)
    m = matcher(tmp_path / "m")
    frame = m.frames(tile)
    rng = np.random.default_rng(6)
    obs = []
    for p in range(8):
        o = sign_rays(frame, p, rng)
        dist = np.linalg.norm(SIGN - frame.from_geodetic(o.lat, o.lon, o.h), axis=1)
        obs.append(replace(o, range_m=dist, sigma_range_m=dist * np.hypot(PANEL, 0.03)))
    ida, idb = m.state.next_id(tile), m.state.next_id(tile)
    lat, lon, h = frame.to_geodetic(SIGN[None])
    two = NewLandmarks(
        np.array([ida, idb], np.uint64), np.full(2, CLS, np.uint16), np.r_[lat, lat],
        np.r_[lon, lon], np.r_[h, h],
    )  # fmt: skip

    def entry(seq: int, ids: list[int], created: NewLandmarks):
        o = Observations.concat(obs)
        n = len(o)
        links = Links(
            np.repeat(np.array(ids, np.uint64), n // len(ids)),
            np.zeros(n, np.uint32),
            np.repeat(np.arange(8, dtype=np.uint64), n // 8),
            np.full(n, 1.7e9),
            np.ones(n, np.float32),
        )
        return assoc_entry(seq, tile, vehicles=["veh-1"], obs=o, links=links, created=created)

    merged = SolverService(ServiceOptions(data_dir=tmp_path / "a"), SolverConfig())
    merged.pubs = Sink()  # type: ignore[assignment]
    merged._apply_in_transaction([entry(1, [ida, idb], two)])
    merged._apply_in_transaction([assoc_entry(2, tile, retired=[idb], merged_into=[ida])])
    one = SolverService(ServiceOptions(data_dir=tmp_path / "b"), SolverConfig())
    one.pubs = Sink()  # type: ignore[assignment]
    one._apply_in_transaction([entry(1, [ida], two.take(np.array([0])))])
    got, want = merged.state.landmarks[ida].ranges, one.state.landmarks[ida].ranges
    assert want[4] > 0
    np.testing.assert_allclose(got, want, rtol=1e-12)
    # the looming passes, open on both, moved with the merge; once quiet, closed the same
    a, b = merged.state.landmarks[ida], one.state.landmarks[ida]
    assert len(a.loom_open) == 8
    np.testing.assert_allclose(
        SolverState.looming_sums([a]), SolverState.looming_sums([b]), rtol=1e-9
    )
    # every ray on the dropped one: its open passes still close on the kept one
    moved = SolverService(ServiceOptions(data_dir=tmp_path / "c"), SolverConfig())
    moved.pubs = Sink()  # type: ignore[assignment]
    moved._apply_in_transaction([entry(1, [idb], two)])
    moved._apply_in_transaction([assoc_entry(2, tile, retired=[idb], merged_into=[ida])])
    c = moved.state.landmarks[ida]
    for s in (merged, one, moved):
        assert s.state.close_loom(s.state.event_time + 1.0) == 8
    np.testing.assert_allclose(a.ranges, b.ranges, rtol=1e-9)
    np.testing.assert_allclose(c.ranges, b.ranges, rtol=1e-9)
    moved.db.close()
    merged.db.close()
    one.db.close()


def test_the_panel_update_is_consistent_and_helps_where_the_bearings_are_weak():
    """400 head-on landmarks whose bearing estimate is 4 m (1 sigma) off along the road:
    after the update their error along the road over its sigma is standard normal (mean
    square in the chi-square 99.9 % interval), and the error is smaller than before. One
    located to 0.2 m hardly moves."""
    rng = np.random.default_rng(8)
    n = 400
    sums = np.zeros((n, box_ranges.N_SUMS))
    for k in range(n):
        eps = rng.normal(0.0, PANEL)
        for _ in range(5):
            a, d, r, sr = approach(rng, eps)
            h, w = box_ranges.ray_terms(a, d, r, sr, 0.5, PANEL)
            sums[k] += box_ranges.summed(np.zeros(len(r), np.int64), h, w)[0]
    weak = np.tile(np.diag([0.2**2, 4.0**2, 0.2**2]), (n, 1, 1))
    xb = np.c_[np.zeros(n), rng.normal(0.0, 4.0, n), np.zeros(n)]
    x, c, _ = box_ranges.panel_update(sums, xb, weak, PANEL)
    z2 = x[:, 1] ** 2 / c[:, 1, 1]
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], n) / n
    assert lo <= float(np.mean(z2)) <= hi
    assert float(np.mean(x[:, 1] ** 2)) < 0.5 * float(np.mean(xb[:, 1] ** 2))
    sharp = np.tile(np.eye(3) * 0.2**2, (n, 1, 1))
    xs = np.c_[np.zeros(n), rng.normal(0.0, 0.2, n), np.zeros(n)]
    x2, c2, _ = box_ranges.panel_update(sums, xs, sharp, PANEL)
    assert float(np.abs(x2 - xs).max()) < 0.05  # metres
    assert float((c2[:, 1, 1] / sharp[:, 1, 1]).min()) > 0.9
