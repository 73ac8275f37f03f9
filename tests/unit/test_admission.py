"""Ingest admission beyond the schema: rows in tiles past an upload's tile budget."""

from __future__ import annotations

import numpy as np

from fleetsim.synthetic import make_observations
from hdmap.geo.tiles import route_rays
from schemas import Observations
from services.ingest.admission import AdmissionPolicy, admit


def _tiles(obs: Observations) -> np.ndarray:
    return route_rays(obs.lat, obs.lon, obs.h, obs.direction, obs.range_m)


def test_an_upload_spread_over_the_globe_keeps_only_its_first_tiles():
    obs = make_observations(10_000, seed=3, t=1.7e9)
    rng = np.random.default_rng(3)
    obs = Observations(
        **{
            **obs.__dict__,
            "lat": rng.uniform(-80, 80, 10_000),
            "lon": rng.uniform(-179, 179, 10_000),
        }
    )
    tiles = _tiles(obs)
    policy = AdmissionPolicy()
    keep, rejected = admit(obs, policy, 1.7e9, tiles)
    assert np.unique(tiles[keep]).size == policy.max_tiles
    # the kept tiles are the first ones in batch order, every row of them kept
    first = list(dict.fromkeys(tiles.tolist()))[: policy.max_tiles]
    assert keep.tolist() == np.isin(tiles, first).tolist()
    assert len(rejected) == int((~keep).sum())
    assert {r.field for r in rejected} == {"obs.lat"}
    assert all(f"first {policy.max_tiles}" in r.reason for r in rejected)


def test_a_batch_from_one_stretch_of_road_is_admitted_whole():
    obs = make_observations(500, seed=4, t=1.7e9)  # one place, 1e-4 deg of spread
    keep, rejected = admit(obs, AdmissionPolicy(), 1.7e9, _tiles(obs))
    assert keep.all() and rejected == []
