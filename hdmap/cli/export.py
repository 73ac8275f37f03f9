"""``hdmap export``: the published map of a bounding box as GeoJSON, OSM XML or CSV.

    hdmap export --connect tcp/127.0.0.1:7447 --format osm \\
        --bbox 24.93,60.16,24.96,60.18 --out signs.osm

Fetches the snapshots of the box's tiles from the running publishers
(:mod:`hdmap.ops.export`) and writes the landmarks inside the box
(:mod:`hdmap.ops.export_formats` says what each format holds; revoked landmarks are not
exported). ``--bbox`` is required: the publishers offer no index of their tiles. Exit
status 0; 1 when some tiles got no answer (the file is written without them: a partial
map); 2 when the bus cannot be reached or an argument is wrong.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import zenoh

from hdmap.cli.common import (
    add_bus_arguments,
    add_progress_argument,
    bus_from_args,
    bus_unreachable,
    positive_float,
)
from hdmap.geo.area import BBox
from hdmap.geo.tiles import DEFAULT_ZOOM
from hdmap.ops.export import MAX_TILES, export_map
from hdmap.ops.export_formats import FORMATS
from hdmap.ops.progress import Progress, progress_wanted
from hdmap.runtime.bus import open_session


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--format", required=True, choices=FORMATS, help="output format")
    p.add_argument(
        "--bbox",
        required=True,
        metavar="MINLON,MINLAT,MAXLON,MAXLAT",
        help="the area, WGS84 degrees (required: the publishers keep no index of their "
        "tiles, so there is no export of everything)",
    )
    p.add_argument("--out", metavar="FILE", help="write here (default: standard output)")
    p.add_argument(
        "--zoom", type=int, default=DEFAULT_ZOOM, help="tile zoom of the deployment (default 16)"
    )
    p.add_argument(
        "--timeout",
        type=positive_float,
        default=60.0,
        help="seconds for fetching every tile (default 60; a large box needs more: the "
        "publisher answers one client about 20 snapshots/s)",
    )
    add_progress_argument(p)
    add_bus_arguments(p)


def run(args: argparse.Namespace) -> int:
    try:
        bbox = BBox.parse(args.bbox)
        tiles = bbox.tiles(args.zoom, MAX_TILES)
    except ValueError as exc:
        print(f"hdmap export: {exc}", file=sys.stderr)
        return 2
    bus = bus_from_args(args)
    bar = Progress(len(tiles), "tiles", enabled=progress_wanted(args.no_progress), quiet_s=1.0)
    try:
        with open_session(bus) as session, bar:
            exp = export_map(session, bbox, args.format, args.zoom, args.timeout, bar.update, tiles)
    except zenoh.ZError as exc:
        return bus_unreachable("hdmap export", bus, exc)
    except ValueError as exc:
        print(f"hdmap export: {exc}", file=sys.stderr)
        return 2
    if args.out:
        out = Path(args.out)
        tmp = out.with_name(out.name + ".tmp")
        tmp.write_text(exp.text, encoding="utf-8")
        os.replace(tmp, out)  # a reader never sees half a file
    else:
        sys.stdout.write(exp.text)
        sys.stdout.flush()
    f = exp.fetched
    print(
        f"hdmap export: {len(exp.rows)} landmarks from {len(f.snapshots)} of {len(exp.tiles)} "
        f"tiles ({args.format}{', ' + args.out if args.out else ''})",
        file=sys.stderr,
    )
    for tile, err in sorted(f.errors.items()):
        print(f"hdmap export: tile {tile}: {err}", file=sys.stderr)
    missing = sorted(f.unanswered) + sorted(f.errors)
    if missing:
        shown = ", ".join(missing[:5]) + (" ..." if len(missing) > 5 else "")
        print(
            f"hdmap export: {len(missing)} tiles got no snapshot ({shown}): the export lacks "
            "them (no publisher serves them, or --timeout is too short)",
            file=sys.stderr,
        )
        return 1
    return 0
