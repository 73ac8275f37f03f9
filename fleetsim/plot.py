"""Plots of simulated drives in the world's local metres (matplotlib, Agg, no pyplot).

:func:`plot_vehicle_rays` draws the roads, buildings, true signs (one marker and
colour per class), the true camera track, the geolocated camera centres and the
horizontal projection of every ray, drawn to its range estimate (or a default
length when it has none); rays of false positives are dashed grey.
"""

from __future__ import annotations

from pathlib import Path as FsPath

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Rectangle
from numpy.typing import NDArray

from fleetsim.drive import DriveTruth
from fleetsim.world import World
from hdmap.geo.signs import CATALOG, SignCatalog

Array = NDArray[np.float64]

_MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*", "h", "<", ">", "p", "d")


def class_style(code: int) -> tuple[str, tuple[float, float, float, float]]:
    """A stable (marker, colour) per sign class code."""
    from matplotlib import colormaps

    cmap = colormaps["tab20"]
    return _MARKERS[code % len(_MARKERS)], cmap((code * 7) % 20 / 20.0)


def plot_vehicle_rays(
    world: World,
    truth: DriveTruth,
    origin_enu: Array,
    direction_enu: Array,
    range_m: Array,
    sign_class: NDArray,
    out_png: str | FsPath,
    *,
    title: str = "",
    default_length_m: float = 40.0,
    margin_m: float = 25.0,
    catalog: SignCatalog = CATALOG,
) -> None:
    """Write a PNG of one pass's rays (all positions in the world's ENU metres)."""
    o = np.asarray(origin_enu, float).reshape(-1, 3)
    d = np.asarray(direction_enu, float).reshape(-1, 3)
    rng = np.asarray(range_m, float).reshape(-1)
    dh = d[:, :2]
    norm_h = np.maximum(np.linalg.norm(dh, axis=1), 1e-9)
    length = np.where(rng > 0, rng * norm_h, default_length_m)
    end = o[:, :2] + dh / norm_h[:, None] * length[:, None]

    cam = truth.camera_enu[:, :2]
    # Frame the rays and the signs they truly saw; the rest of the track may run off.
    seen = world.signs.index_of(truth.sign_id[truth.sign_id >= 0])
    pts = np.vstack([o[:, :2], end, world.signs.position[seen, :2]]) if len(o) else cam
    x0, y0 = pts.min(axis=0) - margin_m
    x1, y1 = pts.max(axis=0) + margin_m
    aspect = (y1 - y0) / max(x1 - x0, 1e-9)
    fig = Figure(figsize=(11.5, float(np.clip(8.0 * aspect + 1.2, 4.5, 11.0))), dpi=110)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)

    for b in world.buildings:
        ax.add_patch(Rectangle((b[0], b[1]), b[2] - b[0], b[3] - b[1], color="0.92", zorder=0))
    for seg in world.roads():
        ax.plot(seg[:, 0], seg[:, 1], color="0.75", lw=7, solid_capstyle="butt", zorder=1)
        ax.plot(seg[:, 0], seg[:, 1], color="white", lw=0.8, ls=(0, (6, 6)), zorder=1)

    ax.plot(cam[:, 0], cam[:, 1], color="black", lw=1.2, zorder=3, label="true camera track")

    sc = np.asarray(sign_class, np.int64).reshape(-1)
    fp = truth.sign_id < 0
    for i in range(len(o)):
        _, colour = class_style(int(sc[i]))
        style = {"color": "0.45", "ls": "--", "lw": 0.8} if fp[i] else {"color": colour, "lw": 0.7}
        ax.plot([o[i, 0], end[i, 0]], [o[i, 1], end[i, 1]], alpha=0.75, zorder=2, **style)
    ax.scatter(o[:, 0], o[:, 1], s=9, color="tab:red", zorder=4, label="geolocated camera centres")
    ends = rng > 0
    ax.scatter(end[ends, 0], end[ends, 1], s=5, color="0.2", marker=".", zorder=4,
               label="range estimates")  # fmt: skip

    sg = world.signs
    inside = (
        (sg.position[:, 0] >= x0) & (sg.position[:, 0] <= x1)
        & (sg.position[:, 1] >= y0) & (sg.position[:, 1] <= y1)
    )  # fmt: skip
    for code in np.unique(sg.sign_class[inside]):
        sel = inside & (sg.sign_class == code)
        marker, colour = class_style(int(code))
        p = sg.position[sel]
        ax.scatter(p[:, 0], p[:, 1], marker=marker, s=90, color=colour, edgecolor="black",
                   zorder=5, label=f"sign: {catalog.by_code(int(code)).name}")  # fmt: skip
        f = sg.facing[sel]
        ax.quiver(p[:, 0], p[:, 1], f[:, 0], f[:, 1], color=colour, scale=30, width=0.003,
                  zorder=5)  # fmt: skip
    if fp.any():
        ax.plot([], [], color="0.45", ls="--", label="ray of a false positive")

    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.set_xlabel("East [m]")
    ax.set_ylabel("North [m]")
    ax.grid(True, color="0.85", lw=0.5)
    ax.set_title(title or "Projection lines of one pass")
    handles, labels = ax.get_legend_handles_labels()
    handles.insert(0, Line2D([], [], color="0.6", lw=0.8))
    labels.insert(0, f"ray (to its range, else {default_length_m:g} m)")
    ax.legend(handles, labels, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    fig.tight_layout()
    fig.savefig(str(out_png))
