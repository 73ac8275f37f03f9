"""Many units associated at once (hdmap/mapping/batch_association.py) give each unit the
association it gets alone, to the bit, in any batch and any order: what lets the matcher
associate a gating tick's units together and keep replays exact.

Scene: a row of same-class signs 8.5 m apart beside a road (the lattice where offset
hypotheses matter) and signs of two other classes; each unit is a pass of 12 images along
part of the road with its own GNSS bias (2 m per axis), with or without onboard tracks and
facings, some with no candidate of their classes, one with no rays."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from hdmap.mapping.association import GateConfig
from hdmap.mapping.batch_association import UnitInput, associate, associate_units
from hdmap.mapping.facing import Facing
from tests.support.association import rays_to

SIGNS = np.array([[8.5 * k, 4.0, 2.0] for k in range(12)] + [[30.0, -4.0, 2.5], [61.0, 5.0, 2.2]])
CLASSES = np.array([4] * 12 + [7, 9])


def unit(rng: np.random.Generator, k: int) -> UnitInput:
    x0 = rng.uniform(-10.0, 60.0)
    cam = np.array([[x0 + 2.0 * i, -1.5, 1.4] for i in range(12)])
    bias = np.r_[rng.normal(0.0, 2.0, 2), 0.0]
    rows, imgs, signs = [], [], []
    for i, c in enumerate(cam):
        ahead = np.flatnonzero((SIGNS[:, 0] - c[0] > 4.0) & (SIGNS[:, 0] - c[0] < 40.0))
        seen = ahead[rng.random(ahead.size) < 0.8]
        rows += [c] * seen.size
        imgs += [i] * seen.size
        signs += seen.tolist()
    sel = np.array(signs, np.int64)
    origins = np.array(rows).reshape(-1, 3)
    r = rays_to(SIGNS[sel], origins, rng, s_ang=0.01, s_pos=0.5, bias=bias, images=np.array(imgs))
    r = replace(r, sign_class=CLASSES[sel])
    if k % 3 != 0:  # tracked: one track per sign seen (arbitrary ids from the vehicle)
        ids = rng.permutation(1000)[: SIGNS.shape[0]] + 1
        r = replace(r, track=ids[sel])
    if k == 5:
        r = r.take(np.zeros(0, np.int64))
    cand = np.arange(SIGNS.shape[0]) if k % 4 else np.flatnonzero(CLASSES != 4)
    x = SIGNS[cand] + rng.normal(0.0, 0.3, (cand.size, 3))
    cov = np.repeat(np.diag([0.5, 0.5, 1.0])[None], cand.size, axis=0)
    facing = None
    if k % 2:
        known = rng.random(cand.size) < 0.7
        facing = Facing(
            np.full(cand.size, np.pi), np.full(cand.size, 0.1), np.zeros(cand.size), known
        )
    return UnitInput(r, x, cov, CLASSES[cand], facing)


def same(a, b) -> None:
    np.testing.assert_array_equal(a.landmark, b.landmark)
    np.testing.assert_array_equal(a.chi2, b.chi2)
    np.testing.assert_array_equal(a.offset, b.offset)
    np.testing.assert_array_equal(a.offset_cov, b.offset_cov)
    assert (a.unlinked is None) == (b.unlinked is None)
    if a.unlinked is not None:
        np.testing.assert_array_equal(a.unlinked, b.unlinked)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_unit_gets_the_same_association_alone_and_in_any_batch(seed: int) -> None:
    rng = np.random.default_rng(seed)
    units = [unit(rng, k) for k in range(16)]
    cfg = GateConfig()
    alone = [associate(u.rays, u.x, u.cov, u.cls, cfg, u.facing) for u in units]
    assert sum(int((a.landmark >= 0).sum()) for a in alone) > 100  # the scene associates
    for a, b in zip(alone, associate_units(units, cfg), strict=True):
        same(a, b)
    order = rng.permutation(len(units))
    for k, b in zip(order, associate_units([units[k] for k in order], cfg), strict=True):
        same(alone[k], b)


def test_alternative_offsets_run_in_a_batch_as_alone() -> None:
    """A 5 m bias along the row of identical signs: the alternatives (the longest track put
    on each of its candidates) change the unit's association, and the unit gets the same
    one in a batch as alone."""
    rng = np.random.default_rng(7)
    u = unit(rng, 1)
    u5 = replace(u, rays=replace(u.rays, origin=u.rays.origin + np.array([5.0, 0.0, 0.0])))
    cfg = GateConfig()
    one = associate(u5.rays, u5.x, u5.cov, u5.cls, cfg, u5.facing)
    first_only = associate(
        u5.rays, u5.x, u5.cov, u5.cls, replace(cfg, offset_hypotheses=0), u5.facing
    )
    assert not np.array_equal(one.landmark, first_only.landmark)
    same(one, associate_units([unit(rng, 2), u5, unit(rng, 3)], cfg)[1])
