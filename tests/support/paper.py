"""The paper simulation with several estimators on the same rays."""

from __future__ import annotations

import numpy as np

from fleetsim.evaluation.paper_sim import (
    Geometry,
    simulate_pass,
)
from hdmap.mapping.estimator import LandmarkSums, triangulate


def side_by_side(
    noise, trials: int, passes: int, cfgs: dict, seed: int, solve_every: int = 1
) -> tuple[dict, Geometry]:
    """The paper simulation with several estimators on the same rays (each initialised from
    the first passing, solved every ``solve_every`` passings as the evaluation does each):
    their final solutions, without moving the references."""
    rng, geom = np.random.default_rng(seed), Geometry()
    f = geom.frames().size
    rows = np.repeat(np.arange(trials), f)
    sums: dict = {}
    for p in range(1, passes + 1):
        rays = simulate_pass(rng, trials, geom, noise)
        if p == 1:
            x0, _ = triangulate(rays, rows)
            x0 = np.where(np.isfinite(x0), x0, rays.origin[::f] + 30.0 * rays.direction[::f])
            for k, c in cfgs.items():
                sums[k] = LandmarkSums(c, capacity=trials)
                sums[k].new_rows(trials, x0)
        for s in sums.values():
            s.accumulate(rows, np.full(rows.size, p, np.int64), rays)
            s.close_passes()
            if p % solve_every == 0:
                s.solve(np.arange(trials))
    return {k: s.solve(np.arange(trials), update_reference=False) for k, s in sums.items()}, geom
