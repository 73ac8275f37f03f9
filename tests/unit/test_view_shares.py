"""``vehicle.pose.view_shares``: the part of each claimed GNSS sigma that changes within a
view of a sign, measured from the fixes alone (issue #18 point 4).

Synthetic fix tracks with known error structure (fixed seeds): 5 Hz with 10 ms jitter and
5 % of the fixes missing, 3,000 fixes (10 minutes of driving). Bounds: the share is
``1.4826 median |z|`` over the claim, a MAD scale estimate whose relative standard
deviation for ``n`` independent normal ``z`` is ``1.166 / sqrt(n)`` (asymptotic variance
of the median of ``|z|``: ``1 / (4 n f(q)^2)``, ``f`` the half-normal density at its
median ``q = 0.6745``). Overlapping triples share fixes, so ``n`` is taken as a stated
fraction of the triples (an effective count, conservative), and every check is at four of
those standard deviations.
"""

from __future__ import annotations

import numpy as np

from vehicle.pose import STRAIGHT_K, straight_lag_triples, view_shares, white_share

LAG_S = 2.0
RATE_HZ = 5.0
N_FIXES = 3000


def fix_times(rng: np.random.Generator, n: int = N_FIXES) -> np.ndarray:
    t = np.arange(n) / RATE_HZ + rng.normal(0.0, 0.01, n)
    keep = rng.random(n) > 0.05
    return np.sort(t[keep])


def mad_band(n_triples: int, effective_fraction: float, k: float = 4.0) -> float:
    """``k`` relative standard deviations of the MAD scale over an effective count."""
    return k * 1.166 / np.sqrt(effective_fraction * n_triples)


def straight_count(t: np.ndarray, psi: np.ndarray, s: np.ndarray) -> int:
    tri = straight_lag_triples(t, psi, s, LAG_S)
    return 0 if tri is None else int(tri[0].size)


def test_white_heading_counts_whole_and_a_pass_bias_not_at_all():
    rng = np.random.default_rng(11)
    t = fix_times(rng)
    s = np.full(t.size, 0.01)
    white = rng.normal(0.0, 0.01, t.size)
    n = straight_count(t, white, s)
    assert n > 0.9 * t.size
    # each triple shares a fix with four others: half of them counted as independent
    band = mad_band(n, 0.5)
    assert view_shares(t, white, s, LAG_S)[0] >= 1.0 - band
    assert view_shares(t, np.full(t.size, 0.02), s, LAG_S)[0] == 0.0


def test_a_bias_plus_white_claiming_the_total_gives_the_white_share():
    """What receivers report is the total; the share must find the white part in it."""
    rng = np.random.default_rng(12)
    t = fix_times(rng)
    bias, w = 0.02, 0.01
    total = np.hypot(bias, w)
    s = np.full(t.size, total)
    psi = bias * np.sign(rng.normal()) + rng.normal(0.0, w, t.size)
    r = view_shares(t, psi, s, LAG_S)[0]
    expected = w / total  # 0.447
    assert abs(r - expected) <= mad_band(straight_count(t, psi, s), 0.5) * expected


def test_an_error_that_holds_a_second_then_jumps_counts_whole_at_a_two_second_lag():
    """A 1 Hz receiver's course error, sampled at 5 Hz: consecutive fixes share it (the
    consecutive-fix share sees a fraction of it), but across a view it is independent."""
    rng = np.random.default_rng(13)
    t = fix_times(rng)
    per_second = rng.normal(0.0, 0.015, int(t.max()) + 2)
    psi = per_second[np.floor(t).astype(int)]
    s = np.full(t.size, 0.015)
    n = straight_count(t, psi, s)
    # five fixes per second hold one error: a tenth of the triples counted as independent
    assert view_shares(t, psi, s, LAG_S)[0] >= 1.0 - mad_band(n, 0.1)
    assert white_share(t, psi, s, angle=True) < 0.5


def test_turns_do_not_count_as_noise():
    """Right-angle turns (90 degrees in 3 s) every 30 s, white heading noise claimed at
    twice its size: the share stays at one half, the turning triples left out."""
    rng = np.random.default_rng(14)
    t = fix_times(rng)
    phase = np.mod(t, 30.0)
    turns = np.floor(t / 30.0) + np.clip((phase - 27.0) / 3.0, 0.0, 1.0)
    psi = np.pi / 2 * turns + rng.normal(0.0, 0.01, t.size)
    s = np.full(t.size, 0.02)
    n = straight_count(t, psi, s)
    assert n < 0.85 * t.size  # the corners' triples are out
    r = view_shares(t, psi, s, LAG_S)[0]
    assert abs(r - 0.5) <= mad_band(n, 0.5) * 0.5
    tri = straight_lag_triples(t, psi, s, LAG_S)
    assert tri is not None
    a, _, c = tri
    assert np.all(np.abs(psi[c] - psi[a]) < STRAIGHT_K * np.hypot(s[a], s[c]))


def test_positions_split_across_the_track_and_in_height():
    """A biased track (3 m East, 4 m up) with white noise of 0.5 m per horizontal axis and
    1 m in height, claimed as totals: shares of the white part. Speed changes along the
    track do not count (the across-track component only)."""
    rng = np.random.default_rng(15)
    t = fix_times(rng)
    psi = np.full(t.size, np.radians(30.0))
    speed = 10.0 + 3.0 * np.sin(t / 7.0)  # accelerating and braking
    dist = np.cumsum(np.r_[0.0, np.diff(t) * 0.5 * (speed[1:] + speed[:-1])])
    east, north = dist * np.sin(psi), dist * np.cos(psi)
    xyz = np.column_stack([east + 3.0, north, np.full(t.size, 4.0)])
    xyz[:, :2] += rng.normal(0.0, 0.5, (t.size, 2))
    xyz[:, 2] += rng.normal(0.0, 1.0, t.size)
    s_h, s_v = np.full(t.size, np.hypot(3.0, 0.5)), np.full(t.size, np.hypot(4.0, 1.0))
    s_psi = np.full(t.size, 0.01)
    _, r_h, r_v = view_shares(t, psi, s_psi, LAG_S, xyz, s_h, s_v)
    band = mad_band(straight_count(t, psi, s_psi), 0.5)
    assert abs(r_h - 0.5 / s_h[0]) <= band * 0.5 / s_h[0]
    assert abs(r_v - 1.0 / s_v[0]) <= band * 1.0 / s_v[0]


def test_too_few_fixes_claim_the_sigma_whole():
    t = np.arange(8) / RATE_HZ
    assert view_shares(t, np.zeros(8), np.full(8, 0.01), LAG_S) == (1.0, 1.0, 1.0)
    assert view_shares(np.arange(100) / 5.0, np.zeros(100), np.full(100, 0.01), 0.0) == (
        1.0,
        1.0,
        1.0,
    )
