"""A finished fleet evaluation's uploads replayed through a matcher and a solver in-process,
with matcher settings changed, and the final map scored against the truth: an A/B for
matcher changes that a live run cannot give (a live run's upload order follows the code's
speed, so two runs of one code differ by a few landmarks; one log replayed does not).

Usage: python scripts/diagnostics/replay_ab.py RUN_DIR SEED [gnss=gsdc] [rounds=1] [KEY=JSON ...]
``RUN_DIR/seed-SEED`` is one seed's output of ``hdmap eval fleet --out RUN_DIR`` (give
``gnss=gsdc`` for a ``--gnss gsdc`` run: the truth's world is rebuilt from the seed).
``KEY=JSON`` sets a ``MatcherConfig`` field (``gate.chi2_gate=12`` for a nested one); the
solver takes the run's ``services.toml``, and ``solver.KEY=JSON`` sets one of its fields.
Prints the final map's confirmed landmarks with
50+ passes: how many pair with a sign within 5 m (one to one, confirmed first), the
unpaired ones (duplicates: within 5 m of a paired sign of their class), and each unpaired
landmark's nearest same-class sign. With no KEY the map is the live run's (the replay
invariant of ``services/matcher/replay.py``), up to the solver's batches. ``rounds=1``
also scores the map at each round's end of the run (the uploads cut where its
``fleet.json`` says the round's observations end): false confirmed landmarks and
confirmed duplicates per round, as the live evaluation's round lines count them.
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
from dataclasses import fields
from pathlib import Path

import numpy as np

from fleetsim.evaluation.fleet_eval import FleetEvalConfig, evaluation_world
from fleetsim.score import duplicate_mask
from fleetsim.truth import match_map
from hdmap.runtime.config import dotted_table, from_mapping, load_toml, parse_settings
from hdmap.runtime.service import ServiceOptions
from schemas import STATUS_CONFIRMED, Landmarks, LandmarkUpdates, LogEntry, ObsGroup
from services.matcher.replay import (
    Sink,
    matcher_config,
    open_matcher,
    read_log,
    read_obs_log,
    replay,
)
from services.solver.service import SolverConfig, SolverService


def final_map(entries: list[LogEntry]) -> Landmarks:
    """The map the solver's update log leaves: each landmark's last upsert, less removals."""
    rows: dict[int, Landmarks] = {}
    for e in entries:
        u = LandmarkUpdates.from_bytes(e.body)
        for k in range(len(u.landmarks)):
            rows[int(u.landmarks.id[k])] = u.landmarks.take(np.array([k]))
        for lid in u.removed.id.tolist():
            rows.pop(int(lid), None)
    return Landmarks.concat([rows[k] for k in sorted(rows)]) if rows else Landmarks.empty()


def _round_line(world, lm: Landmarks, r: int) -> None:
    """One round's map as the live evaluation's round line counts it: unpaired confirmed
    landmarks (all, and with 50+ passes) and confirmed duplicates."""
    match = match_map(world, lm, 5.0)
    paired = np.zeros(len(lm), bool)
    paired[match.landmark] = True
    dup = duplicate_mask(world, lm, match, 5.0)
    conf = np.asarray(lm.status) == STATUS_CONFIRMED
    mature = conf & (np.asarray(lm.n_passes) >= 50)
    print(
        f"  round {r}: {len(lm)} landmarks, false confirmed {int((conf & ~paired).sum())} "
        f"(50+ passes {int((mature & ~paired).sum())}), confirmed duplicates "
        f"{int((conf & dup).sum())}, recall {len(match.landmark) / len(world.signs):.3f}",
        flush=True,
    )


def main(root: Path, seed: int, args: list[str]) -> None:
    gnss = "fleet"
    by_round = False
    solver_over: dict[str, object] = {}
    overrides: dict[str, object] = {}
    for kv in args:
        key, _, value = kv.partition("=")
        if key == "gnss":
            gnss = value
        elif key == "rounds":
            by_round = value not in ("0", "false")
        elif key.startswith("solver."):
            solver_over |= parse_settings([kv[len("solver.") :]])
        else:
            overrides |= parse_settings([kv])
    run = root / f"seed-{seed}" / "run"
    known = {f.name for f in fields(SolverConfig)}
    solver_toml = {k: v for k, v in load_toml(run / "services.toml").get("solver", {}).items()}
    solver_toml = {k: v for k, v in solver_toml.items() if k in known} | solver_over
    solver_cfg = from_mapping(SolverConfig, dotted_table(solver_toml))
    world = evaluation_world(FleetEvalConfig(out=Path(tempfile.gettempdir()), seed=seed, gnss=gnss))
    obs_entries = read_obs_log(run / "var" / "ingest-all" / "state.sqlite")
    report = root / f"seed-{seed}" / "fleet.json"
    cuts = [len(obs_entries)]
    if by_round and report.exists():
        ends = [int(r["observations"]) for r in json.loads(report.read_text())["rounds"]]
        sizes = np.cumsum([len(ObsGroup.from_bytes(e.body).obs) for e in obs_entries])
        cuts = [int(np.searchsorted(sizes, n)) + 1 for n in ends[:-1]] + [len(obs_entries)]
    with tempfile.TemporaryDirectory(prefix="replay-ab-") as tmp:
        t0 = time.process_time()
        m = open_matcher(Path(tmp) / "matcher", matcher_config(overrides))
        s = SolverService(ServiceOptions(data_dir=Path(tmp) / "solver"), solver_cfg)
        s.pubs = Sink()  # type: ignore[assignment]
        done = 0
        for r, cut in enumerate(cuts, 1):
            replay(m, obs_entries[done:cut], 64)
            done = cut
            replay(s, read_log(m.db_path, "assoc"), 64)  # applied entries are skipped
            lm = final_map(read_log(s.db_path, "update"))
            if len(cuts) > 1:
                _round_line(world, lm, r)
        m.db.close()
        s.db.close()
        cpu = time.process_time() - t0
    match = match_map(world, lm, 5.0)
    paired = np.zeros(len(lm), bool)
    paired[match.landmark] = True
    dup = duplicate_mask(world, lm, match, 5.0)
    mature = (np.asarray(lm.status) == STATUS_CONFIRMED) & (np.asarray(lm.n_passes) >= 50)
    n = int(mature.sum())
    print(
        f"seed {seed} {(overrides | solver_over) or 'defaults'}: {len(lm)} landmarks; "
        f"confirmed with 50+ passes "
        f"{n}, paired {int((mature & paired).sum())}, precision "
        f"{(mature & paired).sum() / max(n, 1):.3f}, duplicates {int((mature & dup).sum())} "
        f"({cpu:.0f} s CPU)"
    )
    est = world.frame.from_geodetic(lm.lat, lm.lon, lm.h).reshape(-1, 3)
    signs = world.signs
    confirmed = np.asarray(lm.status) == STATUS_CONFIRMED
    err = np.linalg.norm(match.error_enu, axis=1)
    print(
        f"  all landmarks: unpaired {int((~paired).sum())} "
        f"(confirmed {int((confirmed & ~paired).sum())}); paired {int(paired.sum())}, "
        f"mean error {err.mean():.3f} m"
    )
    for j in np.flatnonzero(mature & ~paired).tolist():
        same = np.flatnonzero(signs.sign_class == lm.sign_class[j])
        d = np.hypot(*(signs.position[same, :2] - est[j, :2]).T)
        k = int(np.argmin(d))
        print(
            f"  unpaired: {int(lm.n_passes[j])} passes, nearest sign {int(signs.id[same[k]])} "
            f"at {d[k]:.1f} m{' (duplicate)' if dup[j] else ''}"
        )


if __name__ == "__main__":
    main(Path(sys.argv[1]), int(sys.argv[2]), sys.argv[3:])
