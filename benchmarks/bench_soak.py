"""Soak: steady load over hours of event time, every service's disk, RSS and the p99.

A router and the four services (hdmap.ops.stack.Stack, on 127.0.0.1) take a simulated
fleet (:mod:`fleetsim.loadgen`: ``--pool-passes`` of the demo town's passes replayed with
fresh ids and fresh GNSS biases, false positives and multipath jumps) at a
steady rate for ``--minutes`` of wall time, the observations' capture times running
``--speedup`` times faster than the wall clock (default 120: 15 minutes cover 30 hours of
traffic on the same town), starting ``--days-back`` days ago so that they stay inside
ingest's 30-day admission window. Every ``--sample-s`` seconds it records, per service,
the bytes of its data dir (the SQLite file, its WAL and shared memory) and its RSS, plus
the p99 latency (upload -> landmark update at a subscribed vehicle) of that interval and
the matcher's landmark count.

What a run that operators can leave alone looks like (issue 20's target): disk and RSS
plateau, growth in the second half of the run under 5 % of the first half's, while the
map keeps its landmarks. After the drain a map client following the town reads the
published map and scores it against the town's truth (``map``: found, false, duplicated,
mean error, 95 % coverage; all landmarks and the confirmed ones). The JSON says whether
each did (``disk.plateau``, ``rss.plateau``) and the disk's growth per hour of event
time; the PNG plots disk and RSS per service against event hours. ``rss_anon`` is the
same for the services' anonymous resident memory (``RssAnon``: heap, stacks, the
SQLite caches): RSS also counts shared mappings a process maps once and keeps, such as
Zenoh's 16 MiB shared-memory segment (``/dev/shm/*.zenoh``), which becomes resident in
the publisher at the first message over Zenoh's shared-memory threshold, hours into a
run; a leak shows in ``rss_anon``.

    .venv/bin/python benchmarks/bench_soak.py [--quick] [--json FILE] [--png FILE]

JSON: ``samples: [{wall_s, event_time_s, disk_bytes, rss_bytes, rss_anon_bytes, p99_s,
landmarks, disk_by_service, rss_by_service, rss_anon_by_service, activity}]``
(``activity``: per service the counters of :data:`ACTIVITY` so far), ``disk``, ``rss``
(``first_half``, ``second_half``: growth in bytes; ``fitted``, ``fitted_ratio``: the
same from a line fitted to each half; ``quarters``: the growth of each quarter;
``ratio``; ``plateau``; ``per_event_hour``), ``rss_anon`` (the same),
``landmarks`` (start, end: the matcher's, candidates included), ``map`` (``all``,
``confirmed``: :class:`fleetsim.score.MapScore`), ``config``, ``machine``, ``command``.
"""

from __future__ import annotations

import argparse
import itertools
import math
import sys
import tempfile
import threading
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import machine, machine_line, write_json
from fleetsim.loadgen import (
    Counters,
    LoadConfig,
    Reader,
    Vehicle,
    build_pool,
    new_run_id,
    percentiles,
    town_tiles_with_halo,
)
from fleetsim.score import score
from fleetsim.town_run import follow_town
from hdmap.cli.common import add_progress_argument
from hdmap.ops.progress import Progress, progress_wanted
from hdmap.ops.quiesce import totals, wait_quiet
from hdmap.ops.stack import SERVICE_NAMES, Stack
from hdmap.ops.status import collect
from hdmap.runtime.bus import open_session
from schemas.tables import STATUS_CONFIRMED
from vehicle.mapclient import MapClient

DAY = 86_400.0
ACTIVITY = (
    "catchups",
    "entries_replayed",
    "entries_gap",
    "checkpoints_taken",
    "snapshots",
    "inbox_overflows",
    "log_truncated",
)
"""Counters sampled with each service's RSS: what it was doing when its memory moved."""


def dir_bytes(path: Path) -> int:
    """Bytes of the files under ``path`` (a service's data dir)."""
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def sample(stack: Stack, session, t0: float, cfg: LoadConfig, counters: Counters, last: int):
    """One sample (and how many latencies were counted so far)."""
    t = totals(collect(session, 2.0))
    disk = {n: dir_bytes(stack.data_dir / f"{n}-all") for n in SERVICE_NAMES}
    rss = {n: int(t.get(n, {}).get("rss_bytes", 0)) for n in SERVICE_NAMES}
    anon = {n: int(t.get(n, {}).get("rss_anon_bytes", 0)) for n in SERVICE_NAMES}
    with counters.lock:
        n = counters.latency_count
        fresh = min(n - last, len(counters.latencies), 50_000)
        lat = list(itertools.islice(reversed(counters.latencies), fresh))
    wall = time.time()
    return {
        "wall_s": round(time.monotonic() - t0, 2),
        "event_time_s": round(cfg.capture_time(wall) - (cfg.event_start or 0.0), 1),
        "disk_bytes": sum(disk.values()),
        "rss_bytes": sum(rss.values()),
        "rss_anon_bytes": sum(anon.values()),
        "p99_s": percentiles(lat)["p99"],
        "landmarks": int(t.get("matcher", {}).get("landmarks", 0)),
        "disk_by_service": disk,
        "rss_by_service": rss,
        "rss_anon_by_service": anon,
        "activity": {
            name: {k: t.get(name, {}).get(k, 0) for k in ACTIVITY} for name in SERVICE_NAMES
        },
    }, n


def _fitted_growth(samples: list[dict], key: str) -> float:
    """Growth of ``key`` over ``samples`` from the least-squares line through all of them
    (slope times the span): a sample's scatter (RSS moves +-1.5 MB from sample to sample)
    weighs 1/n, not all of it as in the difference of the two end samples."""
    t = np.array([x["event_time_s"] for x in samples], float)
    y = np.array([x[key] for x in samples], float)
    if t.size < 2 or np.ptp(t) == 0:
        return 0.0
    return float(np.polyfit(t, y, 1)[0] * np.ptp(t))


def growth(samples: list[dict], key: str) -> dict:
    """Growth of ``key`` over the first and second half of the run (by event time): the
    end samples' differences (``first_half``, ``second_half``, ``ratio``, ``plateau``:
    ratio under 5 %) and the same from a line fitted to each half's samples (``fitted``,
    ``fitted_ratio``)."""
    if len(samples) < 3:
        return {"first_half": None, "second_half": None, "ratio": None, "plateau": None}
    mid = len(samples) // 2
    a, m, b = samples[0][key], samples[mid][key], samples[-1][key]
    first, second = m - a, b - m
    hours = (samples[-1]["event_time_s"] - samples[0]["event_time_s"]) / 3600.0
    ratio = second / first if first > 0 else None
    at = [samples[round(i * (len(samples) - 1) / 4)][key] for i in range(5)]
    fit = [_fitted_growth(samples[: mid + 1], key), _fitted_growth(samples[mid:], key)]
    return {
        "first_half": first,
        "second_half": second,
        "fitted": fit,
        "fitted_ratio": fit[1] / fit[0] if fit[0] > 0 else None,
        "quarters": [at[i + 1] - at[i] for i in range(4)],
        "ratio": ratio,
        "plateau": bool(ratio is not None and ratio < 0.05),
        "per_event_hour": (b - a) / hours if hours > 0 else None,
    }


def plot(report: dict, png: Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    s = report["samples"]
    hours = [x["event_time_s"] / 3600.0 for x in s]
    fig = Figure(figsize=(10, 10))
    FigureCanvasAgg(fig)
    panels = (
        ("disk_by_service", "disk MB"),
        ("rss_by_service", "RSS MB"),
        ("rss_anon_by_service", "anonymous RSS MB"),
    )
    for i, (key, label) in enumerate(panels):
        ax = fig.add_subplot(len(panels), 1, i + 1)
        for name in SERVICE_NAMES:
            ax.plot(hours, [x.get(key, {}).get(name, 0) / 1e6 for x in s], label=name)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        if i == 0:
            d = report["disk"]
            ratio = "-" if d["ratio"] is None else f"{d['ratio']:.2f}"
            ax.set_title(
                f"soak: {report['config']['rate']:.0f} obs/s, event time x{report['speedup']:g}; "
                f"disk growth 2nd/1st half {ratio}"
            )
            ax.legend(loc="upper left")
    fig.axes[-1].set_xlabel("event time, hours")
    fig.savefig(png, dpi=110)


def run(args: argparse.Namespace) -> dict:
    wall0 = time.time()
    cfg = LoadConfig(
        vehicles=args.vehicles,
        rate=args.rate,
        duration_s=args.minutes * 60.0,
        subscribers=1,
        pool_passes=args.pool_passes,
        run_id=new_run_id(),
        event_start=wall0 - args.days_back * DAY,
        event_speedup=args.speedup,
        event_wall0=wall0,
    )
    with tempfile.TemporaryDirectory(prefix="soak-") as tmp:
        stack = Stack(Path(tmp) / "stack")
        if args.retain_s > 0:  # every producer keeps its log this long past its consumers
            cfg_file = Path(tmp) / "retention.toml"
            cfg_file.write_text(
                "".join(
                    f"[{n}.retention]\nretain_s = {args.retain_s}\nevery_s = {args.truncate_s}\n"
                    for n in ("ingest", "matcher", "solver")
                )
                + f"[ingest.policy]\nmax_lag_s = {args.max_lag_s}\n"
            )
            for n in ("ingest", "matcher", "solver"):
                stack.extra_service_args[n] = ["--config", str(cfg_file)]
        try:
            stack.start_all()
            with open_session(stack.bus) as session:
                world, pool = build_pool(cfg)
                counters = Counters()
                stop = threading.Event()
                reader = Reader(session, town_tiles_with_halo(world), counters)
                vehicles = [
                    Vehicle(i, session, pool, cfg, counters, stop, cfg.run_id)
                    for i in range(cfg.vehicles)
                ]
                t0 = time.monotonic()
                samples, seen = [], 0
                n_samples = math.ceil(cfg.duration_s / args.sample_s)
                bar = Progress(n_samples, "samples", enabled=progress_wanted(args.no_progress))
                try:
                    for v in vehicles:
                        v.start()
                    while time.monotonic() - t0 < cfg.duration_s:
                        time.sleep(
                            min(args.sample_s, max(0.0, cfg.duration_s - (time.monotonic() - t0)))
                        )
                        x, seen = sample(stack, session, t0, cfg, counters, seen)
                        samples.append(x)
                        bar.note(
                            f"{x['wall_s']:6.0f} s  event {x['event_time_s'] / 3600:6.2f} h  "
                            f"disk {x['disk_bytes'] / 1e6:8.1f} MB  "
                            f"rss {x['rss_bytes'] / 1e6:7.1f} MB  "
                            f"p99 {x['p99_s'] if x['p99_s'] is None else round(x['p99_s'], 3)} s  "
                            f"landmarks {x['landmarks']}  acked {counters.accepted}"
                        )
                        bar.update()
                finally:
                    bar.close()
                    stop.set()
                    for v in vehicles:
                        v.join(timeout=cfg.max_attempts * (cfg.upload_timeout_s + 2.0) + 5.0)
                    drained = wait_quiet(session, timeout=120.0)
                    reader.close()
                end, _ = sample(stack, session, t0, cfg, counters, seen)
                scores = score_map(session, world)
        finally:
            stack.stop_all()
    return {
        "command": " ".join(sys.argv),
        "machine": machine(),
        "config": asdict(cfg),
        "speedup": args.speedup,
        "retain_s": args.retain_s,
        "max_lag_s": args.max_lag_s,
        "samples": samples,
        "after_drain": end,
        "drained": drained,
        "accepted": counters.accepted,
        "failed": counters.failed,
        "disk": growth(samples, "disk_bytes"),
        "rss": growth(samples, "rss_bytes"),
        "rss_anon": growth(samples, "rss_anon_bytes"),
        "landmarks": {
            "start": samples[0]["landmarks"] if samples else None,
            "end": end["landmarks"],
        },
        "map": scores,
    }


def score_map(session, world) -> dict:
    """The published map as a vehicle following the town reads it, scored against the
    town's signs: all landmarks, and the confirmed ones."""
    client = MapClient(session, radius_m=0.0)
    try:
        follow_town(client, world)
        client.wait_idle(30.0)
        lm = client.landmarks()
    finally:
        client.close()
    confirmed = lm.take(np.flatnonzero(lm.status == STATUS_CONFIRMED))
    return {"all": score(world, lm).as_dict(), "confirmed": score(world, confirmed).as_dict()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=15.0)
    ap.add_argument("--rate", type=float, default=1000.0, help="observations/s, whole fleet")
    ap.add_argument("--vehicles", type=int, default=10)
    ap.add_argument("--speedup", type=float, default=120.0)
    ap.add_argument(
        "--pool-passes",
        type=int,
        default=600,
        help="simulated passes the vehicles replay (a few dozen repeat each sign's "
        "detector errors too often: see fleetsim.loadgen)",
    )
    ap.add_argument("--days-back", type=float, default=29.0)
    ap.add_argument("--sample-s", type=float, default=30.0)
    ap.add_argument(
        "--retain-s",
        type=float,
        default=60.0,
        help="[NAME.retention] retain_s of the producers (0: their default, one day)",
    )
    ap.add_argument("--truncate-s", type=float, default=10.0, help="[NAME.retention] every_s")
    ap.add_argument(
        "--max-lag-s",
        type=float,
        default=3600.0,
        help="[ingest.policy] max_lag_s: the event time ingest's dedup table holds",
    )
    ap.add_argument(
        "--quick", action="store_true", help="2 minutes, 500 obs/s, a sample every 10 s"
    )
    ap.add_argument("--json", type=Path)
    ap.add_argument("--png", type=Path)
    add_progress_argument(ap)
    args = ap.parse_args()
    if args.quick:
        args.minutes, args.rate, args.sample_s = 2.0, 500.0, 10.0
    print(machine_line(machine()), file=sys.stderr)
    report = run(args)
    d, r, a = report["disk"], report["rss"], report["rss_anon"]
    print(
        f"disk: +{(d['first_half'] or 0) / 1e6:.1f} MB "
        f"then +{(d['second_half'] or 0) / 1e6:.1f} MB "
        f"({(d['per_event_hour'] or 0) / 1e6:.1f} MB per event hour; plateau: {d['plateau']}); "
        f"rss: +{(r['first_half'] or 0) / 1e6:.1f} MB "
        f"then +{(r['second_half'] or 0) / 1e6:.1f} MB "
        f"(plateau: {r['plateau']}); rss anon: +{(a['first_half'] or 0) / 1e6:.1f} MB "
        f"then +{(a['second_half'] or 0) / 1e6:.1f} MB (plateau: {a['plateau']}); "
        f"landmarks {report['landmarks']['start']} -> "
        f"{report['landmarks']['end']}; accepted {report['accepted']}, failed {report['failed']}"
    )
    for kind, m in report["map"].items():
        print(
            f"map ({kind}): {m['n_landmarks']} landmarks, found {m['found']} of {m['n_true']}, "
            f"false {m['false']}, duplicated {m['duplicated']}, "
            f"mean error {m['mean_err_m']:.2f} m, 95 % coverage {m['coverage95']:.2f}"
        )
    write_json(args.json, report)
    if args.png is not None:
        plot(report, args.png)
        print(f"wrote {args.png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
