"""``hdmap vehicle-demo``: the vehicle side alone, on embedded defaults.

One simulated vehicle (FLEET noise) drives past a few signs of the demo town;
its detections become projection lines (:func:`vehicle.geoloc.geolocate`). Prints
a table of the rays and writes ``DIR/vehicle_rays.png`` (roads, true signs,
camera centres, rays in local metres) and ``DIR/vehicle_rays.json`` (the same
data). The town is fixed (``--town-seed``); ``--seed`` picks the route and noise
(:mod:`fleetsim.vehicle_demo`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from fleetsim.vehicle_demo import VehicleDemoOptions, ray_table, run_vehicle_demo
from vehicle.config import VehicleConfigError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="output directory")
    p.add_argument("--seed", type=int, default=0, help="route and noise seed (default 0)")
    p.add_argument("--town-seed", type=int, default=0, help="demo town layout seed (default 0)")
    p.add_argument(
        "--vehicle-config",
        type=Path,
        default=None,
        metavar="FILE",
        help="vehicle/camera TOML (default: the packaged vehicle/default_vehicle.toml)",
    )
    p.add_argument(
        "--max-rows", type=int, default=40, help="rays printed in the table (all go to the JSON)"
    )


def run(args: argparse.Namespace) -> int:
    opts = VehicleDemoOptions(
        out=Path(args.out),
        seed=args.seed,
        town_seed=args.town_seed,
        vehicle_config=args.vehicle_config,
    )
    try:
        result = run_vehicle_demo(opts)
    except VehicleConfigError as e:
        print(f"hdmap vehicle-demo: bad vehicle config: {e}", file=sys.stderr)
        return 2
    print(result.summary)
    print(ray_table(result.rays, args.max_rows))
    print(f"wrote {result.png} and {result.json}")
    return 0
