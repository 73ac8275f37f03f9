"""What batch size costs: the matcher and the solver on captured logs, in-process, at
several batch sizes side by side (CPU microseconds per observation; the result the same).

A stage service applies each batch of entries its worker takes from the inbox in one
transaction (:class:`hdmap.runtime.service.Batching`): one commit, one state save and, in
the solver, one re-solve and publish of what the batch touched. Live at a moderate rate a
worker that takes only what is there gets one entry at a time. This replays a run's logs
(its data dir: ``ingest-*/state.sqlite`` holds the obs log the matcher consumed,
``matcher-*/state.sqlite`` the assoc log the solver consumed) into a fresh matcher and a
fresh solver on real SQLite files, in batches of each of ``--batches`` entries, the
sizes alternated over ``--repeat`` rounds; per service and batch size the CPU seconds
(best of the rounds) over the observations, and the result's checksum (the matcher's
landmark digest; the solver's published updates), which must not depend on the batch size.

By default the capture is a fleet evaluation of ``--passes`` passes (made once under
``--capture DIR``, as ``bench_matcher_replay.py`` makes it); ``--stack DIR`` replays any
run's data dir instead (``bench_e2e.py --data-dir DIR`` keeps a load test's, under
``DIR/stack``).

    .venv/bin/python benchmarks/bench_batching.py [--stack DIR | --capture DIR] \
        [--batches 1 4 16 64] [--repeat 2] [--json out/bench/batching.json]
"""

from __future__ import annotations

import argparse
import hashlib
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.bench_matcher_replay import capture
from benchmarks.common import machine, machine_line, write_json
from hdmap.runtime.service import ServiceOptions
from schemas import AssocGroup, LandmarkUpdates, LogEntry, ObsGroup
from services.matcher.replay import Sink, landmark_digest, open_matcher, read_log, replay
from services.solver.service import SolverService


def one_db(root: Path, service: str) -> Path:
    """The state file of the one ``service`` instance under a data dir."""
    found = sorted(root.glob(f"{service}-*/state.sqlite"))
    if len(found) != 1:
        raise SystemExit(f"{root}: expected one {service}-*/state.sqlite, found {len(found)}")
    return found[0]


def run_matcher(entries: list[LogEntry], batch: int, tmp: Path) -> tuple[float, str]:
    svc = open_matcher(tmp)
    cpu0 = time.process_time()
    replay(svc, entries, batch)
    cpu = time.process_time() - cpu0
    digest = landmark_digest(svc)
    svc.db.close()
    return cpu, digest


def run_solver(entries: list[LogEntry], batch: int, tmp: Path) -> tuple[float, str]:
    svc = SolverService(ServiceOptions(data_dir=tmp))
    sink = Sink(keep=True)
    svc.pubs = sink  # type: ignore[assignment]
    cpu0 = time.process_time()
    replay(svc, entries, batch)  # type: ignore[arg-type]
    cpu = time.process_time() - cpu0
    svc.db.close()
    return cpu, final_digest(sink.sent)


def final_digest(sent: list[tuple[str, bytes]]) -> str:
    """Checksum of every landmark's last published state (id, revision aside: a larger
    batch publishes a landmark fewer times), and of the removals."""
    last: dict[int, tuple] = {}
    removed: set[int] = set()
    for _key, payload in sent:
        u = LandmarkUpdates.from_bytes(LogEntry.from_bytes(payload).body)
        lm = u.landmarks
        for k, i in enumerate(lm.id.tolist()):
            last[i] = (lm.lat[k], lm.lon[k], lm.h[k], *lm.cov[k], lm.status[k], lm.n_obs[k])
            removed.discard(i)
        for i in u.removed.id.tolist():
            removed.add(i)
            last.pop(i, None)
    h = hashlib.sha256(repr(sorted(last.items())).encode())
    h.update(repr(sorted(removed)).encode())
    return h.hexdigest()[:16]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--stack", type=Path, help="a run's data dir (ingest-*/, matcher-*/)")
    ap.add_argument("--capture", type=Path, help="fleet capture dir (kept, reused)")
    ap.add_argument("--passes", type=int, default=160)
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 4, 16, 64])
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench-batching-") as tmp_s:
        tmp = Path(tmp_s)
        if args.stack is None:
            db = capture(args.capture or tmp / "capture", args.passes, 1)
            root = db.parents[1]
        else:
            root = args.stack
        obs = read_log(one_db(root, "ingest"), "obs")
        assoc = read_log(one_db(root, "matcher"), "assoc")
        n_obs = sum(len(ObsGroup.from_bytes(e.body).obs) for e in obs)
        n_links = sum(len(AssocGroup.from_bytes(e.body).links) for e in assoc)
        print(machine_line(machine()), file=sys.stderr)
        print(
            f"{root}: {len(obs)} obs entries ({n_obs} obs), {len(assoc)} assoc entries "
            f"({n_links} links)",
            file=sys.stderr,
            flush=True,
        )
        runs: dict[str, dict[int, list[float]]] = {"matcher": {}, "solver": {}}
        digests: dict[str, dict[int, str]] = {"matcher": {}, "solver": {}}
        k = 0
        for rnd in range(args.repeat):
            order = args.batches if rnd % 2 == 0 else list(reversed(args.batches))
            for b in order:
                for name, fn, entries in (
                    ("matcher", run_matcher, obs),
                    ("solver", run_solver, assoc),
                ):
                    k += 1
                    cpu, dig = fn(entries, b, tmp / f"{name}-{k}")
                    runs[name].setdefault(b, []).append(cpu)
                    digests[name][b] = dig
                    print(
                        f"round {rnd + 1} {name} batch {b}: {cpu:.2f} s CPU, digest {dig}",
                        file=sys.stderr,
                        flush=True,
                    )
    per = {"matcher": n_obs, "solver": n_links}
    table = {
        name: {
            str(b): {
                "cpu_s": min(cpus),
                "cpu_us_per_obs": 1e6 * min(cpus) / per[name],
                "ratio_to_largest": min(cpus) / min(runs[name][max(args.batches)]),
                "digest": digests[name][b],
            }
            for b, cpus in sorted(runs[name].items())
        }
        for name in runs
    }
    same = {name: len(set(digests[name].values())) == 1 for name in digests}
    out = {
        "machine": machine(),
        "source": str(root),
        "observations": n_obs,
        "links": n_links,
        "repeat": args.repeat,
        "batches": table,
        "same_result": same,
    }
    for name, rows in table.items():
        cells = ", ".join(
            f"batch {b}: {r['cpu_us_per_obs']:.0f} us ({r['ratio_to_largest']:.2f}x)"
            for b, r in rows.items()
        )
        print(f"{name} CPU per observation: {cells}; same result at every size: {same[name]}")
    if args.json:
        write_json(args.json, out)
    return 0 if all(same.values()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
