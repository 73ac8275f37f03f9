"""PNG figures of :mod:`fleetsim.evaluation.paper_sim` results.

- ``paper_figure_<model>.png``: the paper's figure for one example trial: errors East
  and North per passing, single-passing measurements (blue), our collaborative estimate
  (red) with its +/-2 sigma band, the paper's estimator (grey), zero (yellow);
- ``convergence.png``: mean horizontal error vs passings (log-log) per error model, with
  the fitted slopes;
- ``coverage.png``: share of trials whose truth is inside the reported 95% ellipse.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

STYLE = {
    "ours": dict(color="tab:red", lw=2.0, label="ours (compensated, pass-level cov.)"),
    "independent": dict(color="tab:purple", lw=1.2, ls="--", label="ours, rays independent"),
    "ours_no_floor": dict(color="tab:orange", lw=1.2, ls="-.", label="ours, reported sigmas only"),
    "ours_pull": dict(color="tab:green", lw=1.2, ls=":", label="ours + position-bias budget"),
    "paper": dict(color="black", lw=1.5, label="paper (textbook sums)"),
}


def _arr(v: list) -> np.ndarray:
    return np.array([np.nan if x is None else x for x in v], float)


def paper_figure(result: dict, model: str, path: Path) -> Path:
    ex = result["models"][model]["example"]
    n = _arr(ex["n"])
    fig, axes = plt.subplots(2, 1, figsize=(10, 7), sharex=True)
    for ax, axis in zip(axes, ("east", "north"), strict=True):
        single = _arr(ex[f"single_{axis}"])
        ax.plot(n, single, ".", color="tab:blue", ms=3, label="single passing")
        if "paper_" + axis in ex:
            ax.plot(n, _arr(ex[f"paper_{axis}"]), color="0.45", lw=1.2, label="paper's estimator")
        e, s = _arr(ex[f"ours_{axis}"]), _arr(ex[f"ours_sigma_{axis}"])
        ax.fill_between(
            n, e - 2 * s, e + 2 * s, color="tab:red", alpha=0.2, label="ours +/- 2 sigma"
        )
        ax.plot(n, e, color="tab:red", lw=1.8, label="ours (collaborative)")
        ax.axhline(0.0, color="gold", lw=2, label="ground truth")
        finite = single[np.isfinite(single)]
        lim = float(np.percentile(np.abs(finite), 95)) if finite.size else 30.0
        ax.set_ylim(-max(lim, 5.0), max(lim, 5.0))
        ax.set_ylabel(f"error {axis.capitalize()} (m)")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8, ncol=3)
    axes[1].set_xlabel("vehicle passing")
    axes[1].set_xscale("log")
    fig.suptitle(f"Paper's simulation, {model} noise, trial {ex['trial']}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def convergence_figure(result: dict, path: Path) -> Path:
    models = list(result["models"])
    cps = np.array(result["checkpoints"], float)
    fig, axes = plt.subplots(1, len(models), figsize=(6.5 * len(models), 5), squeeze=False)
    for ax, model in zip(axes[0], models, strict=True):
        block = result["models"][model]
        for name, est in block["estimators"].items():
            y = _arr(est["mean_error_m"])
            fit = block.get("fits", {}).get(name, {})
            slope = fit.get("slope")
            lab = STYLE.get(name, {}).get("label", name)
            if slope is not None and np.isfinite(slope):
                lab += f"  (slope {slope:+.2f})"
            ax.plot(cps, y, marker="o", ms=3, **{**STYLE.get(name, {}), "label": lab})
            if name == "ours" and slope is not None and np.isfinite(slope):
                lo, hi = fit["n_range"]
                nn = np.array([lo, hi], float)
                ax.plot(nn, np.exp(fit["intercept"]) * nn**slope, color="tab:red", lw=6, alpha=0.2)
        sp = block["single_pass"]["mean_error_m"]
        ax.axhline(sp, color="tab:blue", ls=":", label=f"single passing ({sp:.1f} m)")
        ref = cps[cps >= 1]
        ours = _arr(block["estimators"]["ours"]["mean_error_m"])
        k = np.flatnonzero(np.isfinite(ours))
        if k.size:
            i = k[-1]
            ax.plot(
                ref,
                ours[i] * np.sqrt(cps[i] / ref),
                color="0.6",
                lw=0.8,
                ls="--",
                label="1/sqrt(n)",
            )
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("passings n")
        ax.set_ylabel("mean horizontal error (m), published trials")
        ax.set_title(f"{model} noise")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def coverage_figure(result: dict, path: Path) -> Path:
    models = list(result["models"])
    cps = np.array(result["checkpoints"], float)
    fig, axes = plt.subplots(1, len(models), figsize=(6.5 * len(models), 4.5), squeeze=False)
    for ax, model in zip(axes[0], models, strict=True):
        block = result["models"][model]
        ax.axhspan(0.92, 0.98, color="tab:green", alpha=0.12, label="target 0.92-0.98")
        ax.axhline(0.95, color="tab:green", lw=0.8)
        for name, est in block["estimators"].items():
            ax.plot(
                cps,
                _arr(est["coverage_ellipse"]),
                marker="o",
                ms=3,
                **STYLE.get(name, {"label": name}),
            )
        ours = block["estimators"]["ours"]
        ax.plot(
            cps,
            _arr(ours["published"]),
            color="tab:red",
            lw=0.8,
            ls=":",
            label="ours: share published",
        )
        ax.set_xscale("log")
        ax.set_ylim(-0.02, 1.02)
        ax.set_xlabel("passings n")
        ax.set_ylabel("truth inside reported 95% ellipse")
        ax.set_title(f"{model} noise")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_figures(result: dict, out: Path) -> list[Path]:
    out = Path(out)
    paths = [paper_figure(result, m, out / f"paper_figure_{m}.png") for m in result["models"]]
    paths.append(convergence_figure(result, out / "convergence.png"))
    paths.append(coverage_figure(result, out / "coverage.png"))
    return paths
