"""Cross-checks of the incremental estimator against batch nonlinear least squares.

(a) scipy.optimize.least_squares on the textbook (weighted) orthogonal-distance residuals
    gives the incremental textbook sums' solution;
(b) the incremental compensated solution agrees with a batch maximum-likelihood fit on
    the angular residuals (known origins) within a small fraction of the reported sigma;
(c) accumulating in random batch splits (passes interleaved, unsorted) equals one shot;
(d) the pass-weighted sums (``pass_sigma_m``) equal a batch least squares over the landmark
    AND one unknown offset per pass with a Gaussian prior of that size (the random-effects
    model the weighting eliminates in closed form).

(a) and (b) are ray-level costs (no pass error in their data): ``pass_sigma_m = 0``.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from hdmap.mapping.estimator import EstimatorConfig, LandmarkSums, Rays, weights, wrap
from hdmap.mapping.estimator.model import ray_angles

X_TRUE = np.array([5.0, 0.0, 2.5])
NO_PASS = (0.0, 0.0, 0.0)


def corridor(rng, n_pass, per_pass, s_az, s_el, s_pos, x=X_TRUE):
    """Rays from passes along a road toward ``x``; returns rays and their pass ids."""
    n = n_pass * per_pass
    a = np.stack(
        [
            rng.uniform(-1.5, 1.5, n),
            np.tile(np.linspace(-45, -8, per_pass), n_pass),
            np.full(n, 1.4),
        ],
        1,
    )
    az, el = ray_angles(x - a)
    a_meas = a + rng.normal(0, s_pos, (n, 3)) if s_pos > 0 else a
    rays = Rays.from_angles(
        a_meas, az + rng.normal(0, s_az, n), el + rng.normal(0, s_el, n), s_az, s_el, s_pos, s_pos
    )
    return rays, np.repeat(np.arange(n_pass), per_pass)


def incremental(rays, passes, cfg, x0, rng=None, splits=1):
    s = LandmarkSums(cfg)
    row = s.new_rows(1, x0[None])
    order = np.arange(len(rays)) if rng is None else rng.permutation(len(rays))
    for part in np.array_split(order, splits):
        s.accumulate(np.repeat(row, part.size), passes[part], rays.take(part))
    return s, s.solve(row, update_reference=False)


def test_a_batch_least_squares_on_textbook_residuals_equals_incremental_sums():
    rng = np.random.default_rng(21)
    rays, passes = corridor(rng, 40, 15, 0.05, 0.01, 1.0)
    x0 = X_TRUE + np.array([1.5, -3.0, 0.5])
    cfg = EstimatorConfig(
        compensate=False, weight_correction=False, min_significance=0.0, pass_sigma_m=NO_PASS
    )
    _, sol = incremental(rays, passes, cfg, x0, rng, splits=7)
    # the same cost in batch: horizontal and vertical orthogonal distances, same weights
    w_h, w_v, _, _ = weights(rays, rays.origin, np.broadcast_to(x0, rays.origin.shape), cfg)
    az, el = ray_angles(rays.direction)
    h = np.stack([np.cos(az), -np.sin(az), np.zeros_like(az)], 1)
    v = np.stack([-np.sin(el) * np.sin(az), -np.sin(el) * np.cos(az), np.cos(el)], 1)

    def resid(x):
        d = x - rays.origin
        return np.concatenate([np.sqrt(w_h) * (d * h).sum(1), np.sqrt(w_v) * (d * v).sum(1)])

    jac = np.concatenate([np.sqrt(w_h)[:, None] * h, np.sqrt(w_v)[:, None] * v])
    fit = least_squares(
        resid, x0, jac=lambda x: jac, xtol=1e-15, ftol=1e-15, gtol=1e-15, method="lm"
    )
    np.testing.assert_allclose(sol.x_raw[0], fit.x, rtol=1e-9, atol=1e-9)
    # and the textbook solution is measurably pulled toward the origins at this noise
    assert sol.x_raw[0, 1] < X_TRUE[1]


def ml_fit(rays, x_start):
    """Batch maximum likelihood on the angular residuals (origins known)."""

    def resid(x):
        az, el = ray_angles(x - rays.origin)
        az_m, el_m = ray_angles(rays.direction)
        return np.concatenate([wrap(az - az_m) / rays.sigma_az, (el - el_m) / rays.sigma_el])

    return least_squares(resid, x_start, xtol=1e-12, ftol=1e-12, method="lm").x


@pytest.mark.parametrize(("s_az", "tol_sigma"), [(0.01, 0.1), (0.05, 0.1)])
def test_b_compensated_incremental_agrees_with_batch_ml(s_az, tol_sigma):
    rng = np.random.default_rng(22)
    rays, passes = corridor(rng, 150, 20, s_az, 0.005, 0.0)
    cfg = EstimatorConfig(min_sigma_pos_m=1e-6, pass_sigma_m=NO_PASS)  # known origins
    x0 = X_TRUE + np.array([2.0, 5.0, 0.5])
    _, first = incremental(rays, passes, cfg, x0)
    # the solver's recursion: weights at the previous estimate
    _, sol = incremental(rays, passes, cfg, first.x[0])
    assert sol.ok[0]
    x_ml = ml_fit(rays, x0)
    d = sol.x[0] - x_ml
    maha = float(np.sqrt(d @ np.linalg.solve(sol.cov[0], d)))
    assert maha < tol_sigma, (maha, d, np.sqrt(np.diag(sol.cov[0])))
    # both are close to the truth in the same units
    e = x_ml - X_TRUE
    assert float(np.sqrt(e @ np.linalg.solve(sol.cov[0], e))) < 4.0


def test_b_at_the_papers_noise_compensated_is_consistent_but_not_ml():
    """0.35 rad of azimuth noise: the compensated sums stay unbiased but are less
    efficient than ML along the weakly observed line of sight (documented)."""
    rng = np.random.default_rng(23)
    diffs = []
    for _ in range(8):
        rays, passes = corridor(rng, 200, 20, 0.35, 0.005, 0.0)
        x0 = X_TRUE + np.array([2.0, 5.0, 0.5])
        cfg = EstimatorConfig(min_sigma_pos_m=1e-6, pass_sigma_m=NO_PASS)
        _, first = incremental(rays, passes, cfg, x0)
        _, sol = incremental(rays, passes, cfg, first.x[0])
        d = sol.x[0] - ml_fit(rays, x0)
        diffs.append(float(np.sqrt(d @ np.linalg.solve(sol.cov[0], d))))
    assert np.median(diffs) < 1.5


def test_c_random_batch_splits_equal_one_shot():
    rng = np.random.default_rng(24)
    parts, rows, cls = [], [], []
    x0 = np.array([[5.0, 0.0, 2.5], [-20.0, 40.0, 3.0], [60.0, -10.0, 2.0]])
    for k, x in enumerate(x0):
        r, p = corridor(rng, 25, 12, 0.1, 0.01, 2.0, x=x)
        parts.append(r)
        rows.append(np.full(len(r), k))
        cls.append(p + 1000 * (k % 2))  # pass ids shared across landmarks
    rays, rows, cls = Rays.concat(parts), np.concatenate(rows), np.concatenate(cls)
    cfg = EstimatorConfig(max_open_passes=64)
    one = LandmarkSums(cfg)
    one.new_rows(3, x0 + 1.0)
    one.accumulate(rows, cls, rays)
    ref = one.solve([0, 1, 2], update_reference=False)
    for seed in range(4):
        many = LandmarkSums(cfg)
        many.new_rows(3, x0 + 1.0)
        order = np.random.default_rng(seed).permutation(len(rays))
        cuts = np.sort(np.random.default_rng(seed + 10).choice(len(rays), 9, replace=False))
        for part in np.split(order, cuts):
            many.accumulate(rows[part], cls[part], rays.take(part))
            if seed % 2:
                many.solve([0, 1, 2], update_reference=False)  # queries change nothing
        if seed == 3:
            many.close_passes()
        got = many.solve([0, 1, 2], update_reference=False)
        np.testing.assert_allclose(got.x, ref.x, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(got.cov, ref.cov, rtol=1e-8, atol=1e-14)
        assert np.array_equal(got.n_clusters, ref.n_clusters)
        assert np.array_equal(got.ok, ref.ok)


def test_d_pass_weighting_equals_batch_least_squares_with_one_offset_per_pass():
    rng = np.random.default_rng(25)
    n_pass, per = 12, 10
    rays, passes = corridor(rng, n_pass, per, 0.03, 0.01, 0.5)
    bias = rng.normal(0, 2.0, (n_pass, 3))  # what the passes share
    rays = Rays(rays.origin + bias[passes], rays.direction, rays.sigma_az, rays.sigma_el,
                rays.sigma_pos_h, rays.sigma_pos_v)  # fmt: skip
    sigma = np.array([2.0, 2.5, 3.0])
    x0 = X_TRUE + np.array([1.0, -2.0, 0.5])
    cfg = EstimatorConfig(
        compensate=False,
        weight_correction=False,
        min_significance=0.0,
        pass_sigma_m=tuple(sigma),
        max_open_passes=n_pass,  # interleaved passes all stay open (none split by eviction)
    )
    _, sol = incremental(rays, passes, cfg, x0, rng, splits=5)
    w_h, w_v, _, _ = weights(rays, rays.origin, np.broadcast_to(x0, rays.origin.shape), cfg)
    az, el = ray_angles(rays.direction)
    h = np.stack([np.cos(az), -np.sin(az), np.zeros_like(az)], 1)
    v = np.stack([-np.sin(el) * np.sin(az), -np.sin(el) * np.cos(az), np.cos(el)], 1)

    def resid(z):  # z = landmark (3) + one offset per pass (3 each)
        x, beta = z[:3], z[3:].reshape(n_pass, 3)
        d = x - rays.origin + beta[passes]
        return np.concatenate(
            [np.sqrt(w_h) * (d * h).sum(1), np.sqrt(w_v) * (d * v).sum(1), (beta / sigma).ravel()]
        )

    fit = least_squares(resid, np.r_[x0, np.zeros(3 * n_pass)], xtol=1e-15, ftol=1e-15,
                        gtol=1e-15, method="lm")  # fmt: skip
    np.testing.assert_allclose(sol.x_raw[0], fit.x[:3], rtol=0, atol=1e-6)  # LM tolerance
    # and it is not the ray-level answer: the passes' shared offsets matter here
    flat = EstimatorConfig(
        compensate=False, weight_correction=False, min_significance=0.0, pass_sigma_m=NO_PASS
    )
    _, ray_level = incremental(rays, passes, flat, x0)
    assert np.abs(ray_level.x_raw[0] - fit.x[:3]).max() > 0.05
