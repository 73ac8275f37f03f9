"""The fleet evaluation as a job (``hdmap eval fleet``): one seed, or several summarised.

One run (:func:`fleetsim.evaluation.fleet_eval.run_fleet_eval`: central Helsinki through
the real pipeline with the realistic fleet noise) writes ``out/fleet.json`` and the PNG
figures and prints its table (:func:`format_fleet_table`) on stderr. With ``seeds``, each
seed runs into ``out/seed-<s>/`` and ``out/fleet_seeds.json`` summarises them
(:mod:`fleetsim.evaluation.fleet_seeds`); with ``jobs`` > 1 the seeds run as separate
``hdmap eval fleet`` processes, at most ``jobs`` at once, each with its own stack.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import IO

from fleetsim.evaluation.fleet_eval import FleetEvalConfig, run_fleet_eval
from fleetsim.evaluation.fleet_plots import write_fleet_figures, write_seed_figure
from fleetsim.evaluation.fleet_seeds import FLEET_COLUMNS, seed_row, summarise_seeds
from fleetsim.evaluation.map_floor_file import FLOOR_FILE, record_floor
from fleetsim.evaluation.results import write_json, write_seed_summary
from hdmap.ops.progress import Progress
from hdmap.runtime.orphan import PARENT_ENV

SEED_STALL_TIMEOUT_S = 1800.0
"""A seed's run whose log has not grown for this long is stopped (and the job fails)."""
SEED_RUN_S_PER_PASS = 10.0
"""A seed's run that has not finished after this many seconds per pass is stopped: a
fixed limit (30 minutes) stopped 1,200-pass runs that two jobs on a busy 2-core machine
made take longer, with nothing wrong (at least ``SEED_STALL_TIMEOUT_S``)."""


class SeedRunError(RuntimeError):
    """A seed's separate run failed or did not finish in time."""


@dataclass(frozen=True)
class FleetRunOptions:
    out: Path
    seed: int = 0
    seeds: tuple[int, ...] = ()
    """Instead of ``seed``: run each into ``out/seed-<s>/`` and summarise them."""
    jobs: int = 1
    """With ``seeds``: runs at once, each its own process with a router and four services."""
    passes: int | None = None
    """Passes in all; None: :class:`FleetEvalConfig`'s (or its ``quick``)."""
    rounds: int | None = None
    """Scoring rounds; None: :class:`FleetEvalConfig`'s (or its ``quick``)."""
    box_size_sigma_px: float = 0.0
    """Noise on the detected boxes' width and height, px."""
    gnss: str = "fleet"
    """GNSS errors: ``fleet`` (the simulated receiver of :data:`fleetsim.noise.FLEET`) or
    ``gsdc`` (real phone errors replayed, :mod:`fleetsim.gnss_replay`)."""
    shared_floor: bool = True
    """With ``gsdc``: the solver's shared-error floor measured from the replayed log
    (:attr:`FleetEvalConfig.shared_floor`); False: ``--no-shared-floor``."""
    bulk_every: int | None = None
    """Every this-th vehicle uploads a round at once (None: :class:`FleetEvalConfig`'s;
    0: none)."""
    gnss_rate_hz: float | None = None
    """The receivers' fix rate (None: :class:`FleetEvalConfig`'s, the simulator's 5 Hz)."""
    panel_size_rel_sigma: float | None = None
    """Panels' size spread (None: the catalogue's; :class:`FleetEvalConfig`)."""
    map_floor: str = FleetEvalConfig.map_floor
    """The form of the map floor measured on held-out seeds (:attr:`FleetEvalConfig.map_floor`,
    ``--map-floor``)."""
    calibrate_floor: bool = False
    """Write the floor each run measures into the calibration file
    (:func:`fleetsim.evaluation.map_floor_file.record_floor`): for held-out seeds only."""
    quick: bool = False
    """A small run for the test suite."""
    progress: bool = False
    """Progress lines on stderr: the passes of a run, the seeds of separate runs (``hdmap
    eval fleet``: unless ``--no-progress``); not one of :meth:`run_flags` (it changes no
    result)."""

    def run_flags(self) -> list[str]:
        """The command-line options every seed's run shares (``--passes``, ``--rounds``,
        ``--box-size-sigma``, ``--quick``)."""
        flags = [f"--passes {self.passes}"] if self.passes else []
        flags += [f"--rounds {self.rounds}"] if self.rounds else []
        flags += [f"--box-size-sigma {self.box_size_sigma_px:g}"] if self.box_size_sigma_px else []
        flags += [f"--gnss {self.gnss}"] if self.gnss != "fleet" else []
        flags += [f"--bulk-every {self.bulk_every}"] if self.bulk_every is not None else []
        flags += [f"--gnss-rate {self.gnss_rate_hz:g}"] if self.gnss_rate_hz else []
        if self.panel_size_rel_sigma is not None:
            flags += [f"--panel-size-sigma {self.panel_size_rel_sigma:g}"]
        flags += [] if self.shared_floor else ["--no-shared-floor"]
        flags += (
            [] if self.map_floor == FleetEvalConfig.map_floor else [f"--map-floor {self.map_floor}"]
        )
        flags += ["--calibrate-floor"] if self.calibrate_floor else []
        return flags + (["--quick"] if self.quick else [])


def run_fleet_job(opts: FleetRunOptions) -> dict:
    """One run (its result) or, with ``opts.seeds``, every seed's (the summary). Raises
    :class:`SeedRunError` when a separate seed's run (``jobs`` > 1) fails."""
    out = Path(opts.out)
    out.mkdir(parents=True, exist_ok=True)
    if not opts.seeds:
        return run_fleet_once(opts, out, opts.seed)
    rows = run_seeds_apart(opts, out) if opts.jobs > 1 else {}
    for k, seed in enumerate(opts.seeds, start=1):
        if seed not in rows:
            print(f"fleet: seed {seed} ({k}/{len(opts.seeds)})", file=sys.stderr, flush=True)
            rows[seed] = seed_row(run_fleet_once(opts, out / f"seed-{seed}", seed))
    summary = summarise_seeds(rows)
    flags = [f"--out {opts.out}", f"--seeds {','.join(map(str, opts.seeds))}"]
    flags += [f"--jobs {opts.jobs}"] if opts.jobs > 1 else []
    summary["meta"] = {
        "command": "hdmap eval fleet " + " ".join(flags + opts.run_flags()),
        "figures": [write_seed_figure(summary, out).name],
    }
    write_seed_summary(summary, out / "fleet_seeds.json", FLEET_COLUMNS, "fleet")
    return summary


def _check_alive(seed: int, log: Path, t0: float, limit: float) -> None:
    """Raise :class:`SeedRunError` if the run started at ``t0`` (monotonic) is past
    ``limit`` seconds or its ``log`` has not grown for ``SEED_STALL_TIMEOUT_S``."""
    now = time.monotonic()
    if now - t0 > limit:
        raise SeedRunError(f"seed {seed}: no result after {limit:.0f} s")
    quiet = time.time() - log.stat().st_mtime
    if quiet > SEED_STALL_TIMEOUT_S and now - t0 > SEED_STALL_TIMEOUT_S:
        raise SeedRunError(f"seed {seed}: its log {log} has not grown for {quiet:.0f} s")


def run_seeds_apart(opts: FleetRunOptions, out: Path) -> dict[int, dict]:
    """Each seed as its own ``hdmap eval fleet`` process, at most ``opts.jobs`` at once,
    its stderr in ``out/seed-<s>.log``; their summary rows. A failed or overdue run stops
    the others (:class:`SeedRunError` naming it). The runs watch this process
    (hdmap.runtime.orphan)."""
    env = dict(os.environ, PYTHONUNBUFFERED="1", **{PARENT_ENV: str(os.getpid())})
    extra = [word for flag in opts.run_flags() for word in flag.split()]
    extra += [] if opts.progress else ["--no-progress"]
    todo = list(opts.seeds)
    limit = max(SEED_STALL_TIMEOUT_S, SEED_RUN_S_PER_PASS * (opts.passes or FleetEvalConfig.passes))
    running: dict[int, tuple[subprocess.Popen, IO[bytes], float]] = {}
    rows: dict[int, dict] = {}
    bar = Progress(len(todo), "seeds", enabled=opts.progress)
    try:
        while todo or running:
            while todo and len(running) < opts.jobs:
                seed = todo.pop(0)
                argv = [sys.executable, "-m", "hdmap.cli", "eval", "fleet"]
                argv += ["--out", str(out / f"seed-{seed}"), "--seed", str(seed), *extra]
                log = open(out / f"seed-{seed}.log", "wb")  # closed when the run ends
                proc = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, env=env)
                running[seed] = (proc, log, time.monotonic())
                bar.note(f"fleet: seed {seed} started ({out / f'seed-{seed}.log'})")
            for seed, (proc, log, t0) in list(running.items()):
                rc = proc.poll()
                if rc is None:
                    _check_alive(seed, out / f"seed-{seed}.log", t0, limit)
                    continue
                del running[seed]
                log.close()
                if rc != 0:
                    tail = (out / f"seed-{seed}.log").read_text(errors="replace")[-2000:]
                    raise SeedRunError(f"seed {seed}: exit status {rc}\n{tail}")
                result = json.loads((out / f"seed-{seed}" / "fleet.json").read_text())
                rows[seed] = seed_row(result)
                bar.note(f"fleet: seed {seed} done")
                bar.update()
            time.sleep(0.5)
    finally:
        bar.close()
        for proc, log, _ in running.values():
            proc.terminate()
            try:
                proc.wait(60)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(10)
            log.close()
    return rows


def run_fleet_once(opts: FleetRunOptions, out: Path, seed: int) -> dict:
    """One fleet run with ``seed`` into ``out``; its result (also written there)."""
    out.mkdir(parents=True, exist_ok=True)
    cfg = FleetEvalConfig.quick(out) if opts.quick else FleetEvalConfig(out)
    if opts.passes:
        cfg = replace(cfg, passes=opts.passes)
    if opts.rounds:
        cfg = replace(cfg, rounds=opts.rounds)
    cfg = replace(
        cfg,
        seed=seed,
        box_size_sigma_px=opts.box_size_sigma_px,
        gnss=opts.gnss,
        shared_floor=opts.shared_floor,
        map_floor=opts.map_floor,
    )
    if opts.bulk_every is not None:
        cfg = replace(cfg, bulk_every=opts.bulk_every)
    if opts.gnss_rate_hz:
        cfg = replace(cfg, gnss_rate_hz=opts.gnss_rate_hz)
    if opts.panel_size_rel_sigma is not None:
        cfg = replace(cfg, panel_size_rel_sigma=opts.panel_size_rel_sigma)
    result, state, final = run_fleet_eval(cfg, progress_bar=opts.progress)
    result["meta"]["command"] = "hdmap eval fleet " + " ".join(
        [f"--out {out}", f"--passes {cfg.passes}", f"--rounds {cfg.rounds}"]
        + [f"--seed {cfg.seed}"]
        + ([f"--box-size-sigma {cfg.box_size_sigma_px:g}"] if cfg.box_size_sigma_px else [])
        + ([f"--gnss {cfg.gnss}"] if cfg.gnss != "fleet" else [])
        + [f"--bulk-every {cfg.bulk_every}"]
        + ([] if cfg.shared_floor else ["--no-shared-floor"])
        + [f"--map-floor {cfg.map_floor}"]
        + (["--quick"] if opts.quick else [])
    )
    measured = result["map_floor"]["measured"]
    if opts.calibrate_floor:
        if measured is None:
            raise SeedRunError(f"seed {seed}: too few signs to measure the map floor")
        command = result["meta"]["command"] + " --calibrate-floor"
        record_floor(cfg.noise().name, measured, command, cfg.seed)
        print(f"fleet: map floor of {cfg.noise().name} written to {FLOOR_FILE}", file=sys.stderr)
    figures = write_fleet_figures(result, state.world, final, out)
    result["meta"]["figures"] = [f.name for f in figures]
    path = out / "fleet.json"
    write_json(result, path)
    print(format_fleet_table(result), file=sys.stderr)
    print(f"fleet: wrote {path} and {len(figures)} figures", file=sys.stderr, flush=True)
    return result


def format_fleet_table(result: dict) -> str:
    """Recall, precision, duplicates, error, coverage and association per bin of passes,
    and the verdicts at 50+ passes."""
    head = (
        f"{'passes':>9} {'signs':>5} {'recall':>6} {'lms':>5} {'prec':>5} {'dup':>3} "
        f"{'mean m':>6} {'p95 m':>6} {'in95':>5} {'assoc':>6}"
    )
    lines = [head, "-" * len(head)]

    def f(v: object, fmt: str) -> str:
        return format(v, fmt) if isinstance(v, int | float) else "-"

    for r in result["by_passes"]:
        hi = r["passes_hi"]
        rng = f"{r['passes_lo']}-{hi - 1}" if hi else f"{r['passes_lo']}+"
        lines.append(
            f"{rng:>9} {r['signs']:>5} {f(r['recall'], '.3f'):>6} {r['landmarks']:>5} "
            f"{f(r['precision'], '.3f'):>5} {r['duplicated']:>3} {f(r['mean_err_m'], '.2f'):>6} "
            f"{f(r['p95_err_m'], '.2f'):>6} {f(r['coverage95'], '.2f'):>5} "
            f"{f(r['assoc_right'], '.3f'):>6}"
        )
    t = result.get("targets_at_50_passes", {})
    if t.get("evaluated"):
        verdicts = ", ".join(f"{k} {v}" for k, v in t["pass"].items())
        lines.append(f"targets at 50+ passes: {verdicts}")
    return "\n".join(lines)
