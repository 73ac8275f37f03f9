"""``hdmap eval``: accuracy evaluations.

Sub-subcommands (each ``add_<name>_arguments(parser)`` / ``run_<name>(args)``, registered
in :data:`EVALUATIONS`):

- ``paper-sim``: the paper's simulation (section IV-A), ours vs the paper's estimator,
  written to ``DIR/paper_sim.json`` and PNG figures (:mod:`fleetsim.evaluation.paper_sim`);
  ``--seeds`` runs several seeds and summarises the claims (``DIR/paper_sim_seeds.json``).
- ``fleet``: central Helsinki through the real pipeline with the realistic fleet noise,
  written to ``DIR/fleet.json`` and PNG figures (:mod:`fleetsim.evaluation.fleet_eval`).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path


def add_paper_sim_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.add_argument(
        "--trials",
        type=int,
        default=None,
        help="Monte-Carlo trials per error model (default 500; --quick 40)",
    )
    p.add_argument(
        "--max-passes",
        type=int,
        default=None,
        help="passings per trial (default 1000; --quick 100)",
    )
    p.add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    p.add_argument(
        "--seeds",
        type=_seed_list,
        default=None,
        metavar="S,S,...",
        help="instead of --seed: run each seed into DIR/seed-<s>/ and summarise the claims "
        "over them (DIR/paper_sim_seeds.json)",
    )
    p.add_argument(
        "--quick", action="store_true", help="small run for the test suite (< 30 s, one process)"
    )
    p.add_argument(
        "--workers",
        type=int,
        default=2,
        help="processes, one error model each (default 2; --quick forces 1)",
    )
    p.add_argument(
        "--models",
        default=None,
        help="comma-separated error models (default white,correlated,correlated_equal; "
        "--quick: white,correlated)",
    )


def _json_default(o: object) -> object:
    if hasattr(o, "tolist"):
        return o.tolist()
    if hasattr(o, "item"):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _clean(o: object) -> object:
    """NaN/inf -> None so the file is strict JSON."""
    if isinstance(o, float):
        return o if math.isfinite(o) else None
    if isinstance(o, dict):
        return {k: _clean(v) for k, v in o.items()}
    if isinstance(o, list | tuple):
        return [_clean(v) for v in o]
    return o


def run_paper_sim_command(args: argparse.Namespace) -> int:
    seeds = getattr(args, "seeds", None)
    if not seeds:
        _run_paper_once(args, Path(args.out), int(args.seed))
        return 0
    from fleetsim.evaluation.fleet_seeds import summarise_seeds
    from fleetsim.evaluation.paper_sim import SEED_COLUMNS, claims_row

    out = Path(args.out)
    rows = {}
    for k, seed in enumerate(seeds, start=1):
        print(f"paper-sim: seed {seed} ({k}/{len(seeds)})", file=sys.stderr, flush=True)
        rows[seed] = claims_row(_run_paper_once(args, out / f"seed-{seed}", seed))
    summary = summarise_seeds(rows)
    opts = [f"--out {args.out}", f"--seeds {','.join(map(str, seeds))}"]
    opts += [f"--trials {args.trials}"] if args.trials else []
    opts += [f"--max-passes {args.max_passes}"] if args.max_passes else []
    if getattr(args, "quick", False):
        opts.append("--quick")
    summary["meta"] = {"command": "hdmap eval paper-sim " + " ".join(opts)}
    _write_seed_summary(summary, out / "paper_sim_seeds.json", SEED_COLUMNS, "paper-sim")
    return 0


def _write_seed_summary(
    summary: dict, path: Path, columns: list[tuple[str, str, str]], prog: str
) -> None:
    """Write a ``--seeds`` summary as JSON and print its table (``columns``, see
    :func:`fleetsim.evaluation.fleet_seeds.format_seed_table`)."""
    from fleetsim.evaluation.fleet_seeds import format_seed_table

    path.write_text(json.dumps(_clean(summary), indent=1, default=_json_default))
    print(format_seed_table(summary, columns), file=sys.stderr)
    print(f"{prog}: wrote {path}", file=sys.stderr, flush=True)


def _run_paper_once(args: argparse.Namespace, out: Path, seed: int) -> dict:
    """One paper-sim run with ``seed`` into ``out``; its result (also written there)."""
    from fleetsim.evaluation.paper_plots import write_figures
    from fleetsim.evaluation.paper_sim import run_paper_sim

    quick = bool(getattr(args, "quick", False))
    trials = args.trials or (40 if quick else 500)
    passes = args.max_passes or (100 if quick else 1000)
    workers = 1 if quick else max(1, int(getattr(args, "workers", 2) or 1))
    names = getattr(args, "models", None) or (
        "white,correlated" if quick else "white,correlated,correlated_equal"
    )
    models = tuple(m for m in str(names).split(",") if m)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    print(
        f"paper-sim: {trials} trials x {passes} passings, models {', '.join(models)}, "
        f"seed {seed}, {workers} process(es)",
        file=sys.stderr,
        flush=True,
    )
    result = run_paper_sim(
        trials=trials,
        max_passes=passes,
        seed=seed,
        models=models,
        workers=workers,
        pilot=(20, 30) if quick else (100, 100),
    )
    result["meta"]["command"] = "hdmap eval paper-sim " + " ".join(
        [f"--out {out}", f"--trials {trials}", f"--max-passes {passes}", f"--seed {seed}"]
        + (["--quick"] if quick else [])
    )
    figures = write_figures(result, out)
    result["meta"]["figures"] = [f.name for f in figures]
    result["meta"]["wall_seconds"] = time.perf_counter() - t0
    path = out / "paper_sim.json"
    path.write_text(json.dumps(_clean(result), indent=1, default=_json_default))
    keys = [
        k
        for k in result
        if k.startswith(("slope_", "coverage_", "paper_plateau", "independent_", "claims_"))
    ]
    for k in keys:
        v = result[k]
        print(f"  {k:45s} {v:.3f}" if isinstance(v, float) else f"  {k:45s} {v}", file=sys.stderr)
    print(
        f"paper-sim: wrote {path} and {len(figures)} figures in "
        f"{result['meta']['wall_seconds']:.1f} s",
        file=sys.stderr,
        flush=True,
    )
    return result


def add_fleet_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.add_argument("--passes", type=int, default=None, help="passes in all (default 160)")
    p.add_argument("--rounds", type=int, default=None, help="scoring rounds (default 8)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--seeds",
        type=_seed_list,
        default=None,
        metavar="S,S,...",
        help="instead of --seed: run each seed into DIR/seed-<s>/ and summarise them "
        "(DIR/fleet_seeds.json)",
    )
    p.add_argument(
        "--jobs",
        type=_positive,
        default=1,
        metavar="N",
        help="with --seeds: runs at once, each its own process with a router and four "
        "services (2 suits a 2-core machine; default 1)",
    )
    p.add_argument(
        "--box-size-sigma",
        type=_non_negative,
        default=0.0,
        metavar="PX",
        help="noise on the detected boxes' width and height, px (default 0: the issue's "
        "noise is on the box centre only; 4.24 is what the vehicle model assumes)",
    )
    p.add_argument("--quick", action="store_true", help="small run for the test suite")


def _positive(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"need a whole number >= 1, got {text!r}")
    return n


def _non_negative(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not (math.isfinite(v) and v >= 0.0):
        raise argparse.ArgumentTypeError(f"need a finite number >= 0, got {text!r}")
    return v


def _seed_list(text: str) -> list[int]:
    try:
        seeds = [int(s) for s in text.split(",") if s.strip()]
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"not a comma-separated list of ints: {text!r}") from exc
    if not seeds or len(set(seeds)) != len(seeds):
        raise argparse.ArgumentTypeError(f"need distinct seeds, got {text!r}")
    return seeds


def run_fleet_command(args: argparse.Namespace) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if not args.seeds:
        _run_fleet_once(args, out, args.seed)
        return 0
    from fleetsim.evaluation.fleet_plots import write_seed_figure
    from fleetsim.evaluation.fleet_seeds import FLEET_COLUMNS, seed_row, summarise_seeds

    rows = {}
    if args.jobs > 1:
        try:
            rows = _run_seeds_apart(args, out)
        except RuntimeError as exc:
            print(f"fleet: {exc}", file=sys.stderr, flush=True)
            return 1
    for k, seed in enumerate(args.seeds, start=1):
        if seed not in rows:
            print(f"fleet: seed {seed} ({k}/{len(args.seeds)})", file=sys.stderr, flush=True)
            rows[seed] = seed_row(_run_fleet_once(args, out / f"seed-{seed}", seed))
    summary = summarise_seeds(rows)
    opts = [f"--out {args.out}", f"--seeds {','.join(map(str, args.seeds))}"]
    opts += [f"--jobs {args.jobs}"] if args.jobs > 1 else []
    summary["meta"] = {
        "command": "hdmap eval fleet " + " ".join(opts + _run_options(args)),
        "figures": [write_seed_figure(summary, out).name],
    }
    _write_seed_summary(summary, out / "fleet_seeds.json", FLEET_COLUMNS, "fleet")
    return 0


SEED_RUN_TIMEOUT_S = 1800.0
"""A seed's run that has not finished after this is stopped (and the command fails)."""


def _run_options(args: argparse.Namespace) -> list[str]:
    """The options every seed's run shares (``--passes``, ``--rounds``, ``--quick``)."""
    opts = [f"--passes {args.passes}"] if args.passes else []
    opts += [f"--rounds {args.rounds}"] if args.rounds else []
    opts += [f"--box-size-sigma {args.box_size_sigma:g}"] if args.box_size_sigma else []
    return opts + (["--quick"] if args.quick else [])


def _run_seeds_apart(args: argparse.Namespace, out: Path) -> dict[int, dict]:
    """Each seed as its own ``hdmap eval fleet`` process, at most ``args.jobs`` at once,
    its stderr in ``DIR/seed-<s>.log``; their summary rows. A failed or overdue run stops
    the others (RuntimeError naming it). The runs watch this process (hdmap.runtime.orphan)."""
    import os
    import subprocess
    from typing import IO

    from fleetsim.evaluation.fleet_seeds import seed_row
    from hdmap.runtime.orphan import PARENT_ENV

    env = dict(os.environ, PYTHONUNBUFFERED="1", **{PARENT_ENV: str(os.getpid())})
    extra = [word for opt in _run_options(args) for word in opt.split()]
    todo = list(args.seeds)
    running: dict[int, tuple[subprocess.Popen, IO[bytes], float]] = {}
    rows: dict[int, dict] = {}
    try:
        while todo or running:
            while todo and len(running) < args.jobs:
                seed = todo.pop(0)
                argv = [sys.executable, "-m", "hdmap.cli", "eval", "fleet"]
                argv += ["--out", str(out / f"seed-{seed}"), "--seed", str(seed), *extra]
                log = open(out / f"seed-{seed}.log", "wb")  # closed when the run ends
                proc = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, env=env)
                running[seed] = (proc, log, time.monotonic())
                print(f"fleet: seed {seed} started ({out / f'seed-{seed}.log'})", file=sys.stderr)
            for seed, (proc, log, t0) in list(running.items()):
                rc = proc.poll()
                if rc is None:
                    if time.monotonic() - t0 > SEED_RUN_TIMEOUT_S:
                        raise RuntimeError(f"seed {seed}: no result after {SEED_RUN_TIMEOUT_S} s")
                    continue
                del running[seed]
                log.close()
                if rc != 0:
                    tail = (out / f"seed-{seed}.log").read_text(errors="replace")[-2000:]
                    raise RuntimeError(f"seed {seed}: exit status {rc}\n{tail}")
                result = json.loads((out / f"seed-{seed}" / "fleet.json").read_text())
                rows[seed] = seed_row(result)
                print(f"fleet: seed {seed} done", file=sys.stderr, flush=True)
            time.sleep(0.5)
    finally:
        for proc, log, _ in running.values():
            proc.terminate()
            try:
                proc.wait(60)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(10)
            log.close()
    return rows


def _run_fleet_once(args: argparse.Namespace, out: Path, seed: int) -> dict:
    from dataclasses import replace

    from fleetsim.evaluation.fleet_eval import FleetEvalConfig, run_fleet_eval
    from fleetsim.evaluation.fleet_plots import write_fleet_figures

    out.mkdir(parents=True, exist_ok=True)
    cfg = FleetEvalConfig.quick(out) if args.quick else FleetEvalConfig(out)
    if args.passes:
        cfg = replace(cfg, passes=args.passes)
    if args.rounds:
        cfg = replace(cfg, rounds=args.rounds)
    cfg = replace(cfg, seed=seed, box_size_sigma_px=args.box_size_sigma)
    result, state, final = run_fleet_eval(cfg)
    result["meta"]["command"] = "hdmap eval fleet " + " ".join(
        [f"--out {out}", f"--passes {cfg.passes}", f"--rounds {cfg.rounds}"]
        + [f"--seed {cfg.seed}"]
        + ([f"--box-size-sigma {cfg.box_size_sigma_px:g}"] if cfg.box_size_sigma_px else [])
        + (["--quick"] if args.quick else [])
    )
    figures = write_fleet_figures(result, state.world, final, out)
    result["meta"]["figures"] = [f.name for f in figures]
    path = out / "fleet.json"
    path.write_text(json.dumps(_clean(result), indent=1, default=_json_default))
    print(format_fleet_table(result), file=sys.stderr)
    print(f"fleet: wrote {path} and {len(figures)} figures", file=sys.stderr, flush=True)
    return result


def format_fleet_table(result: dict) -> str:
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


EVALUATIONS: dict[str, tuple[Callable, Callable, str]] = {
    "fleet": (
        add_fleet_arguments,
        run_fleet_command,
        "central Helsinki through the real pipeline: error, coverage, recall per passes",
    ),
    "paper-sim": (
        add_paper_sim_arguments,
        run_paper_sim_command,
        "the paper's simulation: ours vs the paper's estimator, convergence, coverage",
    ),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="evaluation", required=True, metavar="EVALUATION")
    for name, (add, run_fn, help_text) in EVALUATIONS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        add(p)
        p.set_defaults(_eval_run=run_fn)


def run(args: argparse.Namespace) -> int:
    fn = getattr(args, "_eval_run", None)
    if fn is None:  # called directly with a Namespace (tests): dispatch by name
        fn = EVALUATIONS[getattr(args, "evaluation", "paper-sim")][1]
    return int(fn(args) or 0)
