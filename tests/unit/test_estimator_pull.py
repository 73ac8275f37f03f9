"""The pull of an unreported per-pass origin bias (``EstimatorConfig.extra_sigma_pos_m``,
docs/estimator.md section 6): exact bookkeeping through the sums, and the correlated
paper simulation's coverage at many passings (fixed seed; ranges, not exact values)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from fleetsim.evaluation.paper_sim import CHI2_2_95, CORRELATED
from hdmap.mapping.estimator import EstimatorConfig, LandmarkSums, Rays
from hdmap.mapping.estimator.model import pull_terms, sym_to_mat
from hdmap.mapping.estimator.solve import pull_inflation
from hdmap.mapping.estimator.terms import ray_terms
from tests.support.paper import side_by_side

SIGN = np.array([6.0, 40.0, 2.0])


def road_rays(rng: np.random.Generator, passes: int) -> tuple[np.ndarray, Rays]:
    """Rays toward SIGN from a road along North, a bias per pass, trust weights < 1."""
    clusters, origin, az, el = [], [], [], []
    for p in range(passes):
        y = np.linspace(0.0, 30.0, 12)
        a = np.column_stack([rng.uniform(-1, 1, y.size), y, np.full(y.size, 1.5)])
        v = SIGN - a
        origin.append(a + rng.normal(0, 2.0, 3) + rng.normal(0, 0.5, a.shape))
        az.append(np.arctan2(v[:, 0], v[:, 1]) + rng.normal(0, 0.01, y.size))
        el.append(np.arctan2(v[:, 2], np.hypot(v[:, 0], v[:, 1])) + rng.normal(0, 0.01, y.size))
        clusters.append(np.full(y.size, p))
    n = sum(c.size for c in clusters)
    r = Rays.from_angles(np.concatenate(origin), np.concatenate(az), np.concatenate(el),
                         0.01, 0.01, 0.5, 0.8)  # fmt: skip
    return np.concatenate(clusters), replace(r, weight=rng.uniform(0.3, 1.0, n))


def _fed(cfg: EstimatorConfig, cl, rays, x0, hold_first: bool = False):
    s = LandmarkSums(cfg)
    row = s.new_rows(1, x0[None])
    h = np.where((cl < 3) & hold_first, 5, 0)
    s.accumulate(np.zeros(cl.size, np.int64) + row[0], cl, rays, hold=h)
    if hold_first:
        s.release(5, 1.0)  # as if those rays had come with weight 1
    return s, row


def test_the_pull_scales_the_covariance_by_its_share_of_the_information():
    """Passes entered unweighted (``pass_sigma_m`` 0): the covariance is the one without the
    budget times ``1 / (1 - kappa)^2``, ``kappa = sum_j tr C_j / (A_EE + A_NN)``; the
    estimate is the same."""
    rng = np.random.default_rng(8)
    cl, rays = road_rays(rng, 12)
    base = EstimatorConfig(model_floor=False, pass_sigma_m=(0.0, 0.0, 0.0))
    x0 = SIGN + np.array([1.0, -2.0, 0.5])
    off, row = _fed(base, cl, rays, x0)
    on, _ = _fed(replace(base, extra_sigma_pos_m=2.5), cl, rays, x0)
    a, b = (s.solve(row, update_reference=False) for s in (off, on))
    np.testing.assert_array_equal(a.x, b.x)
    pull = pull_terms(rays, rays.origin - x0, np.zeros((cl.size, 3)), on.config).sum()
    alpha, _ = ray_terms(rays, rays.origin - x0, np.zeros((cl.size, 3)), on.config)
    f = pull_inflation(np.array([pull]), sym_to_mat(alpha.sum(0))[None])[0]
    assert 1.0005 < f < 1.2
    np.testing.assert_allclose(b.cov, a.cov * f, rtol=1e-9)


def test_the_pull_survives_pass_weighting_holds_packs_and_merges():
    rng = np.random.default_rng(9)
    cl, rays = road_rays(rng, 12)
    cfg = EstimatorConfig(model_floor=False, extra_sigma_pos_m=2.5)
    x0 = SIGN + np.array([1.0, -2.0, 0.5])
    on, row = _fed(cfg, cl, rays, x0)
    off, _ = _fed(replace(cfg, extra_sigma_pos_m=0.0), cl, rays, x0)
    b, a = on.solve(row, False), off.solve(row, False)
    ratio = np.linalg.eigvals(np.linalg.solve(a.cov[0], b.cov[0])).real
    np.testing.assert_allclose(ratio, ratio[0], rtol=1e-9)  # one factor for the matrix
    assert 1.0005 < ratio[0] < 1.2  # the pass weighting scales the pull like A_p
    # held (its rays at one weight, as a vehicle's are), then released at weight 1: as if
    # those rays had come with weight 1
    rays = replace(rays, weight=np.where(cl < 3, 0.4, rays.weight))
    held, _ = _fed(cfg, cl, rays, x0, hold_first=True)
    w1 = replace(rays, weight=np.where(cl < 3, 1.0, rays.weight))
    ref, r_ref = _fed(cfg, cl, w1, x0)
    np.testing.assert_allclose(held.solve(row, False).cov, ref.solve(r_ref, False).cov, rtol=1e-9)
    # closed, packed and restored; and merged from two halves: the same covariance
    b = held.solve(row, False)
    held.close_passes()
    np.testing.assert_allclose(held.solve(row, False).cov, b.cov, rtol=1e-9)
    again = LandmarkSums(cfg)
    r2 = again.unpack_rows(held.pack_rows(row))
    np.testing.assert_allclose(again.solve(r2, False).cov, b.cov, rtol=1e-9)
    halves = LandmarkSums(cfg)
    rows = halves.new_rows(2, np.stack([x0, x0]))
    for k, m in enumerate((cl % 2 == 0, cl % 2 == 1)):
        halves.accumulate(np.full(int(m.sum()), rows[k]), cl[m], w1.take(m))
    halves.merge_rows(int(rows[0]), int(rows[1]))
    np.testing.assert_allclose(halves.solve(rows[:1], False).cov, b.cov, rtol=1e-9)


def test_the_pull_removes_the_coverage_drift_of_the_correlated_simulation():
    """Correlated noise (3.54 m position bias per passing, unreported), 300 trials x 600
    passings, seed 2: without the position budget the reported ellipse is too small (the
    passes' pull toward the previous estimate links them), with it the mean squared
    Mahalanobis distance is close to its value for an honest region (2)."""
    ours = EstimatorConfig(extra_sigma_az=CORRELATED.heading_bias_rad)
    cfgs = {"ours": ours, "pull": replace(ours, extra_sigma_pos_m=CORRELATED.pos_bias_m)}
    sol, geom = side_by_side(CORRELATED, 300, 600, cfgs, seed=2, solve_every=20)
    ok = sol["ours"].ok
    assert np.array_equal(ok, sol["pull"].ok) and ok.mean() > 0.95
    e = (sol["ours"].x - geom.sign)[ok][:, :2]
    m2 = {
        k: np.einsum("ti,tij,tj->t", e, np.linalg.inv(v.cov[ok][:, :2, :2]), e)
        for k, v in sol.items()
    }
    assert m2["ours"].mean() > 2.1  # the defect: too small a region (measured 2.16)
    assert 1.75 < m2["pull"].mean() < 2.05  # measured 1.83
    assert 0.935 <= (m2["pull"] <= CHI2_2_95).mean() <= 0.985
