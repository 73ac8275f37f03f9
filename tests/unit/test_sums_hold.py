"""Held passes (a vehicle on probation): released, they equal the same rays fed at the new
weight from the start; dropped, they equal never having been fed; neither eviction,
closing, merging nor a pack/unpack round trip mixes them into the closed sums."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from hdmap.mapping.estimator import EstimatorConfig, LandmarkSums, Rays
from hdmap.mapping.estimator.packing import (
    OPEN_DTYPE_V2,
    OPEN_DTYPE_V3,
    OPEN_DTYPE_V4,
    ROW_DTYPE_V2,
    ROW_DTYPE_V4,
    decode,
)
from tests.support.estimator import SIGN, passes

HOLD = 7_000_001  # the key of the vehicle on probation
PROBATION = 0.05


def weighted(r: Rays, w: float) -> Rays:
    return replace(r, weight=np.full(len(r), w))


def fresh(cfg: EstimatorConfig) -> tuple[LandmarkSums, np.ndarray]:
    s = LandmarkSums(cfg)
    row = s.new_rows(1, [SIGN + np.array([1.0, -2.0, 0.0])])
    s.set_reference(row, [SIGN + np.array([0.3, 0.5, 0.0])])
    return s, row


def feed(s, row, parts):
    """``parts``: (clusters, rays, held) in order; held parts get ``hold=HOLD``."""
    for cl, r, held in parts:
        h = np.full(cl.size, HOLD if held else 0)
        s.accumulate(np.full(cl.size, row[0]), cl, r, hold=h)


def same(a, b):
    np.testing.assert_allclose(a.x, b.x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(a.cov, b.cov, rtol=1e-9, atol=1e-13)
    assert a.n_obs.tolist() == b.n_obs.tolist()
    assert a.n_clusters.tolist() == b.n_clusters.tolist()
    assert a.ok.tolist() == b.ok.tolist()


@pytest.fixture
def data():
    rng = np.random.default_rng(3)
    honest = [passes(rng, 4, 100 * i) for i in range(1, 5)]  # 16 passes in 4 calls
    rogue = [passes(rng, 3, 10_000 + 100 * i, bias_m=5.0) for i in range(4)]  # 12 passes
    return honest, rogue


@pytest.mark.parametrize("max_open", [4, 64])  # honest passes evicted (closed) or not
def test_released_passes_equal_rays_fed_at_the_new_weight(data, max_open):
    honest, rogue = data
    cfg = EstimatorConfig(max_open_passes=max_open)
    held, row = fresh(cfg)
    plain, prow = fresh(cfg)
    for (hc, hr), (rc, rr) in zip(honest, rogue, strict=True):
        feed(held, row, [(hc, hr, False), (rc, weighted(rr, PROBATION), True)])
        feed(plain, prow, [(hc, hr, False), (rc, rr, False)])
    assert held.n_held() == 12  # never evicted, whatever max_open_passes
    before = held.solve(row, update_reference=False)
    assert held.release(HOLD, 1.0).tolist() == row.tolist() and held.n_held() == 0
    same(held.solve(row, update_reference=False), plain.solve(prow, update_reference=False))
    # while held they counted, 20 times less: the shifted passes pulled less
    x_full = plain.solve(prow, update_reference=False).x[0]
    assert abs(before.x[0, 0] - SIGN[0]) < abs(x_full[0] - SIGN[0])
    # released passes are ordinary open passes now: closing them changes nothing
    held.close_passes()
    plain.close_passes()
    same(held.solve(row, update_reference=False), plain.solve(prow, update_reference=False))


def test_dropped_passes_equal_never_fed(data):
    honest, rogue = data
    cfg = EstimatorConfig(max_open_passes=4)
    held, row = fresh(cfg)
    clean, crow = fresh(cfg)
    for (hc, hr), (rc, rr) in zip(honest, rogue, strict=True):
        feed(held, row, [(rc, weighted(rr, PROBATION), True), (hc, hr, False)])
        feed(clean, crow, [(hc, hr, False)])
    held.close_passes()  # closes the honest ones only
    clean.close_passes()
    assert held.drop_held(HOLD).tolist() == row.tolist() and held.drop_held(HOLD).size == 0
    same(held.solve(row, update_reference=False), clean.solve(crow, update_reference=False))
    assert held.n_open_passes == 0


def test_pack_unpack_and_merge_keep_passes_held(data):
    honest, rogue = data
    cfg = EstimatorConfig(max_open_passes=4)
    a, ra = fresh(cfg)
    b, rb = fresh(cfg)
    for i, ((hc, hr), (rc, rr)) in enumerate(zip(honest, rogue, strict=True)):
        # a: everything in one row; b: the later half in a second row, merged back
        feed(a, ra, [(hc, hr, False), (rc, weighted(rr, PROBATION), True)])
        if i == 2:
            extra = b.new_rows(1, [SIGN + np.array([2.0, 1.0, 0.0])])
            b.set_reference(extra, b.reference(rb))
        feed(b, rb if i < 2 else extra, [(hc, hr, False), (rc, weighted(rr, PROBATION), True)])
    b.merge_rows(int(rb[0]), int(extra[0]))
    assert b.n_held() == a.n_held() == 12
    restored = LandmarkSums(cfg)
    r2 = restored.unpack_rows(a.pack_rows(ra))
    assert restored.n_held() == 12
    for s in (a, b, restored):
        s.release(HOLD, 1.0)
    same(b.solve(rb, update_reference=False), a.solve(ra, update_reference=False))
    same(restored.solve(r2, update_reference=False), a.solve(ra, update_reference=False))


def test_a_pass_is_held_or_not_for_good(data):
    hc, hr = data[0][0]
    s, row = fresh(EstimatorConfig())
    s.accumulate(np.full(hc.size, row[0]), hc, hr)
    with pytest.raises(ValueError, match="held and not"):
        s.accumulate(np.full(hc.size, row[0]), hc, hr, hold=np.full(hc.size, HOLD))
    mixed = np.where(np.arange(hc.size) % 2 == 0, HOLD, 0)
    with pytest.raises(ValueError, match="held and not"):
        s.accumulate(np.full(hc.size, row[0]), hc + 1000, hr, hold=mixed)
    paper = LandmarkSums(EstimatorConfig.paper())
    paper.new_rows(1, [SIGN])
    with pytest.raises(ValueError, match="pass-level"):
        paper.accumulate(np.zeros(hc.size, int), hc, hr, hold=np.full(hc.size, HOLD))


def _downgrade(blob: bytes, version: int, row_dt: np.dtype, open_dt: np.dtype) -> bytes:
    """An older blob: the current one with only the older version's columns."""
    _, rec, op = decode(blob)
    r_old, o_old = np.zeros(1, row_dt), np.zeros(op.size, open_dt)
    for name in row_dt.names:
        r_old[name] = rec[name]
    for name in open_dt.names:
        o_old[name] = op[name]
    return bytes([version]) + r_old.tobytes() + o_old.tobytes()


def test_version_3_and_4_blobs_still_load(data):
    """A v3 blob (before held passes) is a v4 one without the held-pass columns; a v4 one
    (before the pull sum) a v5 one without it."""
    hc, hr = data[0][0]
    s, row = fresh(EstimatorConfig())
    s.accumulate(np.full(hc.size, row[0]), hc, hr)
    blob = s.pack_rows(row)[0]
    assert blob[0] == 4  # no pull: written without the pull columns
    pulled, _ = fresh(EstimatorConfig(extra_sigma_pos_m=2.0))
    pulled.accumulate(np.full(hc.size, row[0]), hc, hr)
    assert pulled.pack_rows(row)[0][0] == 5
    for version, open_dt in ((3, OPEN_DTYPE_V3), (4, OPEN_DTYPE_V4)):
        old = LandmarkSums(EstimatorConfig())
        r_old = old.unpack_rows([_downgrade(blob, version, ROW_DTYPE_V4, open_dt)])
        same(old.solve(r_old, update_reference=False), s.solve(row, update_reference=False))


def test_version_2_blob_with_open_passes_loads(data):
    """A v2 blob (no ray weight sums: its open records have no ``w``, 104 bytes) with open
    passes loads; with rays of weight 1 it is the same state."""
    hc, hr = data[0][0]
    s, row = fresh(EstimatorConfig())
    s.accumulate(np.full(hc.size, row[0]), hc, hr)
    assert s.n_open_passes > 0
    blob = _downgrade(s.pack_rows(row)[0], 2, ROW_DTYPE_V2, OPEN_DTYPE_V2)
    assert len(blob) == 1 + ROW_DTYPE_V2.itemsize + s.n_open_passes * 104
    old = LandmarkSums(EstimatorConfig())
    r_old = old.unpack_rows([blob])
    assert old.n_open_passes == s.n_open_passes
    same(old.solve(r_old, update_reference=False), s.solve(row, update_reference=False))
