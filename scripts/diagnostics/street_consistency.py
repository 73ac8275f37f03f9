"""Per landmark of a finished fleet evaluation: do its rays from one street agree with the rest?
(docs/experiments/2026-12-line-of-sight-mixture.md)

Usage: python scripts/diagnostics/street_consistency.py RUN_DIR SEED [SPLIT_DEG]
``RUN_DIR/seed-SEED`` is one seed's output of ``hdmap eval fleet --out RUN_DIR``. Every
link of the matcher's association log goes to the landmark that holds it at the end
(merges followed); for each published landmark with 50+ passes its rays are solved in a
fresh ``LandmarkSums`` (default ``EstimatorConfig``, passes as clusters), then split by
viewing azimuth into the rays within ``SPLIT_DEG`` (default 35) of their circular mean and
the rest. Where both parts have 10+ passes, each part is solved alone and compared with the
whole: ``chi2`` of the horizontal offset against the part's covariance plus the map floor
the run applied. Prints the 25 largest (label, status, part, its passes, offset, the
part's sigmas) and the paired landmarks' percentiles; labels: ``sN`` paired with sign N,
``UN`` unpaired whose rays mostly saw sign N.
"""

from __future__ import annotations

import json
import sqlite3
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
from landmark_pairs import labels, successors

from fleetsim.evaluation.fleet_eval import FleetEvalConfig, evaluation_world
from hdmap.mapping.estimator import EstimatorConfig, LandmarkSums, Rays
from schemas.logs import AssocGroup


def rays_by_landmark(run: Path, world, keep: set[int]) -> dict[int, tuple]:
    """Per final landmark id in ``keep``: origins, directions, sigmas and pass keys."""
    db = sqlite3.connect(f"file:{run / 'run/var/matcher-all/state.sqlite'}?mode=ro", uri=True)
    groups = [
        AssocGroup.from_bytes(b) for (b,) in db.execute("SELECT body FROM log_out ORDER BY gseq")
    ]
    final = successors(groups)
    wanted = np.array(sorted(keep), dtype=np.uint64)
    parts: dict[int, list] = defaultdict(list)
    pkeys: dict[tuple, int] = {}
    for g in groups:
        if not len(g.links):
            continue
        ids = g.links.landmark_id.tolist()
        fl = np.array([final.get(int(x), int(x)) for x in ids], dtype=np.uint64)
        m = np.isin(fl, wanted)
        if not m.any():
            continue
        o = g.obs
        origin = world.frame.from_geodetic(o.lat[m], o.lon[m], o.h[m]).reshape(-1, 3)
        veh = np.array(g.vehicles)[g.links.vehicle[m]]
        pk = np.array(
            [
                pkeys.setdefault((v, p), len(pkeys))
                for v, p in zip(veh, g.links.pass_id[m].tolist(), strict=True)
            ]
        )
        cols = (
            origin,
            o.direction[m],
            o.sigma_az[m],
            o.sigma_el[m],
            o.sigma_pos_h[m],
            o.sigma_pos_v[m],
            pk,
        )
        for lid in np.unique(fl[m]).tolist():
            k = fl[m] == lid
            parts[int(lid)].append(tuple(c[k] for c in cols))
    return {
        lid: tuple(np.concatenate(z) for z in zip(*ps, strict=True)) for lid, ps in parts.items()
    }


def solve(cols: tuple, sel: np.ndarray, x0: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    origin, d, s_az, s_el, s_h, s_v, pk = (c[sel] for c in cols)
    sums = LandmarkSums(EstimatorConfig())
    row = sums.new_rows(1, x0[None])
    sums.accumulate(
        np.full(len(origin), row[0]),
        pk.astype(np.int64),
        Rays(origin, d, s_az, s_el, s_h, s_v, None),
    )
    sol = sums.solve(row)
    return sol.x[0], sol.cov[0], bool(sol.ok[0])


def main(root: Path, seed: int, split_deg: float) -> None:
    run = root / f"seed-{seed}"
    world = evaluation_world(FleetEvalConfig(out=Path("/tmp"), seed=seed))
    pub = sqlite3.connect(f"file:{run / 'run/var/publisher-all/state.sqlite'}?mode=ro", uri=True)
    status = {
        lid: st for lid, st, n in pub.execute("SELECT id, status, n_passes FROM current") if n >= 50
    }
    report = json.loads((run / "fleet.json").read_text())
    lab = labels(report)
    floor = np.diag(np.square(report["map_floor"]["applied"]["sigma_m"][:2]))
    rows = []
    for lid, cols in rays_by_landmark(run, world, set(status)).items():
        origin, d, pk = cols[0], cols[1], cols[6]
        everything = np.ones(len(origin), bool)
        x, _, ok = solve(cols, everything, np.median(origin + 30.0 * d, axis=0))
        if not ok:
            continue
        view = np.arctan2(d[:, 0], d[:, 1])
        mean = np.angle(np.mean(np.exp(1j * view)))
        off = np.abs(np.degrees((view - mean + np.pi) % (2 * np.pi) - np.pi))
        worst = (0.0, "")
        for name, m in (("main", off <= split_deg), ("rest", off > split_deg)):
            if min(np.unique(pk[m]).size, np.unique(pk[~m]).size) < 10:
                continue
            xs, cs, oks = solve(cols, m, x)
            if not oks:
                continue
            dx = (xs - x)[:2]
            cov = cs[:2, :2] + floor
            chi2 = float(dx @ np.linalg.solve(cov, dx))
            if chi2 > worst[0]:
                sig = np.sqrt(np.linalg.eigvalsh(cov)).round(2).tolist()
                worst = (
                    chi2,
                    f"{name} {np.unique(pk[m]).size} passes, {np.hypot(*dx):.1f} m off, "
                    f"sigmas {sig}",
                )
        rows.append((worst[0], lab.get(lid, "-"), status[lid], worst[1]))
    rows.sort(key=lambda r: -r[0])
    for chi2, name, st, what in rows[:25]:
        print(f"{chi2:8.1f} {name:8s} status {st}  {what}")
    paired = np.array([r[0] for r in rows if r[1].startswith("s")])
    print(
        f"paired: {paired.size}, chi2 50/90/99/100 % "
        f"{np.percentile(paired, [50, 90, 99, 100]).round(1).tolist()}, above 13.8: "
        f"{int((paired > 13.8).sum())}"
    )
    print("unpaired:", [(round(r[0], 1), r[1]) for r in rows if not r[1].startswith("s")])


if __name__ == "__main__":
    main(Path(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3]) if len(sys.argv) > 3 else 35.0)
