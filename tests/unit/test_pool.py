"""The pending pool of a tile (hdmap/mapping/pool.py): append-only, its columns the rows
added in order less those dropped, its per-pass and per-vehicle counts kept as rows come
and go, and its kept conversions the ones a conversion anew gives."""

from __future__ import annotations

import numpy as np

from hdmap.geo.tiles import TileFrames
from hdmap.mapping.linking import to_local
from hdmap.mapping.pool import PendingTile
from schemas import Observations
from schemas.ids import pass_key
from tests.support.services import sign_rays, tile_of


def _pool_and_passes() -> tuple[PendingTile, list[tuple[str, int, Observations]], object]:
    frame = TileFrames()(tile_of(18))
    pool = PendingTile(Observations.empty())
    passes = []
    for k in range(5):
        obs = sign_rays(frame, k + 1, np.random.default_rng(k), n=4 + k)
        vehicle = f"veh-{k % 2}"
        local = to_local(frame, obs)
        kept = np.hstack([local.origin, local.direction]) if k % 2 else None
        pool.add(obs, vehicle, k + 1, 100.0 + k, 200.0 + k, kept)
        passes.append((vehicle, k + 1, obs))
    return pool, passes, frame


def test_the_columns_are_the_rows_added_in_order_less_those_dropped() -> None:
    pool, passes, frame = _pool_and_passes()
    n = sum(len(o) for _v, _p, o in passes)
    assert len(pool) == n  # counted as added, before the columns are read
    assert pool.count_of(pass_key("veh-1", 2)) == 5 and pool.per_vehicle["veh-0"] == 4 + 6 + 8
    ids = np.concatenate([o.obs_id for _v, _p, o in passes])
    np.testing.assert_array_equal(pool.obs.obs_id, ids)
    assert pool.vehicle.tolist() == [v for v, _p, o in passes for _ in range(len(o))]
    np.testing.assert_array_equal(
        pool.pass_id, np.repeat([p for _v, p, _o in passes], [4, 5, 6, 7, 8])
    )
    assert not pool.tried.any() and not pool.saved.any()
    # the kept conversions: rows of odd passes; the others NaN until converted
    local = pool.local
    odd = np.repeat([k % 2 == 1 for k in range(5)], [4, 5, 6, 7, 8])
    assert np.isfinite(local[odd]).all() and np.isnan(local[~odd]).all()
    anew = to_local(frame, pool.obs)
    assert local[odd].tobytes() == np.hstack([anew.origin, anew.direction])[odd].tobytes()
    # drop the second pass and every other ray of the last
    keep = np.ones(n, bool)
    keep[4:9] = False
    keep[np.arange(22, 30, 2)] = False
    pool.keep(keep)
    np.testing.assert_array_equal(pool.obs.obs_id, ids[keep])
    assert len(pool) == int(keep.sum())
    assert pool.count_of(pass_key("veh-1", 2)) == 0 and pool.count_of(pass_key("veh-0", 5)) == 4
    assert pool.per_vehicle == {"veh-0": 4 + 6 + 4, "veh-1": 7}
    # more rows after a drop go after the kept ones
    more = sign_rays(frame, 9, np.random.default_rng(9), n=3)
    pool.add(more, "veh-2", 9, 109.0, 209.0)
    assert pool.obs.obs_id[-3:].tolist() == more.obs_id.tolist() and len(pool) == keep.sum() + 3
    assert pool.added_at[-1] == 109.0 and pool.received_at[-1] == 209.0
