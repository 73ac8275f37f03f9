"""Merging two landmark rows (one sign that became two landmarks) equals one row fed
every ray: same frame, and across tile frames (shifted, rotated about the vertical)."""

from __future__ import annotations

import numpy as np
import pytest

from hdmap.mapping.estimator import EstimatorConfig, LandmarkSums, Rays
from tests.support.estimator import random_batch


def rot_z(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def moved(r: Rays, rot: np.ndarray, t: np.ndarray) -> Rays:
    return Rays(
        r.origin @ rot.T + t, r.direction @ rot.T, r.sigma_az, r.sigma_el,
        r.sigma_pos_h, r.sigma_pos_v, r.weight,
    )  # fmt: skip


@pytest.mark.parametrize("theta, t", [(0.0, (0.0, 0.0, 0.0)), (0.3, (120.0, -45.0, 1.5))])
def test_merged_rows_equal_one_row_fed_every_ray(theta, t):
    rng = np.random.default_rng(11)
    _, clusters, r, xs = random_batch(rng, n_rows=1, n=480)
    rot, t = rot_z(theta), np.asarray(t)
    cfg = EstimatorConfig(max_open_passes=16)
    # src holds passes 0-5, dst 8-11, passes 6 and 7 are split between both
    shared = np.isin(clusters, [6, 7])
    to_src = (clusters < 6) | (shared & (rng.random(clusters.size) < 0.5))
    ref_dst = xs[0] @ rot.T + t + np.array([0.4, -0.3, 0.1])  # one physical reference
    m = LandmarkSums(cfg)
    anchors = np.stack([ref_dst + np.array([3.0, 1.0, 0.0]), xs[0] - np.array([2.0, 5.0, 0.5])])
    dst, src = m.new_rows(2, anchors)
    m.set_reference([dst], [ref_dst])
    m.set_reference([src], [(ref_dst - t) @ rot])  # the same point in src's frame
    whole = LandmarkSums(cfg)
    w = whole.new_rows(1, [ref_dst - np.array([1.0, 2.0, 0.0])])
    whole.set_reference(w, [ref_dst])
    order = rng.permutation(clusters.size)
    for part in np.array_split(order, 5):  # passes split over calls
        ps, pd = part[to_src[part]], part[~to_src[part]]
        m.accumulate(np.full(ps.size, src), clusters[ps], r.take(ps))
        m.accumulate(np.full(pd.size, dst), clusters[pd], moved(r.take(pd), rot, t))
        whole.accumulate(np.zeros(part.size, int), clusters[part], moved(r.take(part), rot, t))
    m.close_passes(rows=[src], clusters=[0])  # closed and open passes both move
    whole.close_passes(rows=w, clusters=[0])
    m.merge_rows(int(dst), int(src), rot, t)
    a, b = m.solve([dst], update_reference=False), whole.solve(w, update_reference=False)
    assert a.n_obs[0] == b.n_obs[0] == clusters.size
    assert a.n_clusters[0] == b.n_clusters[0] == 12
    np.testing.assert_allclose(a.x, b.x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(a.cov, b.cov, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(a.cov_sandwich, b.cov_sandwich, rtol=1e-9, atol=1e-12)
    assert m.solve([src], update_reference=False).n_obs[0] == 0  # src left empty
    assert m.n_open_passes == whole.n_open_passes
    # later rays of an open pass keep adding to the same cluster, also after a restart
    more = random_batch(np.random.default_rng(12), n_rows=1, n=60)
    r2 = moved(more[2], rot, t)
    blobs = m.pack_rows([dst])
    m2 = LandmarkSums(cfg)
    d2 = m2.unpack_rows(blobs)
    m2.accumulate(np.full(60, d2[0]), more[1], r2)
    whole.accumulate(np.zeros(60, int), more[1], r2)
    a, b = m2.solve(d2, update_reference=False), whole.solve(w, update_reference=False)
    np.testing.assert_allclose(a.x, b.x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(a.cov, b.cov, rtol=1e-9, atol=1e-12)


def test_merge_rejects_a_row_into_itself():
    s = LandmarkSums()
    s.new_rows(1, [[0.0, 0.0, 0.0]])
    with pytest.raises(ValueError):
        s.merge_rows(0, 0)
    with pytest.raises(IndexError):
        s.merge_rows(0, 3)
