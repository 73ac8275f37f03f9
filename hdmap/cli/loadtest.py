"""``hdmap loadtest``: a simulated fleet against a running stack, with a live progress line.

    hdmap loadtest --vehicles N --rate R --duration S [--connect ENDPOINT] [--json FILE]

Waits until the stack is quiet, snapshots every service's counters, runs the fleet
for ``--duration`` seconds, waits until the chain has applied everything (the drain,
bounded by ``--drain-timeout``), snapshots again and reports the differences
(:mod:`fleetsim.loadtest`, whose docstring lists the keys of the ``--json`` report).
Exit status 0 when nothing was lost, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import zenoh

from fleetsim.loadgen import LoadConfig
from fleetsim.loadtest import LoadtestOptions, format_report, run_loadtest
from hdmap.cli.common import add_bus_arguments, bus_from_args
from hdmap.ops.progress import progress_wanted


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--vehicles", type=int, default=20)
    p.add_argument("--rate", type=float, default=5000.0, help="observations/s over the fleet")
    p.add_argument("--duration", type=float, default=30.0, help="seconds of load")
    p.add_argument("--batch", type=int, default=500, help="at most this many observations/upload")
    p.add_argument("--subscribers", type=int, default=2, help="subscribed vehicles (map readers)")
    p.add_argument("--drain-timeout", type=float, default=120.0)
    p.add_argument("--json", type=Path, metavar="FILE", help="write the report as JSON")
    p.add_argument(
        "--quiet",
        "--no-progress",
        dest="quiet",
        action="store_true",
        help="no live progress line (also HDMAP_NO_PROGRESS=1)",
    )
    add_bus_arguments(p)


def run(args: argparse.Namespace) -> int:
    for name in ("vehicles", "rate", "duration", "batch"):
        if not getattr(args, name) > 0:
            print(f"hdmap loadtest: --{name} must be > 0", file=sys.stderr)
            return 2
    opts = LoadtestOptions(
        load=LoadConfig(
            vehicles=args.vehicles,
            rate=args.rate,
            duration_s=args.duration,
            batch=args.batch,
            subscribers=args.subscribers,
        ),
        bus=bus_from_args(args),
        drain_timeout=args.drain_timeout,
        progress=progress_wanted(args.quiet),
    )
    try:
        r = run_loadtest(opts)
    except (RuntimeError, zenoh.ZError) as exc:
        print(f"hdmap loadtest: {exc}", file=sys.stderr)
        return 2
    print(format_report(r))
    if args.json:
        args.json.write_text(json.dumps(r, indent=1))
    return 0 if r["zero_loss"] and not r["failed"] else 1
