"""Plots of a map against the ground truth (Agg backend, no pyplot state)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Ellipse

from fleetsim.score import CHI2_95_2D, cov_en
from fleetsim.world import World
from schemas import Landmarks


def ellipse_params(c: np.ndarray, k2: float = CHI2_95_2D) -> tuple[float, float, float]:
    """(width, height, angle deg) of the k2 ellipse of a 2x2 covariance (E, N axes)."""
    w, v = np.linalg.eigh(c)
    w = np.clip(w, 0.0, None)
    angle = float(np.degrees(np.arctan2(v[1, 1], v[0, 1])))
    return 2 * np.sqrt(k2 * w[1]), 2 * np.sqrt(k2 * w[0]), angle


def town_axes(world: World, figsize: tuple[float, float] = (11, 10)) -> tuple[Figure, Axes]:
    """A figure with one axes showing the town's roads (local metres, grey)."""
    fig = Figure(figsize=figsize, dpi=110)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    for road in world.roads():
        ax.plot(road[:, 0], road[:, 1], color="0.85", lw=6, solid_capstyle="round", zorder=0)
    return fig, ax


def plot_map(
    world: World, lm: Landmarks, out_png: str | Path, title: str = "", zoom_sign: int | None = None
) -> None:
    """True signs, estimated landmarks and their 95% ellipses, roads, in local metres."""
    fig, ax = town_axes(world)
    t = world.signs.position
    ax.scatter(t[:, 0], t[:, 1], marker="x", s=40, color="black", label="true sign", zorder=3)
    if len(lm):
        est = world.frame.from_geodetic(lm.lat, lm.lon, lm.h)
        confirmed = lm.status == 1
        ax.scatter(
            est[confirmed, 0],
            est[confirmed, 1],
            s=14,
            color="tab:red",
            label="landmark (confirmed)",
            zorder=4,
        )
        ax.scatter(
            est[~confirmed, 0],
            est[~confirmed, 1],
            s=14,
            color="tab:orange",
            label="landmark (candidate)",
            zorder=4,
        )
        for c, p in zip(cov_en(lm.cov), est, strict=True):
            w, h, a = ellipse_params(c)
            ax.add_patch(
                Ellipse(
                    (p[0], p[1]),
                    w,
                    h,
                    angle=a,
                    fill=False,
                    lw=0.8,
                    color="tab:red",
                    alpha=0.7,
                    zorder=2,
                )
            )
    if zoom_sign is not None:
        c = t[zoom_sign]
        ax.set_xlim(c[0] - 15, c[0] + 15)
        ax.set_ylim(c[1] - 15, c[1] + 15)
    else:  # the town, not the largest ellipse (a young landmark's can be hundreds of metres)
        pts = [t[:, :2]] + (
            [world.frame.from_geodetic(lm.lat, lm.lon, lm.h)[:, :2]] if len(lm) else []
        )
        xy = np.concatenate(pts)
        lo, hi = xy.min(axis=0) - 30.0, xy.max(axis=0) + 30.0
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("East (m)")
    ax.set_ylabel("North (m)")
    ax.set_title(title or "Estimated landmarks (95% ellipses) vs true signs")
    ax.legend(loc="upper right", fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out_png)


def plot_convergence(rows: list[dict], out_png: str | Path, title: str = "") -> None:
    """Mean error and 95% coverage per round of passes."""
    fig = Figure(figsize=(10, 4), dpi=110)
    FigureCanvasAgg(fig)
    ax1, ax2 = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    x = [r["passes_per_sign"] for r in rows]
    ax1.plot(x, [r["mean_err_m"] for r in rows], "o-", label="mean")
    ax1.plot(x, [r["p95_err_m"] for r in rows], "s--", label="95th percentile")
    ax1.set_xlabel("passes per sign (median)")
    ax1.set_ylabel("horizontal error (m)")
    ax1.legend()
    ax1.grid(alpha=0.3)
    ax2.plot(x, [r["coverage95"] for r in rows], "o-", label="2D chi-square 95%")
    ax2.axhline(0.95, color="0.5", ls=":")
    ax2.set_ylim(0, 1.02)
    ax2.set_xlabel("passes per sign (median)")
    ax2.set_ylabel("truth inside reported 95% region")
    ax2.legend()
    ax2.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(out_png)
