"""``hdmap demo``: the whole stack on embedded defaults with a simulated fleet.

Starts a router and the four services as processes, drives a fleet through a small
town, prints a table per round of passes, and writes the final map as GeoJSON and PNGs
with uncertainty ellipses, plus every number as JSON (:mod:`fleetsim.demo`).

By default it runs twice on a fresh stack each: first with the paper's GNSS noise (5 m and
0.35 rad white per fix, into ``OUT``), then with the realistic fleet noise of the accuracy
evaluation (per-pass bias, drift, multipath, into ``OUT/fleet``), and ends with the two
final rows side by side. ``--noise paper`` or ``--noise fleet`` runs one of them.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from fleetsim.demo import DemoOptions, run_demo, side_by_side
from fleetsim.town_run import NOISES


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=Path("out/demo"), help="output directory")
    p.add_argument("--rounds", type=int, default=12, help="rounds of passes (default 12)")
    p.add_argument("--vehicles", type=int, default=10, help="passes per round (default 10)")
    p.add_argument(
        "--noise",
        choices=[*sorted(NOISES), "both"],
        default="both",
        help="GNSS/detector noise model: paper (5 m and 0.35 rad white per fix), fleet "
        "(per-pass bias, drift, multipath), or both (default: paper into OUT, then fleet "
        "into OUT/fleet)",
    )
    p.add_argument("--signs", type=int, default=40, help="signs in the town (default 40)")
    p.add_argument("--seed", type=int, default=0)


def run(args: argparse.Namespace) -> int:
    opts = DemoOptions(
        out=args.out,
        rounds=args.rounds,
        vehicles=args.vehicles,
        noise=args.noise,
        signs=args.signs,
        seed=args.seed,
    )
    finals = run_demo(opts)
    if len(finals) > 1:
        print(side_by_side(finals))
    return 0
