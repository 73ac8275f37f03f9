"""A periodic catch-up as the tiles a producer ever wrote grow: per-tile offsets against
the watermark.

A consumer catches up every few seconds (and on every gap). This script runs a real
router, a producer's replay queryable (:class:`hdmap.runtime.log_out.LogServer`) over a
log of one entry in each of N tiles, and a consumer that has applied all of them; then
ten new entries are written and, side by side in one run, fetched with:

- ``per_tile``: the query form that lists every tile's offset (what consumers sent
  before the watermark; the producer answers it by scanning every tile it wrote);
- ``watermark``: :func:`hdmap.runtime.catchup.catch_up` (the tiles active
  since the last catch-up and a ``gseq`` watermark per producer).

It reports the query's size and the seconds per catch-up for each N, and checks both
got the ten entries. ``--quick``: N up to 10,000.

    .venv/bin/python benchmarks/bench_catchup.py --json out/bench/catchup.json
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import machine, machine_line, write_json
from hdmap.ops.stack import Stack
from hdmap.runtime.bus import open_session, query
from hdmap.runtime.catchup import catch_up
from hdmap.runtime.log_out import LogServer, LogWriter
from hdmap.runtime.store import connect, transaction
from hdmap.runtime.stream import LogConsumer
from schemas import LogEntry, LogQuery

PRODUCER = "ingest-bench"
REPEATS = 5


def quadkey(i: int, zoom: int = 12) -> str:
    return "".join(str((i >> (2 * k)) & 3) for k in reversed(range(zoom)))


def _per_tile(session, consumer: LogConsumer) -> tuple[int, int]:
    offsets: dict[str, dict[str, int]] = {}
    for (p, t), s in consumer.offsets.items():
        offsets.setdefault(p, {})[t] = s
    req = LogQuery("obs", offsets, [], 2000).to_bytes()
    got = [
        LogEntry.from_bytes(ok)
        for _k, ok, _e in query(session, "hdmap/v1/log/obs/*/*", req, timeout=60)
        if ok is not None
    ]
    return len(req), len(got)


def _one(st: Stack, tmp: Path, n_tiles: int) -> dict:
    prod = connect(tmp / f"p{n_tiles}.sqlite")
    writer = LogWriter(prod, "obs", PRODUCER)
    with transaction(prod, [writer]):
        for i in range(n_tiles):
            writer.append(quadkey(i), b"x" * 64)
    cons = connect(tmp / f"c{n_tiles}.sqlite")
    consumer = LogConsumer(cons, "obs", [])
    out: dict = {"tiles": n_tiles}
    with open_session(st.bus) as s:
        server = LogServer(s, tmp / f"p{n_tiles}.sqlite", "obs", PRODUCER)
        try:
            time.sleep(0.3)
            got = catch_up(consumer, s, timeout=60)
            with transaction(cons, [consumer]):
                consumer.record(got)
            assert len(got) == n_tiles, (len(got), n_tiles)
            for strategy in ("per_tile", "watermark"):
                secs, sizes, counts = [], [], []
                for r in range(REPEATS):
                    with transaction(prod, [writer]):
                        new = [writer.append(quadkey(i), b"y") for i in range(10 * r, 10 * r + 10)]
                    t0 = time.perf_counter()
                    if strategy == "per_tile":
                        size, n = _per_tile(s, consumer)
                    else:
                        size = len(consumer.query(2000).to_bytes())
                        n = len(catch_up(consumer, s, timeout=60))
                    secs.append(time.perf_counter() - t0)
                    sizes.append(size)
                    counts.append(n)
                    with transaction(cons, [consumer]):  # both: the ten are applied
                        consumer.record(new)
                out[strategy] = {
                    "seconds": secs,
                    "median_s": sorted(secs)[len(secs) // 2],
                    "query_bytes": max(sizes),
                    "entries_received": counts,
                }
                print(
                    f"{n_tiles:>7} tiles {strategy:>9}: query {max(sizes):>9} bytes, "
                    f"median {out[strategy]['median_s'] * 1000:8.1f} ms, got {counts}",
                    flush=True,
                )
        finally:
            server.close()
            prod.close()
            cons.close()
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tiles", default="1000,10000,100000")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    sizes = [1000, 10_000] if args.quick else [int(x) for x in args.tiles.split(",")]
    m = machine()
    print(machine_line(m), flush=True)
    report: dict = {"machine": m, "repeats": REPEATS, "runs": []}
    with tempfile.TemporaryDirectory() as tmp, Stack(Path(tmp)) as st:
        st.start_router()
        for n in sizes:
            report["runs"].append(_one(st, Path(tmp), n))
    ok = all(
        all(c == 10 for c in run[s]["entries_received"])
        for run in report["runs"]
        for s in ("per_tile", "watermark")
    )
    last = report["runs"][-1]
    report["ratio_per_tile_over_watermark"] = (
        last["per_tile"]["median_s"] / last["watermark"]["median_s"]
    )
    print(
        f"at {last['tiles']} tiles: per-tile {last['per_tile']['median_s'] * 1000:.1f} ms, "
        f"watermark {last['watermark']['median_s'] * 1000:.1f} ms "
        f"({report['ratio_per_tile_over_watermark']:.0f}x); every catch-up got its ten: {ok}",
        flush=True,
    )
    write_json(args.json, report)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
