"""The realistic evaluation: central Helsinki, a simulated fleet, the real pipeline.

Starts a router and the four services as processes (:class:`hdmap.ops.stack.Stack`), drives a
fleet with the fixed :data:`fleetsim.noise.FLEET` noise through them round by round, and
after each round scores the map a subscribed vehicle holds against the ground truth.

The scores are :mod:`fleetsim.evaluation.fleet_scoring`'s (its doc says what each
figure means and how the targets are judged).

``DIR/fleet.json``: ``meta`` (town, noise, seed, wall time), ``rounds`` (per round: map
size, false landmarks and duplicates, all and confirmed, recall, mean error, coverage),
``by_passes`` (the bins of passes,
:func:`~fleetsim.evaluation.fleet_scoring.bin_table`), ``observations`` (uploaded, of true
signs, linked), ``services`` (the services' counters at the end), ``targets_at_50_passes``
(:func:`~fleetsim.evaluation.fleet_scoring.targets`, with
:func:`~fleetsim.evaluation.fleet_scoring.assoc_shares`) and ``signs``
(:func:`~fleetsim.evaluation.fleet_scoring.sign_table`: per sign its final passes,
landmark, error vector, reported sigmas, ellipse test and association share) and
``map_floor`` (the solver's map floor, where it came from, and the floor this run's final
map would need: :mod:`fleetsim.evaluation.map_floor_file`).
"""

from __future__ import annotations

import math
import shutil
import sqlite3
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from fleetsim.evaluation.fleet_scoring import (
    EvalState,
    Linked,
    ObsKeys,
    assoc_shares,
    bin_table,
    landmark_counts,
    landmark_rows,
    score_round,
    sign_table,
    targets,
    unpaired_table,
)
from fleetsim.evaluation.map_floor_file import AppliedFloor, applied_floor, measured_floor
from fleetsim.fleet import Fleet, FleetConfig, vehicle_id
from fleetsim.gnss_replay import gsdc
from fleetsim.noise import FLEET, GnssNoise, NoiseModel
from fleetsim.osm_town import helsinki_town, same_class_pairs
from fleetsim.pipeline import FleetDriver, model_for
from fleetsim.town_run import follow_town
from fleetsim.world import World, tile_border_distance
from hdmap.geo.signs import CATALOG
from hdmap.mapping.gnss_floor import SharedFloor, floor_enu, shared_floor, shared_floor_m2
from hdmap.ops.progress import Progress
from hdmap.ops.quiesce import totals, wait_quiet
from hdmap.ops.stack import Stack
from hdmap.ops.status import collect
from hdmap.runtime.bus import open_session
from hdmap.runtime.catchup import catch_up
from hdmap.runtime.stream import LogConsumer
from schemas import AssocGroup, Landmarks
from services.solver.service import SolverConfig
from vehicle.config import load_vehicle_model
from vehicle.mapclient import MapClient

CENTRE = (60.1716, 24.9443)
"""Centre of the evaluated area (Helsinki centre, inside the OSM extract)."""


PASS_S = 90.0
"""A typical pass's duration (600-1200 m at 8-14 m/s), s: the span over which a receiver's
total error is reckoned (:func:`totals_reported`)."""


def totals_reported(g: GnssNoise, span_s: float = PASS_S) -> GnssNoise:
    """``g`` with its fixes claiming their total errors over ``span_s`` rather than the
    white levels: per horizontal axis ``sqrt(white^2 + bias^2 + walk^2 span)``, the same
    vertically, and the heading's ``hypot(white, bias)`` (FLEET: 3.29 m, 4.75 m,
    1.28 deg; what a receiver's accuracy figures are, issue 18 point 4)."""
    return replace(
        g,
        reported_sigma_h_m=math.sqrt(
            g.white_h_m**2 + g.bias_h_m**2 + span_s * g.walk_h_m_per_sqrt_s**2
        ),
        reported_sigma_v_m=math.sqrt(
            g.white_v_m**2 + g.bias_v_m**2 + span_s * g.walk_v_m_per_sqrt_s**2
        ),
        reported_sigma_heading_deg=math.degrees(
            math.hypot(g.white_heading_rad, g.bias_heading_rad)
        ),
    )


@dataclass(frozen=True)
class FleetEvalConfig:
    out: Path
    passes: int = 160
    """Passes in all (spread over ``rounds``)."""
    rounds: int = 8
    vehicles: int = 10
    half_height_deg: float = 0.0025
    """Area: CENTRE +- this in latitude, +- twice it in longitude (~560 m x ~560 m)."""
    seed: int = 0
    match_m: float = 5.0
    quiet_timeout_s: float = 600.0
    box_size_sigma_px: float = 0.0
    """Noise on the detected boxes' width and height, px (``DetectorNoise.size_sigma_px``).
    The issue's noise puts 3 px on the box centre only (0 here, the default); the vehicle
    model assumes ``sqrt(2) * 3`` px on the height (4.24: a sensitivity check)."""
    gnss: str = "fleet"
    """``fleet``: FLEET's simulated receiver, its fixes claiming its white levels;
    ``fleet-totals``: the same errors, the fixes claiming their totals (what receivers
    report; :func:`totals_reported`); ``gsdc``: real phone position errors replayed
    (:func:`fleetsim.gnss_replay.gsdc`), heading from the fix track,
    FLEET's detector."""
    shared_floor: bool = True
    """With ``gnss == "gsdc"``, the solver's ``shared_floor_m2`` measured from the replayed
    error log (:func:`gsdc_floor`), as a deployment calibrates its receivers; False: none.
    FLEET's simulated receiver draws its biases independently per pass: no floor."""
    panel_size_rel_sigma: float | None = None
    """Each sign's panel differs from its class's nominal height by ``exp(N(0, this))``
    (:meth:`fleetsim.world.Signs.with_real_sizes`): what the vehicle's box ranges get
    wrong about a given panel, the same at every look. None: the catalogue's
    ``size_rel_sigma`` per class (10 % unless a class says otherwise); 0: every panel
    at its nominal size."""
    gnss_rate_hz: float | None = None
    """The receivers' fix rate, Hz (None: the simulator's, ``DriveParams.gnss_rate_hz``)."""
    map_floor: str = "isotropic"
    """The map floor measured for this noise on held-out seeds, in the form it names
    (:data:`fleetsim.evaluation.map_floor_file.FORMS`: ``correlation``, the solver's
    ``pass_correlation``; ``isotropic``, its ``systematic_sigma_m``); ``none``, or none
    measured: the solver's defaults."""
    bulk_every: int = 4
    """Every ``bulk_every``-th vehicle (indices 3, 7, ...) uploads its round's passes at once
    at the round's end, after the others' later passes (0: every vehicle uploads each pass
    as it ends). The map must not depend on it (event time, docs/operations.md)."""

    def bulk_vehicles(self) -> frozenset[str]:
        """The vehicles that upload in bulk (:attr:`bulk_every`)."""
        k = self.bulk_every
        if k <= 0:
            return frozenset()
        return frozenset(vehicle_id(i) for i in range(self.vehicles) if i % k == k - 1)

    def noise(self) -> NoiseModel:
        """The fleet's noise: :data:`fleetsim.noise.FLEET`, with the box-size noise if set,
        and the replayed GNSS errors with ``gnss == "gsdc"``."""
        noise = FLEET
        if self.gnss == "gsdc":
            noise = replace(noise, name="fleet+gsdc", gnss=gsdc())
        elif self.gnss == "fleet-totals":
            noise = replace(noise, name="fleet-totals", gnss=totals_reported(FLEET.gnss))
        elif self.gnss != "fleet":
            raise ValueError(f"gnss {self.gnss!r}: one of fleet, fleet-totals, gsdc")
        if self.box_size_sigma_px <= 0:
            return noise
        det = replace(noise.detector, size_sigma_px=self.box_size_sigma_px)
        return replace(noise, name=f"{noise.name}+size{self.box_size_sigma_px:g}px", detector=det)

    @staticmethod
    def quick(out: Path) -> FleetEvalConfig:
        return FleetEvalConfig(out, passes=24, rounds=2, vehicles=6, half_height_deg=0.0018)


def gsdc_floor() -> SharedFloor:
    """The shared-error floor of the GSDC receivers, from the log the replay draws from
    (:mod:`hdmap.mapping.gnss_floor`: per trace its mean, less the batch-means variance)."""
    traces = gsdc().traces
    return shared_floor([t.t for t in traces], [np.column_stack([t.east, t.north]) for t in traces])


def solver_floor_args(
    cfg: FleetEvalConfig, run_dir: Path
) -> tuple[dict, AppliedFloor, dict[str, list[str]]]:
    """The GNSS floor the evaluation gives the solver (as JSON values), the map floor
    (:func:`fleetsim.evaluation.map_floor_file.applied_floor` of ``cfg.map_floor``) and
    the services' extra arguments that pass both (a services config file in ``run_dir``)."""
    path = run_dir / "services.toml"
    args = {"solver": ["--config", str(path)]}
    default = SolverConfig().systematic_sigma_m
    if cfg.gnss != "gsdc" or not cfg.shared_floor:
        floor = applied_floor(cfg.noise().name, cfg.map_floor, np.zeros((3, 3)), default)
        path.write_text("[solver]\n" + "\n".join(floor.solver_lines()) + "\n")
        return {"source": None, "cov_enu_m2": None}, floor, args
    f = gsdc_floor()
    six = shared_floor_m2(f)
    floor = applied_floor(cfg.noise().name, cfg.map_floor, floor_enu(f), default)
    lines = [*floor.solver_lines(), f"shared_floor_m2 = [{', '.join(repr(v) for v in six)}]"]
    path.write_text("[solver]\n" + "\n".join(lines) + "\n")
    info = {
        "source": "fleetsim/data/gsdc2020_mtv1_phone_gnss_errors.csv (hdmap.mapping.gnss_floor)",
        "cov_enu_m2": floor_enu(f).tolist(),
        "sigma_en_m": f.sigma.tolist(),
        "drives": f.drives,
        "batches": list(f.batches),
        "drive_means_en_m": f.drive_means.tolist(),
    }
    return info, floor, args


def evaluation_world(cfg: FleetEvalConfig) -> World:
    """The evaluation's part of central Helsinki, its panels of real sizes
    (:attr:`FleetEvalConfig.panel_size_rel_sigma`)."""
    lat0, lon0 = CENTRE
    d = cfg.half_height_deg
    world = helsinki_town(cfg.seed, bbox=(lat0 - d, lon0 - 2 * d, lat0 + d, lon0 + 2 * d))
    rel = cfg.panel_size_rel_sigma
    if rel is None:
        rel = CATALOG.rel_sigmas(world.signs.sign_class)
    if not np.any(np.asarray(rel) > 0):
        return world
    return replace(world, signs=world.signs.with_real_sizes(rel, cfg.seed))


def replay_links(session) -> list[ObsKeys]:
    """Landmark id of every linked observation, from the matcher's association log; an
    observation of a landmark that was later merged into another counts for the one that
    holds it now."""
    consumer = LogConsumer(sqlite3.connect(":memory:"), "assoc", [""])
    out: list[ObsKeys] = []
    successor: dict[int, int] = {}
    for e in catch_up(consumer, session, timeout=30.0):
        g = AssocGroup.from_bytes(e.body)
        for vi, vid in enumerate(g.vehicles):
            mine = g.links.vehicle == vi
            lid = g.links.landmark_id[mine].astype(np.int64)  # ids < 2^63 (tile << 24)
            out.append(ObsKeys(vid, g.obs.obs_id[mine], lid))
        n = g.merged_into.size
        successor.update(zip(g.retired[:n].tolist(), g.merged_into.tolist(), strict=True))
    if not successor:
        return out
    final = {}
    for lid in successor:  # follow chains a -> b -> c
        k, seen = lid, set()
        while k in successor and k not in seen:
            seen.add(k)
            k = successor[k]
        final[lid] = k
    src = np.array(sorted(final), np.int64)
    dst = np.array([final[int(k)] for k in src], np.int64)
    for t in out:
        j = np.clip(np.searchsorted(src, t.value), 0, src.size - 1)
        hit = src[j] == t.value
        t.value[hit] = dst[j[hit]]
    return out


def run_fleet_eval(
    cfg: FleetEvalConfig,
    progress: Callable[[str], None] | None = None,
    progress_bar: bool = False,
) -> tuple[dict, EvalState, Landmarks]:
    """One run (see the module doc); ``progress`` takes its log lines (default: stderr),
    ``progress_bar`` adds a progress line of the passes driven."""
    world = evaluation_world(cfg)
    noise = cfg.noise()
    model = model_for(noise, load_vehicle_model())
    per_round = max(1, cfg.passes // cfg.rounds)
    total = per_round * cfg.rounds
    bar = Progress(total, "passes", enabled=progress_bar)
    say = progress or bar.note
    start = time.time() - (total + 2) * 30.0 - 600.0
    rate = {"gnss_rate_hz": cfg.gnss_rate_hz} if cfg.gnss_rate_hz else {}
    fleet_cfg = FleetConfig(
        n_vehicles=cfg.vehicles,
        start_time=start,
        pass_interval_s=30.0,
        route_length_m=(600.0, 1200.0),
        **rate,
    )
    fleet = Fleet(world, model, noise, fleet_cfg, seed=cfg.seed)
    state = EvalState(world)
    run_dir = cfg.out / "run"
    if run_dir.exists():
        shutil.rmtree(run_dir)
    lms: list[Landmarks] = []
    t0 = time.monotonic()
    say(
        f"fleet eval: Helsinki, {len(world.signs)} signs of "
        f"{np.unique(world.signs.sign_class).size} classes, {total} passes in {cfg.rounds} rounds"
    )
    run_dir.mkdir(parents=True)
    floor_info, floor, service_args = solver_floor_args(cfg, run_dir)
    say(
        f"map floor: pass correlation {floor.kappa:.4g}, sigma (E, N, U) "
        f"{np.round(floor.sigma_m, 3).tolist()} m, from {floor.source}"
    )
    if floor_info["cov_enu_m2"] is not None:
        say(f"shared-error floor (E, N sigma m): {np.round(floor_info['sigma_en_m'], 3).tolist()}")
    with Stack(run_dir / "var", extra_service_args=service_args) as stack:
        stack.start_all()
        with open_session(stack.bus) as session:
            client = MapClient(session, radius_m=0.0)
            follow_town(client, world)
            driver = FleetDriver(world, fleet, run_dir / "vehicles", bulk=cfg.bulk_vehicles())

            def on_pass(p) -> None:
                _remember(state, driver, p)
                bar.update()

            try:
                for r in range(cfg.rounds):
                    passes = fleet.passes(per_round, r * per_round)
                    driver.run(session, passes, on_pass=on_pass)
                    left = driver.flush(session)
                    quiet = wait_quiet(session, timeout=cfg.quiet_timeout_s)
                    time.sleep(0.8)
                    client.wait_idle(20.0)
                    lm = client.landmarks()
                    rec = score_round(world, lm, driver.seen.passes, cfg.match_m)
                    state.records.append(rec)
                    lms.append(lm)
                    e = rec.err[rec.found]
                    kinds = landmark_counts(world, lm, driver.seen.passes, cfg.match_m)
                    row = {
                        "round": r + 1,
                        "passes": (r + 1) * per_round,
                        "median_passes_per_sign": float(np.median(rec.n)),
                        "landmarks": len(lm),
                        "false_landmarks": int((~kinds["paired"]).sum()),
                        "false_confirmed": int((~kinds["paired"] & kinds["confirmed"]).sum()),
                        "left_queued": left,
                        "duplicates": int(kinds["dup"].sum()),
                        "duplicates_confirmed": int((kinds["dup"] & kinds["confirmed"]).sum()),
                        "recall": float(rec.found.mean()),
                        "mean_err_m": float(e.mean()) if e.size else None,
                        "coverage95": float(rec.inside[rec.found].mean()) if e.size else None,
                        "observations": driver.seen.observations,
                        "quiet": bool(quiet),
                        "wall_s": time.monotonic() - t0,
                    }
                    state.rounds.append(row)
                    say(
                        f"round {r + 1}/{cfg.rounds}: median {row['median_passes_per_sign']:.0f} "
                        f"passes/sign, {len(lm)} landmarks ({row['false_landmarks']} false, "
                        f"{row['false_confirmed']} of them confirmed), "
                        f"recall {row['recall']:.3f}, "
                        f"error {row['mean_err_m'] or float('nan'):.2f} m, "
                        f"coverage {row['coverage95'] or float('nan'):.2f}, "
                        f"{row['wall_s']:.0f} s"
                    )
                links = replay_links(session)
                services = totals(collect(session))
            finally:
                bar.close()
                client.close()
                driver.close()
    linked = Linked.of(state, links)
    table = bin_table(state, landmark_rows(state, lms, cfg.match_m), linked)
    n_links = sum(t.obs_id.size for t in links)
    n_true_obs = sum(int((t.value >= 0).sum()) for t in state.truth)
    pairs = same_class_pairs(world)
    border = tile_border_distance(world, world.signs.position[:, :2])
    result = {
        "meta": {
            "town": "central Helsinki (OpenStreetMap, ODbL; fleetsim/data/helsinki.json)",
            "centre": CENTRE,
            "half_height_deg": cfg.half_height_deg,
            "signs": len(world.signs),
            "classes": int(np.unique(world.signs.sign_class).size),
            "same_class_pairs_3_10m": len(pairs),
            "signs_within_10m_of_tile_border": int((border <= 10.0).sum()),
            "passes": total,
            "rounds": cfg.rounds,
            "vehicles": cfg.vehicles,
            "bulk_vehicles": sorted(cfg.bulk_vehicles()),
            "seed": cfg.seed,
            "noise": f"{noise.name} (fleetsim/noise.py)",
            "box_size_sigma_px": cfg.box_size_sigma_px,
            "panel_size_rel_sigma": cfg.panel_size_rel_sigma,
            "gnss_rate_hz": fleet_cfg.gnss_rate_hz,
            "shared_floor": floor_info,
            "match_m": cfg.match_m,
            "wall_s": time.monotonic() - t0,
        },
        "rounds": state.rounds,
        "by_passes": table,
        "observations": {
            "uploaded": driver.seen.observations,
            "of_true_signs": n_true_obs,
            "linked": n_links,
        },
        "services": services,
        "targets_at_50_passes": targets(table),
        "signs": sign_table(state, linked),
        "unpaired": unpaired_table(world, lms[-1], cfg.match_m, linked),
        "map_floor": {
            "applied": floor.as_dict(),
            "measured": measured_floor(state.records[-1], floor),
        },
    }
    if result["targets_at_50_passes"]["evaluated"]:
        result["targets_at_50_passes"].update(assoc_shares(state, linked))
    write_truth(state, run_dir / "truth.npz")
    return result, state, lms[-1]


def write_truth(state: EvalState, path: Path) -> None:
    """The run's truth per uploaded observation, for replays of its logs against it
    (``services.matcher.replay``): ``vehicle``, ``obs_id`` (the pair names an observation
    in the ingest log) and ``sign_id`` (the true sign's id; -1 a false positive)."""
    parts = state.truth or [ObsKeys("", np.zeros(0, np.uint64), np.zeros(0, np.int64))]
    rows = np.concatenate([t.value for t in parts])
    np.savez_compressed(
        path,
        vehicle=np.concatenate([np.full(t.obs_id.size, t.vehicle) for t in parts]),
        obs_id=np.concatenate([t.obs_id for t in parts]).astype(np.uint64),
        sign_id=np.where(rows >= 0, state.world.signs.id[np.maximum(rows, 0)], -1).astype(np.int64),
    )


def _remember(state: EvalState, driver: FleetDriver, p) -> None:
    """Truth of the observations the agent just queued: their ids and true sign rows
    (detections the vehicle dropped for a suspect fix were not queued)."""
    agent = driver.agent(p.vehicle_id)
    kept = agent.last_kept
    sign_id = p.truth.sign_id[kept]
    n = len(sign_id)
    last = agent.uploader.last_obs_id
    rows = np.where(sign_id >= 0, state.world.signs.index_of(sign_id), -1)
    state.truth.append(ObsKeys(p.vehicle_id, np.arange(last - n + 1, last + 1), rows))
