"""Group check: the rays of one unit given to one landmark must meet near it.

Landmark B (class 7, 30 m up the road, known to 0.3 m); a pass with a well-determined
offset (0.3 m, as when other landmarks in view fix it) whose rays of sign A, 12 m before
B, were given to B ray by ray: together they meet at A, and the check takes them back;
the same pass's rays of B itself stay. Taken back, tracked rays are dropped (their track
chose the landmark as a whole) and untracked ones wait in the pending pool.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from hdmap.mapping.association import Association
from hdmap.mapping.linking import to_local
from hdmap.mapping.matching import MatchingConfig
from hdmap.mapping.unit import discarded, group_check
from hdmap.runtime.service import ServiceOptions
from services.matcher.service import MatcherService
from tests.support.services import SIGN, Sink, sign_rays, tile_of

SIGN_A = SIGN - np.array([0.0, 12.0, 0.0])


RES = Association(np.zeros(8, np.int64), np.zeros(8), np.zeros(3), np.eye(3) * 0.09)


def check(svc: MatcherService, at: np.ndarray, seed: int, track: int = 0) -> np.ndarray:
    frame = svc.frames(tile_of(svc.opts.zoom))
    rays = to_local(frame, sign_rays(frame, 0, np.random.default_rng(seed), at=at, n=8))
    if track:
        rays = replace(rays, track=np.full(8, track, np.int64))
    return group_check(svc.matching, rays, RES, SIGN[None], np.eye(3)[None] * 0.09)


def test_rays_meeting_at_another_sign_are_taken_back(tmp_path: Path) -> None:
    svc = MatcherService(ServiceOptions(data_dir=tmp_path))
    svc.pubs = Sink()  # type: ignore[assignment]
    for seed in range(5):
        assert (check(svc, SIGN_A, seed) == -1).all()
        assert (check(svc, SIGN, seed) == 0).all()
    assert svc.counters["group_rejected"] == 5 * 8


def test_tracked_rays_taken_back_are_dropped_untracked_wait(tmp_path: Path) -> None:
    svc = MatcherService(ServiceOptions(data_dir=tmp_path))
    svc.pubs = Sink()  # type: ignore[assignment]
    tracked, loose = np.full(8, 4), np.zeros(8, np.int64)
    for seed in range(3):
        back = check(svc, SIGN_A, seed, track=4)
        assert (back == -1).all()
        assert discarded(RES, back, tracked, svc.matching.config).all()
        assert not discarded(RES, check(svc, SIGN_A, seed), loose, svc.matching.config).any()
        kept = check(svc, SIGN, seed, track=4)  # B's own track stays linked, nothing dropped
        assert (kept == 0).all() and not discarded(RES, kept, tracked, svc.matching.config).any()
    pooled = MatchingConfig(group_drop_tracked=False)
    assert not discarded(RES, np.full(8, -1), tracked, pooled).any()
