"""``hdmap loadtest``: a simulated fleet against a running stack, with a live progress line.

Reports sustained accepted observations/s, deltas/s delivered to subscribed
vehicles, end-to-end latency (ingest receipt of an observation -> the landmark
update carrying it arrives at a subscribed vehicle; p50/p95/p99), losses (every
accepted observation applied exactly once: counts along the chain), and CPU and
peak RSS per service. Stops by itself after ``--duration`` and the drain.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from pathlib import Path

from fleetsim.loadgen import (
    Counters,
    LoadConfig,
    Reader,
    Vehicle,
    build_pool,
    percentiles,
    town_tiles_with_halo,
)
from hdmap.bus import open_session
from hdmap.commands.common import add_bus_arguments, bus_from_args
from hdmap.commands.status import collect
from hdmap.quiesce import totals, wait_quiet


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--vehicles", type=int, default=20)
    p.add_argument("--rate", type=float, default=5000.0, help="observations/s over the fleet")
    p.add_argument("--duration", type=float, default=30.0, help="seconds of load")
    p.add_argument("--batch", type=int, default=500, help="observations per upload")
    p.add_argument("--subscribers", type=int, default=2)
    p.add_argument("--drain-timeout", type=float, default=120.0)
    p.add_argument("--json", type=Path, metavar="FILE", help="write the report as JSON")
    p.add_argument("--quiet", action="store_true", help="no live progress line")
    add_bus_arguments(p)


def run_load(session, cfg: LoadConfig, drain_timeout: float = 120.0, progress: bool = True) -> dict:
    world, pool = build_pool(cfg)
    tiles = town_tiles_with_halo(world)
    counters = Counters()
    before = totals(collect(session))
    readers = [Reader(session, tiles, counters) for _ in range(cfg.subscribers)]
    stop = threading.Event()
    vehicles = [Vehicle(i, session, pool, cfg, counters, stop) for i in range(cfg.vehicles)]
    t0 = time.monotonic()
    for v in vehicles:
        v.start()
    last = (t0, 0, 0)
    try:
        while (now := time.monotonic()) - t0 < cfg.duration_s:
            time.sleep(1.0)
            with counters.lock:
                acc, dl = counters.accepted, counters.deltas
                lat = list(counters.latencies)[-5000:]
            dt = time.monotonic() - last[0]
            if progress:
                pc = percentiles(lat)
                print(
                    f"\r{now - t0:5.0f}s accepted {(acc - last[1]) / dt:8.0f} obs/s  "
                    f"deltas {(dl - last[2]) / dt:6.0f}/s  latency p50 {pc['p50']:.3f}s "
                    f"p99 {pc['p99']:.3f}s   ",
                    end="",
                    file=sys.stderr,
                    flush=True,
                )
            last = (time.monotonic(), acc, dl)
    finally:
        stop.set()
        for v in vehicles:
            v.join(15)
    load_s = time.monotonic() - t0
    drained = wait_quiet(session, timeout=drain_timeout)
    time.sleep(1.0)
    drain_s = time.monotonic() - t0 - load_s
    for r in readers:
        r.close()
    after = totals(collect(session))
    if progress:
        print(file=sys.stderr)
    return report(cfg, counters, before, after, load_s, drain_s, drained)


def _delta(after: dict, before: dict, svc: str, key: str) -> float:
    return after.get(svc, {}).get(key, 0.0) - before.get(svc, {}).get(key, 0.0)


def report(
    cfg: LoadConfig,
    c: Counters,
    before: dict,
    after: dict,
    load_s: float,
    drain_s: float,
    drained: bool,
) -> dict:
    d = {s: {k: _delta(after, before, s, k) for k in after.get(s, {})} for s in after}
    chain = {
        "acked_by_ingest": c.accepted - c.duplicates,
        "ingest_accepted": d.get("ingest", {}).get("accepted", 0),
        "matcher_received": d.get("matcher", {}).get("received", 0),
        "matcher_linked": d.get("matcher", {}).get("linked", 0),
        "solver_applied": d.get("solver", {}).get("observations", 0),
        "ingest_log_entries": d.get("ingest", {}).get("log_entries", 0),
        "matcher_entries_applied": d.get("matcher", {}).get("entries_applied", 0),
        "solver_log_entries": d.get("solver", {}).get("log_entries", 0),
        "publisher_entries_applied": d.get("publisher", {}).get("entries_applied", 0),
    }
    losses = {
        "ingest_vs_acked": chain["acked_by_ingest"] - chain["ingest_accepted"],
        "matcher_vs_ingest": chain["ingest_accepted"] - chain["matcher_received"],
        "solver_vs_matcher": chain["matcher_linked"] - chain["solver_applied"],
        "obs_entries_unapplied": chain["ingest_log_entries"] - chain["matcher_entries_applied"],
        "update_entries_unapplied": chain["solver_log_entries"]
        - chain["publisher_entries_applied"],
    }
    services = {
        s: {
            "cpu_s": d[s].get("cpu_s", 0.0),
            "cpu_share": d[s].get("cpu_s", 0.0) / max(load_s + drain_s, 1e-9),
            "rss_peak_mb": after[s].get("rss_peak_bytes", 0.0) / 1e6,
        }
        for s in sorted(after)
    }
    lat = percentiles(c.latencies)
    return {
        "config": cfg.__dict__,
        "load_s": load_s,
        "drain_s": drain_s,
        "drained": drained,
        "sent": c.sent,
        "accepted": c.accepted,
        "rejected": c.rejected,
        "failed": c.failed,
        "accepted_per_s": c.accepted / load_s,
        "sustained_per_s": chain["solver_applied"] / (load_s + drain_s),
        "deltas": c.deltas,
        "deltas_per_s": c.deltas / (load_s + drain_s),
        "delta_landmarks": c.delta_landmarks,
        "latency_s": lat,
        "chain": chain,
        "losses": losses,
        "zero_loss": drained and all(v == 0 for v in losses.values()),
        "services": services,
    }


def print_report(r: dict) -> None:
    print(
        f"load {r['load_s']:.1f} s + drain {r['drain_s']:.1f} s "
        f"({'drained' if r['drained'] else 'NOT drained'})"
    )
    print(
        f"accepted {r['accepted']} of {r['sent']} sent ({r['accepted_per_s']:.0f} obs/s during "
        f"load; {r['sustained_per_s']:.0f} obs/s applied end to end incl. drain)"
    )
    lat = r["latency_s"]
    print(
        f"deltas delivered {r['deltas']} ({r['deltas_per_s']:.1f}/s per subscriber set); "
        f"latency p50 {lat['p50']:.3f} s  p95 {lat['p95']:.3f} s  p99 {lat['p99']:.3f} s"
    )
    print(
        "losses: "
        + ", ".join(f"{k}={v:g}" for k, v in r["losses"].items())
        + f"  -> {'ZERO LOSS' if r['zero_loss'] else 'LOSS OR NOT DRAINED'}"
    )
    for s, v in r["services"].items():
        print(
            f"  {s:<10} cpu {v['cpu_s']:7.1f} s ({100 * v['cpu_share']:4.0f}% of a core)  "
            f"peak RSS {v['rss_peak_mb']:6.0f} MB"
        )


def run(args: argparse.Namespace) -> int:
    cfg = LoadConfig(
        vehicles=args.vehicles,
        rate=args.rate,
        duration_s=args.duration,
        batch=args.batch,
        subscribers=args.subscribers,
    )
    with open_session(bus_from_args(args)) as session:
        r = run_load(session, cfg, args.drain_timeout, progress=not args.quiet)
    print_report(r)
    if args.json:
        args.json.write_text(json.dumps(r, indent=1, default=float))
    return 0 if r["zero_loss"] else 1
