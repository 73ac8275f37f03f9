"""The map floor against synthetic controls with a known floor (hdmap.mapping.map_floor).

Controls: ``n`` landmarks, each with a random sandwich covariance ``C_i`` (horizontal,
0.1-0.5 m per axis, random orientation), published as ``C_i + s0^2 I``; the true error
``e_i ~ N(0, C_i + s^2 I)``. At the true ``s`` a control is inside its 95 % region with
probability 0.95 exactly, so ``s`` is the 0.95 quantile of the least floors ``s_i``
(module doc), and the distribution-free interval holds it with probability >= 0.95.
Bounds on counts over seeds are binomial quantiles at 0.1 %.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import binom, chi2

from hdmap.mapping.map_floor import coverage_floor, least_floors, quantile_interval

SEEDS = 100
LOW = binom.ppf(0.001, SEEDS, 0.95)
"""Fewest seeds (of 100) that may hold a 95 % statement, at 0.1 %."""


def _controls(rng, n: int, floor: float, base: float = 0.0, k: int = 2):
    sd = rng.uniform(0.1, 0.5, (n, k))
    rot = np.linalg.qr(rng.normal(size=(n, k, k)))[0]
    own = rot @ (sd[:, :, None] ** 2 * np.eye(k)) @ np.swapaxes(rot, -1, -2)
    true = own + floor**2 * np.eye(k)
    err = np.einsum("nij,nj->ni", np.linalg.cholesky(true), rng.normal(size=(n, k)))
    return err, own + base**2 * np.eye(k)


@pytest.mark.parametrize("k", [1, 2])
def test_the_interval_holds_the_true_floor(k):
    hits = 0
    for seed in range(SEEDS):
        err, cov = _controls(np.random.default_rng(seed), 200, 0.3, k=k)
        f = coverage_floor(err, cov)
        hits += f.interval_m[0] <= 0.3 <= f.interval_m[1]
    assert hits >= LOW, hits


def test_a_floor_measured_on_some_controls_covers_new_ones():
    """Measured on 200 controls, applied to 200 others: the mean share inside over the
    seeds is within 3 standard errors of its conformal expectation ``191 / 201`` (each
    seed's share varies by the binomial of the new controls and by the floor's own
    estimate; the spread is taken from the seeds)."""
    shares = []
    for seed in range(SEEDS):
        rng = np.random.default_rng(1000 + seed)
        err, cov = _controls(rng, 200, 0.25, base=0.1)
        f = coverage_floor(err, cov, base_sigma_m=0.1)
        e2, c2 = _controls(rng, 200, 0.25)
        m2 = np.einsum(
            "ni,ni->n", e2, np.linalg.solve(c2 + f.sigma_m**2 * np.eye(2), e2[..., None])[..., 0]
        )
        shares.append(np.mean(m2 <= chi2.ppf(0.95, 2)))
    s = np.array(shares)
    assert abs(s.mean() - 191 / 201) <= 3 * s.std(ddof=1) / np.sqrt(SEEDS), (s.mean(), s.std())


def test_no_floor_where_the_covariance_is_right():
    """Errors drawn from the published covariances: the interval reaches 0 on at least the
    binomial share of seeds."""
    zero = 0
    for seed in range(SEEDS):
        err, cov = _controls(np.random.default_rng(2000 + seed), 200, 0.0)
        zero += coverage_floor(err, cov).interval_m[0] == 0.0
    assert zero >= LOW, zero


def test_the_floor_a_map_was_published_with_is_taken_out():
    rng = np.random.default_rng(7)
    err, own = _controls(rng, 300, 0.2)
    a = coverage_floor(err, own)
    b = coverage_floor(err, own + 0.15**2 * np.eye(2), base_sigma_m=0.15)
    assert b.sigma_m == pytest.approx(a.sigma_m, abs=1e-9)
    assert b.inside_after == a.inside_after
    assert b.inside_before >= a.inside_before


def test_a_few_contaminated_controls_move_the_floor_less_than_a_second_moment():
    """3 % of the controls hold a neighbour's rays (5 m off): the quantile floor grows so
    that 95 % of all stay inside; the moment floor ``sqrt(mean(|e|^2 - tr C) / 2)`` is
    dominated by them."""
    rng = np.random.default_rng(11)
    err, cov = _controls(rng, 400, 0.2)
    bad = rng.random(400) < 0.03
    err[bad] += 5.0 * np.array([1.0, 0.0])
    f = coverage_floor(err, cov)
    moment = np.sqrt(np.mean(np.sum(err**2, axis=1) - np.trace(cov, axis1=1, axis2=2)) / 2)
    assert f.inside_after >= 0.95
    assert f.sigma_m < 0.5 * moment, (f.sigma_m, moment)


def test_least_floors_put_each_control_on_its_boundary():
    rng = np.random.default_rng(3)
    err, cov = _controls(rng, 50, 0.4)
    s = least_floors(err, cov, 0.95)
    out = s > 0
    m2 = np.einsum(
        "ni,ni->n",
        err,
        np.linalg.solve(cov + (s**2)[:, None, None] * np.eye(2), err[..., None])[..., 0],
    )
    assert np.allclose(m2[out], chi2.ppf(0.95, 2), rtol=1e-6)
    assert np.all(m2[~out] <= chi2.ppf(0.95, 2))


def test_quantile_interval_ranks():
    x = np.arange(1.0, 101.0)
    q, lo, hi = quantile_interval(x, 0.95, 0.95)
    assert q == 96.0  # rank ceil(0.95 * 101)
    assert lo < q < hi
    with pytest.raises(ValueError, match="no values"):
        quantile_interval(np.array([]), 0.95)


def test_bad_shapes_are_refused():
    with pytest.raises(ValueError, match="err"):
        coverage_floor(np.zeros((3, 2)), np.zeros((3, 3, 3)))
    with pytest.raises(ValueError, match="level"):
        coverage_floor(np.zeros((3, 2)), np.repeat(np.eye(2)[None], 3, 0), level=1.5)


def test_the_evaluation_measures_records_and_reads_its_floor(tmp_path):
    """``fleetsim.evaluation.map_floor_file``: a round's signs with 150+ passes are the
    controls (the others, and unpaired signs, left out); the measured floor written for a
    noise name is what later runs of that noise give the solver."""
    from fleetsim.evaluation.fleet_scoring import SignRecord
    from fleetsim.evaluation.map_floor_file import calibrated_sigma, measured_floor, record_floor

    rng = np.random.default_rng(5)
    k = 120
    err_h, cov_h = _controls(rng, k, 0.3, base=0.1)
    err_v, cov_v = _controls(rng, k, 0.5, base=0.1, k=1)
    cov6 = np.column_stack(
        [cov_h[:, 0, 0], cov_h[:, 0, 1], np.zeros(k), cov_h[:, 1, 1], np.zeros(k), cov_v[:, 0, 0]]
    )
    n = np.where(np.arange(k) < 100, 400, 20)
    found = np.arange(k) != 3
    rec = SignRecord(
        n, found, np.hypot(*err_h.T), np.zeros(k, bool), np.zeros(k, np.uint64),
        err_enu=np.column_stack([err_h, err_v]), cov_enu=cov6,
    )  # fmt: skip
    m = measured_floor(rec, (0.1, 0.1, 0.1))
    assert m["horizontal"]["controls"] == 99 and m["vertical"]["controls"] == 99
    lo, hi = m["horizontal"]["interval_m"]
    assert lo <= m["horizontal"]["sigma_m"] <= hi
    few = SignRecord(
        n, found & (np.arange(k) < 19), rec.err, rec.inside, rec.landmark,
        err_enu=rec.err_enu, cov_enu=cov6,
    )  # fmt: skip
    assert measured_floor(few, (0.1, 0.1, 0.1)) is None
    path = tmp_path / "floor.json"
    assert calibrated_sigma("fleet", path) is None
    record_floor("fleet", m, "hdmap eval fleet --seed 10", path)
    h, v = m["horizontal"]["sigma_m"], m["vertical"]["sigma_m"]
    assert calibrated_sigma("fleet", path) == (h, h, v)
    assert calibrated_sigma("fleet+gsdc", path) is None
