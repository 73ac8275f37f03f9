"""The matcher alone on a captured obs log, in-process: observations per second per core
(issue #19 point 5).

A captured log is an ingest's ``log_out`` table (its SQLite file, ``var/ingest-*/state.sqlite``
of any run): the obs entries exactly as the matcher received them. By default the capture
is made first, by a fleet evaluation (`hdmap eval fleet`, central Helsinki, the fleet
noise; ``--passes``, default 160), whose data dir is kept under ``--capture DIR`` and
reused when it is there already.

The replay: a fresh ``MatcherService`` on a real SQLite file (the bus replaced by a sink),
the entries in their original order (``gseq``) in batches of ``--batch`` entries, each
batch applied in one transaction as the stage loop does. Measured: the process CPU time
and the wall time of the replay (not of the reading), so observations/s per core is the
observations replayed over the CPU seconds. Also the memory the matcher's state holds at
the end, per landmark and per pending ray (``tracemalloc`` over a reload of the final
state into a second service, which allocates exactly what the state needs), and a
checksum of the final landmark table, so two code versions can be compared on the same
capture for both speed and result. ``--solver``: the matcher's assoc log is then replayed
through a fresh ``SolverService`` the same way (``--solver-batch`` entries a transaction),
its CPU per observation received and a checksum of its final sums.

    .venv/bin/python benchmarks/bench_matcher_replay.py [--quick] [--capture DIR] \
        [--passes N] [--batch N] [--set KEY=JSON ...] [--solver [--solver-batch N]] \
        [--json out/bench/matcher_replay.json]
"""

from __future__ import annotations

import argparse
import hashlib
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import machine, machine_line, write_json
from hdmap.runtime.config import parse_settings
from hdmap.runtime.service import ServiceOptions
from schemas import LogEntry, ObsGroup
from services.matcher.replay import (
    Sink,
    landmark_digest,
    matcher_config,
    open_matcher,
    read_log,
    read_obs_log,
    replay,
)
from services.matcher.service import MatcherConfig
from services.solver.service import SolverService


def capture(out: Path, passes: int, rounds: int) -> Path:
    """The ingest database of a fleet evaluation run into ``out`` (made if missing)."""
    db = out / "run" / "var" / "ingest-all" / "state.sqlite"
    if db.exists():
        return db
    cmd = [sys.executable, "-m", "hdmap.cli", "eval", "fleet", "--out", str(out)]
    cmd += ["--passes", str(passes), "--rounds", str(rounds)]
    print(f"capture: {' '.join(cmd[2:])}", file=sys.stderr, flush=True)
    subprocess.run(cmd, check=True, timeout=3600, stdout=subprocess.DEVNULL)
    return db


def timed_replay(
    entries: list[LogEntry], batch: int, data_dir: Path, config: MatcherConfig | None = None
) -> dict:
    """Apply ``entries`` to a fresh matcher in batches; CPU and wall seconds, counts."""
    svc = open_matcher(data_dir, config)
    n_obs = sum(len(ObsGroup.from_bytes(e.body).obs) for e in entries)
    every = max(1, len(entries) // 20)

    def progress(done: int) -> None:
        if done % every < batch or done == len(entries):
            print(f"replay: {done}/{len(entries)} entries", file=sys.stderr, flush=True)

    cpu0, wall0 = time.process_time(), time.perf_counter()
    replay(svc, entries, batch, progress)
    cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
    out = {
        "entries": len(entries),
        "observations": n_obs,
        "batch_entries": batch,
        "cpu_s": cpu,
        "wall_s": wall,
        "obs_per_cpu_s": n_obs / cpu if cpu > 0 else None,
        "cpu_us_per_obs": 1e6 * cpu / n_obs if n_obs else None,
        "gating_ticks": svc.matching.tick_serial,
        "units_per_tick": len(entries) / max(1, svc.matching.tick_serial),
        "landmarks": len(svc.state.landmarks),
        "pending_rays": svc.state.pending_count(),
        "counters": {k: v for k, v in sorted(svc.counters.items()) if isinstance(v, int | float)},
        "landmark_digest": landmark_digest(svc),
    }
    svc.db.close()
    return out


def timed_solver(matcher_db: Path, n_obs: int, batch: int, data_dir: Path) -> dict:
    """Apply the matcher's assoc log to a fresh solver in batches; CPU per observation the
    matcher received, and a checksum of the solver's final sums (every row array)."""
    assoc = read_log(matcher_db, "assoc")
    svc = SolverService(ServiceOptions(data_dir=data_dir))
    svc.pubs = Sink()  # type: ignore[assignment]
    cpu0 = time.process_time()
    replay(svc, assoc, batch)
    cpu = time.process_time() - cpu0
    h = hashlib.sha256()
    for name in svc.sums.ROW_ARRAYS:
        h.update(getattr(svc.sums, name).tobytes())
    out = {
        "entries": len(assoc),
        "batch_entries": batch,
        "cpu_s": cpu,
        "cpu_us_per_obs": 1e6 * cpu / n_obs if n_obs else None,
        "landmarks": len(svc.state.landmarks),
        "sums_digest": h.hexdigest()[:16],
    }
    svc.db.close()
    return out


def state_memory(data_dir: Path, config: MatcherConfig | None = None) -> dict:
    """Bytes the matcher allocates to hold the saved state (a reload, traced)."""
    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    svc = open_matcher(data_dir, config)
    held = tracemalloc.get_traced_memory()[0] - before
    tracemalloc.stop()
    n_lm, n_pend = len(svc.state.landmarks), svc.state.pending_count()
    svc.db.close()
    return {
        "state_bytes": held,
        "landmarks": n_lm,
        "pending_rays": n_pend,
        "bytes_per_landmark_and_pending_ray": held / max(1, n_lm + n_pend),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="24 passes, a smoke test")
    ap.add_argument("--capture", type=Path, default=None, help="capture dir (kept, reused)")
    ap.add_argument("--log", type=Path, default=None, help="an ingest state.sqlite to replay")
    ap.add_argument("--passes", type=int, default=160)
    ap.add_argument("--batch", type=int, default=64, help="entries per transaction")
    ap.add_argument(
        "--set",
        metavar="KEY=JSON",
        action="append",
        default=[],
        help="a matcher setting for the replay (dotted for nested: gate.chi2_gate=12; "
        "repeatable), to compare settings on one capture",
    )
    ap.add_argument("--solver", action="store_true", help="replay the assoc log in a solver")
    ap.add_argument("--solver-batch", type=int, default=16, help="its entries per transaction")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    overrides = parse_settings(args.set)
    config = matcher_config(overrides)
    passes, rounds = (24, 1) if args.quick else (args.passes, 1)
    with tempfile.TemporaryDirectory(prefix="bench-matcher-") as tmp:
        db = args.log or capture(args.capture or Path(tmp) / "capture", passes, rounds)
        entries = read_obs_log(db)
        print(f"matcher replay: {len(entries)} obs entries from {db}", file=sys.stderr)
        print(machine_line(machine()), file=sys.stderr)
        data_dir = Path(tmp) / "matcher"
        result = timed_replay(entries, args.batch, data_dir, config)
        result["memory"] = state_memory(data_dir, config)
        if args.solver:
            (db_file,) = data_dir.glob("*/state.sqlite")  # the service's own directory
            solved = timed_solver(
                db_file, result["observations"], args.solver_batch, Path(tmp) / "s"
            )
            result["solver"] = solved
    result = {"machine": machine(), "source": str(db), "settings": overrides, "replay": result}
    r = result["replay"]
    print(
        f"{r['observations']} observations in {r['entries']} entries: {r['cpu_s']:.1f} s CPU, "
        f"{r['wall_s']:.1f} s wall; {r['obs_per_cpu_s']:,.0f} obs/s per core "
        f"({r['cpu_us_per_obs']:.0f} us CPU per observation); {r['gating_ticks']} gating "
        f"ticks ({r['units_per_tick']:.1f} units a tick); {r['landmarks']} landmarks, "
        f"{r['pending_rays']} pending rays; state {r['memory']['state_bytes'] / 1e6:.1f} MB "
        f"({r['memory']['bytes_per_landmark_and_pending_ray']:.0f} B per landmark or pending "
        f"ray); digest {r['landmark_digest']}"
    )
    if "solver" in r:
        sv = r["solver"]
        print(
            f"solver: {sv['entries']} assoc entries, {sv['cpu_s']:.1f} s CPU "
            f"({sv['cpu_us_per_obs']:.1f} us per observation); {sv['landmarks']} landmarks; "
            f"sums digest {sv['sums_digest']}"
        )
    if args.json:
        write_json(args.json, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
