"""The load generator's pool replays: each replay a fresh GNSS bias, false positives and
multipath jumps somewhere new (:class:`fleetsim.loadgen.Pool`).

Checked against the simulator's own truth of the pool passes: a replay drawn from a
model without bias removes exactly the bias the pass was simulated with; drawn from the
pool's model, the constant bias of replays has the model's spread (chi-square interval
for the stated count); the pool's own passes are never changed.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy import stats

from fleetsim.loadgen import LoadConfig, Pool, build_pool


@pytest.fixture(scope="module")
def built():
    return build_pool(LoadConfig(pool_passes=6, seed=3))


def _enu(world, obs):
    return world.frame.from_geodetic(obs.lat, obs.lon, obs.h).reshape(-1, 3)


def _az(obs):
    return np.arctan2(obs.direction[:, 0], obs.direction[:, 1])


def _no_noise(pool: Pool) -> Pool:
    g = replace(
        pool.gnss,
        bias_h_m=0.0,
        bias_v_m=0.0,
        bias_heading_rad=0.0,
        walk_h_m_per_sqrt_s=0.0,
        walk_v_m_per_sqrt_s=0.0,
    )
    return replace(pool, gnss=g)


def _busiest(pool: Pool) -> int:
    return int(np.argmax([sum(len(p) for p in parts) for parts in pool]))


def test_a_replay_without_noise_removes_the_simulated_bias(built):
    world, pool = built
    k = _busiest(pool)
    quiet = _no_noise(pool)
    before = [p.lat.copy() for p in pool[k]]
    out = quiet.replay(k, np.random.default_rng(0))
    for part, rep, fp, mp in zip(
        pool[k], out, pool.false_positive[k], pool.multipath[k], strict=True
    ):
        keep = ~mp
        old = np.column_stack(
            [np.interp(part.t, pool.fix_t[k], pool.bias_enu[k][:, i]) for i in range(3)]
        )
        moved = _enu(world, rep) - _enu(world, part)
        np.testing.assert_allclose(moved[keep], -old[keep], atol=0.02)
        turn = (_az(rep) - _az(part) + np.pi) % (2 * np.pi) - np.pi
        np.testing.assert_allclose(turn[~fp], -pool.heading_bias_rad[k], atol=1e-9)
        assert np.all(np.abs(turn[fp] + pool.heading_bias_rad[k]) <= np.radians(25.0) + 1e-9)
        jump = np.hypot(*(moved[mp] + old[mp])[:, :2].T)
        g = pool.gnss
        assert np.all((jump >= g.multipath_min_m - 0.05) & (jump <= g.multipath_max_m + 0.05))
        np.testing.assert_array_equal(rep.obs_id, part.obs_id)
        np.testing.assert_array_equal(rep.sign_class, part.sign_class)
    for b, part in zip(before, pool[k], strict=True):
        np.testing.assert_array_equal(b, part.lat)  # the pool's passes are not touched


def test_replayed_biases_have_the_models_spread(built):
    world, pool = built
    k = _busiest(pool)
    part = pool[k][0]
    row = int(np.flatnonzero(~pool.multipath[k][0])[0])
    old = np.array(
        [np.interp(part.t[row], pool.fix_t[k], pool.bias_enu[k][:, i]) for i in range(3)]
    )
    n = 400
    rng = np.random.default_rng(11)
    east = np.array(
        [(_enu(world, pool.replay(k, rng)[0]) - _enu(world, part))[row, 0] for _ in range(n)]
    )
    bias = east + old[0]  # the replay's own bias at that observation, East
    g = pool.gnss
    t = part.t[row] - pool.fix_t[k][0]
    sigma = np.hypot(g.bias_h_m, g.walk_h_m_per_sqrt_s * np.sqrt(max(t, 0.0)))
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], n)
    assert lo / n <= np.mean(bias**2) / sigma**2 <= hi / n
    assert abs(bias.mean()) <= stats.norm.ppf(0.9995) * sigma / np.sqrt(n)
