"""The map floor against synthetic controls with a known floor (hdmap.mapping.map_floor).

Controls: ``n`` landmarks, each with a random sandwich covariance ``C_i`` (horizontal,
0.1-0.5 m per axis, random orientation), published as ``C_i + s0^2 I``; the true error
``e_i ~ N(0, C_i + s^2 I)``. At the true ``s`` a control is inside its 95 % region with
probability 0.95 exactly, so ``s`` is the 0.95 quantile of the least floors ``s_i``
(module doc), and the distribution-free interval holds it with probability >= 0.95.
Bounds on counts over seeds are binomial quantiles at 0.1 %.
"""

from __future__ import annotations

import json
import multiprocessing
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import binom, chi2

from hdmap.mapping.map_floor import (
    coverage_floor,
    least_scales,
    pass_correlation,
    quantile_interval,
)

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
        hits += f.interval[0] <= 0.3 <= f.interval[1]
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
            "ni,ni->n", e2, np.linalg.solve(c2 + f.value**2 * np.eye(2), e2[..., None])[..., 0]
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
        zero += coverage_floor(err, cov).interval[0] == 0.0
    assert zero >= LOW, zero


def test_the_floor_a_map_was_published_with_is_taken_out():
    rng = np.random.default_rng(7)
    err, own = _controls(rng, 300, 0.2)
    a = coverage_floor(err, own)
    b = coverage_floor(err, own + 0.15**2 * np.eye(2), base_sigma_m=0.15)
    assert b.value == pytest.approx(a.value, abs=1e-9)
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
    assert f.value < 0.5 * moment, (f.value, moment)


def test_least_scales_put_each_control_on_its_boundary():
    rng = np.random.default_rng(3)
    err, cov = _controls(rng, 50, 0.4)
    s = np.sqrt(least_scales(err, cov, np.broadcast_to(np.eye(2), cov.shape), 0.95))
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


def _correlated(rng, n: int, kappa: float):
    """Controls whose passes share a part of their error: between-pass covariance ``V_i``
    (0.2-2 m per axis per pass over ``G_i`` of 150-900 passes), true error covariance
    ``V_i (1 + kappa G_i)``."""
    g = rng.integers(150, 900, n)
    sd = rng.uniform(0.2, 2.0, (n, 2)) / np.sqrt(g)[:, None]
    rot = np.linalg.qr(rng.normal(size=(n, 2, 2)))[0]
    v = rot @ (sd[:, :, None] ** 2 * np.eye(2)) @ np.swapaxes(rot, -1, -2)
    true = v * (1 + kappa * g)[:, None, None]
    err = np.einsum("nij,nj->ni", np.linalg.cholesky(true), rng.normal(size=(n, 2)))
    return err, v, g


def test_the_pass_correlation_interval_holds_the_true_one():
    """At the true ``kappa`` a control is inside its 95 % region with probability 0.95
    exactly, so ``kappa`` is the 0.95 quantile of the least ones: the interval holds it
    on at least the binomial share of seeds."""
    hits = 0
    for seed in range(SEEDS):
        err, v, g = _correlated(np.random.default_rng(3000 + seed), 200, 0.004)
        f = pass_correlation(err, v, g, v)
        hits += f.interval[0] <= 0.004 <= f.interval[1]
    assert hits >= LOW, hits


def test_a_pass_correlation_covers_controls_with_few_and_many_passes_alike():
    """Controls with correlated passes: measured on one half, applied to the other, the
    correlation covers those with 150-400 passes and those with 650-900 alike, each share
    within the binomial 99.9 % range of 0.95 for its count."""
    rng = np.random.default_rng(17)
    err, v, g = _correlated(rng, 2000, 0.004)
    fit, test = np.arange(2000) < 1000, np.arange(2000) >= 1000
    k = pass_correlation(err[fit], v[fit], g[fit], v[fit]).value
    cov = v * (1 + k * g)[:, None, None]
    m2 = np.einsum("ni,ni->n", err, np.linalg.solve(cov, err[..., None])[..., 0])
    for m in (test & (g < 400), test & (g >= 650)):
        n = int(m.sum())
        share = float(np.mean(m2[m] <= chi2.ppf(0.95, 2)))
        assert binom.ppf(0.0005, n, 0.95) / n <= share <= binom.isf(0.0005, n, 0.95) / n, (n, share)


def test_the_evaluation_measures_records_and_reads_its_floor(tmp_path):
    """``fleetsim.evaluation.map_floor_file``: a round's signs with 150+ passes are the
    controls (the others, and unpaired signs, left out); the measured floor written for a
    noise name is what later runs of that noise give the solver."""
    from fleetsim.evaluation.fleet_scoring import SignRecord
    from fleetsim.evaluation.map_floor_file import (
        AppliedFloor,
        applied_floor,
        measured_floor,
        record_floor,
    )

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
    applied = AppliedFloor(0.0, (0.1, 0.1, 0.1), np.zeros((3, 3)), "test")
    m = measured_floor(rec, applied)
    assert m["horizontal"]["controls"] == 99 and m["vertical"]["controls"] == 99
    assert m["pass_correlation"]["controls"] == 99
    lo, hi = m["horizontal"]["interval"]
    assert lo <= m["horizontal"]["sigma_m"] <= hi
    few = SignRecord(
        n, found & (np.arange(k) < 19), rec.err, rec.inside, rec.landmark,
        err_enu=rec.err_enu, cov_enu=cov6,
    )  # fmt: skip
    assert measured_floor(few, applied) is None
    path = tmp_path / "floor.json"
    zero = np.zeros((3, 3))
    none = applied_floor("fleet", "isotropic", zero, (0.1, 0.1, 0.1), path)
    assert (none.kappa, none.sigma_m) == (0.0, (0.1, 0.1, 0.1))
    entry = record_floor("fleet", m, "hdmap eval fleet --seed 10", 10, path)
    assert entry["seeds"] == [10] and entry["horizontal"]["sigma_m"] == m["horizontal"]["sigma_m"]
    h, v = m["horizontal"]["sigma_m"], m["vertical"]["sigma_m"]
    iso = applied_floor("fleet", "isotropic", zero, (0.1, 0.1, 0.1), path)
    assert (iso.kappa, iso.sigma_m) == (0.0, (h, h, v))
    cor = applied_floor("fleet", "correlation", zero, (0.1, 0.1, 0.1), path)
    assert (cor.kappa, cor.sigma_m) == (m["pass_correlation"]["kappa"], (0.0, 0.0, 0.0))
    assert applied_floor("fleet+gsdc", "correlation", zero, (0.1,) * 3, path).kappa == 0.0
    assert "pass_correlation = " in cor.solver_lines()[0]
    with pytest.raises(ValueError, match="one of"):
        applied_floor("fleet", "both", zero, (0.1,) * 3, path)
    # a second held-out seed pools its controls with the first's; the same seed again
    # replaces its own run
    err2, cov2 = _controls(np.random.default_rng(6), k, 0.3, base=0.1)
    cov6_2 = cov6.copy()
    cov6_2[:, [0, 1, 3]] = cov2[:, [0, 0, 1], [0, 1, 1]]
    rec2 = SignRecord(
        n, found, np.hypot(*err2.T), np.zeros(k, bool), np.zeros(k, np.uint64),
        err_enu=np.column_stack([err2, err_v]), cov_enu=cov6_2,
    )  # fmt: skip
    m2 = measured_floor(rec2, applied)
    both = record_floor("fleet", m2, "hdmap eval fleet --seed 11", 11, path)
    union = m["horizontal"]["least"] + m2["horizontal"]["least"]
    assert both["seeds"] == [10, 11] and both["horizontal"]["controls"] == 198
    assert both["horizontal"]["sigma_m"] == quantile_interval(np.array(union), 0.95)[0]
    again = record_floor("fleet", m2, "hdmap eval fleet --seed 11", 11, path)
    assert again["horizontal"] == both["horizontal"]


def _record_seeds(path: str, seeds: list[int], measured: dict) -> None:
    from fleetsim.evaluation.map_floor_file import record_floor

    for s in seeds:
        record_floor("fleet", measured, f"hdmap eval fleet --seed {s}", s, Path(path))


def test_seeds_recorded_at_once_are_all_kept(tmp_path: Path) -> None:
    """``--seeds 11,12 --jobs 2 --calibrate-floor`` records from two processes: each
    record reads, pools and rewrites the file, so without the lock one process's seed
    can be lost (read before the other's write). Two processes, 15 seeds each."""
    least = np.linspace(0.05, 0.5, 40).tolist()
    form = {"least": least, "level": 0.95, "confidence": 0.95}
    measured = {"horizontal": form, "vertical": form, "pass_correlation": form}
    path = tmp_path / "floor.json"
    ctx = multiprocessing.get_context("fork")
    procs = [
        ctx.Process(target=_record_seeds, args=(str(path), list(range(k, 30, 2)), measured))
        for k in (0, 1)
    ]
    try:
        for p in procs:
            p.start()
        for p in procs:
            p.join(timeout=60)
            assert p.exitcode == 0
    finally:  # stopped also when one failed or hung
        for p in procs:
            if p.is_alive():
                p.kill()
                p.join(timeout=10)
    data = json.loads(path.read_text())
    assert data["fleet"]["seeds"] == list(range(30))
    assert data["fleet"]["horizontal"]["controls"] == 30 * 40
