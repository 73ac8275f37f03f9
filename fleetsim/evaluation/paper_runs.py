"""The paper simulation as a job (``hdmap eval paper-sim``): one seed, or several summarised.

One run (:func:`run_paper_sim`, ours vs the paper's estimator) writes ``out/paper_sim.json``
and the PNG figures (:func:`fleetsim.evaluation.paper_plots.write_figures`) and prints its
claims on stderr. With ``seeds``, each seed runs into ``out/seed-<s>/`` and
``out/paper_sim_seeds.json`` summarises the claims over them
(:func:`fleetsim.evaluation.fleet_seeds.summarise_seeds` of
:func:`fleetsim.evaluation.paper_sim.claims_row`).
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

from fleetsim.evaluation.fleet_seeds import summarise_seeds
from fleetsim.evaluation.paper_plots import write_figures
from fleetsim.evaluation.paper_sim import SEED_COLUMNS, claims_row, run_paper_sim
from fleetsim.evaluation.results import write_json, write_seed_summary


@dataclass(frozen=True)
class PaperSimOptions:
    out: Path
    seed: int = 1
    seeds: tuple[int, ...] = ()
    """Instead of ``seed``: run each into ``out/seed-<s>/`` and summarise them."""
    trials: int | None = None
    """Monte-Carlo trials per error model; None: 500 (``quick``: 40)."""
    max_passes: int | None = None
    """Passings per trial; None: 1000 (``quick``: 100)."""
    quick: bool = False
    """A small run for the test suite (one process)."""
    workers: int = 2
    """Processes, one error model each (``quick``: 1)."""
    models: tuple[str, ...] = ()
    """Error models; empty: white, correlated, correlated_equal (``quick``: white,
    correlated)."""
    progress: bool = False
    """A progress line of the passings on stderr (``hdmap eval``: unless ``--no-progress``)."""

    def run_trials(self) -> int:
        return self.trials or (40 if self.quick else 500)

    def run_passes(self) -> int:
        return self.max_passes or (100 if self.quick else 1000)

    def run_workers(self) -> int:
        return 1 if self.quick else max(1, int(self.workers or 1))

    def run_models(self) -> tuple[str, ...]:
        if self.models:
            return self.models
        return (
            ("white", "correlated") if self.quick else ("white", "correlated", "correlated_equal")
        )


def run_paper_sim_job(opts: PaperSimOptions) -> dict:
    """One run (its result) or, with ``opts.seeds``, every seed's (the summary)."""
    if not opts.seeds:
        return run_paper_sim_once(opts, Path(opts.out), int(opts.seed))
    out = Path(opts.out)
    seeds = opts.seeds
    rows = {}
    for k, seed in enumerate(seeds, start=1):
        print(f"paper-sim: seed {seed} ({k}/{len(seeds)})", file=sys.stderr, flush=True)
        rows[seed] = claims_row(run_paper_sim_once(opts, out / f"seed-{seed}", seed))
    summary = summarise_seeds(rows)
    flags = [f"--out {opts.out}", f"--seeds {','.join(map(str, seeds))}"]
    flags += [f"--trials {opts.trials}"] if opts.trials else []
    flags += [f"--max-passes {opts.max_passes}"] if opts.max_passes else []
    if opts.quick:
        flags.append("--quick")
    summary["meta"] = {"command": "hdmap eval paper-sim " + " ".join(flags)}
    write_seed_summary(summary, out / "paper_sim_seeds.json", SEED_COLUMNS, "paper-sim")
    return summary


def run_paper_sim_once(opts: PaperSimOptions, out: Path, seed: int) -> dict:
    """One paper-sim run with ``seed`` into ``out``; its result (also written there)."""
    quick = opts.quick
    trials, passes = opts.run_trials(), opts.run_passes()
    workers, models = opts.run_workers(), opts.run_models()
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
        progress_bar=opts.progress,
    )
    result["meta"]["command"] = "hdmap eval paper-sim " + " ".join(
        [f"--out {out}", f"--trials {trials}", f"--max-passes {passes}", f"--seed {seed}"]
        + (["--quick"] if quick else [])
    )
    figures = write_figures(result, out)
    result["meta"]["figures"] = [f.name for f in figures]
    result["meta"]["wall_seconds"] = time.perf_counter() - t0
    path = out / "paper_sim.json"
    write_json(result, path)
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
