"""The publisher's own work per snapshot query it refuses: key parse, the client's and the
total bucket, and encoding the error reply (what runs on the Zenoh callback thread before
``reply_err``), in-process, for a Sybil flood (a new client id per query).

    .venv/bin/python benchmarks/bench_snapshot_admit.py --json out/bench/snapshot_admit.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import machine, machine_line, write_json
from schemas import keys
from services.publisher.limits import SnapshotLimiter, SnapshotLimits

TILE = "1202032333101011"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--queries", type=int, default=200_000)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    n = 20_000 if args.quick else args.queries
    m = machine()
    print(machine_line(m), flush=True)
    limiter = SnapshotLimiter(SnapshotLimits())
    selectors = [keys.map_snapshot_for(f"sybil-{i}", TILE) for i in range(n)]
    refused = 0
    t0 = time.perf_counter()
    for sel in selectors:
        _tile, client = keys.snapshot_request(sel)
        err = limiter.check(client)
        if err is not None:
            err.to_bytes()
            refused += 1
    per_query_us = (time.perf_counter() - t0) / n * 1e6
    print(f"{n} queries, {refused} refused: {per_query_us:.1f} us per query", flush=True)
    write_json(
        args.json, {"machine": m, "queries": n, "refused": refused, "us_per_query": per_query_us}
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
