"""``hdmap dashboard``: a live web page of the map and the services' health.

Serves on ``--listen`` (default 127.0.0.1:8080) a MapLibre map of the landmarks of an
area (``--bbox`` or ``--tiles``; with neither, of every tile that publishes a change
after it started): their 95 % ellipses coloured by status and sized and labelled by
passes, their facing arrows, live from the publisher's deltas; a panel of the services'
backlog, accepted and rejected counts and rates; a click on a landmark shows its
history as the dashboard saw it. Works offline: MapLibre ships with the package, the
background is plain (no tile server). See :mod:`hdmap.ops.dashboard.server`.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading

import zenoh

from hdmap.cli.common import (
    add_bus_arguments,
    bus_from_args,
    bus_unreachable,
    positive_float,
    setup_logging,
)
from hdmap.geo.area import BBox
from hdmap.geo.tiles import DEFAULT_ZOOM, MAX_ZOOM, valid_quadkey
from hdmap.ops.dashboard.geometry import MAX_AREA_TILES
from hdmap.ops.dashboard.server import DashboardConfig, serve
from schemas.codec import valid_id


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--listen",
        default="127.0.0.1:8080",
        metavar="HOST:PORT",
        help="where the web page is served (default 127.0.0.1:8080; port 0: any free one)",
    )
    area = p.add_mutually_exclusive_group()
    area.add_argument(
        "--bbox",
        metavar="MINLON,MINLAT,MAXLON,MAXLAT",
        help=f"the area shown: every tile touching this box (at most {MAX_AREA_TILES})",
    )
    area.add_argument(
        "--tiles",
        action="append",
        default=[],
        metavar="QUADKEYS",
        help="the area shown: comma-separated quadkeys at --zoom (repeatable). With neither "
        "option: every tile whose map changes after the dashboard started",
    )
    p.add_argument(
        "--zoom",
        type=int,
        default=DEFAULT_ZOOM,
        help=f"zoom of the publisher's tiles (default {DEFAULT_ZOOM})",
    )
    p.add_argument(
        "--client-id",
        default="dashboard",
        help="the id snapshot queries are made under (the publisher limits each id's)",
    )
    p.add_argument(
        "--stats-interval",
        type=positive_float,
        default=2.0,
        metavar="S",
        help="seconds between two polls of the services' stats (default 2)",
    )
    p.add_argument("--log-level", default="INFO")
    add_bus_arguments(p)


def parse_listen(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[::1]:8080`` for IPv6) -> (host, port).

    >>> parse_listen("127.0.0.1:8080"), parse_listen("[::1]:0")
    (('127.0.0.1', 8080), ('::1', 0))
    """
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or int(port) > 65535:
        raise ValueError(f"need HOST:PORT, got {text!r}")
    return host.strip("[]"), int(port)


def area_tiles(args: argparse.Namespace) -> tuple[str, ...]:
    """The tiles of ``--bbox`` or ``--tiles`` (none: every tile that publishes)."""
    if not 1 <= args.zoom <= MAX_ZOOM:
        raise ValueError(f"--zoom must be in 1..{MAX_ZOOM}")
    if args.bbox:
        return tuple(BBox.parse(args.bbox).tiles(args.zoom, MAX_AREA_TILES))
    tiles = sorted({t.strip() for arg in args.tiles for t in arg.split(",") if t.strip()})
    bad = [t for t in tiles if not valid_quadkey(t, args.zoom)]
    if bad:
        raise ValueError(f"not quadkeys of zoom {args.zoom}: {', '.join(bad[:5])}")
    if len(tiles) > MAX_AREA_TILES:
        raise ValueError(f"{len(tiles)} tiles; at most {MAX_AREA_TILES}")
    return tuple(tiles)


def run(args: argparse.Namespace) -> int:
    setup_logging(args.log_level)
    try:
        host, port = parse_listen(args.listen)
        tiles = area_tiles(args)
    except ValueError as exc:
        print(f"hdmap dashboard: {exc}", file=sys.stderr)
        return 2
    if not valid_id(args.client_id):
        print("hdmap dashboard: --client-id: 1-64 characters of [A-Za-z0-9_.-]", file=sys.stderr)
        return 2
    config = DashboardConfig(
        tiles=tiles,
        zoom=args.zoom,
        client_id=args.client_id,
        stats_interval_s=args.stats_interval,
        stats_timeout_s=min(2.0, args.stats_interval),
    )
    stop = threading.Event()
    for s in (signal.SIGTERM, signal.SIGINT):
        signal.signal(s, lambda *_: stop.set())
    bus = bus_from_args(args)
    area = f"{len(tiles)} tiles" if tiles else "every tile that publishes from now on"

    def ready(url: str) -> None:
        print(f"hdmap dashboard: serving {url} ({area}); Ctrl-C stops", flush=True)

    try:
        serve(bus, host, port, config, stop, ready)
    except zenoh.ZError as exc:
        return bus_unreachable("hdmap dashboard", bus, exc)
    except OSError as exc:
        print(f"hdmap dashboard: cannot listen on {args.listen}: {exc}", file=sys.stderr)
        return 2
    return 0
