"""``hdmap eval localize``: run the seeds (:mod:`fleetsim.evaluation.localize_eval`), write
``DIR/localize.json`` and ``DIR/localize.png`` (error against time, raw GNSS and map-aided,
with the reported 95 % radius; and the errors' distributions), print the headline."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from fleetsim.evaluation.localize_eval import (
    TARGETS,
    LocalizeEvalConfig,
    PassSeconds,
    run_localize_eval,
)
from fleetsim.evaluation.results import write_json

HEADLINE = (
    "gnss_p50_m",
    "gnss_p95_m",
    "map_aided_p50_m",
    "map_aided_p95_m",
    "coverage95",
    "map_aided_share",
    "map_aided_share_all",
    "map_frame_p50_m",
    "map_frame_p95_m",
    "matches_right_share",
)


def plot_localize(series: dict[int, list[PassSeconds]], report: dict, png: Path) -> None:
    """Top: every held-out pass of the first seed one after another, per second the raw
    GNSS error, the localiser's (map-aided seconds marked) and its reported 95 % radius
    (the ellipse's major semi-axis); the seconds before the condition shaded. Bottom: the
    distributions over all seeds after the condition (raw, map-aided, map frame)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 7.5))
    FigureCanvasAgg(fig)
    ax, ax2 = fig.subplots(2, 1, gridspec_kw={"height_ratios": [3, 2]})
    seed = min(series)
    x0 = 0.0
    for k, p in enumerate(series[seed]):
        x = x0 + p.t
        ax.plot(x, p.gnss_err, color="0.55", lw=1, label="raw GNSS" if k == 0 else None)
        out = np.where(p.aided, p.out_err, np.nan)
        ax.plot(x, out, color="C0", lw=1.3, label="map-aided" if k == 0 else None)
        rad = np.where(p.aided, p.radius95, np.nan)
        ax.plot(
            x,
            rad,
            color="C3",
            lw=0.8,
            ls="--",
            label="reported 95 % radius (major axis)" if k == 0 else None,
        )
        before = x[~p.after]
        if before.size:
            ax.axvspan(x0, before.max(), color="0.92", lw=0)
        ax.axvline(x0, color="0.8", lw=0.6)
        x0 = float(x.max()) + 5.0 if x.size else x0 + 5.0
    ax.axhline(TARGETS["map_aided_p50_m"], color="C2", lw=0.8, ls=":", label="target p50 0.3 m")
    ax.axhline(TARGETS["map_aided_p95_m"], color="C1", lw=0.8, ls=":", label="target p95 0.8 m")
    ax.set_yscale("log")
    ax.set_ylim(0.02, 60.0)
    ax.set_xlabel(
        f"seconds of drive (seed {seed}: held-out passes one after another; "
        "shaded: before the 3rd mapped sign)"
    )
    ax.set_ylabel("horizontal error (m)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8, loc="upper right", ncol=3)
    ax.set_title(
        f"localisation against the fleet's map ({report['per_seed'][str(seed)]['noise']}): "
        f"raw GNSS p50 {_f(report['gnss_p50_m'])} m, map-aided p50 "
        f"{_f(report['map_aided_p50_m'])} / p95 {_f(report['map_aided_p95_m'])} m, coverage "
        f"{_f(report['coverage95'], 3)}, map-aided {_f(report['map_aided_share'], 3)} of the time",
        fontsize=9,
    )

    def pooled(name: str, aided_only: bool) -> np.ndarray:
        vals = []
        for ps in series.values():
            for p in ps:
                m = p.after & (p.aided if aided_only else True)
                vals.append(getattr(p, name)[m])
        return np.sort(np.concatenate(vals)) if vals else np.zeros(0)

    for name, aided_only, label, colour in (
        ("gnss_err", False, "raw GNSS", "0.55"),
        ("out_err", True, "map-aided", "C0"),
        ("map_frame_err", True, "map-aided, in the map's frame", "C4"),
    ):
        v = pooled(name, aided_only)
        if v.size:
            ax2.plot(v, np.arange(1, v.size + 1) / v.size, color=colour, label=label)
    ax2.axvline(TARGETS["map_aided_p50_m"], color="C2", lw=0.8, ls=":")
    ax2.axvline(TARGETS["map_aided_p95_m"], color="C1", lw=0.8, ls=":")
    ax2.set_xscale("log")
    ax2.set_xlim(0.02, 60.0)
    ax2.set_xlabel("horizontal error after the 3rd mapped sign (m), all seeds")
    ax2.set_ylabel("share of seconds")
    ax2.grid(alpha=0.3, which="both")
    ax2.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(png, dpi=110)


def _f(v: float | None, digits: int = 2) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def run_localize_job(cfg: LocalizeEvalConfig) -> dict:
    """Run ``cfg``'s seeds, write ``localize.json`` and ``localize.png`` under ``cfg.out``;
    returns the report."""
    cfg.out.mkdir(parents=True, exist_ok=True)
    report, series = run_localize_eval(cfg)
    write_json(report, cfg.out / "localize.json")
    plot_localize(series, report, cfg.out / "localize.png")
    for k in HEADLINE:
        print(f"  {k:>22}: {_f(report.get(k), 3)}", file=sys.stderr)
    print(f"  targets met: {report['targets_met']}", file=sys.stderr)
    print(f"wrote {cfg.out / 'localize.json'}, {cfg.out / 'localize.png'}", file=sys.stderr)
    return report
