"""``hdmap eval changes`` over one seed or several: ``DIR/changes.json`` and the timeline
``DIR/changes.png`` (:mod:`fleetsim.evaluation.changes_eval` runs one seed).

With several seeds the JSON holds each seed's result under ``seeds`` and the summary
keys pooled over them: the passes to reflect every event of a kind pooled before the
median and p95, the false and rogue revocations summed.
"""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

from fleetsim.evaluation.changes_eval import ChangesEvalConfig, run_changes_eval
from fleetsim.evaluation.changes_scoring import event_key as key_of
from fleetsim.evaluation.changes_scoring import passes_keys

KIND_COLOURS = {
    "remove": "tab:red",
    "move": "tab:orange",
    "replace": "tab:purple",
    "add": "tab:green",
    "temporary": "tab:blue",
}


def event_key(e: dict) -> str:
    """The summary key of an event (``removal``, ``move``, ..., ``temporary_up``)."""
    return key_of(e["kind"], e["present"])


def pooled(results: dict[int, dict]) -> dict:
    """The summary keys over several seeds' results: every event of a kind pooled before
    the median and p95, the revocations summed."""
    out = passes_keys(
        [
            (event_key(e), e["passes_to_reflect"], e["passes_to_locate"])
            for r in results.values()
            for e in r["events"]
        ]
    )
    for key in ("false_revocations", "rogue_revocations"):
        out[key] = int(sum(r[key] for r in results.values()))
    return out


def plot_timeline(results: dict[int, dict], png: Path) -> None:
    """Per seed, each change from its time to when the map reflected it (in passes of the
    whole fleet); and the map's doubtful landmarks and false revocations per round."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 3.0 + 0.9 * len(results)))
    FigureCanvasAgg(fig)
    axes = fig.subplots(len(results) + 1, 1, squeeze=False)[:, 0]
    for ax, (seed, r) in zip(axes, sorted(results.items()), strict=False):
        interval = r["config"]["pass_interval_s"]
        start = r["start_time"]
        end = r["rounds"][-1]["passes"]
        for y, e in enumerate(r["events"]):
            x0 = (e["t"] - start) / interval
            done = e["hours_to_reflect"]
            x1 = end if done is None else x0 + done * 3600.0 / interval
            colour = KIND_COLOURS.get(e["kind"], "k")
            ax.plot([x0, x1], [y, y], color=colour, lw=3, alpha=0.8)
            mark = "x" if done is None else "o"
            ax.plot([x1], [y], mark, color=colour)
            label = f"{event_key(e)}: {e['passes_to_reflect'] if done is not None else 'not yet'}"
            ax.text(x1 + end * 0.005, y, label, va="center", fontsize=7)
        ax.set_ylim(-1, len(r["events"]))
        ax.set_yticks([])
        ax.set_xlim(0, end * 1.12)
        ax.set_title(
            f"seed {seed}: changes from when they happen to when the map shows them "
            "(label: passes past the place)",
            fontsize=9,
        )
    ax = axes[-1]
    for seed, r in sorted(results.items()):
        x = [row["passes"] for row in r["rounds"]]
        ax.plot(x, [row["doubtful"] for row in r["rounds"]], label=f"seed {seed}: doubtful")
        ax.plot(
            x,
            [row["false_revocations"] for row in r["rounds"]],
            "--",
            label=f"seed {seed}: false revocations",
        )
    ax.set_xlabel("passes of the fleet")
    ax.legend(fontsize=7, loc="upper left")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(png, dpi=110)


def changes_table(report: dict) -> str:
    """One line per change of a one-seed report: what, when, passes until the map showed it."""
    lines = [f"{'change':>10} {'at pass':>8} {'passes to show it':>18} {'hours':>6}"]
    start, interval = report["start_time"], report["config"]["pass_interval_s"]
    for e in report["events"]:
        p = e["passes_to_reflect"]
        h = e["hours_to_reflect"]
        lines.append(
            f"{event_key(e):>10} {(e['t'] - start) / interval:8.0f} "
            f"{'not yet' if p is None else p:>18} {'-' if h is None else f'{h:.2f}':>6}"
        )
    lines.append(
        f"false revocations {report['false_revocations']}, by the blind vehicle "
        f"{report['rogue_revocations']} (it reported {report['rogue']['reported_landmarks']} "
        "landmarks missing)"
    )
    return "\n".join(lines)


def run_changes_job(
    cfg: ChangesEvalConfig, seeds: tuple[int, ...] = (), progress: bool = False
) -> dict:
    """Run the seeds (``cfg.seed`` alone when none are given) one after another, write
    ``changes.json`` and ``changes.png`` under ``cfg.out``; returns the JSON. ``progress``:
    a progress line of each seed's passes on stderr."""
    cfg.out.mkdir(parents=True, exist_ok=True)
    results: dict[int, dict] = {}
    for k, seed in enumerate(seeds or (cfg.seed,), start=1):
        one = replace(cfg, seed=seed, out=cfg.out / f"seed{seed}" if seeds else cfg.out)
        if len(seeds) > 1:
            print(f"changes: seed {seed} ({k}/{len(seeds)})", file=sys.stderr, flush=True)
        results[seed] = run_changes_eval(one, progress_bar=progress)
    if len(results) == 1:
        report = next(iter(results.values()))
    else:
        report = {**pooled(results), "seeds": {str(s): r for s, r in results.items()}}
    (cfg.out / "changes.json").write_text(json.dumps(report, indent=1, default=str))
    plot_timeline(results, cfg.out / "changes.png")
    keys = {k: v for k, v in report.items() if k.endswith(("_passes", "_revocations"))}
    print(json.dumps(keys, indent=1), file=sys.stderr)
    print(f"wrote {cfg.out / 'changes.json'}, {cfg.out / 'changes.png'}", file=sys.stderr)
    return report
