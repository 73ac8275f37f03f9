"""``hdmap eval localize``: how well a vehicle knows where it is with the fleet's map
(issue 22 point 1; the localiser: :mod:`vehicle.localizer`, the method and the figures:
docs/localization.md).

Per seed: a fleet of ``vehicles`` drives ``map_passes`` passes through the fleet
evaluation's part of central Helsinki (:func:`fleetsim.evaluation.fleet_eval.evaluation_world`,
panels of real sizes) with its noise (``gnss``: FLEET's simulated receiver, or ``gsdc``:
the real phone errors replayed, and then the solver's shared floor measured from the same
log, as ``hdmap eval fleet --gnss gsdc`` runs it), and the map is built in-process
through the matcher and the solver (:mod:`fleetsim.evaluation.localize_map`). Then
``held_out`` passes of other vehicles (another fleet seed: routes, speeds and receiver
errors the map never saw, the same noise model) are localised against that map, once per
second of each drive (whole seconds from the first fix, online: each pose uses what came
before it), and compared with the truth (the GNSS antenna's true position, interpolated
between the fixes' true positions).

Per second: the raw GNSS error (the fix track interpolated, suspect fixes dropped: what the
receiver gives), the localiser's output error (map-aided where it reports a fix, else the
GNSS pose it falls back to), whether the truth is inside its reported 95 % ellipse, and the
part of the error the map's own landmark errors carry in (the localiser's gains times the
landmarks' true errors; "map frame": the error less that part, what the localiser gets
wrong against the map as it is).

**The condition** of the target: the seconds after the pass has detected its third
distinct *mapped* sign (a sign that a confirmed landmark of the map pairs with, same class,
within ``match_m``; from the simulator's truth). ``localize.json``'s headline keys are over
those seconds, pooled over passes and seeds: ``gnss_p50_m``/``gnss_p95_m`` (raw GNSS),
``map_aided_p50_m``/``map_aided_p95_m`` (the seconds with a map-aided fix),
``coverage95`` (of those, the truth inside the reported ellipse), ``map_aided_share``
(share of the seconds with a map-aided fix); beside them the output over every second
after the condition (``output_*``), the map-frame errors, the share over the whole drives,
the matches' correctness, the map's own error and its mean vector (what every landmark
shares), and per seed and per pass the same.
"""

from __future__ import annotations

import shutil
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from fleetsim.evaluation.fleet_eval import FleetEvalConfig, evaluation_world, solver_floor_args
from fleetsim.evaluation.localize_map import build_map, solver_config
from fleetsim.fleet import Fleet, FleetConfig, Pass
from fleetsim.pipeline import model_for
from fleetsim.truth import match_map
from fleetsim.world import World
from hdmap.runtime.config import load_toml
from schemas import STATUS_CONFIRMED
from schemas.map import MapLandmarks
from vehicle.config import load_vehicle_model
from vehicle.localizer import DEFAULT_LOCALIZER, LocalizedPoses, LocalizerConfig, localize

CHI2_2_95 = 5.991464547107979
START_TIME = 1.7e9
"""Capture time of the first pass (fixed: a run is repeatable; the matcher and the solver
run on event time, in-process nothing compares it with the wall clock's)."""
HELD_OUT_SEED = 1000
"""The held-out passes' fleet seed is this plus the run's seed."""

RECEIVERS = {
    "fleet": LocalizerConfig(prior_sigma_m=3.3, corr_s=0.2),
    "gsdc": LocalizerConfig(prior_sigma_m=1.5, corr_s=1.0),
}
"""The localiser's receiver model per noise (what a vehicle knows of its own receiver, as
the solver's floor is calibrated per receiver): the offset's prior is the receiver's
total error per axis (FLEET: 2.5 m bias, 1 m white and its 0.2 m/sqrt(s) walk over a
90 s pass, ``fleet_eval.totals_reported``; the phones: 1.17 m RMS, rounded up); FLEET's
simulated fixes carry white noise of their own at 5 Hz (rays 0.2 s apart share none of
it), the phones' errors, logged at 1 Hz and interpolated, hold for about a second."""

TARGETS = {"map_aided_p50_m": 0.3, "map_aided_p95_m": 0.8, "coverage95": (0.90, 0.98)}
"""Issue 22's target for map-aided localisation with the real phone errors."""


@dataclass(frozen=True)
class LocalizeEvalConfig:
    out: Path
    gnss: str = "fleet"
    """``fleet`` (FLEET's simulated receiver) or ``gsdc`` (real phone errors; see
    :class:`fleetsim.evaluation.fleet_eval.FleetEvalConfig.gnss`)."""
    seeds: tuple[int, ...] = (0,)
    map_passes: int = 300
    vehicles: int = 10
    held_out: int = 16
    """Passes localised per seed (4 held-out vehicles)."""
    half_height_deg: float = 0.0025
    """The town: the fleet evaluation's area (~560 m x 560 m, 243 signs)."""
    match_m: float = 5.0
    min_mapped_signs: int = 3
    localizer: LocalizerConfig | None = None
    """None: the receiver's (:data:`RECEIVERS`, else the localiser's defaults)."""

    def localizer_config(self) -> LocalizerConfig:
        if self.localizer is not None:
            return self.localizer
        return RECEIVERS.get(self.gnss, DEFAULT_LOCALIZER)

    @staticmethod
    def quick(out: Path, gnss: str = "fleet") -> LocalizeEvalConfig:
        return LocalizeEvalConfig(
            out, gnss=gnss, map_passes=40, vehicles=6, held_out=3, half_height_deg=0.0018
        )


@dataclass
class PassSeconds:
    """One held-out pass, per second (arrays of the pass's query times)."""

    vehicle_id: str
    pass_id: int
    t: np.ndarray
    """Seconds since the pass's first fix."""
    gnss_err: np.ndarray
    out_err: np.ndarray
    map_frame_err: np.ndarray
    radius95: np.ndarray
    """The reported 95 % ellipse's major semi-axis, m."""
    inside95: np.ndarray
    gnss_inside95: np.ndarray
    """The truth inside the GNSS pose's 95 % ellipse (the localiser's GNSS error model)."""
    aided: np.ndarray
    after: np.ndarray
    """After the pass detected its ``min_mapped_signs``-th mapped sign."""
    gnss_white_err: np.ndarray
    """The horizontal size of the receiver's white error at the second (FLEET's per-fix
    noise; 0 for the replay): what no estimate of a slow offset removes."""
    matches: int
    matches_right: int


def world_frame_en(res: LocalizedPoses, en: np.ndarray, world: World) -> np.ndarray:
    """East-North positions in the localiser's frame -> the world's frame."""
    lat, lon, _ = res.frame.to_geodetic(np.column_stack([en, np.zeros(len(en))]))
    return world.frame.from_geodetic(lat, lon, np.zeros(np.size(lat))).reshape(-1, 3)[:, :2]


def truth_at(p: Pass, t: np.ndarray) -> np.ndarray:
    """The GNSS antenna's true position at times ``t`` (world East-North, m)."""
    tr = p.truth
    return np.column_stack([np.interp(t, tr.fix_t, tr.antenna_enu[:, i]) for i in range(2)])


def score_pass(
    p: Pass,
    res: LocalizedPoses,
    world: World,
    lm_err: dict[int, np.ndarray],
    mapped_sign: dict[int, int],
    min_mapped: int,
) -> PassSeconds:
    """A localised pass against the truth (module docstring). ``lm_err``: the map error
    (East-North, m) of each landmark paired with a sign; ``mapped_sign``: landmark id ->
    the sign id it pairs with."""
    t = res.t
    truth = truth_at(p, t)
    out = world_frame_en(res, res.en, world)
    gnss = world_frame_en(res, res.gnss_en, world)
    e = out - truth
    carried = np.zeros((t.size, 2))
    for q in range(t.size):
        for g, lid in zip(res.landmark_gains[q], res.landmark_ids[q].tolist(), strict=True):
            carried[q] += g @ lm_err.get(int(lid), np.zeros(2))
    carried = np.where(res.map_aided[:, None], carried, 0.0)
    d2 = np.einsum("ni,nij,nj->n", e, np.linalg.inv(res.cov), e)
    eg = gnss - truth
    d2g = np.einsum("ni,nij,nj->n", eg, np.linalg.inv(res.gnss_cov), eg)
    radius = np.sqrt(CHI2_2_95 * np.linalg.eigvalsh(res.cov)[:, -1])
    det = p.detections
    sid = p.truth.sign_id
    mapped = np.isin(sid, np.array(sorted(set(mapped_sign.values())), np.int64))
    first_t: dict[int, float] = {}
    for s, tt in zip(sid[mapped].tolist(), np.asarray(det.t, float)[mapped].tolist(), strict=True):
        first_t[s] = min(tt, first_t.get(s, np.inf))
    times = sorted(first_t.values())
    t_cond = times[min_mapped - 1] if len(times) >= min_mapped else np.inf
    tr = p.truth
    white = np.column_stack([np.interp(t, tr.fix_t, tr.gnss.white_enu[:, i]) for i in range(2)])
    m = res.matches
    ok = ~m.rejected
    right = np.array(
        [
            mapped_sign.get(int(lid), -2) == int(s)
            for lid, s in zip(m.landmark_id[ok], sid[m.detection[ok]], strict=True)
        ],
        bool,
    )
    t0 = float(tr.fix_t[0])
    return PassSeconds(
        vehicle_id=p.vehicle_id,
        pass_id=p.pass_id,
        t=t - t0,
        gnss_err=np.hypot(*(gnss - truth).T),
        out_err=np.hypot(*e.T),
        map_frame_err=np.hypot(*(e - carried).T),
        radius95=radius,
        inside95=d2 <= CHI2_2_95,
        gnss_inside95=d2g <= CHI2_2_95,
        aided=res.map_aided.copy(),
        after=t >= t_cond,
        gnss_white_err=np.hypot(*white.T),
        matches=int(ok.sum()),
        matches_right=int(right.sum()),
    )


def map_errors(world: World, lm: MapLandmarks, match_m: float) -> tuple[dict, dict, dict]:
    """Per landmark paired with a sign (confirmed ones first): its error (East-North, m)
    and its sign's id; and the map's summary (counts, error, mean error vector)."""
    m = match_map(world, lm, match_m)
    ids = np.asarray(lm.id, np.uint64)
    err = {int(ids[i]): m.error_enu[k, :2] for k, i in enumerate(m.landmark.tolist())}
    confirmed = np.asarray(lm.status) == STATUS_CONFIRMED
    sign = {
        int(ids[i]): int(world.signs.id[s])
        for i, s in zip(m.landmark.tolist(), m.sign_row.tolist(), strict=True)
        if confirmed[i]
    }
    h = m.horizontal_error_m[confirmed[m.landmark]]
    vec = m.error_enu[confirmed[m.landmark], :2]
    info = {
        "landmarks": len(lm),
        "confirmed": int(confirmed.sum()),
        "signs": len(world.signs),
        "signs_mapped": len(sign),
        "error_mean_m": float(h.mean()) if h.size else None,
        "error_p50_m": float(np.median(h)) if h.size else None,
        "error_p95_m": float(np.percentile(h, 95)) if h.size else None,
        "error_mean_vector_en_m": vec.mean(axis=0).tolist() if h.size else None,
    }
    return err, sign, info


def run_seed(
    cfg: LocalizeEvalConfig, seed: int, say: Callable[[str], None]
) -> tuple[list[PassSeconds], dict]:
    """One seed: the fleet's map, then the held-out passes localised against it."""
    fcfg = FleetEvalConfig(
        out=cfg.out, seed=seed, gnss=cfg.gnss, half_height_deg=cfg.half_height_deg
    )
    world = evaluation_world(fcfg)
    noise = fcfg.noise()
    model = model_for(noise, load_vehicle_model())
    work = cfg.out / "run" / f"seed-{seed}"
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    solver_floor_args(fcfg, work)  # writes work/services.toml, as the fleet evaluation does
    solver = solver_config(load_toml(work / "services.toml").get("solver", {}))
    start = START_TIME
    fleet = Fleet(
        world,
        model,
        noise,
        FleetConfig(n_vehicles=cfg.vehicles, start_time=start, pass_interval_s=30.0),
        seed=seed,
    )
    say(
        f"localize seed {seed} ({noise.name}): {len(world.signs)} signs, map of "
        f"{cfg.map_passes} passes"
    )
    lm, build = build_map(fleet, cfg.map_passes, work, solver=solver, say=say)
    lm_err, mapped_sign, map_info = map_errors(world, lm, cfg.match_m)
    held = Fleet(
        world,
        model,
        noise,
        FleetConfig(n_vehicles=4, start_time=start + (cfg.map_passes + 1) * 30.0),
        seed=HELD_OUT_SEED + seed,
    )
    passes: list[PassSeconds] = []
    t0 = time.monotonic()
    for p in held.passes(cfg.held_out):
        tq = p.fixes.t[0] + np.arange(1.0, p.fixes.t[-1] - p.fixes.t[0])
        res = localize(p.fixes, p.detections, lm, model, tq, cfg.localizer_config())
        passes.append(score_pass(p, res, world, lm_err, mapped_sign, cfg.min_mapped_signs))
    say(
        f"localize seed {seed}: {cfg.held_out} held-out passes localised "
        f"({time.monotonic() - t0:.0f} s)"
    )
    info = {"map": map_info, "map_build": build, "noise": noise.name, "solver": asdict(solver)}
    return passes, info


def _pct(x: np.ndarray, q: float) -> float | None:
    return float(np.percentile(x, q)) if x.size else None


def summarise(passes: list[PassSeconds]) -> dict:
    """The headline keys over the seconds after the condition (module docstring)."""

    def cat(name: str) -> np.ndarray:
        return np.concatenate([getattr(p, name) for p in passes]) if passes else np.zeros(0)

    after, aided = cat("after").astype(bool), cat("aided").astype(bool)
    fix = after & aided
    gnss, out, frame_err = cat("gnss_err"), cat("out_err"), cat("map_frame_err")
    inside = cat("inside95").astype(bool)
    n_m = sum(p.matches for p in passes)
    return {
        "seconds": int(after.size),
        "seconds_after_condition": int(after.sum()),
        "gnss_p50_m": _pct(gnss[after], 50),
        "gnss_p95_m": _pct(gnss[after], 95),
        "map_aided_p50_m": _pct(out[fix], 50),
        "map_aided_p95_m": _pct(out[fix], 95),
        "coverage95": float(inside[fix].mean()) if fix.any() else None,
        "map_aided_share": float(aided[after].mean()) if after.any() else None,
        "map_aided_share_all": float(aided.mean()) if aided.size else None,
        "output_p50_m": _pct(out[after], 50),
        "output_p95_m": _pct(out[after], 95),
        "map_frame_p50_m": _pct(frame_err[fix], 50),
        "map_frame_p95_m": _pct(frame_err[fix], 95),
        "gnss_white_p50_m": _pct(cat("gnss_white_err")[fix], 50),
        "gnss_coverage95": float(cat("gnss_inside95")[after].mean()) if after.any() else None,
        "matches": n_m,
        "matches_right_share": sum(p.matches_right for p in passes) / n_m if n_m else None,
    }


def targets_met(s: dict) -> dict:
    """Each target against the pooled figures (None: not measured)."""
    lo, hi = TARGETS["coverage95"]

    def le(k: str) -> bool | None:
        return None if s.get(k) is None else bool(s[k] <= TARGETS[k])

    cov = s.get("coverage95")
    return {
        "map_aided_p50_m": le("map_aided_p50_m"),
        "map_aided_p95_m": le("map_aided_p95_m"),
        "coverage95": None if cov is None else bool(lo <= cov <= hi),
    }


def pass_rows(passes: list[PassSeconds]) -> list[dict]:
    """Per pass: its figures after the condition, and when the condition started."""
    rows = []
    for p in passes:
        s = summarise([p])
        cond = p.t[p.after]
        rows.append(
            {
                "vehicle_id": p.vehicle_id,
                "pass_id": p.pass_id,
                "condition_from_s": float(cond[0]) if cond.size else None,
                **{
                    k: s[k]
                    for k in (
                        "seconds",
                        "seconds_after_condition",
                        "gnss_p50_m",
                        "map_aided_p50_m",
                        "map_aided_p95_m",
                        "coverage95",
                        "map_aided_share",
                        "matches_right_share",
                    )
                },
            }
        )
    return rows


def run_localize_eval(
    cfg: LocalizeEvalConfig, progress: Callable[[str], None] | None = None
) -> tuple[dict, dict[int, list[PassSeconds]]]:
    """Every seed of ``cfg``; the report (without writing it) and the per-second series."""
    say = progress or (lambda m: print(m, file=sys.stderr, flush=True))
    t0 = time.monotonic()
    series: dict[int, list[PassSeconds]] = {}
    per_seed = {}
    for seed in cfg.seeds:
        passes, info = run_seed(cfg, seed, say)
        series[seed] = passes
        s = summarise(passes)
        per_seed[str(seed)] = {**s, **info, "passes": pass_rows(passes)}
    pooled = summarise([p for ps in series.values() for p in ps])
    report = {
        **pooled,
        "condition": (
            f"seconds after the pass detected its {cfg.min_mapped_signs}rd distinct mapped sign "
            f"(a sign a confirmed landmark pairs with, same class, within {cfg.match_m:g} m)"
            if cfg.min_mapped_signs == 3
            else f"seconds after the pass detected {cfg.min_mapped_signs} distinct mapped signs"
        ),
        "targets": {k: list(v) if isinstance(v, tuple) else v for k, v in TARGETS.items()},
        "targets_met": targets_met(pooled),
        "per_seed": per_seed,
        "meta": {
            "config": {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(cfg).items()},
            "localizer": asdict(cfg.localizer_config()),
            "wall_s": time.monotonic() - t0,
            "held_out_seed": f"{HELD_OUT_SEED} + seed",
        },
    }
    return report, series
