"""The matcher's fast paths against their dense reference: the gating statistic evaluated
only on the plausible pairs (``pair_chi2``, its 2x2 and 3x3 products written out) and the
sightings' reach prefilter (``in_view``) must give, pair by pair and landmark by landmark,
what the evaluation over every pair gives (the same mask; the statistic to rounding); and
a pair's statistic must not depend on which other pairs are evaluated with it (the
matcher's replays compare maps to the bit)."""

from __future__ import annotations

import math

import numpy as np

from hdmap.mapping.association import (
    GateConfig,
    LocalRays,
    Pairs,
    origin_cov,
    pair_chi2,
    pair_stat,
)
from hdmap.mapping.estimator.gating import angle_jacobian, wrap
from hdmap.mapping.estimator.model import ray_angles as angles
from hdmap.mapping.sightings import SightingConfig, in_view
from tests.support.association import rays_to


def dense_pair_chi2(rays: LocalRays, ri, x, cov, a_cov, cfg: GateConfig, offset=None):
    """The statistic and mask over every pair (the form before the subset evaluation)."""
    a = rays.origin[ri] + (0.0 if offset is None else offset)
    d = rays.direction[ri]
    v = x - a
    rng = np.linalg.norm(v, axis=-1)
    az, el = angles(v)
    az_m, el_m = angles(d)
    res = np.stack([wrap(az - az_m), el - el_m], axis=-1)
    j = angle_jacobian(v)
    c = cov + a_cov[ri]
    s = j @ c @ j.transpose(0, 2, 1)
    s[:, 0, 0] += rays.sigma_az[ri] ** 2 + cfg.angle_floor_rad**2
    s[:, 1, 1] += rays.sigma_el[ri] ** 2 + cfg.angle_floor_rad**2
    det = s[:, 0, 0] * s[:, 1, 1] - s[:, 0, 1] * s[:, 1, 0]
    det = np.where(det > 0, det, 1e-30)
    chi2 = (
        res[:, 0] ** 2 * s[:, 1, 1]
        - 2 * res[:, 0] * res[:, 1] * s[:, 0, 1]
        + res[:, 1] ** 2 * s[:, 0, 0]
    ) / det
    ok = (np.einsum("kj,kj->k", v, d) > 0) & (rng >= cfg.min_range_m) & (rng <= cfg.max_range_m)
    r_est = rays.range_m[ri]
    has_r = r_est > 0
    s_r = np.hypot(rays.sigma_range_m[ri], np.sqrt(np.einsum("ki,kij,kj->k", d, c, d)))
    ok &= ~has_r | (np.abs(rng - r_est) <= cfg.range_k * s_r)
    if cfg.range_in_cost:
        chi2 = chi2 + np.where(has_r, ((rng - r_est) / np.where(has_r, s_r, 1.0)) ** 2, 0.0)
    return chi2, ok


def test_statistic_on_plausible_pairs_equals_the_dense_evaluation():
    rng = np.random.default_rng(7)
    n, m = 60, 40
    marks = np.c_[rng.uniform(-80, 80, (m, 2)), rng.uniform(1.5, 3.5, m)]
    origins = np.c_[rng.uniform(-60, 60, (n, 2)), np.full(n, 1.4)]
    rays = rays_to(marks[rng.integers(0, m, n)], origins, rng, s_ang=0.02, s_pos=1.5)
    ri, li = (a.ravel() for a in np.meshgrid(np.arange(n), np.arange(m), indexing="ij"))
    cov = np.einsum("kij,klj->kil", *(2 * [rng.normal(0, 0.7, (m, 3, 3))]))[li]
    for offset, a_cov in ((None, origin_cov(rays, 2.5, 1.0)), (np.array([1.2, -0.7, 0.3]), None)):
        a_cov = origin_cov(rays, 0.0, 0.0) if a_cov is None else a_cov
        got, ok = pair_chi2(rays, ri, marks[li], cov, a_cov, GateConfig(), offset)
        want, want_ok = dense_pair_chi2(rays, ri, marks[li], cov, a_cov, GateConfig(), offset)
        assert 0 < ok.sum() < ok.size  # both kinds of pairs are exercised
        assert np.array_equal(ok, want_ok)
        np.testing.assert_allclose(got[ok], want[ok], rtol=1e-10)  # products in another order
        assert np.isinf(got[~ok]).all()
        rows = np.flatnonzero(rng.random(ri.size) < 0.3)
        pairs = Pairs.of(rays, ri, marks[li], cov)
        part, part_ok = pair_stat(rays, pairs, a_cov, GateConfig(), offset, rows)
        assert np.array_equal(part_ok[rows], ok[rows])
        assert np.array_equal(part[rows], got[rows])  # to the bit, whatever else is evaluated


def dense_in_view(origin, direction, x, facing_az, facing_known, cfg: SightingConfig):
    v = x[None, :, :2] - origin[:, None, :2]
    dist = np.linalg.norm(v, axis=2)
    lo, hi = cfg.range_m
    ok = (dist >= lo) & (dist <= hi)
    dh = direction[:, :2] / np.linalg.norm(direction[:, :2], axis=1, keepdims=True)
    ok &= np.einsum("nkj,nj->nk", v, dh) / np.maximum(dist, 1e-12) >= math.cos(
        math.radians(cfg.half_fov_deg)
    )
    off = np.abs((np.arctan2(-v[..., 0], -v[..., 1]) - facing_az + np.pi) % (2 * np.pi) - np.pi)
    ok &= ~facing_known | (off <= math.radians(cfg.max_view_deg))
    return ok.any(axis=0)


def test_reach_prefilter_keeps_every_landmark_in_view():
    rng = np.random.default_rng(8)
    origin = np.c_[rng.uniform(0, 40, (30, 2)), np.zeros(30)]
    direction = np.c_[rng.normal(size=(30, 2)), rng.normal(0, 0.05, 30)]
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    x = np.c_[rng.uniform(-100, 140, (400, 2)), np.full(400, 2.0)]
    az = rng.uniform(0, 2 * np.pi, 400)
    known = rng.random(400) < 0.7
    cfg = SightingConfig()
    got = in_view(origin, direction, x, az, known, cfg)
    assert got.any() and not got.all()
    assert np.array_equal(got, dense_in_view(origin, direction, x, az, known, cfg))
