"""Box ranges in the estimator's normal equations (``EstimatorConfig.box_range``).

Synthetic head-on approach with fixed seeds: a sign 50 m up a straight road, 3 m to its
side, cars driving toward it and looking at it from 45 m to 10 m, one ray per metre. Per
pass a GNSS bias (1 m per axis) and a heading bias (0.01 rad) shared by its rays, white
noise per ray (0.3 m, 0.003 rad), the claims honest. The bearings hardly fix the distance
along the road; the ranges do. Two kinds of box range: 15 % noise, independent per ray
and unbiased (the panel at its nominal size: ``range_scale="nominal"`` may take them as
they are), and 3 % noise from a panel 15 % larger than its class's nominal size, an error
all its rays share (``range_scale="per_pass"``: only the ratios within a pass count).
"""

from __future__ import annotations

import numpy as np
from scipy.stats import binom, chi2

from hdmap.geo.geodesy import direction_from_angles
from hdmap.mapping.estimator import EstimatorConfig, LandmarkSums, Rays

SIGN = np.array([3.0, 50.0, 2.0])
BIAS_M, WHITE_M = 1.0, 0.3
BIAS_RAD, WHITE_RAD = 0.01, 0.003
RANGE_REL = 0.15
PASSES = 30
SEEDS = 40


def head_on_pass(
    rng: np.random.Generator,
    exact: bool = False,
    panel_scale: float = 1.0,
    range_rel: float = RANGE_REL,
    claim_rel: float = RANGE_REL,
    claim_from_box: bool = False,
) -> Rays:
    """One pass; the box ranges are the true ones over ``panel_scale`` with ``range_rel``
    noise, ``claim_rel`` of the range claimed as their sigma: of the measured one with
    ``claim_from_box`` (as the vehicle does), else of the noise-free one."""
    y = np.arange(5.0, 41.0)
    true_o = np.column_stack([np.zeros_like(y), y, np.full_like(y, 1.5)])
    v = SIGN - true_o
    az = np.arctan2(v[:, 0], v[:, 1])
    el = np.arctan2(v[:, 2], np.hypot(v[:, 0], v[:, 1]))
    r = np.linalg.norm(v, axis=1)
    n = y.size
    s_az = np.full(n, np.hypot(BIAS_RAD, WHITE_RAD))
    s_pos = np.full(n, np.hypot(BIAS_M, WHITE_M))
    if exact:  # no noise, and none claimed on the angles (the compensation removes a claim)
        o, box = true_o, r / panel_scale
        s_az = np.full(n, 1e-9)
    else:
        o = true_o + rng.normal(0.0, BIAS_M, 3) + rng.normal(0.0, WHITE_M, (n, 3))
        az = az + rng.normal(0.0, BIAS_RAD) + rng.normal(0.0, WHITE_RAD, n)
        el = el + rng.normal(0.0, WHITE_RAD, n)
        box = r / panel_scale * (1.0 + rng.normal(0.0, range_rel, n))
    d = direction_from_angles(az, el)
    s_el = np.full(n, 1e-9 if exact else WHITE_RAD)
    sigma_r = claim_rel * (box if claim_from_box else r / panel_scale)
    return Rays(o, d, s_az, s_el, s_pos, s_pos, None, box, sigma_r)


def solve(
    passes: list[Rays], box_range: bool, scale: str = "nominal"
) -> tuple[np.ndarray, np.ndarray]:
    sums = LandmarkSums(EstimatorConfig(box_range=box_range, range_scale=scale))
    row = sums.new_rows(1, SIGN[None] + np.array([2.0, -5.0, 0.5]))
    for k, rays in enumerate(passes):
        sums.accumulate(np.repeat(row, len(rays)), np.full(len(rays), k), rays)
    sol = sums.solve(row)
    return sol.x[0], sol.cov[0]


def test_exact_rays_and_ranges_give_the_sign_with_and_without_ranges():
    passes = [head_on_pass(np.random.default_rng(0), exact=True) for _ in range(8)]
    for box_range, scale in ((False, "nominal"), (True, "nominal"), (True, "per_pass")):
        x, _ = solve(passes, box_range, scale)
        np.testing.assert_allclose(x, SIGN, atol=1e-6)


def test_a_per_pass_scale_takes_any_panel_size():
    """Exact rays, ranges of a panel 30 % off its nominal size: the nominal ranges pull the
    landmark along the line of sight, a per-pass scale does not."""
    passes = [head_on_pass(np.random.default_rng(0), exact=True, panel_scale=1.3) for _ in range(8)]
    x, _ = solve(passes, True, "per_pass")
    np.testing.assert_allclose(x, SIGN, atol=1e-6)
    x, _ = solve(passes, True, "nominal")
    assert np.linalg.norm(x - SIGN) > 1.0


def test_a_per_pass_scale_fixes_the_line_of_sight_of_an_off_size_panel():
    """Over ``SEEDS`` fleets of ``PASSES`` passes, a panel 15 % larger than nominal, 3 %
    white range noise, the vehicle claiming its total (white and the catalogue's 10 %):
    the per-pass scale beats bearings alone on most seeds (paired, binomial 99.9 % bound
    of a coin flip) and its 95 % region covers at the binomial 0.1 % lower bound; the
    nominal ranges do worse than bearings alone (they carry the panel's error)."""
    err: dict[str, list[float]] = {"off": [], "nominal": [], "per_pass": []}
    inside = 0
    claim = float(np.hypot(0.03, 0.10))
    for seed in range(SEEDS):
        rng = np.random.default_rng(300 + seed)
        passes = [
            head_on_pass(
                rng, panel_scale=1.15, range_rel=0.03, claim_rel=claim, claim_from_box=True
            )
            for _ in range(PASSES)
        ]
        for mode in err:
            box_range = mode != "off"
            x, cov = solve(passes, box_range, mode if box_range else "nominal")
            e = x - SIGN
            err[mode].append(float(np.hypot(e[0], e[1])))
            if mode == "per_pass":
                inside += float(e[:2] @ np.linalg.solve(cov[:2, :2], e[:2])) <= chi2.ppf(0.95, 2)
    pp, off, nom = (np.array(err[k]) for k in ("per_pass", "off", "nominal"))
    assert (pp < off).sum() > binom.ppf(0.999, SEEDS, 0.5)
    assert np.median(pp) < 0.5 * np.median(off)
    assert (off < nom).sum() > binom.ppf(0.999, SEEDS, 0.5)
    assert inside >= binom.ppf(0.001, SEEDS, 0.95)


def test_ranges_fix_the_line_of_sight_and_the_covariance_still_covers():
    """Over ``SEEDS`` fleets of ``PASSES`` passes: with the ranges the error is smaller (a
    paired comparison on the same draws, every seed counted) and the published 95 %
    region (horizontal, 2 dof) holds the sign at least as often as a calibrated one would
    at the binomial 0.1 % lower bound."""
    err = {False: [], True: []}
    inside = 0
    for seed in range(SEEDS):
        rng = np.random.default_rng(100 + seed)
        passes = [head_on_pass(rng) for _ in range(PASSES)]
        for box_range in (False, True):
            x, cov = solve(passes, box_range)
            e = x - SIGN
            err[box_range].append(float(np.hypot(e[0], e[1])))
            if box_range:
                inside += float(e[:2] @ np.linalg.solve(cov[:2, :2], e[:2])) <= chi2.ppf(0.95, 2)
    with_r, without = np.array(err[True]), np.array(err[False])
    # the ranges help on most seeds: more than the binomial 99.9 % bound of a coin flip
    assert (with_r < without).sum() > binom.ppf(0.999, SEEDS, 0.5)
    assert np.median(with_r) < 0.5 * np.median(without)
    assert inside >= binom.ppf(0.001, SEEDS, 0.95)


def test_rays_without_ranges_leave_the_sums_as_bearings_only():
    rng = np.random.default_rng(7)
    passes = [head_on_pass(rng) for _ in range(5)]
    bare = [
        Rays(r.origin, r.direction, r.sigma_az, r.sigma_el, r.sigma_pos_h, r.sigma_pos_v)
        for r in passes
    ]
    zero = [
        Rays(
            *(getattr(r, f) for f in ("origin", "direction", "sigma_az", "sigma_el")),
            r.sigma_pos_h,
            r.sigma_pos_v,
            None,
            np.zeros(len(r)),
            np.zeros(len(r)),
        )
        for r in passes
    ]
    x_off, _ = solve(passes, box_range=False)
    for rays in (bare, zero):
        for scale in ("nominal", "per_pass"):
            x, _ = solve(rays, box_range=True, scale=scale)
            np.testing.assert_allclose(x, x_off, rtol=0, atol=1e-9)


def one_row(
    passes: list[Rays], cfg: EstimatorConfig, x0: np.ndarray
) -> tuple[LandmarkSums, np.ndarray]:
    """One row fed every ray of ``passes`` (pass ``k`` as cluster ``k``)."""
    sums = LandmarkSums(cfg)
    row = sums.new_rows(1, x0)
    for k, rays in enumerate(passes):
        sums.accumulate(np.repeat(row, len(rays)), np.full(len(rays), k), rays)
    return sums, row


def split_and_merged(
    passes: list[Rays], cfg: EstimatorConfig, x0: np.ndarray
) -> tuple[LandmarkSums, int]:
    """Two rows (another anchor, the same reference) each fed every other ray of every pass,
    then merged: the sums and the row kept."""
    two = LandmarkSums(cfg)
    a, b = two.new_rows(2, np.vstack([x0, x0 + np.array([7.0, -3.0, 1.0])]))
    two.set_reference([b], x0)  # the same reference: the same weights
    for k, rays in enumerate(passes):
        half = np.arange(len(rays)) % 2 == 0
        for dst, m in ((a, half), (b, ~half)):
            two.accumulate(np.full(int(m.sum()), dst), np.full(int(m.sum()), k), rays.take(m))
    assert two.n_open_passes == 2 * len(passes)
    two.merge_rows(int(a), int(b))
    return two, int(a)


def test_per_pass_scale_sums_survive_merge_and_packing():
    """Open passes' range scale sums move with a merge (another anchor) and a pack /
    unpack round trip: both give the solution of one row fed every ray."""
    rng = np.random.default_rng(11)
    passes = [head_on_pass(rng, panel_scale=1.2, range_rel=0.03, claim_rel=0.05) for _ in range(6)]
    cfg = EstimatorConfig(box_range=True, range_scale="per_pass")
    x0 = SIGN[None] + np.array([2.0, -5.0, 0.5])

    one, row = one_row(passes, cfg, x0)
    want = one.solve(row, update_reference=False).x[0]

    two, a = split_and_merged(passes, cfg, x0)
    np.testing.assert_allclose(two.solve([a], update_reference=False).x[0], want, atol=1e-9)

    blob = one.pack_rows(row)[0]
    assert blob[0] == 6
    back = LandmarkSums(cfg)
    got = back.solve(back.unpack_rows([blob]), update_reference=False).x[0]
    np.testing.assert_allclose(got, want, atol=1e-12)


# --- the inverse-range form with the box noise measured (range_scale="inverse") --------
# Boxes as a detector gives them: a box height of h = F H / r pixels plus N(0, sigma_h)
# pixel noise (F H = 675 px m: 15 px at 45 m), the range F H / h, the vehicle claiming
# CLAIM_PX of box noise and the catalogue's 10 % panel spread whatever the boxes have.
F_H = 675.0
CLAIM_PX = 4.24


def pixel_box_pass(rng: np.random.Generator, sigma_px: float, panel_scale: float = 1.0) -> Rays:
    """One head-on pass (as :func:`head_on_pass`) with pixel noise on the box heights; the
    origin sigma claimed is the white part (what the vehicle claims of a view,
    ``vehicle.pose.view_shares``; the pass's bias is the pass weighting's)."""
    y = np.arange(5.0, 41.0)
    true_o = np.column_stack([np.zeros_like(y), y, np.full_like(y, 1.5)])
    v = SIGN - true_o
    az = np.arctan2(v[:, 0], v[:, 1]) + rng.normal(0.0, BIAS_RAD)
    el = np.arctan2(v[:, 2], np.hypot(v[:, 0], v[:, 1]))
    r = np.linalg.norm(v, axis=1)
    n = y.size
    s_az = np.full(n, np.hypot(BIAS_RAD, WHITE_RAD))
    s_pos = np.full(n, WHITE_M)
    o = true_o + rng.normal(0.0, BIAS_M, 3) + rng.normal(0.0, WHITE_M, (n, 3))
    white = rng.normal(0.0, WHITE_RAD, (2, n))
    d = direction_from_angles(az + white[0], el + white[1])
    h = np.maximum(F_H * panel_scale / r + rng.normal(0.0, sigma_px, n), 1.0)
    box = F_H / h
    claim = box * np.hypot(CLAIM_PX / h, 0.10)
    return Rays(o, d, s_az, np.full(n, WHITE_RAD), s_pos, s_pos, None, box, claim)


X0 = SIGN + np.array([2.0, -5.0, 0.5])
"""The landmarks' first position in these tests: 5.4 m off the sign."""


def solve_inverse(
    passes: list[Rays], x0: np.ndarray = X0, **cfg
) -> tuple[np.ndarray, np.ndarray, float]:
    sums = LandmarkSums(EstimatorConfig(box_range=True, range_scale="inverse", **cfg))
    row = sums.new_rows(1, x0[None])
    for k, rays in enumerate(passes):
        sums.accumulate(np.repeat(row, len(rays)), np.full(len(rays), k), rays)
    sol = sums.solve(row)
    return sol.x[0], sol.cov[0], float(sums.box_noise_ratio(row)[0])


def box_share(sigma_px: float) -> float:
    """The ratio the fit should measure: the box noise over the claim (the white origin
    noise's share, ``rho WHITE_M`` per ray, is taken out as claimed)."""
    return (sigma_px / CLAIM_PX) ** 2


def test_inverse_form_is_exact_on_exact_boxes_of_any_panel_size():
    passes = [head_on_pass(np.random.default_rng(0), exact=True, panel_scale=1.3) for _ in range(8)]
    # the reference at the sign: every pass's fit is exact, nothing is compensated
    x, _, ratio = solve_inverse(passes, SIGN, range_noise_prior_dof=0.0)
    assert ratio < 1e-9
    np.testing.assert_allclose(x, SIGN, atol=1e-6)


def test_inverse_form_measures_the_box_noise_whatever_the_claim():
    """Over ``SEEDS`` fleets of ``PASSES`` passes, boxes with 0, 4.24 and 6 px of noise
    while the vehicle claims 4.24: the measured ratio lies within its chi-square 99.9 %
    interval (about 32 degrees of freedom a pass; below its upper end for exact boxes;
    99.9 % rather than 99 % because the first-order fit and the average-leverage share of
    the origin noise leave the ratio a few percent low, box_noise.py)
    about :func:`box_share` on at least the binomial 0.1 % lower
    bound of the seeds; the landmark beats bearings alone on most seeds (paired, above the
    99.9 % bound of a coin flip) and its 95 % region covers at the binomial 0.1 % bound."""
    dof = PASSES * (36 - 4)
    lo, hi = chi2.ppf(0.0005, dof) / dof, chi2.ppf(0.9995, dof) / dof
    for sigma_px in (0.0, CLAIM_PX, 6.0):
        want = max(box_share(sigma_px), 1e-9)
        in_interval = better = inside = 0
        for seed in range(SEEDS):
            rng = np.random.default_rng(500 + seed)
            passes = [pixel_box_pass(rng, sigma_px) for _ in range(PASSES)]
            x, cov, ratio = solve_inverse(passes)
            x_off, _ = solve(passes, False)
            if sigma_px == 0.0:  # exact boxes: no more than the prior's pseudo-dof leave
                in_interval += ratio <= hi * 4.0 / dof
            else:
                in_interval += lo <= ratio / want <= hi
            e = x - SIGN
            better += np.hypot(e[0], e[1]) < np.hypot(*(x_off - SIGN)[:2])
            inside += float(e[:2] @ np.linalg.solve(cov[:2, :2], e[:2])) <= chi2.ppf(0.95, 2)
        assert in_interval >= binom.ppf(0.001, SEEDS, 0.99), sigma_px
        assert better > binom.ppf(0.999, SEEDS, 0.5), sigma_px
        assert inside >= binom.ppf(0.001, SEEDS, 0.95), sigma_px


def test_inverse_form_sums_survive_merge_and_packing():
    """Packing keeps the box-noise sums exactly; a merge of two rows that split every pass
    settles the two halves' fits apart (two fits: four more coefficients a pass, ``4 P``
    degrees of freedom fewer), so it measures the same noise within three standard
    deviations of a chi-square of ``4 P`` over its degrees of freedom, and gives a landmark
    closer to one row fed every ray than the 1 % quantile of that row's own error."""
    rng = np.random.default_rng(13)
    passes = [pixel_box_pass(rng, CLAIM_PX, panel_scale=1.1) for _ in range(6)]
    cfg = EstimatorConfig(box_range=True, range_scale="inverse")
    x0 = SIGN[None] + np.array([2.0, -5.0, 0.5])
    one, row = one_row(passes, cfg, x0)
    want = one.solve(row, update_reference=False).x[0]

    closed = LandmarkSums(cfg)  # some passes closed: the row's pooled sums are packed too
    unpacked = closed.unpack_rows(one.pack_rows(row))
    closed.close_passes(clusters=[0, 1, 2])
    blob = closed.pack_rows(unpacked)[0]
    assert blob[0] == 7
    back = LandmarkSums(cfg)
    rows = back.unpack_rows([blob])
    np.testing.assert_allclose(
        back.solve(rows, update_reference=False).x[0],
        closed.solve(unpacked, update_reference=False).x[0],
        atol=1e-12,
    )
    assert back.box_noise_ratio(rows)[0] == closed.box_noise_ratio(unpacked)[0]

    two, a = split_and_merged(passes, cfg, x0)
    r1, r2 = one.box_noise_ratio(row)[0], two.box_noise_ratio([a])[0]
    n_passes, n_rays = len(passes), len(passes[0])
    assert abs(r2 / r1 - 1.0) < 3.0 * np.sqrt(8.0 * n_passes) / (n_passes * (n_rays - 8))
    diff = two.solve([a], update_reference=False).x[0] - want
    cov = one.solve(row, update_reference=False).cov[0]
    assert float(diff @ np.linalg.solve(cov, diff)) < chi2.ppf(0.01, 3)


def test_only_the_inverse_form_keeps_box_noise_sums():
    """Off by default, the box-noise sums cost nothing per open pass (pack version 6 sizes);
    the inverse form keeps its 28 floats more."""
    off, on = LandmarkSums(), LandmarkSums(EstimatorConfig(box_range=True, range_scale="inverse"))
    assert (off.open_pass_bytes, on.open_pass_bytes) == (224, 224 + 28 * 8)
    rays = head_on_pass(np.random.default_rng(1))
    for sums in (off, on):
        row = sums.new_rows(1, SIGN[None])
        sums.accumulate(np.repeat(row, len(rays)), np.zeros(len(rays)), rays)
        assert sums.pack_rows(row)[0][0] == (7 if sums is on else 4)
