"""The fleet evaluation's town and passes, each sign's true rays straight into ``LandmarkSums``:
the estimator's own error, without the matcher.

Usage: python scripts/diagnostics/true_association_fleet.py GNSS PASSES
``GNSS``: ``fleet`` (FLEET's receiver), ``exact`` (no GNSS error, FLEET's white sigmas
reported) or ``exact0`` (no GNSS error, the heading sigma reported as 0.001 deg).
Prints, over the signs with 50+ passes, the horizontal error and, for those more than 1 m
off, how much of it lies along their mean viewing direction (negative: short of the sign).
"""

from __future__ import annotations

import math
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
from true_rays import true_rays  # a sibling module: scripts run from their directory

from fleetsim.evaluation.fleet_eval import FleetEvalConfig, evaluation_world
from fleetsim.fleet import Fleet, FleetConfig
from fleetsim.noise import FLEET, NoiseModel
from fleetsim.pipeline import model_for
from hdmap.mapping.estimator import EstimatorConfig, LandmarkSums
from vehicle.agent import VehicleAgent
from vehicle.config import load_vehicle_model


def noise_for(which: str) -> NoiseModel:
    if which == "fleet":
        return FLEET
    g = FLEET.gnss
    heading = 1e-3 if which == "exact0" else math.degrees(g.white_heading_rad)
    exact = replace(
        g,
        white_h_m=0.0,
        white_v_m=0.0,
        white_heading_rad=0.0,
        bias_h_m=0.0,
        bias_v_m=0.0,
        bias_heading_rad=0.0,
        walk_h_m_per_sqrt_s=0.0,
        walk_v_m_per_sqrt_s=0.0,
        multipath_prob=0.0,
        reported_sigma_h_m=g.white_h_m,
        reported_sigma_v_m=g.white_v_m,
        reported_sigma_heading_deg=heading,
    )
    return replace(FLEET, gnss=exact)


def main(which: str, n_passes: int) -> None:
    noise = noise_for(which)
    cfg = FleetEvalConfig(Path(tempfile.gettempdir()))
    world = evaluation_world(cfg)
    model = model_for(noise, load_vehicle_model())
    fleet_cfg = FleetConfig(n_vehicles=cfg.vehicles, route_length_m=(600.0, 1200.0))
    fleet = Fleet(world, model, noise, fleet_cfg, 0)
    k_signs = len(world.signs)
    passes, dirs = np.zeros(k_signs, int), np.zeros((k_signs, 3))
    with tempfile.TemporaryDirectory() as queue:
        agent = VehicleAgent("veh-0001", model, queue)
        sums = LandmarkSums(EstimatorConfig())
        rows = sums.new_rows(k_signs, world.signs.position + np.array([1.0, 1.0, 0.0]))
        for k, p in enumerate(fleet.passes(n_passes)):
            seen = true_rays(world, agent, p, agent.record(p.pass_id, p.fixes, p.detections))
            if seen is None:
                continue
            rays, r = seen
            passes[np.unique(r)] += 1
            np.add.at(dirs, r, rays.direction)
            sums.accumulate(rows[r], np.full(r.size, k), rays)
        agent.close()
    sol = sums.solve(rows)
    e = sol.x - world.signs.position
    h = np.linalg.norm(e[:, :2], axis=1)
    m = passes >= 50
    print(
        f"{which}, {n_passes} passes: {int(m.sum())} signs with 50+ passes, horizontal error "
        f"mean {np.nanmean(h[m]):.3f} m, median {np.nanmedian(h[m]):.3f}, p95 "
        f"{np.nanpercentile(h[m], 95):.3f}; mean error vector {np.nanmean(e[m], 0).round(3)}"
    )
    big = m & (h > 1.0)
    if big.any():
        d = dirs[big, :2] / np.linalg.norm(dirs[big, :2], axis=1, keepdims=True)
        along = np.einsum("ij,ij->i", e[big, :2], d)
        print(
            f"{int(big.sum())} more than 1 m off; along their viewing direction "
            f"{np.round(along, 2).tolist()} m (median share of the error "
            f"{np.median(np.abs(along) / h[big]):.2f})"
        )


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]))
