"""``hdmap status``: the live services, their regions and counters."""

from __future__ import annotations

import argparse
import json

import zenoh

from hdmap.cli.common import add_bus_arguments, bus_from_args, bus_unreachable
from hdmap.ops.status import collect
from hdmap.runtime.bus import open_session


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.add_argument("--timeout", type=float, default=3.0)
    add_bus_arguments(p)


def run(args: argparse.Namespace) -> int:
    bus = bus_from_args(args)
    try:
        with open_session(bus) as session:
            stats = collect(session, args.timeout)
    except zenoh.ZError as exc:
        return bus_unreachable("hdmap status", bus, exc)
    if args.json:
        print(json.dumps([s._encode() for s in stats], indent=2, default=float))
        return 0
    if not stats:
        print("no live services")
        return 1
    for s in stats:
        region = ",".join(s.region) or "all"
        print(f"{s.service:<10} {s.instance:<40} region={region}")
        for line in attention(s.counters):
            print(f"  ! {line}")
        for k in sorted(s.counters):
            v = s.counters[k]
            print(f"    {k:<22} {v:.3f}" if isinstance(v, float) else f"    {k:<22} {v}")
        for reason, n in sorted(s.rejected.items()):
            print(f"    rejected[{reason}] {n}")
    return 0


def attention(c: dict[str, float]) -> list[str]:
    """What an operator should look at in a service's counters (gaps in its input log).

    >>> for line in attention({"gaps_open": 1, "gap_oldest_s": 12.5, "entries_ahead": 3}):
    ...     print(line)
    gap in the input log open for 12.5 s (3 entries waiting behind it)
    """
    out = []
    if c.get("gaps_open", 0):
        out.append(
            f"gap in the input log open for {c.get('gap_oldest_s', 0):.1f} s "
            f"({int(c.get('entries_ahead', 0))} entries waiting behind it)"
        )
    if c.get("replay_refused", 0):
        out.append(
            f"{int(c['replay_refused'])} catch-ups refused: a producer deleted entries this "
            "consumer lacks (it must be rebuilt; see its log)"
        )
    if c.get("handover_paused", 0):
        out.append(
            "paused for a region handover (hdmap region split/merge): applying nothing; "
            "it resumes by itself if the tool is silent for a while"
        )
    if c.get("gaps_expired", 0):
        out.append(
            f"{int(c['gaps_expired'])} gaps not filled in time (their waiting entries were "
            "dropped and asked for again)"
        )
    return out
