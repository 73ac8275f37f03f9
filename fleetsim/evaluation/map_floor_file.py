"""The fleet evaluation's map floor: measured on held-out seeds, applied to the others.

The solver's ``systematic_sigma_m`` is the error more passes do not average away
(:mod:`hdmap.mapping.map_floor`). A deployment measures it against surveyed signs; the
evaluation's surveyed signs are the simulated town's truth, so the floor it applies is
measured on *other* seeds (other towns, other fleets) than the ones it scores:

    hdmap eval fleet --seed 10 --passes 1200 --rounds 4 --calibrate-floor --out DIR

measures it on the final map (controls: paired signs with at least ``CONTROL_MIN_PASSES``
passes) and writes it into :data:`FLOOR_FILE` under the run's noise name, with the command
that made it; later runs of that noise read it (``--no-map-floor``: the solver's default).
Every run also reports the floor its own map would need (``fleet.json`` ``map_floor.measured``),
in-sample, as a check.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from fleetsim.evaluation.fleet_scoring import SignRecord
from hdmap.mapping.map_floor import coverage_floor

FLOOR_FILE = Path(__file__).resolve().parents[1] / "data" / "map_floor.json"
"""Per noise name: the measured floor (horizontal and vertical sigma, m) and its provenance."""

CONTROL_MIN_PASSES = 150
"""Controls are signs with at least this many passes: the floor shows where the
between-pass part has averaged out (below, it hides under the sandwich)."""


def measured_floor(
    rec: SignRecord, base_sigma_m: tuple[float, float, float], min_passes: int = CONTROL_MIN_PASSES
) -> dict | None:
    """The floor a round's map needs (:func:`hdmap.mapping.map_floor.coverage_floor`) from
    its paired signs with ``min_passes`` passes or more: horizontal (East/North, 2D region)
    and vertical (1D); None with fewer than 20 such signs."""
    if rec.cov_enu is None or rec.err_enu is None:
        return None
    m = rec.found & (rec.n >= min_passes) & np.all(np.isfinite(rec.cov_enu), axis=1)
    if int(m.sum()) < 20:
        return None
    c = rec.cov_enu[m]
    e = rec.err_enu[m]
    cov_h = np.stack([np.stack([c[:, 0], c[:, 1]], -1), np.stack([c[:, 1], c[:, 3]], -1)], -2)
    h = coverage_floor(e[:, :2], cov_h, base_sigma_m=float(base_sigma_m[0]))
    v = coverage_floor(e[:, 2:3], c[:, 5].reshape(-1, 1, 1), base_sigma_m=float(base_sigma_m[2]))
    return {"min_passes": min_passes, "horizontal": h.as_dict(), "vertical": v.as_dict()}


def calibrated_sigma(noise_name: str, path: Path = FLOOR_FILE) -> tuple[float, float, float] | None:
    """``systematic_sigma_m`` (E, N, U) measured for ``noise_name``, None if not measured."""
    if not path.exists():
        return None
    entry = json.loads(path.read_text()).get(noise_name)
    if entry is None:
        return None
    h, v = float(entry["horizontal"]["sigma_m"]), float(entry["vertical"]["sigma_m"])
    return (h, h, v)


def record_floor(noise_name: str, measured: dict, command: str, path: Path = FLOOR_FILE) -> None:
    """Write ``measured`` (:func:`measured_floor`) for ``noise_name`` into ``path``, with the
    command of the run it came from."""
    data = json.loads(path.read_text()) if path.exists() else {}
    data[noise_name] = {**measured, "command": command}
    path.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")
