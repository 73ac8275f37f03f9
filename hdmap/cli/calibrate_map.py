"""``hdmap calibrate-map``: the solver's map floor from surveyed signs.

Reads the live map around a set of surveyed signs (control points), pairs each with the
published landmark of its class within ``--match-m`` that has ``--min-passes`` passes or
more, and measures the floor the map's covariances lack (:mod:`hdmap.mapping.map_floor`):
the least per-axis sigma that puts 95 % of the controls inside their 95 % regions, with its
distribution-free interval. Prints it as the ``[solver]`` line of a services config.

Control CSV columns: ``traffic_sign`` (an OSM ``traffic_sign=*`` value or a catalogue
name, e.g. ``FI:B5``), ``lat``, ``lon`` (degrees, WGS84) and ``h`` (ellipsoidal height, m).

    hdmap calibrate-map --connect tcp/127.0.0.1:7447 --control surveyed.csv \\
        --config deploy/services.toml
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np
import zenoh

from hdmap.cli.common import add_bus_arguments, bus_from_args
from hdmap.geo.geodesy import EnuFrame
from hdmap.geo.signs import CATALOG, UnknownSignClass
from hdmap.geo.tiles import neighbours, quadkeys_of
from hdmap.mapping.map_floor import coverage_floor, pair_controls
from hdmap.runtime.bus import open_session
from hdmap.runtime.config import ConfigError, from_mapping, load_toml
from services.solver.service import SolverConfig
from vehicle.mapclient import MapClient

COLUMNS = ("traffic_sign", "lat", "lon", "h")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--control", required=True, metavar="CSV", help="surveyed signs (see doc)")
    p.add_argument("--match-m", type=float, default=5.0, help="pairing radius, m (default 5)")
    p.add_argument(
        "--min-passes",
        type=int,
        default=150,
        help="controls only where the landmark has this many passes (default 150: the "
        "floor shows once the between-pass part has averaged out)",
    )
    p.add_argument(
        "--config",
        metavar="TOML",
        help="the services config the map was published with (its [solver] "
        "systematic_sigma_m is taken out first; default: the solver's default)",
    )
    p.add_argument("--timeout", type=float, default=20.0, help="wait for the map, s")
    p.add_argument("--out", metavar="JSON", help="also write the floor and its inputs here")
    add_bus_arguments(p)


def read_controls(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) lat, lon, h and (n,) class codes; ValueError naming the file, line and
    column of a bad row."""
    rows, classes = [], []
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        missing = [c for c in COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise ValueError(f"{path}: missing column(s) {', '.join(missing)}")
        for i, r in enumerate(reader, start=2):
            try:
                classes.append(CATALOG.by_ref(r["traffic_sign"]).code)
            except UnknownSignClass as exc:
                raise ValueError(f"{path}:{i}: traffic_sign: {exc}") from exc
            try:
                vals = [float(r[c]) for c in ("lat", "lon", "h")]
            except (TypeError, ValueError) as exc:
                raise ValueError(f"{path}:{i}: lat/lon/h: not a number ({exc})") from exc
            if not (np.all(np.isfinite(vals)) and -90 <= vals[0] <= 90 and -180 <= vals[1] <= 180):
                raise ValueError(f"{path}:{i}: lat/lon out of range or not finite")
            rows.append(vals)
    if not rows:
        raise ValueError(f"{path}: no rows")
    return np.array(rows), np.array(classes, np.int64)


def published_sigma(config: str | None) -> tuple[float, float, float]:
    if config is None:
        return SolverConfig().systematic_sigma_m
    solver = from_mapping(SolverConfig, load_toml(config).get("solver", {}), "solver")
    return solver.systematic_sigma_m


def floor_from_map(lms, ctl: np.ndarray, ctl_class: np.ndarray, args, base) -> dict:
    """Pair, measure, and the artefact (what a reader needs to judge the figure)."""
    frame = EnuFrame(*np.mean(ctl, axis=0))
    c_xyz = frame.from_geodetic(ctl[:, 0], ctl[:, 1], ctl[:, 2])
    l_xyz = frame.from_geodetic(lms.lat, lms.lon, lms.h)
    ci, li = pair_controls(
        l_xyz,
        lms.sign_class.astype(np.int64),
        lms.n_passes.astype(np.int64),
        c_xyz,
        ctl_class,
        args.match_m,
        args.min_passes,
    )
    if ci.size < 20:
        raise ValueError(
            f"{ci.size} control(s) paired with a landmark of {args.min_passes}+ passes "
            f"within {args.match_m} m: at least 20 are needed"
        )
    err = l_xyz[li] - c_xyz[ci]
    c6 = np.asarray(lms.cov, float)[li]
    cov_h = np.stack([np.stack([c6[:, 0], c6[:, 1]], -1), np.stack([c6[:, 1], c6[:, 3]], -1)], -2)
    h = coverage_floor(err[:, :2], cov_h, base_sigma_m=float(base[0]))
    v = coverage_floor(err[:, 2:3], c6[:, 5].reshape(-1, 1, 1), base_sigma_m=float(base[2]))
    return {
        "controls": len(ctl),
        "paired": int(ci.size),
        "match_m": args.match_m,
        "min_passes": args.min_passes,
        "published_sigma_m": list(base),
        "horizontal": h.as_dict(),
        "vertical": v.as_dict(),
        "systematic_sigma_m": [h.sigma_m, h.sigma_m, v.sigma_m],
    }


def run(args: argparse.Namespace) -> int:
    try:
        ctl, ctl_class = read_controls(Path(args.control))
        base = published_sigma(args.config)
    except (OSError, ValueError, ConfigError) as exc:
        print(f"calibrate-map: {exc}", file=sys.stderr)
        return 2
    bus = bus_from_args(args)
    tiles = {str(t) for t in quadkeys_of(ctl[:, 0], ctl[:, 1])}
    try:
        with open_session(bus) as session:
            client = MapClient(session, radius_m=0.0)
            try:
                for tile in sorted(tiles | {n for t in tiles for n in neighbours(t)}):
                    client.follow(tile)
                client.wait_idle(args.timeout)
                lms = client.landmarks()
            finally:
                client.close()
    except zenoh.ZError as exc:
        print(f"calibrate-map: cannot reach the bus: {exc}", file=sys.stderr)
        return 2
    try:
        art = floor_from_map(lms, ctl, ctl_class, args, base)
    except ValueError as exc:
        print(f"calibrate-map: {exc}", file=sys.stderr)
        return 1
    h, v = art["horizontal"], art["vertical"]
    print(
        f"{art['paired']} of {art['controls']} controls paired; inside their 95 % regions: "
        f"{h['inside_before']:.3f} as published, {h['inside_after']:.3f} with the floor"
    )
    print(
        f"floor sigma horizontal {h['sigma_m']:.3f} m "
        f"[{h['interval_m'][0]:.3f}, {h['interval_m'][1]:.3f}], vertical {v['sigma_m']:.3f} m"
    )
    print("[solver]")
    print(f"systematic_sigma_m = [{', '.join(f'{s:.4g}' for s in art['systematic_sigma_m'])}]")
    if args.out:
        Path(args.out).write_text(json.dumps(art, indent=2) + "\n")
    return 0
