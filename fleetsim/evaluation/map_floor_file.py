"""The fleet evaluation's map floor: measured on held-out seeds, applied to the others.

The error more passes do not average away (:mod:`hdmap.mapping.map_floor`) reaches the
solver in one of two forms: a pass correlation ``kappa`` (``SolverConfig.pass_correlation``:
the between-pass covariance times ``1 + kappa G``) or a per-axis sigma
(``SolverConfig.systematic_sigma_m``). A deployment measures it against surveyed signs;
the evaluation's surveyed signs are the simulated town's truth, so the floor it applies is
measured on *other* seeds (other towns, other fleets) than the ones it scores:

    hdmap eval fleet --seed 10 --passes 1200 --rounds 4 --calibrate-floor --out DIR

measures both forms on the final map (controls: paired signs with at least
``CONTROL_MIN_PASSES`` passes) and writes them into :data:`FLOOR_FILE` under the run's
noise name, with the command that made them; later runs of that noise apply the form
``--map-floor`` names (``none``: the solver's defaults). Every run also reports the floor
its own map would need (``fleet.json`` ``map_floor.measured``), in-sample, as a check.
"""

from __future__ import annotations

import fcntl
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fleetsim.evaluation.fleet_scoring import SignRecord
from hdmap.mapping.map_floor import MIN_CONTROLS, measure_forms, quantile_interval

FLOOR_FILE = Path(__file__).resolve().parents[1] / "data" / "map_floor.json"
"""Per noise name: the measured floor in both forms and its provenance."""

CONTROL_MIN_PASSES = 150
"""Controls are signs with at least this many passes: the floor shows where the
between-pass part has averaged out (below, it hides under the sandwich)."""

FORMS = ("correlation", "isotropic", "none")
"""What ``--map-floor`` may name."""


@dataclass(frozen=True)
class AppliedFloor:
    """What the solver was given: the pass correlation, the per-axis sigma (E, N, U) and
    the shared GNSS floor (ENU, m^2) added after both."""

    kappa: float
    sigma_m: tuple[float, float, float]
    shared_enu_m2: np.ndarray
    source: str

    def solver_lines(self) -> list[str]:
        s = ", ".join(repr(float(v)) for v in self.sigma_m)
        return [f"pass_correlation = {self.kappa!r}", f"systematic_sigma_m = [{s}]"]

    def as_dict(self) -> dict:
        return {"kappa": self.kappa, "sigma_m": list(self.sigma_m), "source": self.source}


def measured_floor(
    rec: SignRecord, applied: AppliedFloor, min_passes: int = CONTROL_MIN_PASSES
) -> dict | None:
    """The floor a round's map needs, from its paired signs with ``min_passes`` passes or
    more (:func:`hdmap.mapping.map_floor.measure_forms`): per-axis sigma horizontally (2D
    regions, ``horizontal``) and vertically (1D, ``vertical``), and the horizontal pass
    correlation (``pass_correlation``), each with the applied floor taken out first; None
    with fewer than ``MIN_CONTROLS`` such signs."""
    if rec.cov_enu is None or rec.err_enu is None:
        return None
    m = rec.found & (rec.n >= min_passes) & np.all(np.isfinite(rec.cov_enu), axis=1)
    if int(m.sum()) < MIN_CONTROLS:
        return None
    fits = measure_forms(
        rec.err_enu[m], rec.cov_enu[m], rec.n[m], applied.kappa, applied.sigma_m,
        applied.shared_enu_m2,
    )  # fmt: skip
    return {"min_passes": min_passes, **{form: f.as_dict() for form, f in fits.items()}}


def applied_floor(
    noise_name: str,
    form: str,
    shared_enu_m2: np.ndarray,
    default_sigma_m: tuple[float, float, float],
    path: Path = FLOOR_FILE,
) -> AppliedFloor:
    """What the evaluation gives the solver for ``form`` (:data:`FORMS`): the measured
    correlation (no per-axis sigma), the measured per-axis sigma (no correlation), or,
    with ``none`` or nothing measured for ``noise_name``, the solver's defaults."""
    if form not in FORMS:
        raise ValueError(f"map floor form {form!r}: one of {', '.join(FORMS)}")
    entry = json.loads(path.read_text()).get(noise_name) if path.exists() else None
    where = f"{path.relative_to(path.parents[2])} ({noise_name})"
    if form == "none" or entry is None:
        return AppliedFloor(0.0, tuple(default_sigma_m), shared_enu_m2, "SolverConfig defaults")
    if form == "correlation":
        kappa = float(entry["pass_correlation"]["kappa"])
        return AppliedFloor(kappa, (0.0, 0.0, 0.0), shared_enu_m2, f"{where}: correlation")
    h, v = float(entry["horizontal"]["sigma_m"]), float(entry["vertical"]["sigma_m"])
    return AppliedFloor(0.0, (h, h, v), shared_enu_m2, f"{where}: isotropic")


PARAMETERS = {"horizontal": "sigma_m", "vertical": "sigma_m", "pass_correlation": "kappa"}
"""The forms a measurement holds and the name of each one's parameter."""


def record_floor(
    noise_name: str, measured: dict, command: str, seed: int, path: Path = FLOOR_FILE
) -> dict:
    """Add ``measured`` (:func:`measured_floor`) of ``seed``'s run to ``noise_name``'s
    entry in ``path`` (replacing an earlier run of that seed) and pool every run's
    controls: each form's value is the conformal quantile of the union of their least
    values (:func:`hdmap.mapping.map_floor.quantile_interval`), with its interval. Several
    held-out seeds give a floor less tied to one town's and one fleet's draw. Returns the
    entry. Runs of several seeds at once (``--seeds 11,12 --jobs 2 --calibrate-floor``)
    record one at a time: the read, pool and write hold an exclusive lock on
    ``path.lock``, and the file is replaced whole (never read half-written)."""
    with open(path.with_suffix(".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        return _record_locked(noise_name, measured, command, seed, path)


def _record_locked(noise_name: str, measured: dict, command: str, seed: int, path: Path) -> dict:
    data = json.loads(path.read_text()) if path.exists() else {}
    runs = data.get(noise_name, {}).get("runs", {})
    runs[str(seed)] = {**measured, "command": command}
    entry: dict = {"seeds": sorted(int(k) for k in runs), "runs": runs}
    for form, param in PARAMETERS.items():
        least = np.concatenate([np.asarray(r[form]["least"], float) for r in runs.values()])
        level, conf = measured[form]["level"], measured[form]["confidence"]
        value, lo, hi = quantile_interval(least, level, conf)
        entry[form] = {param: value, "interval": [lo, hi], "controls": int(least.size),
                       "level": level, "confidence": conf}  # fmt: skip
    data[noise_name] = entry
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")
    os.replace(tmp, path)
    return entry
