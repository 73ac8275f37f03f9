"""Landmark initiation from the rays of one pass (synthetic, fixed seeds)."""

from __future__ import annotations

import numpy as np

from hdmap.mapping.association import GateConfig
from hdmap.mapping.initiation import InitConfig, propose, triangulate
from tests.support.association import rays_to


def test_triangulation_of_exact_rays_hits_the_point():
    rng = np.random.default_rng(0)
    x = np.array([4.0, 40.0, 2.4])
    o = np.c_[np.zeros(10), np.linspace(0, 25, 10), np.full(10, 1.4)]
    r = rays_to(np.broadcast_to(x, (10, 3)), o, rng, s_ang=1e-9, s_pos=1e-9)
    est, cov = triangulate(r)
    assert np.allclose(est, x, atol=1e-4)
    assert np.all(np.linalg.eigvalsh(cov) > 0)


def test_range_makes_a_straight_ahead_sign_solvable():
    rng = np.random.default_rng(1)
    x = np.array([0.0, 50.0, 1.4])  # dead ahead: no parallax at all
    o = np.c_[np.zeros(6), np.linspace(0, 20, 6), np.full(6, 1.4)]
    r = rays_to(np.broadcast_to(x, (6, 3)), o, rng, s_ang=1e-4, s_pos=0.01)
    est, _ = triangulate(r)
    assert np.linalg.norm(est - x) < 3.0


def test_one_pass_two_signs_of_the_same_class_make_two_candidates():
    rng = np.random.default_rng(2)
    a, b = np.array([4.0, 50.0, 2.5]), np.array([4.0, 56.0, 2.5])
    o = np.c_[np.zeros(40), np.linspace(0, 40, 40), np.full(40, 1.4)]
    parts = []
    for s in (a, b):
        ahead = (s[1] - o[:, 1] > 10) & (s[1] - o[:, 1] < 60)
        parts.append(
            rays_to(
                np.broadcast_to(s, (ahead.sum(), 3)),
                o[ahead],
                rng,
                s_ang=0.003,
                s_pos=0.3,
                images=np.flatnonzero(ahead),
            )
        )
    from hdmap.mapping.association import LocalRays

    rays = LocalRays.concat(parts)
    cands = propose(rays, GateConfig(), InitConfig())
    xs = sorted((c.x for c in cands), key=lambda v: v[1])
    assert len(xs) == 2, [c.x for c in cands]
    # one pass: across the line of sight to decimetres, along it (range) to metres
    for est, true in zip(xs, (a, b), strict=True):
        assert abs(est[0] - true[0]) < 0.5
        assert abs(est[1] - true[1]) < 2.0
    members = np.concatenate([c.members for c in cands])
    assert len(members) == len(set(members.tolist()))  # a ray joins one candidate


def test_too_few_rays_make_nothing():
    rng = np.random.default_rng(3)
    x = np.array([4.0, 40.0, 2.4])
    o = np.c_[np.zeros(3), np.linspace(0, 10, 3), np.full(3, 1.4)]
    r = rays_to(np.broadcast_to(x, (3, 3)), o, rng)
    assert propose(r, GateConfig(), InitConfig()) == []


def test_tiny_valid_sigmas_give_finite_weights_not_a_crash():
    """The wire accepts any sigma > 0; 1e-300 squared underflows to zero (a fuzz find:
    the matcher's initiation divided by zero and its SVD failed)."""
    rng = np.random.default_rng(2)
    x = np.array([4.0, 40.0, 2.4])
    o = np.c_[np.zeros(8), np.linspace(0, 20, 8), np.full(8, 1.4)]
    r = rays_to(np.broadcast_to(x, (8, 3)), o, rng, s_ang=1e-300, s_pos=1e-300)
    est, cov = triangulate(r)
    assert np.isfinite(est).all() and np.isfinite(cov).all()
    assert np.allclose(est, x, atol=1e-3)
    for cand in propose(r, GateConfig(), InitConfig()):
        assert np.isfinite(cand.x).all()
