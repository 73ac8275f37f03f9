"""Puts to many distinct keys: the cost per new key, declared publishers against ``session.put``.

An upload spread over many tiles makes ingest write to one key per tile. This script
runs a real router and a subscriber on ``bench/keys/**`` (another session), and, side by
side in one run, writes blocks of 2,000 new keys each with:

- ``declared``: one publisher declared per new key and kept (what ``hdmap.runtime.bus``
  did before it kept no per-key state);
- ``put``: ``hdmap.runtime.bus.Publishers.put`` (``session.put``, BLOCK, nothing kept).

It reports the seconds per block as the keys already written grow, and checks every
message arrived. ``--quick``: 4,000 keys.

    .venv/bin/python benchmarks/bench_keys.py --keys 10000 --json out/bench/keys.json
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
from pathlib import Path

import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import machine, machine_line, write_json
from hdmap.ops.stack import Stack
from hdmap.runtime.bus import Publishers, open_session

BLOCK = 2000


def _run(st: Stack, strategy: str, n_keys: int) -> dict:
    got = [0]
    lock = threading.Lock()

    def on_sample(_s: zenoh.Sample) -> None:
        with lock:
            got[0] += 1

    blocks = []
    with open_session(st.bus) as sub_s, open_session(st.bus) as pub_s:
        sub = sub_s.declare_subscriber(f"bench/keys/{strategy}/**", on_sample)
        time.sleep(0.5)
        pubs = Publishers(pub_s)
        declared: list[zenoh.Publisher] = []
        for b in range(n_keys // BLOCK):
            t0 = time.perf_counter()
            for i in range(BLOCK):
                key = f"bench/keys/{strategy}/{b}/{i}"
                if strategy == "declared":
                    p = pub_s.declare_publisher(
                        key, congestion_control=zenoh.CongestionControl.BLOCK
                    )
                    p.put(b"x" * 64)
                    declared.append(p)
                else:
                    pubs.put(key, b"x" * 64)
            blocks.append(time.perf_counter() - t0)
            print(
                f"{strategy:>8}: keys {b * BLOCK:>6}-{(b + 1) * BLOCK:<6} {blocks[-1]:.3f} s",
                flush=True,
            )
        deadline = time.monotonic() + 30
        while got[0] < n_keys and time.monotonic() < deadline:
            time.sleep(0.05)
        for p in declared:
            p.undeclare()
        sub.undeclare()
    return {"seconds_per_block": blocks, "sent": n_keys, "received": got[0]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keys", type=int, default=10_000)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    n = 4000 if args.quick else max(BLOCK, args.keys // BLOCK * BLOCK)
    m = machine()
    print(machine_line(m), flush=True)
    out: dict = {"machine": m, "keys": n, "block": BLOCK}
    with tempfile.TemporaryDirectory() as tmp, Stack(Path(tmp)) as st:
        st.start_router()
        for strategy in ("put", "declared"):
            out[strategy] = _run(st, strategy, n)
    last = {s: out[s]["seconds_per_block"][-1] for s in ("put", "declared")}
    out["last_block_ratio_declared_over_put"] = last["declared"] / last["put"]
    print(
        f"last block of {BLOCK}: declared {last['declared']:.3f} s, put {last['put']:.3f} s "
        f"({out['last_block_ratio_declared_over_put']:.0f}x); received "
        f"{out['put']['received']}/{n} and {out['declared']['received']}/{n}",
        flush=True,
    )
    write_json(args.json, out)
    return 0 if all(out[s]["received"] == n for s in ("put", "declared")) else 1


if __name__ == "__main__":
    sys.exit(main())
