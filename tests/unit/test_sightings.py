"""Landmarks the passes that have them in view do not detect are retired
(hdmap/mapping/sightings.py): a second copy of a sign 10 m along the road goes, the sign
stays. In-process matcher on real SQLite (scene of tests/support/services.py: a sign at
(10, 30), passes driving north at x = 12 towards it)."""

from __future__ import annotations

from collections import defaultdict
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from hdmap.geo.geodesy import EnuFrame
from hdmap.mapping.landmarks import Landmark
from hdmap.mapping.linking import create, to_local
from hdmap.mapping.matching import AssocOutput
from hdmap.mapping.sightings import (
    SightingConfig,
    outshone,
    share_lower_bound,
    share_upper_bound,
    unseen,
)
from hdmap.mapping.tick import retire_unseen
from hdmap.mapping.trust import TrustConfig
from hdmap.mapping.unit import count_sightings
from hdmap.runtime.service import ServiceOptions
from services.matcher.service import MatcherConfig, MatcherService
from tests.support.services import CLS, SIGN, Sink, sign_rays, tile_of

GHOST = SIGN + np.array([0.0, 12.0, 0.0])


@pytest.mark.parametrize("n", [20, 31, 57, 200])
def test_the_share_bound_is_clopper_pearson(n: int) -> None:
    for s in range(0, n, max(1, n // 7)):
        want = stats.beta.ppf(0.999, s + 1, n - s)
        assert share_upper_bound(s, n, 0.999) == pytest.approx(want, abs=1e-9)


def test_unseen_needs_enough_looks_and_a_low_share() -> None:
    cfg = SightingConfig()
    # 1 - 0.001 ** (1 / n) < 0.2 from n = 31 on: never seen in 30 looks is not yet enough
    assert not unseen(0, 30, cfg) and unseen(0, 31, cfg)
    assert not unseen(0, 19, replace(cfg, min_in_view=20))
    assert not unseen(10, 40, cfg)  # a quarter of the passes: a sign hard to see, kept


def test_neighbours_detected_alike_are_not_outshone_at_the_stated_confidence() -> None:
    """Two signs of one class that the same passes have in view, detected at one true rate:
    the rule retires one only when its share's upper bound falls under half the other's
    lower bound, each at 99.9 %: at most 0.1 % of such pairs (one-sided), here far fewer.
    3,000 pairs (seed 12, rates 0.3-0.9, 20-300 looks each): the count stays within the
    99.9 % binomial quantile of a 0.1 % rate."""
    cfg = SightingConfig()
    rng = np.random.default_rng(12)
    n_pairs, bad = 3000, 0
    for _ in range(n_pairs):
        p = rng.uniform(0.3, 0.9)
        n1, n2 = rng.integers(20, 301, size=2)
        s1, s2 = rng.binomial(n1, p), rng.binomial(n2, p)
        bad += outshone(int(s1), int(n1), [int(s2)], [int(n2)], cfg)
    assert bad <= stats.binom.ppf(0.999, n_pairs, 0.001)
    assert share_lower_bound(10, 40, 0.999) == pytest.approx(stats.beta.ppf(0.001, 10, 31))


@pytest.mark.parametrize("ghost_facing", [np.pi, np.pi / 2])
def test_a_copy_seen_by_a_fraction_of_its_signs_passes_is_outshone(
    tmp_path: Path, ghost_facing: float
) -> None:
    """The sign's passes link their rays to it; three passes in ten put their last ray on
    the copy 12 m along the road: a share (0.3) above ``p_min`` that the absolute test
    keeps for ever, but under half the sign's: retired as outshone once the bounds part
    (about 100 passes); the sign stays. Seen from another side, the copy would be kept."""
    m, frame, sign, ghost = sign_and_copy(tmp_path)
    sign.facing = np.array([np.pi, 0.02, 0.1, 1.0])  # seen from the south (passes go north)
    ghost.facing = np.array([ghost_facing, 0.02, 0.1, 1.0])
    rng = np.random.default_rng(5)
    gone_at = None
    for p in range(1, 201):
        cands = [m.state.landmarks[i] for i in (sign.id, ghost.id) if i in m.state.landmarks]
        rays = to_local(frame, sign_rays(frame, p, rng))
        matched = np.zeros(len(rays), np.int64)
        if p % 10 in (0, 3, 6) and len(cands) == 2:
            matched[-1] = 1
        counted = count_sightings(m.matching, frame, rays, cands, matched)
        gone = retire_unseen(m.matching, counted)
        if gone:
            assert gone == {ghost.id} and gone_at is None
            gone_at = p
    assert m.counters.get("retired_unseen", 0) == 0 and sign.id in m.state.landmarks
    if ghost_facing != np.pi:  # 90 degrees apart: another sign's face, not compared
        assert gone_at is None and ghost.id in m.state.landmarks
        return
    assert gone_at is not None and 60 <= gone_at <= 160, gone_at
    assert m.counters["retired_outshone"] == 1


def sign_and_copy(path: Path) -> tuple[MatcherService, EnuFrame, Landmark, Landmark]:
    """The scene's matcher with two landmarks of the sign's class: at the sign and 12 m
    beyond it along the road (the tile's frame, the two landmarks)."""
    m = service(path)
    tile = tile_of(m.opts.zoom)
    frame = m.frames(tile)
    m.matching.out = defaultdict(AssocOutput)
    sign = create(m.matching, tile, CLS, frame.to_ecef(SIGN[None])[0], np.eye(3))
    ghost = create(m.matching, tile, CLS, frame.to_ecef(GHOST[None])[0], np.eye(3))
    return m, frame, sign, ghost


def service(path: Path) -> MatcherService:
    cfg = MatcherConfig(trust=TrustConfig(probation_passes=0))
    svc = MatcherService(ServiceOptions(data_dir=path), cfg)
    svc.pubs = Sink()  # type: ignore[assignment]
    return svc


def test_a_second_copy_that_passes_never_detect_is_retired(tmp_path: Path) -> None:
    """Each pass links its rays to the sign (as the association does); the copy 12 m
    along the road is in view of the pass's last rays and gets none."""
    m, frame, sign, ghost = sign_and_copy(tmp_path)
    rng = np.random.default_rng(3)
    for p in range(1, 41):
        if p == 11:  # restart: the counts are stored with the landmarks
            with m.transaction([m]):
                m.state.save(m.sums.pack_rows)
            m.db.close()
            m = service(tmp_path)
            m.matching.out = defaultdict(AssocOutput)
        cands = [m.state.landmarks[i] for i in (sign.id, ghost.id) if i in m.state.landmarks]
        rays = to_local(frame, sign_rays(frame, p, rng))
        counted = count_sightings(m.matching, frame, rays, cands, np.zeros(len(rays), np.int64))
        assert counted == sorted(c.id for c in cands)  # the pass had both in view
        gone = retire_unseen(m.matching, counted)  # what the end of its gating tick does
        if gone:
            assert gone == {ghost.id} and p == 31  # the first n with 1 - 0.001^(1/n) < 0.2
    assert sign.id in m.state.landmarks and ghost.id not in m.state.landmarks
    assert m.counters["retired_unseen"] == 1
    kept = m.state.landmarks[sign.id]
    assert kept.seen == kept.in_view == 40
    assert m.matching.out[ghost.home].ended == [ghost.id]  # the solver is told
    with m.transaction([m]):
        m.state.save(m.sums.pack_rows)
    again = service(tmp_path)
    assert ghost.id not in again.state.landmarks
    assert (again.state.landmarks[sign.id].in_view, again.state.landmarks[sign.id].seen) == (40, 40)


def test_a_copy_seen_by_a_third_of_the_passes_stays(tmp_path: Path) -> None:
    m = service(tmp_path)
    tile = tile_of(m.opts.zoom)
    frame = m.frames(tile)
    m.matching.out = defaultdict(AssocOutput)
    lm = create(m.matching, tile, CLS, frame.to_ecef(GHOST[None])[0], np.eye(3))
    rng = np.random.default_rng(4)
    for p in range(1, 201):
        rays = to_local(frame, sign_rays(frame, p, rng))
        matched = np.full(len(rays), 0 if p % 3 == 0 else -1, np.int64)
        counted = count_sightings(m.matching, frame, rays, [lm], matched)
        assert not retire_unseen(m.matching, counted)
    assert lm.in_view == 200 and lm.seen == 66
