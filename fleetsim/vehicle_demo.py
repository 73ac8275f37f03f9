"""The vehicle side alone, on embedded defaults (``hdmap vehicle-demo``).

One simulated vehicle (FLEET noise) drives past a few signs of the demo town; its
detections become projection lines (:func:`vehicle.geoloc.geolocate`).
:func:`run_vehicle_demo` writes ``out/vehicle_rays.png`` (roads, true signs, camera
centres, rays in local metres) and ``out/vehicle_rays.json`` (the same data) and returns
the rays; :func:`ray_table` formats them. The town is fixed (``town_seed``); ``seed`` picks
the route and noise.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fleetsim.fleet import Fleet, FleetConfig, Pass, distinct_signs_seen
from fleetsim.noise import FLEET
from fleetsim.plot import plot_vehicle_rays
from fleetsim.truth import lines_in_world, ray_errors
from fleetsim.world import World, demo_town
from vehicle.config import load_vehicle_model
from vehicle.geoloc import ProjectionLines, VehicleModel, azimuth_elevation, geolocate

MIN_SIGNS = 3
"""The pass detects at least this many different signs."""


@dataclass(frozen=True)
class VehicleDemoOptions:
    out: Path
    seed: int = 0
    """Route and noise seed."""
    town_seed: int = 0
    """Demo town layout seed."""
    vehicle_config: Path | None = None
    """Vehicle/camera TOML; None: the packaged ``vehicle/default_vehicle.toml``."""


@dataclass(frozen=True)
class VehicleDemoResult:
    summary: str
    """One line: the pass, its rays, signs and false positives."""
    rays: list[dict]
    """One record per projection line (as in the JSON's ``rays``)."""
    png: Path
    json: Path


def _drive(world: World, model: VehicleModel, seed: int) -> Pass:
    """A short pass of one vehicle that detects at least MIN_SIGNS different signs."""
    cfg = FleetConfig(n_vehicles=1, route_length_m=(150.0, 250.0))
    fleet = Fleet(world, model, FLEET, cfg, seed=seed)
    return fleet.find_pass(lambda p: distinct_signs_seen(p) >= MIN_SIGNS)


def _ray_records(world: World, p: Pass, lines: ProjectionLines, model: VehicleModel) -> list[dict]:
    az, el = azimuth_elevation(lines.direction)
    origin, _ = lines_in_world(lines, world)
    err = ray_errors(lines, p.truth.sign_id, world)
    miss = np.full(len(lines), np.nan)
    miss[err.rows] = err.miss_m
    cat = model.catalog
    recs = []
    for i in range(len(lines)):
        recs.append(
            {
                "t": float(lines.t[i]),
                "t_rel_s": float(lines.t[i] - p.start_time),
                "image": int(lines.image[i]),
                "class": cat.by_code(int(lines.sign_class[i])).name,
                "class_code": int(lines.sign_class[i]),
                "lat": float(lines.lat[i]),
                "lon": float(lines.lon[i]),
                "h": float(lines.h[i]),
                "east_m": float(origin[i, 0]),
                "north_m": float(origin[i, 1]),
                "up_m": float(origin[i, 2]),
                "direction_enu": [float(v) for v in lines.direction[i]],
                "azimuth_deg": float(np.degrees(az[i]) % 360.0),
                "elevation_deg": float(np.degrees(el[i])),
                "sigma_az_deg": float(np.degrees(lines.sigma_az[i])),
                "sigma_el_deg": float(np.degrees(lines.sigma_el[i])),
                "range_m": float(lines.range_m[i]),
                "sigma_range_m": float(lines.sigma_range_m[i]),
                "score": float(lines.score[i]),
                "true_sign_id": int(p.truth.sign_id[i]),
                "true_miss_m": None if np.isnan(miss[i]) else float(miss[i]),
            }
        )
    return recs


def ray_table(recs: list[dict], max_rows: int) -> str:
    """The first ``max_rows`` rays as a table, and how many more the JSON holds."""
    head = (
        f"{'t[s]':>6} {'class':<20} {'lat':>11} {'lon':>11} {'az[deg]':>8} {'el[deg]':>8}"
        f" {'s_az':>5} {'s_el':>5} {'range[m]':>8} {'true':>5}"
    )
    lines = [head, "-" * len(head)]
    for r in recs[:max_rows]:
        rng = f"{r['range_m']:8.1f}" if r["range_m"] > 0 else f"{'-':>8}"
        true = "FP" if r["true_sign_id"] < 0 else str(r["true_sign_id"])
        lines.append(
            f"{r['t_rel_s']:6.1f} {r['class']:<20} {r['lat']:11.6f} {r['lon']:11.6f}"
            f" {r['azimuth_deg']:8.2f} {r['elevation_deg']:8.2f} {r['sigma_az_deg']:5.2f}"
            f" {r['sigma_el_deg']:5.2f} {rng} {true:>5}"
        )
    if len(recs) > max_rows:
        lines.append(f"... {len(recs) - max_rows} more rays in vehicle_rays.json")
    return "\n".join(lines)


def run_vehicle_demo(opts: VehicleDemoOptions) -> VehicleDemoResult:
    """Drive, geolocate, write the PNG and the JSON; raises
    :class:`vehicle.config.VehicleConfigError` for a bad vehicle config (nothing written)."""
    model = load_vehicle_model(opts.vehicle_config)
    out = Path(opts.out)
    out.mkdir(parents=True, exist_ok=True)

    world = demo_town(opts.town_seed)
    p = _drive(world, model, opts.seed)
    lines = geolocate(p.fixes, p.detections, model)
    recs = _ray_records(world, p, lines, model)

    n_signs = distinct_signs_seen(p)
    n_fp = int(np.sum(p.truth.sign_id < 0))
    duration = float(p.fixes.t[-1] - p.fixes.t[0]) if len(p.fixes) else 0.0
    summary = (
        f"hdmap vehicle-demo: {p.vehicle_id} pass {p.pass_id}, {p.path.length:.0f} m at "
        f"{p.speed_mps:.1f} m/s ({duration:.0f} s, {len(p.truth.t)} frames, {len(p.fixes)} "
        f"fixes), FLEET noise: "
        f"{len(lines)} rays of {n_signs} signs, {n_fp} false positives"
    )

    s = world.signs
    lat, lon, h = world.signs_geodetic()
    doc = {
        "anchor": {"lat0": world.lat0, "lon0": world.lon0, "h0": world.h0, "frame": "ENU"},
        "vehicle_id": p.vehicle_id,
        "pass_id": p.pass_id,
        "seed": opts.seed,
        "town_seed": opts.town_seed,
        "noise": FLEET.name,
        "start_time": p.start_time,
        "speed_mps": p.speed_mps,
        "route_nodes": list(p.route),
        "camera_track_enu": np.round(p.truth.camera_enu, 3).tolist(),
        "signs": [
            {
                "id": int(s.id[i]),
                "class": model.catalog.by_code(int(s.sign_class[i])).name,
                "east_m": float(s.position[i, 0]),
                "north_m": float(s.position[i, 1]),
                "up_m": float(s.position[i, 2]),
                "lat": float(lat[i]),
                "lon": float(lon[i]),
                "h": float(h[i]),
                "facing_deg": float(s.facing_azimuth_deg[i]),
            }
            for i in range(len(s))
        ],
        "rays": recs,
    }
    json_path = out / "vehicle_rays.json"
    json_path.write_text(json.dumps(doc, indent=1))

    origin, direction = lines_in_world(lines, world)
    png_path = out / "vehicle_rays.png"
    plot_vehicle_rays(
        world,
        p.truth,
        origin,
        direction,
        lines.range_m,
        lines.sign_class,
        png_path,
        title=(
            f"{p.vehicle_id} pass {p.pass_id}: {len(lines)} projection lines toward "
            f"{n_signs} signs (FLEET noise, seed {opts.seed})"
        ),
        catalog=model.catalog,
    )
    return VehicleDemoResult(summary=summary, rays=recs, png=png_path, json=json_path)
