"""Raw Zenoh throughput for hdmap's payloads: the physical reference for the pipeline.

Same topology as the pipeline: a client process -> a router process -> a server
process, all on 127.0.0.1. Measured side by side in one run:

- request/reply with an upload-sized payload (an ObservationBatch of ``--batch``
  observations) answered by a trivial queryable with a 100-byte reply, from
  ``--threads`` concurrent requesters (what ingest's transport costs at most);
- publish/subscribe of the same payload with CongestionControl.BLOCK and
  Reliability.RELIABLE (what a stage-to-stage hop costs at most).

    .venv/bin/python benchmarks/bench_zenoh.py [--seconds 5] [--batch 500] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import machine
from fleetsim.synthetic import make_observations
from hdmap.ops.stack import Stack
from hdmap.runtime.bus import BusConfig, Publishers, open_session
from schemas import ObservationBatch


def serve(endpoint: str) -> None:
    """Child process: a queryable that answers 100 bytes, a subscriber that counts."""
    count = [0, 0]
    lock = threading.Lock()

    def on_query(q: zenoh.Query) -> None:
        q.reply(q.key_expr, b"a" * 100)
        q.drop()

    def on_sample(s: zenoh.Sample) -> None:
        with lock:
            count[0] += 1
            count[1] += len(s.payload)

    def on_count(q: zenoh.Query) -> None:
        with lock:
            q.reply(q.key_expr, json.dumps(count).encode())
        q.drop()

    with open_session(BusConfig(connect=(endpoint,))) as s:
        s.declare_queryable("bench/upload/*", on_query)
        s.declare_subscriber("bench/pub/**", on_sample)
        s.declare_queryable("bench/count", on_count)
        print("ready", flush=True)
        sys.stdin.read()  # until the parent closes our stdin


def bench_query(s: zenoh.Session, payload: bytes, seconds: float, threads: int) -> dict:
    lat: list[float] = []
    lock = threading.Lock()
    stop = time.monotonic() + seconds

    def worker(i: int) -> None:
        mine = []
        while time.monotonic() < stop:
            t = time.perf_counter()
            for r in s.get(
                f"bench/upload/v{i}",
                payload=payload,
                timeout=10.0,
                congestion_control=zenoh.CongestionControl.BLOCK,
            ):
                _ = r.ok
            mine.append(time.perf_counter() - t)
        with lock:
            lat.extend(mine)

    ts = [threading.Thread(target=worker, args=(i,)) for i in range(threads)]
    t0 = time.perf_counter()
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    el = time.perf_counter() - t0
    a = np.array(lat)
    return {
        "requests_per_s": len(a) / el,
        "p50_ms": float(np.percentile(a, 50) * 1e3),
        "p99_ms": float(np.percentile(a, 99) * 1e3),
    }


def bench_pub(s: zenoh.Session, payload: bytes, seconds: float) -> dict:
    pubs = Publishers(s)
    before = _count(s)
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        pubs.put("bench/pub/1202", payload)
        n += 1
    deadline = time.monotonic() + 30
    while _count(s)[0] - before[0] < n and time.monotonic() < deadline:
        time.sleep(0.05)
    el = time.perf_counter() - t0
    got = _count(s)[0] - before[0]
    pubs.close()
    return {"messages_per_s": got / el, "sent": n, "received": got, "lost": n - got}


def _count(s: zenoh.Session) -> list[int]:
    for r in s.get("bench/count", timeout=5.0):
        if r.ok is not None:
            return json.loads(r.ok.payload.to_bytes())
    return [0, 0]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--batch", type=int, default=500)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 4, 16])
    ap.add_argument("--json", type=Path)
    ap.add_argument("--serve", metavar="ENDPOINT", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.serve:
        serve(args.serve)
        return 0
    payload = ObservationBatch("veh-1", 1, 1, time.time(), make_observations(args.batch)).to_bytes()
    out: dict = {"machine": machine(), "batch": args.batch, "payload_bytes": len(payload)}
    with tempfile.TemporaryDirectory() as tmp, Stack(Path(tmp)) as st:
        st.start_router()
        child = subprocess.Popen(
            [sys.executable, __file__, "--serve", st.listen],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
        )
        try:
            assert child.stdout is not None and child.stdout.readline().strip() == b"ready"
            time.sleep(0.5)
            with open_session(st.bus) as s:
                for th in args.threads:
                    r = bench_query(s, payload, args.seconds, th)
                    r["obs_per_s"] = r["requests_per_s"] * args.batch
                    out[f"query_threads_{th}"] = r
                    print(
                        f"request/reply {th:>2} threads: {r['requests_per_s']:8.0f} req/s "
                        f"= {r['obs_per_s']:10.0f} obs/s  p50 {r['p50_ms']:.2f} ms  "
                        f"p99 {r['p99_ms']:.2f} ms",
                        flush=True,
                    )
                p = bench_pub(s, payload, args.seconds)
                p["obs_per_s"] = p["messages_per_s"] * args.batch
                out["pubsub"] = p
                print(
                    f"pub/sub BLOCK: {p['messages_per_s']:8.0f} msg/s = {p['obs_per_s']:10.0f}"
                    f" obs/s, lost {p['lost']}",
                    flush=True,
                )
        finally:
            if child.stdin:
                child.stdin.close()
            child.wait(10)
    print(json.dumps(out["machine"]))
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
