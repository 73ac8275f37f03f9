"""``hdmap eval changes``: does the map follow the world? (issue 21, point 6)

A simulated fleet drives a town while scheduled changes take signs down, move them,
replace them by another class, put new ones up and put temporary ones up and down
(:mod:`fleetsim.changes`, drawn by :func:`fleetsim.changes.random_schedule` after a
warm-up that builds the map). The vehicles follow the published map (a map client of the
town) and report the mapped signs they had in view and did not detect
(:mod:`vehicle.absence_report`); one vehicle turns rogue after the warm-up (a blind
camera: it detects nothing, so it reports every mapped sign it passes as not seen). The
services run as separate processes on a real router (:class:`hdmap.ops.stack.Stack`).

After every round the map as a vehicle reads it is scored
(:mod:`fleetsim.evaluation.changes_scoring`): for each change the passes (and event hours)
past its place until the map reflected it, the signs no change touched that the map lost
(false revocations; those the rogue reported: rogue revocations), the calibration of the
published existence probability. ``changes.json`` holds the summary keys
(``removal_median_passes``, ``removal_p95_passes``, ``move_median_passes``,
``addition_median_passes``, ``false_revocations``, ``rogue_revocations``, ...), every
change and every round; ``changes.png`` the timeline.
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from fleetsim.changes import ChangeSchedule, random_schedule
from fleetsim.evaluation.changes_scoring import ChangeScorer, summary
from fleetsim.fleet import Fleet, FleetConfig, Pass, vehicle_id
from fleetsim.noise import FLEET
from fleetsim.pipeline import FleetDriver, model_for
from fleetsim.town_run import follow_town
from fleetsim.world import World, demo_town
from hdmap.ops.progress import Progress
from hdmap.ops.quiesce import totals, wait_quiet
from hdmap.ops.stack import Stack
from hdmap.ops.status import collect
from hdmap.runtime.bus import open_session
from vehicle.absence_report import mounting_yaw_deg
from vehicle.config import load_vehicle_model
from vehicle.mapclient import MapClient


@dataclass(frozen=True)
class ChangesEvalConfig:
    out: Path
    seed: int = 0
    vehicles: int = 8
    passes: int = 480
    rounds: int = 48
    """Checks of the map (one after each round of ``passes / rounds`` passes)."""
    n_signs: int = 30
    n_blocks: int = 3
    warmup: float = 0.3
    """Share of the passes before the first change (the map is built)."""
    changes_until: float = 0.7
    """Share of the passes by which every change has happened (the rest see them)."""
    n_remove: int = 3
    n_move: int = 3
    n_replace: int = 2
    n_add: int = 3
    n_temporary: int = 2
    rogue: bool = True
    """The last vehicle turns blind after the warm-up (it reports every sign not seen)."""
    pass_interval_s: float = 60.0
    match_m: float = 5.0
    quiet_timeout_s: float = 300.0

    @staticmethod
    def quick(out: Path) -> ChangesEvalConfig:
        return ChangesEvalConfig(
            out, vehicles=6, passes=180, rounds=18, n_signs=14, n_blocks=2, n_remove=1,
            n_move=1, n_replace=0, n_add=1, n_temporary=0,
        )  # fmt: skip


def blinded(p: Pass) -> Pass:
    """The pass as a blind camera records it: no detection at all."""
    none = np.zeros(0, np.int64)
    truth = replace(
        p.truth,
        sign_id=p.truth.sign_id[none],
        uv_true=p.truth.uv_true[none],
        distance_m=p.truth.distance_m[none],
    )
    return replace(p, detections=p.detections.take(none), truth=truth)


def schedule_for(cfg: ChangesEvalConfig, world: World, start: float) -> ChangeSchedule:
    """The run's changes, between the warm-up's end and ``changes_until``."""
    span = cfg.passes * cfg.pass_interval_s
    return random_schedule(
        world,
        np.random.default_rng([cfg.seed, 21]),
        start + cfg.warmup * span,
        start + cfg.changes_until * span,
        n_remove=cfg.n_remove,
        n_move=cfg.n_move,
        n_replace=cfg.n_replace,
        n_add=cfg.n_add,
        n_temporary=cfg.n_temporary,
    )


def run_changes_eval(
    cfg: ChangesEvalConfig,
    progress: Callable[[str], None] | None = None,
    progress_bar: bool = False,
) -> dict:
    """One seed's run (see the module doc); ``progress`` takes its log lines (default:
    stderr), ``progress_bar`` adds a progress line of the passes driven."""
    world = demo_town(cfg.seed, n_signs=cfg.n_signs, n_blocks=cfg.n_blocks)
    model = model_for(FLEET, load_vehicle_model())
    per_round = max(1, cfg.passes // cfg.rounds)
    total = per_round * cfg.rounds
    bar = Progress(total, "passes", enabled=progress_bar)
    say = progress or bar.note
    start = time.time() - (total + 2) * cfg.pass_interval_s - 600.0
    schedule = schedule_for(cfg, world, start)
    fleet_cfg = FleetConfig(
        n_vehicles=cfg.vehicles, start_time=start, pass_interval_s=cfg.pass_interval_s
    )
    fleet = Fleet(world, model, FLEET, fleet_cfg, seed=cfg.seed, schedule=schedule)
    scorer = ChangeScorer(world, schedule, cfg.match_m)
    rogue = vehicle_id(cfg.vehicles - 1) if cfg.rogue else None
    turn = start + cfg.warmup * total * cfg.pass_interval_s
    rogue_reported: set[int] = set()
    run_dir = cfg.out / "run"
    if run_dir.exists():
        shutil.rmtree(run_dir)
    run_dir.mkdir(parents=True)
    say(
        f"changes eval: demo town (seed {cfg.seed}), {len(world.signs)} signs, "
        f"{len(schedule.changes)} changes, {total} passes in {cfg.rounds} rounds"
        + (f", {rogue} blind after the warm-up" if rogue else "")
    )
    rounds = []
    t0 = time.monotonic()

    def tamper(p: Pass) -> Pass:
        return blinded(p) if p.vehicle_id == rogue and p.start_time >= turn else p

    with Stack(run_dir / "var") as stack:
        stack.start_all()
        with open_session(stack.bus) as session:
            client = MapClient(session, radius_m=0.0)
            follow_town(client, world)
            driver = FleetDriver(
                world, fleet, run_dir / "vehicles", tamper=tamper, expected_map=client.landmarks
            )

            def on_pass(p: Pass) -> None:
                yaw = np.degrees(p.truth.heading_rad) + mounting_yaw_deg(model)
                scorer.note_pass(p.start_time, p.truth.t, p.truth.camera_enu[:, :2], yaw)
                if p.vehicle_id == rogue:
                    ab = driver.agent(p.vehicle_id).last_absences
                    rogue_reported.update(int(i) for i in ab.landmark_id.tolist())
                bar.update()

            try:
                for r in range(cfg.rounds):
                    driver.run(session, fleet.passes(per_round, r * per_round), on_pass=on_pass)
                    wait_quiet(session, timeout=cfg.quiet_timeout_s)
                    time.sleep(0.8)
                    client.wait_idle(20.0)
                    t_check = (
                        fleet.start_time(0, 0) + ((r + 1) * per_round - 1) * cfg.pass_interval_s
                    )
                    lm = client.landmarks()
                    scorer.check(t_check, lm)
                    done = sum(e.reflected_at is not None for e in scorer.events if e.t <= t_check)
                    due = sum(e.t <= t_check for e in scorer.events)
                    rounds.append(
                        {
                            "round": r + 1,
                            "passes": (r + 1) * per_round,
                            "event_time": t_check,
                            "landmarks": len(lm),
                            "doubtful": int((lm.exist_state == 2).sum()),
                            "events_due": due,
                            "events_reflected": done,
                            "false_revocations": len(scorer.lost),
                            "wall_s": time.monotonic() - t0,
                        }
                    )
                    say(
                        f"round {r + 1}/{cfg.rounds}: {len(lm)} landmarks "
                        f"({rounds[-1]['doubtful']} doubtful), changes reflected {done}/{due}, "
                        f"false revocations {len(scorer.lost)}, {rounds[-1]['wall_s']:.0f} s"
                    )
                services = totals(collect(session))
            finally:
                bar.close()
                client.close()
                driver.close()
    keys = summary(scorer, rogue_reported)
    return {
        **{k: v for k, v in keys.items() if k != "calibration"},
        "calibration": keys["calibration"],
        "config": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(cfg).items()},
        "changes": schedule.describe(world.signs),
        "events": [
            {
                "change": e.change,
                "kind": e.kind,
                "t": e.t,
                "present": list(e.present),
                "gone": list(e.gone),
                "passes_to_reflect": e.passes_to_reflect,
                "hours_to_reflect": e.hours_to_reflect,
                "passes_to_locate": e.passes_to_locate,
                "passes_seen_so_far": e.passes,
                "waiting_for": e.waiting_for,
                "trace": e.trace,
            }
            for e in scorer.events
        ],
        "lost": {str(s): {"t": t, "landmark": lid} for s, (t, lid) in sorted(scorer.lost.items())},
        "rogue": {"vehicle": rogue, "reported_landmarks": len(rogue_reported)},
        "rounds": rounds,
        "services": services,
        "start_time": start,
    }
