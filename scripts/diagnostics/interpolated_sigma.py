"""Per-sign estimates with the true association, straight into ``LandmarkSums``.

Usage: python scripts/diagnostics/interpolated_sigma.py NOISE FIX_PER_FRAME PASSES
(e.g. ``paper 0 120``). docs/experiments/2026-12-interpolated-sigma-overcompensation.md.
"""

import sys
import tempfile

import numpy as np
from true_rays import true_rays  # a sibling module: scripts run from their directory

from fleetsim.fleet import Fleet, FleetConfig
from fleetsim.pipeline import model_for
from fleetsim.town_run import NOISES
from fleetsim.world import demo_town
from hdmap.mapping.estimator import EstimatorConfig, LandmarkSums
from vehicle.agent import VehicleAgent
from vehicle.config import load_vehicle_model


def main(noise_name: str, fix_per_frame: bool, n_passes: int) -> None:
    noise = NOISES[noise_name]
    world = demo_town(0, n_signs=40)
    model = model_for(noise, load_vehicle_model())
    fleet = Fleet(world, model, noise, FleetConfig(n_vehicles=10, fix_per_frame=fix_per_frame), 0)
    with tempfile.TemporaryDirectory() as queue:
        agent = VehicleAgent("veh-0001", model, queue)
        sums = LandmarkSums(EstimatorConfig())
        rows = sums.new_rows(len(world.signs), world.signs.position + np.array([1.0, 1.0, 0.0]))
        for k, p in enumerate(fleet.passes(n_passes)):
            seen = true_rays(world, agent, p, agent.record(p.pass_id, p.fixes, p.detections))
            if seen is not None:
                rays, r = seen
                sums.accumulate(rows[r], np.full(r.size, k), rays)
        agent.close()
    sol = sums.solve(rows)
    err = np.linalg.norm(sol.x[:, :2] - world.signs.position[:, :2], axis=1)
    print(
        f"ok {int(np.sum(sol.ok))} of {len(err)}, median error {np.nanmedian(err):.2f} m, "
        f"within 5 m {int((err < 5).sum())}"
    )


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2] == "1", int(sys.argv[3]))
