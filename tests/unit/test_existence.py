"""A landmark's existence log-odds (hdmap/mapping/existence.py) against simulation with
fixed seeds: how often a standing sign is revoked and how fast a removed one is, against
the exact probabilities of the clamped chain (bounds: binomial intervals for the stated
number of simulated landmarks)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from hdmap.mapping.existence import (
    CONFIRMED,
    DOUBTFUL,
    REVOKED,
    ExistenceConfig,
    l_after,
    passes_to_revoke,
    revocation_probability,
    status,
    update,
)

CFG = ExistenceConfig()


def simulate(p_seen: float, passes: int, n: int, seed: int) -> np.ndarray:
    """Whether each of ``n`` landmarks (from the cap, full looks, each pass seeing it with
    probability ``p_seen``) is revoked within ``passes``."""
    rng = np.random.default_rng(seed)
    l = np.full(n, CFG.l_max)
    for _ in range(passes):
        l = update(l, rng.random(n) < p_seen, np.full(n, CFG.full_frames), CFG)
    return l <= CFG.l_revoked


@pytest.mark.parametrize("p_seen, passes", [(0.8, 60), (0.7, 30), (0.02, 5), (0.02, 8)])
def test_revocations_in_simulation_match_the_exact_chain(p_seen: float, passes: int) -> None:
    n = 20_000
    p = revocation_probability(CFG, p_seen, passes)
    k = int(simulate(p_seen, passes, n, seed=11).sum())
    lo, hi = stats.binom.interval(0.999, n, p)
    assert lo <= k <= hi, (k, p * n, lo, hi)


def test_a_removed_sign_goes_in_five_passes_and_a_standing_one_rarely():
    assert passes_to_revoke(CFG, CFG.full_frames) == 5
    assert passes_to_revoke(CFG, CFG.full_frames // 2) > 5  # half looks: weaker evidence
    # gone, reported seen only by false detections: revoked within 5 passes (0.98^5)
    assert revocation_probability(CFG, CFG.p_false, 5) == pytest.approx(0.98**5, abs=1e-6)
    # standing, missed one pass in ten: under 0.3 % over 200 passes
    assert revocation_probability(CFG, CFG.p_detect, 200) < 3e-3


def test_status_is_clamped_and_revocation_is_final():
    assert status(CFG.l_max, CFG) == CONFIRMED
    assert l_after([True] * 50, CFG.l_max, CFG) == CFG.l_max  # capped
    l = l_after([False] * 3, CFG.l_max, CFG)
    assert status(l, CFG) == DOUBTFUL and l_after([True], l, CFG) > l
    gone = l_after([False] * 5, CFG.l_max, CFG)
    assert status(gone, CFG) == REVOKED
    assert l_after([True] * 10, gone, CFG) == gone  # final: a revoked id is never back


def test_no_frames_in_view_is_no_evidence_and_bad_settings_are_refused():
    l = np.array([0.5])
    assert update(l, [False], [0], CFG)[0] == pytest.approx(0.5)
    with pytest.raises(ValueError, match="p_false"):
        ExistenceConfig(p_detect=0.01, p_false=0.02)
    with pytest.raises(ValueError, match="l_revoked"):
        ExistenceConfig(l_revoked=2.0, l_confirmed=1.0)
