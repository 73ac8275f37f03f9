"""Figures of the fleet evaluation: metrics per passes past a sign, the final map, and the
final errors as arrows (their common offset shows there)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from fleetsim.mapplot import plot_map, town_axes
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
    return [p1, p2, write_error_map(result, world, out)]


ARROW_SCALE = 20.0
"""Error arrows are drawn this many times their length."""


def write_error_map(result: dict, world: World, out: Path, min_passes: int = 30) -> Path:
    """``fleet_errors.png``: per found sign with ``min_passes`` or more passes its error (East,
    North) as an arrow, ``ARROW_SCALE`` times its length, green inside its 95 % ellipse and
    red outside; the mean error of those signs as one arrow in the corner: signs that share
    passes share their GNSS biases, and that common offset moves them together."""
    signs = [
        s
        for s in result.get("signs", [])
        if s["found"] and s["passes"] >= min_passes and s["err_enu_m"] is not None
    ]
    fig, ax = town_axes(world, (10, 9.5))
    pos = world.signs.position
    ax.scatter(pos[:, 0], pos[:, 1], s=6, color="0.6", zorder=1, label="sign")
    mean = np.zeros(2)
    if signs:
        row = np.array([s["sign"] for s in signs])
        e = np.array([s["err_enu_m"][:2] for s in signs])
        inside = np.array([bool(s["inside95"]) for s in signs])
        for ok, colour, label in ((True, "tab:green", "inside"), (False, "tab:red", "outside")):
            m = inside == ok
            text = f"error x{ARROW_SCALE:g}, {label} its 95% ellipse ({m.sum()})"
            ax.quiver(pos[row[m], 0], pos[row[m], 1], e[m, 0], e[m, 1], color=colour,
                      angles="xy", scale_units="xy", scale=1.0 / ARROW_SCALE, width=0.003,
                      label=text)  # fmt: skip
        mean = e.mean(axis=0)
        x0, y0 = pos[:, 0].max(), pos[:, 1].min()
        k = 5.0 * ARROW_SCALE
        ax.quiver([x0], [y0], [mean[0]], [mean[1]], color="black", angles="xy",
                  scale_units="xy", scale=1.0 / k, width=0.006,
                  label=f"mean error x{k:g}: ({mean[0]:+.2f}, {mean[1]:+.2f}) m")  # fmt: skip
    ax.set_aspect("equal")
    ax.set_xlabel("East (m)")
    ax.set_ylabel("North (m)")
    ax.legend(loc="upper left", bbox_to_anchor=(0.0, -0.07), ncol=2, fontsize=8)
    ax.set_title(
        f"Landmark errors, signs with {min_passes}+ passes, after {result['meta']['passes']} "
        f"passes (seed {result['meta']['seed']})",
        fontsize=9,
    )
    fig.tight_layout()
    path = out / "fleet_errors.png"
    fig.savefig(path)
    return path


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
