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

from hdmap.mapping.linking import create, to_local
from hdmap.mapping.matching import AssocOutput
from hdmap.mapping.sightings import SightingConfig, share_upper_bound, unseen
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


def service(path: Path) -> MatcherService:
    cfg = MatcherConfig(trust=TrustConfig(probation_passes=0))
    svc = MatcherService(ServiceOptions(data_dir=path), cfg)
    svc.pubs = Sink()  # type: ignore[assignment]
    return svc


def test_a_second_copy_that_passes_never_detect_is_retired(tmp_path: Path) -> None:
    """Each pass links its rays to the sign (as the association does); the copy 12 m
    along the road is in view of the pass's last rays and gets none."""
    m = service(tmp_path)
    tile = tile_of(m.opts.zoom)
    frame = m.frames(tile)
    m.matching.out = defaultdict(AssocOutput)
    sign = create(m.matching, tile, CLS, frame.to_ecef(SIGN[None])[0], np.eye(3))
    ghost = create(m.matching, tile, CLS, frame.to_ecef(GHOST[None])[0], np.eye(3))
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
