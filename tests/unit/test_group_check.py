"""Group check: the rays of one unit given to one landmark must meet near it.

Landmark B (class 7, 30 m up the road, known to 0.3 m); a pass with a well-determined
offset (0.3 m, as when other landmarks in view fix it) whose rays of sign A, 12 m before
B, were given to B ray by ray: together they meet at A, and the check takes them back;
the same pass's rays of B itself stay.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hdmap.mapping.association import Association
from hdmap.mapping.linking import to_local
from hdmap.mapping.unit import group_check
from hdmap.runtime.service import ServiceOptions
from services.matcher.service import MatcherService
from tests.support.services import SIGN, Sink, sign_rays, tile_of

SIGN_A = SIGN - np.array([0.0, 12.0, 0.0])


def check(svc: MatcherService, at: np.ndarray, seed: int) -> np.ndarray:
    frame = svc.frames(tile_of(svc.opts.zoom))
    rays = to_local(frame, sign_rays(frame, 0, np.random.default_rng(seed), at=at, n=8))
    res = Association(np.zeros(8, np.int64), np.zeros(8), np.zeros(3), np.eye(3) * 0.09)
    return group_check(svc.matching, rays, res, SIGN[None], np.eye(3)[None] * 0.09)


def test_rays_meeting_at_another_sign_are_taken_back(tmp_path: Path) -> None:
    svc = MatcherService(ServiceOptions(data_dir=tmp_path))
    svc.pubs = Sink()  # type: ignore[assignment]
    for seed in range(5):
        assert (check(svc, SIGN_A, seed) == -1).all()
        assert (check(svc, SIGN, seed) == 0).all()
    assert svc.counters["group_rejected"] == 5 * 8
