"""Figures of the fleet evaluation: metrics per passes past a sign, and the final map."""

from __future__ import annotations

from pathlib import Path

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from fleetsim.mapplot import plot_map
from fleetsim.world import World
from schemas import Landmarks


def write_fleet_figures(result: dict, world: World, final: Landmarks, out: Path) -> list[Path]:
    rows = [r for r in result["by_passes"] if r["mean_err_m"] is not None]
    x = [r["passes_lo"] for r in rows]
    fig = Figure(figsize=(13, 4), dpi=110)
    FigureCanvasAgg(fig)
    ax1, ax2, ax3 = (fig.add_subplot(1, 3, k) for k in (1, 2, 3))
    ax1.plot(x, [r["mean_err_m"] for r in rows], "o-", label="mean")
    ax1.plot(x, [r["p95_err_m"] for r in rows], "s--", label="95th percentile")
    ax1.axhline(1.0, color="C0", ls=":", lw=0.8)
    ax1.axhline(2.5, color="C1", ls=":", lw=0.8)
    ax1.set_xscale("log")
    ax1.set_xlabel("passes past the sign (bin start)")
    ax1.set_ylabel("horizontal error (m)")
    ax1.legend()
    ax1.grid(alpha=0.3)
    ax2.plot(x, [r["coverage95"] for r in rows], "o-")
    ax2.axhspan(0.90, 0.98, color="0.9")
    ax2.set_ylim(0, 1.02)
    ax2.set_xscale("log")
    ax2.set_xlabel("passes past the sign (bin start)")
    ax2.set_ylabel("truth inside reported 95% ellipse")
    ax2.grid(alpha=0.3)
    for key, label in (("recall", "recall"), ("precision", "precision"), ("assoc_right", "assoc")):
        y = [r[key] if r[key] is not None else float("nan") for r in rows]
        ax3.plot(x, y, "o-", label=label)
    ax3.set_ylim(0, 1.02)
    ax3.set_xscale("log")
    ax3.set_xlabel("passes past the sign (bin start)")
    ax3.legend()
    ax3.grid(alpha=0.3)
    fig.suptitle(f"Fleet evaluation, {result['meta']['town']}", fontsize=9)
    fig.tight_layout()
    p1 = out / "fleet_by_passes.png"
    fig.savefig(p1)
    p2 = out / "fleet_map.png"
    plot_map(world, final, p2, title=f"Helsinki after {result['meta']['passes']} passes")
    return [p1, p2]


def write_seed_figure(summary: dict, out: Path) -> Path:
    """``fleet_seeds.png``: per seed the figures nearest the targets, with the targets."""
    seeds = summary["seeds"]
    rows = [summary["per_seed"][str(s)] for s in seeds]
    x = list(range(len(seeds)))

    def series(key: str) -> list[float]:
        return [r[key] if isinstance(r.get(key), int | float) else float("nan") for r in rows]

    fig = Figure(figsize=(13, 3.6), dpi=110)
    FigureCanvasAgg(fig)
    axes = [fig.add_subplot(1, 4, k) for k in (1, 2, 3, 4)]
    panels = [
        ([("mean_err_m", "mean"), ("p95_err_m", "p95")], "horizontal error (m)", [1.0, 2.5]),
        ([("coverage95_from_30", "coverage from 30")], "truth inside 95% ellipse", [0.9, 0.98]),
        (
            [("recall", "recall"), ("precision", "precision"), ("assoc_right", "assoc right")],
            "share at 50+ passes",
            [0.95, 0.97],
        ),
        (
            [("duplicated", "duplicates 50+"), ("young_duplicated", "duplicates 3-4")],
            "landmarks",
            [0.0],
        ),
    ]
    for ax, (keys, label, lines) in zip(axes, panels, strict=True):
        for k, name in keys:
            ax.plot(x, series(k), "o", label=name)
        for v in lines:
            ax.axhline(v, color="0.5", ls=":", lw=0.8)
        ax.set_xticks(x, [str(s) for s in seeds])
        ax.set_xlabel("seed")
        ax.set_ylabel(label)
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    fig.suptitle("Fleet evaluation per seed (targets dotted)", fontsize=9)
    fig.tight_layout()
    path = out / "fleet_seeds.png"
    fig.savefig(path)
    return path
