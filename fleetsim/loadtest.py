"""The load test: a simulated fleet against a running stack (``hdmap loadtest``).

:func:`run_load` waits until the stack is quiet, snapshots every service's counters, runs
the fleet for ``LoadConfig.duration_s`` seconds (with a live progress line on stderr:
:class:`hdmap.ops.progress.Progress`, seconds of load done, the ETA and the live rates),
waits until the chain has applied everything (the drain, bounded by ``drain_timeout``),
snapshots again and reports the differences (the services' counters are durable and
cumulative, so only before/after deltas mean anything). :func:`run_loadtest` does the same
on a session of its own (:class:`LoadtestOptions`); :func:`format_report` is the text.

The report has these keys (:data:`REPORT_KEYS`):

- ``run_id``, ``config``: the vehicle id tag and the :class:`LoadConfig`;
- ``load_s``, ``drain_s``, ``drained``, ``started_quiet``: phase lengths and whether the
  chain was quiet at the end of the drain and before the load started;
- ``sent``, ``accepted``, ``duplicates``, ``rejected``, ``failed``, ``retries``,
  ``batches``: what the fleet's vehicles uploaded and got acknowledged (observations);
- ``accepted_per_s``: acknowledged observations/s during the load;
  ``sustained_per_s``: observations the matcher processed / (load + drain), i.e. the rate
  the whole chain sustained; ``target_per_s``: the configured rate;
- ``deltas``, ``deltas_per_s`` (all subscribed vehicles together),
  ``deltas_per_s_per_subscriber``, ``delta_landmarks``: map deltas delivered;
- ``latency_s`` {p50, p95, p99} and ``latency_samples``: ingest receipt of an observation
  -> the landmark update carrying it at a subscribed vehicle (per landmark per delta);
  ``ack_latency_s`` {p50, p95, p99}: upload -> ack at the vehicle;
- ``chain``: counter deltas along the chain; ``losses``: their differences, all 0 when
  every accepted observation was applied exactly once; ``zero_loss``;
- ``services``: per service ``cpu_s``, ``cpu_share`` (of one core over load + drain),
  ``cpu_us_per_obs`` (its CPU over the observations ingest accepted in the run: what one
  observation costs it, the issue's budget is 20 us), ``rss_peak_mb``, ``instances``,
  ``restarted``; ``instances``: the same per instance;
  ``loadgen``: the same for this process. A service's peak RSS is the largest of its
  current RSS (``rss_bytes`` in its stats) sampled about once a second during the run,
  not its ``rss_peak_bytes`` (``ru_maxrss``, which on Linux survives ``exec`` and so
  starts at the RSS of whatever process spawned the service).
"""

from __future__ import annotations

import itertools
import os
import resource
import sys
import threading
import time
from dataclasses import asdict, dataclass, field, replace

import psutil
import zenoh

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
from hdmap.ops.progress import Progress
from hdmap.ops.quiesce import is_quiet, totals, wait_quiet
from hdmap.ops.stack import SERVICE_NAMES
from hdmap.ops.status import collect
from hdmap.runtime.bus import BusConfig, open_session
from schemas import Stats

REPORT_KEYS = (
    "run_id",
    "config",
    "load_s",
    "drain_s",
    "drained",
    "started_quiet",
    "sent",
    "accepted",
    "duplicates",
    "rejected",
    "failed",
    "retries",
    "batches",
    "target_per_s",
    "accepted_per_s",
    "sustained_per_s",
    "deltas",
    "deltas_per_s",
    "deltas_per_s_per_subscriber",
    "delta_landmarks",
    "latency_s",
    "latency_samples",
    "ack_latency_s",
    "chain",
    "losses",
    "zero_loss",
    "services",
    "instances",
    "loadgen",
)
"""Top-level keys of the report (documented in the module docstring)."""


def _lag(t: dict[str, dict[str, float]]) -> str:
    """How far each stage is behind its upstream (entries), for the drain line."""
    parts = []
    for up, down in (("ingest", "matcher"), ("matcher", "solver"), ("solver", "publisher")):
        lag = t.get(up, {}).get("log_entries", 0) - t.get(down, {}).get("entries_applied", 0)
        parts.append(f"{down} {lag:.0f}")
    backlog = sum(v.get("backlog", 0) for v in t.values())
    return "behind by (entries) " + ", ".join(parts) + f"; inbox backlog {backlog:.0f}"


def run_load(
    session: zenoh.Session,
    cfg: LoadConfig,
    drain_timeout: float = 120.0,
    progress: bool = True,
    quiet_timeout: float = 60.0,
) -> dict:
    """Run the fleet against the stack on ``session``; the report (see the module doc).

    Every loop is bounded: the load by ``cfg.duration_s``, vehicles' last uploads by
    their attempts and timeouts, the drain by ``drain_timeout``, the initial wait for
    a quiet chain by ``quiet_timeout``."""
    run_id = cfg.run_id or new_run_id()
    cfg = replace(cfg, run_id=run_id)
    present = {s.service for s in collect(session)}
    missing = [n for n in SERVICE_NAMES if n not in present]
    if missing:
        raise RuntimeError(f"no live {', '.join(missing)} on the bus (is `hdmap up` running?)")
    world, pool = build_pool(cfg)
    tiles = town_tiles_with_halo(world)
    counters = Counters()
    if progress:
        print("waiting for a quiet chain before the load ...", file=sys.stderr, flush=True)
    started_quiet = wait_quiet(session, timeout=quiet_timeout)
    before = collect(session)
    rss = RssPeaks()
    rss.sample(before)
    me = psutil.Process(os.getpid())
    cpu0 = sum(me.cpu_times()[:2])
    readers: list[Reader] = []
    stop = threading.Event()
    vehicles = [Vehicle(i, session, pool, cfg, counters, stop, run_id) for i in range(cfg.vehicles)]
    t0 = time.monotonic()
    line = Progress(cfg.duration_s, "load", unit="s", rate=False, enabled=progress)
    try:
        readers = [Reader(session, tiles, counters) for _ in range(cfg.subscribers)]
        for v in vehicles:
            v.start()
        last = (t0, 0, 0, 0)
        while (elapsed := time.monotonic() - t0) < cfg.duration_s:
            time.sleep(min(1.0, max(0.0, cfg.duration_s - elapsed)))
            rss.sample(collect(session, timeout=1.0))
            now = time.monotonic()
            with counters.lock:
                acc, dl, nlat = counters.accepted, counters.deltas, counters.latency_count
                fresh = min(nlat - last[3], len(counters.latencies), 20000)
                lat = list(itertools.islice(reversed(counters.latencies), fresh))
                failed = counters.failed
            dt = max(now - last[0], 1e-9)
            pc = percentiles(lat)
            lat_txt = f"p50 {pc['p50']:.3f} s p99 {pc['p99']:.3f} s" if lat else "(no update yet)"
            line.set(
                round(min(now - t0, cfg.duration_s), 1),
                f"accepted {(acc - last[1]) / dt:6.0f} obs/s, deltas {(dl - last[2]) / dt:4.0f}/s, "
                f"latency {lat_txt}" + (f", FAILED {failed}" if failed else ""),
            )
            last = (now, acc, dl, nlat)
    finally:
        stop.set()
        join_s = cfg.max_attempts * (cfg.upload_timeout_s + 2.0) + 5.0
        deadline = time.monotonic() + join_s
        for v in vehicles:
            if v.is_alive():
                v.join(max(0.1, deadline - time.monotonic()))
        load_s = time.monotonic() - t0
        line.close()
        if sys.exc_info()[0] is not None:  # failing or interrupted: no drain
            for r in readers:
                r.close()
    drain_line = Progress(None, "drain", unit="s", rate=False, every_s=5.0, enabled=progress)
    try:
        drained = _drain(session, drain_line, drain_timeout, rss)
    finally:
        drain_s = time.monotonic() - t0 - load_s
        time.sleep(0.5)  # the last deltas in flight to the readers
        for r in readers:
            r.close()
        drain_line.close()
    after = collect(session)
    rss.sample(after)
    loadgen = {
        "cpu_s": sum(me.cpu_times()[:2]) - cpu0,
        "rss_peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e6,
    }
    loadgen["cpu_share"] = loadgen["cpu_s"] / max(load_s + drain_s, 1e-9)
    return report(
        cfg, counters, before, after, load_s, drain_s, drained, started_quiet, loadgen, rss.peaks
    )


class RssPeaks:
    """Largest current RSS seen per service instance (sampled from their stats)."""

    def __init__(self) -> None:
        self.peaks: dict[str, float] = {}

    def sample(self, stats: list[Stats]) -> None:
        for s in stats:
            v = float(s.counters.get("rss_bytes", 0.0))
            self.peaks[s.instance] = max(self.peaks.get(s.instance, 0.0), v)


def _drain(session: zenoh.Session, line: Progress, timeout: float, rss: RssPeaks) -> bool:
    """Until the chain is quiet (bounded), with the stages' lag on the progress line."""
    start = time.monotonic()
    deadline = start + timeout
    while (left := deadline - time.monotonic()) > 0:
        if wait_quiet(session, timeout=min(3.0, left)):
            return True
        stats = collect(session, timeout=2.0)
        rss.sample(stats)
        t = totals(stats)
        line.set(round(time.monotonic() - start), _lag(t))
    return is_quiet(totals(collect(session, timeout=2.0)))


def _delta(after: dict, before: dict, svc: str, key: str) -> float:
    return after.get(svc, {}).get(key, 0.0) - before.get(svc, {}).get(key, 0.0)


def _instances(
    before: list[Stats], after: list[Stats], elapsed: float, rss_peaks: dict[str, float]
) -> dict[str, dict]:
    """CPU and peak RSS per live instance over the run (a restarted one: since its start)."""
    prev = {s.instance: s for s in before}
    out = {}
    for s in after:
        b = prev.get(s.instance)
        restarted = b is None or b.started_at != s.started_at
        cpu = s.counters.get("cpu_s", 0.0) - (0.0 if restarted else b.counters.get("cpu_s", 0.0))
        out[s.instance] = {
            "service": s.service,
            "region": list(s.region),
            "cpu_s": cpu,
            "cpu_share": cpu / max(elapsed, 1e-9),
            "rss_peak_mb": max(
                rss_peaks.get(s.instance, 0.0), float(s.counters.get("rss_bytes", 0.0))
            )
            / 1e6,
            "restarted": restarted,
        }
    return out


def report(
    cfg: LoadConfig,
    c: Counters,
    before_stats: list[Stats],
    after_stats: list[Stats],
    load_s: float,
    drain_s: float,
    drained: bool,
    started_quiet: bool = True,
    loadgen: dict | None = None,
    rss_peaks: dict[str, float] | None = None,
) -> dict:
    before, after = totals(before_stats), totals(after_stats)
    d = {s: {k: _delta(after, before, s, k) for k in after.get(s, {})} for s in after}

    def g(svc: str, key: str) -> float:
        return d.get(svc, {}).get(key, 0)

    chain = {
        "acked_by_ingest": c.accepted,
        "ingest_accepted": g("ingest", "accepted"),
        "ingest_duplicates": g("ingest", "duplicates"),
        "matcher_received": g("matcher", "received"),
        "matcher_linked": g("matcher", "linked"),
        "matcher_pending_added": g("matcher", "received") - g("matcher", "linked"),
        "solver_applied": g("solver", "observations"),
        "ingest_log_entries": g("ingest", "log_entries"),
        "matcher_entries_applied": g("matcher", "entries_applied"),
        "matcher_log_entries": g("matcher", "log_entries"),
        "solver_entries_applied": g("solver", "entries_applied"),
        "solver_log_entries": g("solver", "log_entries"),
        "publisher_entries_applied": g("publisher", "entries_applied"),
        "publisher_deltas": g("publisher", "deltas"),
    }
    losses = {
        "ingest_vs_acked": chain["acked_by_ingest"] - chain["ingest_accepted"],
        "matcher_vs_ingest": chain["ingest_accepted"] - chain["matcher_received"],
        "solver_vs_matcher": chain["matcher_linked"] - chain["solver_applied"],
        "obs_entries_unapplied": chain["ingest_log_entries"] - chain["matcher_entries_applied"],
        "assoc_entries_unapplied": chain["matcher_log_entries"] - chain["solver_entries_applied"],
        "update_entries_unapplied": chain["solver_log_entries"]
        - chain["publisher_entries_applied"],
        "dead_lettered": sum(g(s, "entries_failed") for s in ("matcher", "solver", "publisher")),
    }
    elapsed = max(load_s + drain_s, 1e-9)
    instances = _instances(before_stats, after_stats, elapsed, rss_peaks or {})
    services: dict[str, dict] = {}
    for inst in instances.values():
        s = services.setdefault(
            inst["service"],
            {
                "cpu_s": 0.0,
                "cpu_share": 0.0,
                "rss_peak_mb": 0.0,
                "instances": 0,
                "restarted": False,
            },
        )
        s["cpu_s"] += inst["cpu_s"]
        s["cpu_share"] += inst["cpu_share"]
        s["rss_peak_mb"] = max(s["rss_peak_mb"], inst["rss_peak_mb"])
        s["instances"] += 1
        s["restarted"] = s["restarted"] or inst["restarted"]
    n_obs = chain["ingest_accepted"]
    for s in services.values():
        s["cpu_us_per_obs"] = 1e6 * s["cpu_s"] / n_obs if n_obs > 0 else None
    with c.lock:
        lat = percentiles(c.latencies)
        ack = percentiles(c.ack_latencies)
        n_lat = c.latency_count
    subs = max(cfg.subscribers, 1)
    return {
        "run_id": cfg.run_id,
        "config": asdict(cfg),
        "load_s": load_s,
        "drain_s": drain_s,
        "drained": drained,
        "started_quiet": started_quiet,
        "sent": c.sent,
        "accepted": c.accepted,
        "duplicates": c.duplicates,
        "rejected": c.rejected,
        "failed": c.failed,
        "retries": c.retries,
        "batches": c.batches,
        "target_per_s": cfg.rate,
        "accepted_per_s": c.accepted / max(load_s, 1e-9),
        "sustained_per_s": chain["matcher_received"] / elapsed,
        "deltas": c.deltas,
        "deltas_per_s": c.deltas / elapsed,
        "deltas_per_s_per_subscriber": c.deltas / elapsed / subs,
        "delta_landmarks": c.delta_landmarks,
        "latency_s": lat,
        "latency_samples": n_lat,
        "ack_latency_s": ack,
        "chain": chain,
        "losses": losses,
        "zero_loss": drained and all(v == 0 for v in losses.values()),
        "services": dict(sorted(services.items())),
        "instances": instances,
        "loadgen": loadgen or {},
    }


@dataclass(frozen=True)
class LoadtestOptions:
    load: LoadConfig = field(default_factory=LoadConfig)
    bus: BusConfig = field(default_factory=BusConfig)
    """Where to join the stack's bus."""
    drain_timeout: float = 120.0
    progress: bool = True
    """The live progress line on stderr."""


def run_loadtest(opts: LoadtestOptions) -> dict:
    """:func:`run_load` on a session of its own; raises RuntimeError when a service is
    missing and :class:`zenoh.ZError` when the bus cannot be joined."""
    with open_session(opts.bus) as session:
        return run_load(session, opts.load, opts.drain_timeout, progress=opts.progress)


def _s(v: float | None) -> str:
    return "-" if v is None else f"{v:.3f} s"


def format_report(r: dict) -> str:
    """The report as text: phases, throughput, deltas, latency, the chain, losses, and
    CPU and memory per service."""
    lat, ack = r["latency_s"], r["ack_latency_s"]
    ch = r["chain"]
    lines = [
        f"load {r['load_s']:.1f} s + drain {r['drain_s']:.1f} s "
        f"({'drained' if r['drained'] else 'NOT drained'}"
        f"{'' if r['started_quiet'] else '; the chain was NOT quiet before the load'})",
        f"accepted {r['accepted']} of {r['sent']} sent by {r['config']['vehicles']} vehicles "
        f"(run {r['run_id']}; {r['failed']} failed, {r['rejected']} rejected, "
        f"{r['retries']} retries): {r['accepted_per_s']:.0f} obs/s during the load "
        f"(target {r['target_per_s']:.0f}); sustained end to end incl. drain "
        f"{r['sustained_per_s']:.0f} obs/s",
        f"deltas delivered {r['deltas']} to {r['config']['subscribers']} subscribed vehicles "
        f"({r['deltas_per_s']:.1f}/s, {r['deltas_per_s_per_subscriber']:.1f}/s each; "
        f"{r['delta_landmarks']} landmark updates)",
        f"latency upload -> update at a subscribed vehicle: p50 {_s(lat['p50'])}  "
        f"p95 {_s(lat['p95'])}  p99 {_s(lat['p99'])} ({r['latency_samples']} samples); "
        f"upload -> ack p50 {_s(ack['p50'])}  p99 {_s(ack['p99'])}",
        f"chain: acked {ch['acked_by_ingest']:.0f} = ingest accepted {ch['ingest_accepted']:.0f}"
        f" = matcher received {ch['matcher_received']:.0f} (linked {ch['matcher_linked']:.0f}"
        f" + pending {ch['matcher_pending_added']:.0f}); solver applied "
        f"{ch['solver_applied']:.0f}",
        "losses: "
        + ", ".join(f"{k}={v:g}" for k, v in r["losses"].items())
        + f"  -> {'ZERO LOSS' if r['zero_loss'] else 'LOSS OR NOT DRAINED'}",
    ]
    rows = [(s, v) for s, v in r["services"].items()]
    if r["loadgen"]:
        rows.append(("loadgen", {**r["loadgen"], "instances": 1, "restarted": False}))
    for s, v in rows:
        lines.append(
            f"  {s:<10} cpu {v['cpu_s']:7.1f} s ({100 * v['cpu_share']:4.0f}% of a core)  "
            f"peak RSS {v['rss_peak_mb']:6.0f} MB"
            + (f"  ({v['instances']} instances)" if v["instances"] > 1 else "")
            + ("  RESTARTED during the run" if v["restarted"] else "")
        )
    return "\n".join(lines)
