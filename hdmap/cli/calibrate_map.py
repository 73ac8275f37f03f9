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

from hdmap.cli.common import add_bus_arguments, bus_from_args, bus_unreachable
from hdmap.cli.service import service_config
from hdmap.geo.geodesy import EnuFrame
from hdmap.geo.signs import CATALOG, UnknownSignClass
from hdmap.geo.tiles import neighbours, quadkeys_of
from hdmap.mapping.map_floor import MIN_CONTROLS, measure_forms, pair_controls
from hdmap.runtime.bus import open_session
from hdmap.runtime.config import ConfigError, load_toml
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


def published_floor(config: str | None) -> SolverConfig:
    """The solver config the map was published with (its floors are taken out first)."""
    if config is None:
        return SolverConfig()
    return service_config("solver", load_toml(config).get("solver", {}))[1]


def floor_from_map(lms, ctl: np.ndarray, ctl_class: np.ndarray, args, solver: SolverConfig) -> dict:
    """Pair, measure both forms of the floor, and the artefact (what a reader needs to
    judge the figures)."""
    frame = EnuFrame(*np.mean(ctl, axis=0))
    c_xyz = frame.from_geodetic(ctl[:, 0], ctl[:, 1], ctl[:, 2])
    l_xyz = frame.from_geodetic(lms.lat, lms.lon, lms.h)
    passes = lms.n_passes.astype(np.int64)
    ci, li = pair_controls(
        l_xyz, lms.sign_class.astype(np.int64), passes, c_xyz, ctl_class, args.match_m,
        args.min_passes,
    )  # fmt: skip
    if ci.size < MIN_CONTROLS:
        raise ValueError(
            f"{ci.size} control(s) paired with a landmark of {args.min_passes}+ passes "
            f"within {args.match_m} m: at least {MIN_CONTROLS} are needed"
        )
    fits = measure_forms(
        l_xyz[li] - c_xyz[ci], np.asarray(lms.cov, float)[li], passes[li],
        solver.pass_correlation, solver.systematic_sigma_m, solver.shared_floor(),
    )  # fmt: skip
    h, v, k = fits["horizontal"], fits["vertical"], fits["pass_correlation"]
    return {
        "controls": len(ctl),
        "paired": int(ci.size),
        "match_m": args.match_m,
        "min_passes": args.min_passes,
        "published_sigma_m": list(solver.systematic_sigma_m),
        "published_pass_correlation": solver.pass_correlation,
        "horizontal": h.as_dict(),
        "vertical": v.as_dict(),
        "pass_correlation": k.as_dict(),
        "systematic_sigma_m": [h.value, h.value, v.value],
    }


def run(args: argparse.Namespace) -> int:
    try:
        ctl, ctl_class = read_controls(Path(args.control))
        solver = published_floor(args.config)
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
        return bus_unreachable("hdmap calibrate-map", bus, exc)
    try:
        art = floor_from_map(lms, ctl, ctl_class, args, solver)
    except ValueError as exc:
        print(f"calibrate-map: {exc}", file=sys.stderr)
        return 1
    h, v, k = art["horizontal"], art["vertical"], art["pass_correlation"]
    print(
        f"{art['paired']} of {art['controls']} controls paired; inside their 95 % regions: "
        f"{h['inside_before']:.3f} as published"
    )
    print(
        f"as a pass correlation: {k['kappa']:.4g} [{k['interval'][0]:.4g}, "
        f"{k['interval'][1]:.4g}], {k['inside_after']:.3f} inside"
    )
    print(
        f"as a per-axis sigma: horizontal {h['sigma_m']:.3f} m [{h['interval'][0]:.3f}, "
        f"{h['interval'][1]:.3f}], vertical {v['sigma_m']:.3f} m, {h['inside_after']:.3f} inside"
    )
    print("[solver]  # one of the two forms")
    print(f"pass_correlation = {k['kappa']:.4g}")
    print("systematic_sigma_m = [0, 0, 0]")
    print("# or")
    print("pass_correlation = 0")
    print(f"systematic_sigma_m = [{', '.join(f'{x:.4g}' for x in art['systematic_sigma_m'])}]")
    if args.out:
        Path(args.out).write_text(json.dumps(art, indent=2) + "\n")
    return 0
