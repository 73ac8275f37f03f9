"""Units prepared together (hdmap.mapping.unit.prepare_units: the rays of one tile's units
converted in one call) are the units prepared one by one, to the bit: tracked and
untracked units mixed, in two tiles."""

from __future__ import annotations

from dataclasses import fields, replace
from pathlib import Path

import numpy as np

from hdmap.geo.tiles import neighbours
from hdmap.mapping.unit import prepare_unit, prepare_units
from services.matcher.replay import open_matcher
from services.matcher.service import MatcherConfig
from tests.support.services import sign_rays, tile_of


def test_units_prepared_together_are_the_units_prepared_alone(tmp_path: Path) -> None:
    svc = open_matcher(tmp_path, MatcherConfig())
    m = svc.matching
    here = tile_of(svc.opts.zoom)
    there = neighbours(here)[0]
    units = []
    for k in range(6):
        tile = here if k % 3 else there
        obs = sign_rays(m.frames(tile), k + 1, np.random.default_rng(k))
        if k % 2:  # tracked: two tracks of the unit's images
            obs = replace(obs, track=(np.arange(len(obs)) % 2 + 1).astype(obs.track.dtype))
        units.append((tile, f"veh-{k}", k + 1, obs))
    assert any(u[3].track.any() for u in units) and not all(u[3].track.any() for u in units)
    together = prepare_units(m, units)
    for u, t in zip(units, together, strict=True):
        alone = prepare_unit(m, *u)
        for f in fields(alone.rays):
            a, b = getattr(alone.rays, f.name), getattr(t.rays, f.name)
            if a is None or b is None:
                assert a is None and b is None, f.name
            else:
                assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), f.name
    svc.db.close()
