"""``hdmap calibrate-gnss``: the solver's shared-error floor from a truth-referenced GNSS log.

Input: a CSV of receiver fix minus truth (an RTK reference) per epoch, one or more drives,
with columns ``trace`` (the drive), ``t_s`` (seconds), ``err_east_m``, ``err_north_m`` and
optionally ``err_up_m`` (the format of ``fleetsim/data/gsdc2020_mtv1_phone_gnss_errors.csv``).
Output: the floor (:mod:`hdmap.mapping.gnss_floor`) as the ``[solver]`` line of a services
config, and with ``--out`` a JSON artefact with what it was measured from.

    hdmap calibrate-gnss --errors fleetsim/data/gsdc2020_mtv1_phone_gnss_errors.csv
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np

from hdmap.mapping.gnss_floor import SharedFloor, floor_enu, shared_floor, shared_floor_m2

COLUMNS = ("trace", "t_s", "err_east_m", "err_north_m")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--errors", required=True, metavar="CSV", help="fix-minus-truth log (see doc)")
    p.add_argument(
        "--batch-s",
        type=float,
        default=300.0,
        help="batch length for the means' variance, s (longer than the errors' correlation)",
    )
    p.add_argument("--out", metavar="JSON", help="also write the floor and its inputs here")


def read_errors(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per drive (``trace``), epoch times and (n, 2 or 3) errors, in time order."""
    rows: dict[str, list[list[float]]] = {}
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        missing = [c for c in COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise ValueError(f"{path}: missing column(s) {', '.join(missing)}")
        cols = ["t_s", "err_east_m", "err_north_m"]
        cols += ["err_up_m"] if "err_up_m" in (reader.fieldnames or []) else []
        for i, r in enumerate(reader, start=2):
            try:
                rows.setdefault(r["trace"], []).append([float(r[c]) for c in cols])
            except (TypeError, ValueError) as exc:
                raise ValueError(f"{path}:{i}: not a number ({exc})") from exc
    if not rows:
        raise ValueError(f"{path}: no rows")
    out = {}
    for name, vals in rows.items():
        a = np.array(sorted(vals))
        out[name] = (a[:, 0], a[:, 1:])
    return out


def artefact(f: SharedFloor, source: Path, names: list[str], batch_s: float) -> dict:
    c = floor_enu(f)
    return {
        "source": str(source),
        "batch_s": batch_s,
        "drives": names,
        "batches": list(f.batches),
        "drive_means_m": f.drive_means.tolist(),
        "cov_enu_m2": c.tolist(),
        "sigma_m": np.sqrt(np.diag(c)).tolist(),
        "shared_floor_m2": shared_floor_m2(f),
    }


def run(args: argparse.Namespace) -> int:
    path = Path(args.errors)
    try:
        drives = read_errors(path)
        f = shared_floor(
            [t for t, _ in drives.values()], [e for _, e in drives.values()], args.batch_s
        )
    except (OSError, ValueError) as exc:
        print(f"calibrate-gnss: {exc}", file=sys.stderr)
        return 2
    art = artefact(f, path, list(drives), args.batch_s)
    for name, m, b in zip(drives, f.drive_means, f.batches, strict=True):
        print(f"{name}: mean error {np.round(m, 3).tolist()} m over {b} batches")
    sig = ", ".join(f"{s:.3f}" for s in art["sigma_m"])
    print(f"floor sigma (E, N, U) m: {sig}; from {f.drives} drive(s)")
    print("[solver]")
    print(f"shared_floor_m2 = [{', '.join(f'{v:.6g}' for v in art['shared_floor_m2'])}]")
    if args.out:
        Path(args.out).write_text(json.dumps(art, indent=2) + "\n")
    return 0
