"""``hdmap region split REGION --into PART --into PART`` and ``hdmap region merge --from
REGION --from REGION --into REGION``: hand a live region's matcher and solver state over
(:mod:`hdmap.ops.region`), writing the new instances' data dirs under ``--data-dir``."""

from __future__ import annotations

import argparse
import contextlib
import shlex
import sys
from pathlib import Path

import zenoh

from hdmap.cli.common import add_bus_arguments, bus_from_args, bus_unreachable
from hdmap.geo.tiles import region_label, valid_quadkey
from hdmap.ops.region import HandoverError, Timing, handover, parse_region, resume
from hdmap.runtime.bus import open_session


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("action", choices=["split", "merge"])
    p.add_argument("region", nargs="?", help="split: the region ('12', '120+121' or 'all')")
    p.add_argument("--from", dest="sources", action="append", default=[], metavar="REGION",
                   help="merge: a region to join (repeat)")  # fmt: skip
    p.add_argument("--into", action="append", default=[], metavar="REGION",
                   help="split: a sub-region (repeat); merge: the joined region")  # fmt: skip
    p.add_argument("--data-dir", default="var", help="where the new data dirs go (default var)")
    p.add_argument("--drain-timeout", type=float, default=120.0,
                   help="longest wait for the consumers to drain, s")  # fmt: skip
    add_bus_arguments(p)


def _regions(texts: list[str], what: str) -> list[list[str]]:
    out = []
    for t in texts:
        r = parse_region(t)
        if not all(valid_quadkey(p) for p in r):
            raise ValueError(f"{what} {t!r}: not 'all' or quadkey prefixes joined by '+'")
        out.append(r)
    return out


def run(args: argparse.Namespace) -> int:
    try:
        if args.action == "split":
            if not args.region or len(args.into) < 2:
                raise ValueError("split: a region and at least two --into sub-regions")
            old, new = _regions([args.region], "region"), _regions(args.into, "--into")
        else:
            if len(args.sources) < 2 or len(args.into) != 1:
                raise ValueError("merge: at least two --from regions and one --into")
            old, new = _regions(args.sources, "--from"), _regions(args.into, "--into")
    except ValueError as exc:
        print(f"hdmap region: {exc}", file=sys.stderr)
        return 2
    bus = bus_from_args(args)
    timing = Timing(drain_s=args.drain_timeout)
    data_dir = Path(args.data_dir)
    try:
        with open_session(bus) as session:
            try:
                report = handover(session, old, new, data_dir, timing, progress=print)
            except HandoverError as exc:
                print(f"hdmap region {args.action}: {exc}", file=sys.stderr)
                with contextlib.suppress(HandoverError):
                    resume(session, old, timing)
                    print("the paused instances apply their input again", file=sys.stderr)
                return 1
    except zenoh.ZError as exc:
        return bus_unreachable("hdmap region", bus, exc)
    print(f"paused for {report.pause_s:.1f} s so far; start the new instances:")
    bus_args = " ".join(f"--connect {shlex.quote(c)}" for c in bus.connect)
    for r in new:
        regions = " ".join(f"--region {p}" for p in r)
        for svc in ("matcher", "solver"):
            print(f"  hdmap service {svc} {regions} --data-dir {shlex.quote(str(data_dir))} "
                  f"{bus_args}".rstrip())  # fmt: skip
    print(f"(data dirs: {', '.join(region_label(r) for r in new)})")
    return 0
