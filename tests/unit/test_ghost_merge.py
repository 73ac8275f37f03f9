"""A sign's second landmark from a street it does not face (a "ghost") merges into the
sign's landmark on the evidence of its rays' box ranges; two real signs on one line of
sight stay two (:func:`hdmap.mapping.merge.ghost_partner`, :mod:`hdmap.mapping.box_ranges`).

Scene (in-process matcher on real SQLite, through its transactions): sign A at a corner
faces West, seen by eastbound cars; northbound cars on the crossing street see a panel
whose rays converge 8 m beyond A along their line of sight, at B (what a street's shared
heading errors do to a sign seen head-on). In the ghost case their boxes measure the
distance to A (the panel they see is A's, real size 0.95 of the nominal); in the control
a real sign stands at B, its boxes measuring the distance to B (a panel of its own,
0.93 of the nominal). Noise: each pass's GNSS bias 1 m per axis, 0.01 rad on the
directions, 3 % white on the box ranges; seed fixed.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from fleetsim.synthetic import ray_observations
from hdmap.mapping import box_ranges
from hdmap.mapping.facing import Facing, FacingConfig, ray_compatible
from hdmap.runtime.service import ServiceOptions
from schemas import LogEntry, ObsGroup
from services.matcher.service import MatcherConfig, MatcherService
from tests.support.services import CLS, Sink, tile_of

T0 = 1.7e9
A = np.array([-2.7, -4.1, 2.4])
"""Faces West: seen by eastbound cars on y = -1.75."""
LOS = np.array([-4.45, 30.9, 0.0]) / np.hypot(4.45, 30.9)
"""Northbound cars' line of sight to A (from about 35 m south of the junction)."""
B = A + 8.0 * LOS


def a_pass(frame, p: int, rng: np.random.Generator, ghost: bool) -> object:
    """Pass ``p``: the first 12 and then every even one eastbound (rays at A, ranges to A),
    the others northbound (rays at B; ranges to A when ``ghost``, else to B)."""
    s = np.linspace(-60.0, -9.0, 12)
    if p < 12 or p % 2 == 0:
        o = np.stack([s, np.full(12, -1.75), np.full(12, 1.5)], 1)
        at, panel, scale = A, A, 0.95
    else:
        o = np.stack([np.full(12, 1.75), s, np.full(12, 1.5)], 1)
        at, panel, scale = B, (A if ghost else B), (0.95 if ghost else 0.93)
    meas = o + np.r_[rng.normal(0, 1.0, 2), 0.0]
    v = at - o + rng.normal(0, 0.01, (12, 3)) * np.linalg.norm(at - o, axis=1)[:, None]
    d = v / np.linalg.norm(v, axis=1, keepdims=True)
    r = np.linalg.norm(panel - o, axis=1) / scale * (1.0 + rng.normal(0, 0.03, 12))
    lat, lon, h = frame.to_geodetic(meas)
    obs = ray_observations(lat, lon, h, d, np.arange(12), np.arange(12) + 100 * p, CLS, 0.01)
    return replace(
        obs, t=np.full(12, T0 + 30.0 * p), range_m=r, sigma_range_m=r * np.hypot(0.03, 0.1)
    )


def run(tmp_path: Path, ghost: bool, config: MatcherConfig) -> MatcherService:
    """84 passes: 12 eastbound, then the streets alternating (36 northbound)."""
    m = MatcherService(ServiceOptions(data_dir=tmp_path / "m"), config)
    m.pubs = Sink()  # type: ignore[assignment]
    tile = tile_of(m.opts.zoom)
    frame = m.frames(tile)
    rng = np.random.default_rng(5)
    for p in range(84):
        body = ObsGroup(f"veh-{p % 7}", p, p, T0 + 30.0 * p + 5.0, a_pass(frame, p, rng, ghost))
        m._apply_in_transaction([LogEntry("obs", "ingest-t", tile, p + 1, p + 1, body.to_bytes())])
    return m


def positions(m: MatcherService) -> np.ndarray:
    """The landmarks' gating positions in the test tile's frame."""
    frame = m.frames(tile_of(m.opts.zoom))
    return np.array([frame.from_ecef(lm.x[None])[0] for lm in m.state.landmarks.values()])


@pytest.mark.parametrize("ghost", [True, False])
def test_a_second_street_copy_merges_and_two_signs_on_its_line_do_not(
    tmp_path: Path, ghost: bool
) -> None:
    """Without the rule and the second facing both cases end as two landmarks, near A and
    near B (the facing gate keeps the northbound rays off A's landmark and no other merge
    joins them); with the rule alone the ghost folds into A's landmark (counted
    ``merged_ghosts``), with both (the default) the northbound rays join A's landmark once
    an early merge gave it their street's facing; the two signs stay two every way."""
    off = MatcherConfig(merge_ghost_max_m=0.0, merge_second_facing=False)
    x = positions(run(tmp_path / "off", ghost, off))
    assert len(x) == 2
    apart = np.linalg.norm(x[:, None, :2] - np.stack([A, B])[None, :, :2], axis=2)
    assert apart.min(0).max() < 3.0  # one near A, one near B
    rule = run(tmp_path / "rule", ghost, MatcherConfig(merge_second_facing=False))
    both = run(tmp_path / "both", ghost, MatcherConfig())
    for m in (rule, both):
        x = positions(m)
        if ghost:
            assert len(x) == 1 and np.hypot(*(x[0] - A)[:2]) < 3.0
        else:
            assert len(x) == 2 and m.counters.get("merged_ghosts", 0) == 0
    if ghost:
        assert rule.counters.get("merged_ghosts", 0) >= 1


def test_range_sums_move_between_frames_and_add() -> None:
    """Sums built in one frame and moved to another equal the sums built there from the
    moved rays (a rotation about the vertical and a tilt, a translation), and summing two
    landmarks' sums gives the sums of all their rays."""
    rng = np.random.default_rng(2)
    n = 40
    o = rng.normal(0, 30, (n, 3))
    d = rng.normal(0, 1, (n, 3))
    r, sr, sh = rng.uniform(5, 60, n), rng.uniform(0.5, 5, n), rng.uniform(0.5, 2, n)
    ids = rng.integers(0, 3, n)
    h, w = box_ranges.ray_terms(o, d, r, sr, sh, 0.1)
    sums = box_ranges.summed(ids, h, w)
    c, s = np.cos(0.7), np.sin(0.7)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.array(
        [[1.0, 0.0, 0.0], [0.0, np.cos(0.01), -np.sin(0.01)], [0.0, np.sin(0.01), np.cos(0.01)]]
    )
    t = np.array([812.0, -455.0, 3.0])
    h2, w2 = box_ranges.ray_terms(o @ rot.T + t, d @ rot.T, r, sr, sh, 0.1)
    direct = box_ranges.summed(ids, h2, w2)
    np.testing.assert_allclose(box_ranges.in_frame(sums, rot, t), direct, rtol=1e-9, atol=1e-9)
    one = box_ranges.summed(np.zeros(n, np.int64), h, w)
    np.testing.assert_allclose(sums.sum(0), one[0], rtol=1e-12)
    x = rng.normal(0, 5, (1, 3))
    np.testing.assert_allclose(
        box_ranges.mean_relative_range(one, x),
        box_ranges.mean_relative_range(box_ranges.in_frame(one, rot, t), x @ rot.T + t),
        rtol=1e-9,
    )


def test_mean_relative_range_is_the_panel_scale_and_ignores_rays_without_range() -> None:
    """Noiseless rays: at the panel the mean relative range is the panel's size over the
    nominal, whatever it is; rays without a range add nothing."""
    o = np.stack([np.zeros(6), np.linspace(-50, -10, 6), np.zeros(6)], 1)
    d = -o / np.linalg.norm(o, axis=1, keepdims=True)
    r = np.linalg.norm(o, axis=1)
    for scale in (0.8, 1.0, 1.2):
        h, w = box_ranges.ray_terms(o, d, r / scale, r * 0.1, np.ones(6), 0.1)
        s = box_ranges.summed(np.zeros(6, np.int64), h, w)
        assert box_ranges.mean_relative_range(s, np.zeros((1, 3)))[0] == pytest.approx(scale)
    h, w = box_ranges.ray_terms(o, d, np.zeros(6), np.zeros(6), np.ones(6), 0.1)
    assert not w.any()
    empty = np.zeros((1, box_ranges.N_SUMS))
    assert np.isnan(box_ranges.mean_relative_range(empty, np.zeros((1, 3)))).all()


def test_range_sums_and_panel_scales_survive_a_restart(tmp_path: Path) -> None:
    """The box-range sums and gating panel scales are saved with their landmarks and
    loaded as they were."""
    m = run(tmp_path, True, MatcherConfig(merge_ghost_max_m=0.0))
    before = {lid: (lm.ranges.copy(), lm.scale) for lid, lm in m.state.landmarks.items()}
    assert all(r.any() for r, _ in before.values())
    assert any(np.isfinite(s) for _, s in before.values())
    m.db.close()
    again = MatcherService(ServiceOptions(data_dir=tmp_path / "m"), MatcherConfig())
    after = {lid: (lm.ranges, lm.scale) for lid, lm in again.state.landmarks.items()}
    assert before.keys() == after.keys()
    for lid, (r, s) in before.items():
        np.testing.assert_array_equal(after[lid][0], r)
        np.testing.assert_equal(after[lid][1], s)
    again.db.close()


def test_each_landmark_gates_with_its_own_panels_scale(tmp_path: Path) -> None:
    """Two real signs on one line of sight (A 0.95 of the nominal size, B 0.93): each
    landmark's gating scale is its panel's. Bound: a gating position 0.5 m off along
    rays 20-60 m long moves the mean relative range by up to 0.025; the 3 % white noise
    averaged over hundreds of rays adds under 0.003."""
    m = run(tmp_path, False, MatcherConfig())
    x = positions(m)
    scales = np.array([lm.scale for lm in m.state.landmarks.values()])
    for sign, panel in ((A, 0.95), (B, 0.93)):
        k = int(np.argmin(np.linalg.norm(x - sign, axis=1)))
        assert np.linalg.norm(x[k] - sign) < 3.0
        assert abs(scales[k] - panel) <= 0.03
    m.db.close()


def test_a_second_facing_lets_its_street_through_the_gate_and_no_other() -> None:
    """A landmark seen from the West (285 deg) with a second street to its South (180 deg):
    rays seen from the South pass its gate, rays from the East (90 deg) do not; without
    the second facing the southern rays are refused too."""
    cfg = FacingConfig()
    f = Facing(np.radians([285.0]), np.radians([2.0]), np.radians([12.0]), np.array([True]))
    theta = np.radians([280.0, 185.0, 90.0])
    idx = np.zeros(3, np.int64)
    assert ray_compatible(theta, f.take(idx), cfg).tolist() == [True, False, False]
    two = replace(f, second=np.radians([180.0]))
    assert ray_compatible(theta, two.take(idx), cfg).tolist() == [True, True, False]
    both = Facing.concat([two, f])  # one with a second facing, one without
    assert np.isnan(both.second[1]) and both.second[0] == pytest.approx(np.pi)
