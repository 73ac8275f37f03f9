"""The fleet evaluation over several seeds: how much its figures move with the draw.

One fleet run is one draw of routes, noise and detections; the figures near the targets
(duplicates, the association share) move by a few tenths of a point from seed to seed with
the same code, so a change judged on one seed is judged on noise. ``hdmap eval fleet
--seeds 0,1,2,3`` runs each seed into ``DIR/seed-<s>/`` and writes ``DIR/fleet_seeds.json``:

- ``seeds``: the seeds, in order;
- ``per_seed.<s>``: :func:`seed_row` of that run: the targets at 50+ passes (``None`` where
  the run has no sign with 50 passes, as in ``--quick``), the final round (``final_*``) and
  the young map (``young_*``: the bin of 3-4 passes);
- ``per_seed.<s>.pass``: the accuracy issue's targets at 50+ passes and, with a
  ``strict:`` prefix, :func:`strict_targets` (the done-when of the issue on data we did
  not generate: tighter precision and mean error, and false landmarks that do not grow);
- ``summary.<metric>``: ``mean``, ``min``, ``max`` and ``n`` over the seeds that have it;
- ``targets_passed.<criterion>``: how many of the evaluated seeds meet it, and
  ``all_targets_all_seeds`` (every criterion on every seed, false when none evaluated).

>>> r = {"targets_at_50_passes": {"evaluated": False}, "by_passes": [],
...      "rounds": [{"recall": 0.9, "mean_err_m": 1.2, "coverage95": 0.95, "landmarks": 10}]}
>>> seed_row(r)["final_recall"], seed_row(r)["assoc_right"]
(0.9, None)
"""

from __future__ import annotations

import numpy as np

TARGET_KEYS = (
    "mean_err_m",
    "p95_err_m",
    "coverage95_from_30",
    "recall",
    "precision",
    "duplicated",
    "precision_all",
    "duplicated_all",
    "assoc_right",
    "assoc_right_obs_pooled",
    "assoc_right_obs_from_50",
)
"""Figures of ``targets_at_50_passes`` carried per seed."""

FLEET_COLUMNS: list[tuple[str, str, str]] = [
    ("mean_err_m", "mean m", ".2f"),
    ("p95_err_m", "p95 m", ".2f"),
    ("coverage95_from_30", "cov30", ".3f"),
    ("recall", "recall", ".3f"),
    ("precision", "prec", ".3f"),
    ("duplicated", "dup", "d"),
    ("precision_all", "p.all", ".3f"),
    ("duplicated_all", "d.all", "d"),
    ("assoc_right", "assoc", ".3f"),
    ("assoc_right_obs_pooled", "a.obs", ".3f"),
    ("assoc_right_obs_from_50", "a.late", ".3f"),
    ("final_mean_err_m", "fin.m", ".2f"),
    ("final_recall", "fin.rec", ".3f"),
    ("young_precision", "y.prec", ".3f"),
    ("young_duplicated", "y.dup", "d"),
    ("false_confirmed_early", "f.300", "d"),
    ("false_confirmed_final", "f.last", "d"),
]
"""Columns of :func:`format_seed_table` for the fleet."""

STRICT_PRECISION = 0.98
"""Least precision of the confirmed landmarks in every bin from 50 passes (issue 18)."""

STRICT_MEAN_ERR_M = 0.8
"""Greatest mean error from 50 passes with the simulated receiver (issue 18; real phone
errors keep the accuracy issue's 1.0 m)."""

EARLY_PASSES = 300
"""The round whose false confirmed landmarks the last round's may not exceed."""

YOUNG_BIN = 3
"""Lower edge of the pass-count bin reported as the young map (3-4 passes)."""


def seed_row(result: dict) -> dict:
    """One run's figures: targets at 50+ passes, final round, young map."""
    t = result["targets_at_50_passes"]
    row: dict = {k: (t.get(k) if t.get("evaluated") else None) for k in TARGET_KEYS}
    row["evaluated"] = bool(t.get("evaluated"))
    row["pass"] = dict(t["pass"]) if t.get("evaluated") else {}
    strict = strict_targets(result)
    row.update({k: v for k, v in strict.items() if k != "pass"})
    row["pass"].update({f"strict:{c}": ok for c, ok in strict["pass"].items()})
    last = result["rounds"][-1] if result["rounds"] else {}
    for k in ("recall", "mean_err_m", "coverage95", "landmarks"):
        row[f"final_{k}"] = last.get(k)
    young = [r for r in result["by_passes"] if r["passes_lo"] == YOUNG_BIN]
    row["young_precision"] = young[0]["precision"] if young else None
    row["young_duplicated"] = young[0]["duplicated"] if young else None
    return row


def strict_targets(result: dict) -> dict:
    """Issue 18's done-when on one run: from 50 passes precision >= 0.98, no duplicate and
    (simulated receiver only) mean error <= 0.8 m; every coverage bin from 30 passes
    binomially consistent with 95 % and the pooled share within 0.90-0.98 (the accuracy
    issue's coverage criterion); and no more false confirmed landmarks in the last round
    than in the round of :data:`EARLY_PASSES` passes (the first round when none has that
    many). ``pass`` is empty where the run has no sign with 50 passes.

    >>> r = {"meta": {"noise": "fleet"}, "rounds": [
    ...     {"passes": 300, "false_confirmed": 2}, {"passes": 1200, "false_confirmed": 1}],
    ...     "targets_at_50_passes": {"evaluated": True, "mean_err_m": 0.5, "precision": 0.99,
    ...     "duplicated": 0, "pass": {"coverage95_in_0.90_0.98": True}}}
    >>> strict_targets(r)["pass"]
    {'mean_err_m<=0.8': True, 'precision>=0.98': True, 'no_duplicates': True, \
'coverage95_in_0.90_0.98': True, 'false_confirmed_not_growing': True}
    >>> r["meta"]["noise"] = "fleet+gsdc"; sorted(strict_targets(r)["pass"])[0]
    'coverage95_in_0.90_0.98'
    """
    rounds = result.get("rounds") or []
    early = [r for r in rounds if r.get("passes") == EARLY_PASSES] or rounds[:1]
    out: dict = {
        "false_confirmed_early": early[0].get("false_confirmed") if early else None,
        "false_confirmed_final": rounds[-1].get("false_confirmed") if rounds else None,
        "false_landmarks_early": early[0].get("false_landmarks") if early else None,
        "false_landmarks_final": rounds[-1].get("false_landmarks") if rounds else None,
        "pass": {},
    }
    t = result["targets_at_50_passes"]
    if not t.get("evaluated"):
        return out
    checks = {}
    if "gsdc" not in str(result.get("meta", {}).get("noise", "")):
        checks["mean_err_m<=0.8"] = t["mean_err_m"] <= STRICT_MEAN_ERR_M
    checks["precision>=0.98"] = t["precision"] is not None and t["precision"] >= STRICT_PRECISION
    checks["no_duplicates"] = t["duplicated"] == 0
    checks["coverage95_in_0.90_0.98"] = bool(t["pass"]["coverage95_in_0.90_0.98"])
    if out["false_confirmed_early"] is not None and out["false_confirmed_final"] is not None:
        checks["false_confirmed_not_growing"] = (
            out["false_confirmed_final"] <= out["false_confirmed_early"]
        )
    out["pass"] = checks
    return out


def summarise_seeds(per_seed: dict[int, dict]) -> dict:
    """Mean, min and max of every figure over the seeds, and the targets met per seed.

    >>> a = {"evaluated": True, "assoc_right": 0.96, "pass": {"assoc_right>=0.97": False}}
    >>> b = {"evaluated": True, "assoc_right": 0.98, "pass": {"assoc_right>=0.97": True}}
    >>> s = summarise_seeds({0: a, 1: b})
    >>> s["summary"]["assoc_right"]["mean"], s["targets_passed"], s["all_targets_all_seeds"]
    (0.97, {'assoc_right>=0.97': 1}, False)
    """
    seeds = sorted(per_seed)
    summary: dict[str, dict] = {}
    keys = [k for k in per_seed[seeds[0]] if k not in ("evaluated", "pass")] if seeds else []
    for k in keys:
        vals = [per_seed[s][k] for s in seeds if isinstance(per_seed[s].get(k), int | float)]
        vals = [float(v) for v in vals if not isinstance(v, bool)]
        if vals:
            v = np.array(vals)
            summary[k] = {
                "mean": round(float(v.mean()), 6),
                "min": float(v.min()),
                "max": float(v.max()),
                "n": len(vals),
            }
    evaluated = [s for s in seeds if per_seed[s].get("evaluated")]
    criteria = sorted({c for s in evaluated for c in per_seed[s]["pass"]})
    passed = {c: sum(bool(per_seed[s]["pass"].get(c)) for s in evaluated) for c in criteria}
    return {
        "seeds": seeds,
        "per_seed": {str(s): per_seed[s] for s in seeds},
        "summary": summary,
        "targets_passed": passed,
        "evaluated_seeds": len(evaluated),
        "all_targets_all_seeds": bool(evaluated)
        and len(evaluated) == len(seeds)
        and all(n == len(evaluated) for n in passed.values()),
    }


def format_seed_table(summary: dict, cols: list[tuple[str, str, str]] | None = None) -> str:
    """Per seed one line of the figures nearest the targets, then mean / min / max.

    ``cols``: (key, heading, format) per column; default the fleet's figures."""
    cols = cols or FLEET_COLUMNS

    def cell(v: object, fmt: str) -> str:
        if isinstance(v, int | float) and not isinstance(v, bool):
            return format(int(v), "d") if fmt == "d" else format(v, fmt)
        return "-"

    head = f"{'seed':>6} " + " ".join(f"{h:>7}" for _, h, _ in cols)
    lines = [head, "-" * len(head)]
    for s in summary["seeds"]:
        row = summary["per_seed"][str(s)]
        lines.append(f"{s:>6} " + " ".join(f"{cell(row.get(k), f):>7}" for k, _, f in cols))
    for stat in ("mean", "min", "max"):
        vals = [summary["summary"].get(k, {}).get(stat) for k, _, _ in cols]
        fmts = [".2f" if f == "d" and stat == "mean" else f for _, _, f in cols]
        lines.append(
            f"{stat:>6} " + " ".join(f"{cell(v, f):>7}" for v, f in zip(vals, fmts, strict=True))
        )
    met = summary["targets_passed"]
    n = summary["evaluated_seeds"]
    lines.append(
        f"targets met over {n} evaluated seed(s): "
        + (", ".join(f"{c} {k}/{n}" for c, k in met.items()) if met else "none evaluated")
    )
    return "\n".join(lines)
