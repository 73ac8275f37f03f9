"""``hdmap demo``: the whole stack on embedded defaults with a simulated fleet.

Starts a router and the four services as processes, drives a fleet through a small
town, prints a table per round of passes, and writes the final map as GeoJSON and PNGs
with uncertainty ellipses, plus every number as JSON (:mod:`fleetsim.demo`).

By default it runs twice on a fresh stack each: first with the paper's GNSS noise (5 m and
0.35 rad white per fix, into ``OUT``), then with the realistic fleet noise of the accuracy
evaluation (per-pass bias, drift, multipath, into ``OUT/fleet``), and ends with the two
final rows side by side. ``--noise paper`` or ``--noise fleet`` runs one of them.

Then (unless ``--no-changes``) the map following the world: a smaller town where, once
the map is built, one sign is taken down, one moved 14 m and one put up, driven by a fleet
that follows the map (one vehicle blind); it prints each change with the passes the map
needed to show it (``OUT/changes``: :mod:`fleetsim.evaluation.changes_runs`).
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
    p.add_argument(
        "--no-changes",
        action="store_true",
        help="skip the last part (signs taken down, moved, put up: the map following them)",
    )


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
    if not args.no_changes:
        from fleetsim.evaluation.changes_eval import ChangesEvalConfig
        from fleetsim.evaluation.changes_runs import changes_table, run_changes_job

        print(
            "\nhdmap demo: the map following the world (a sign taken down, one moved, one put up)"
        )
        report = run_changes_job(ChangesEvalConfig.quick(args.out / "changes"))
        print(changes_table(report))
    return 0
