"""End to end: the highest sustained observations/s with zero loss and p99 latency < 1 s.

A router and the four services (hdmap.ops.stack.Stack, on 127.0.0.1) get a simulated fleet
(``hdmap loadtest``'s :func:`run_load`) at stepped rates (1k, 2k, 5k, 10k, 20k, 30k, 50k,
100k obs/s; the goal is 100k, issue 19's target 30k), each step ``--seconds`` of load plus
its drain, on one stack (the map built by the first steps stays, like a running
deployment). A step passes when every accepted observation was applied exactly once (zero
loss, nothing failed), the fleet got its target rate acknowledged (>= 90 %), and the p99
latency (upload -> landmark update at a subscribed vehicle) is under 1 s; the ladder stops
at the first step that fails ``--retries`` + 1 times in a row (default twice: the machine
may be shared with other jobs; the load average is recorded with every step).

In the same run, before the ladder, the raw Zenoh throughput of the same payloads
(real upload payloads from the load generator's pool) through the same router,
measured with benchmarks/bench_zenoh.py's functions: request/reply (what an upload
costs at most) and BLOCK pub/sub (what a stage hop costs at most). The result is
reported as end-to-end / raw.

With ``--profile`` (default: when the goal is missed) the bottleneck service (the one
using the most CPU in the first failing step) is run again under cProfile at that rate,
on a fresh stack, and its top costs are printed.

    .venv/bin/python benchmarks/bench_e2e.py [--quick] [--json FILE] [--profile SERVICE]
"""

from __future__ import annotations

import argparse
import json
import os
import pstats
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import psutil

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks import bench_zenoh
from fleetsim.loadgen import LoadConfig, build_pool, upload_payloads
from fleetsim.loadtest import run_load
from hdmap.ops.stack import Stack
from hdmap.runtime.bus import open_session
from hdmap.runtime.config import parse_settings
from services.matcher.replay import matcher_config

ROOT = Path(__file__).resolve().parent.parent
RATES = (1_000, 2_000, 5_000, 10_000, 20_000, 30_000, 50_000, 100_000)
GOAL = 100_000
P99_MAX_S = 1.0


def load_average() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def vehicles_for(rate: float) -> int:
    """About 100 obs/s per vehicle (an upload every ~1 s), 10 to 200 vehicles."""
    return int(min(200, max(10, rate // 100)))


def fleet_admission(
    workdir: Path,
    linger_s: float | None = None,
    publish_interval_s: float | None = None,
    matcher_set: dict[str, object] | None = None,
) -> dict[str, list[str]]:
    """``Stack(extra_service_args=...)`` for an ingest that admits the load generator's
    fleet at once: its vehicles are new in every run (a fresh run tag), and up to 200 of
    them start together, past ingest's default budget of new vehicles (50 at once). With
    ``linger_s``, the stage services' batches linger that long (``[NAME.batching]``;
    None: their default); with ``publish_interval_s``, the publisher coalesces a tile's
    changes that long (``[publisher] interval_s``); ``matcher_set``: matcher settings
    (dotted keys for nested tables, ``gate.chi2_gate``), checked by the matcher's own
    config loading before the stack starts."""
    workdir.mkdir(parents=True, exist_ok=True)
    cfg = workdir / "stack.toml"
    text = "[ingest.rate_limit]\nnew_vehicle_burst = 1000.0\n"
    if matcher_set:
        matcher_config(matcher_set)  # an unknown key or a wrong type: an error naming it
        tables: dict[str, list[str]] = {}
        for key, value in matcher_set.items():
            head, _, last = key.rpartition(".")
            tables.setdefault(f"matcher.{head}" if head else "matcher", []).append(
                f"{last} = {toml_value(value)}"
            )
        text += "".join(f"[{t}]\n" + "\n".join(rows) + "\n" for t, rows in tables.items())
    if publish_interval_s is not None:
        text += f"[publisher]\ninterval_s = {float(publish_interval_s)!r}\n"
    if linger_s is not None:
        for name in ("matcher", "solver", "publisher"):
            text += f"[{name}.batching]\nlinger_s = {float(linger_s)!r}\n"
    cfg.write_text(text)
    return {name: ["--config", str(cfg)] for name in ("ingest", "matcher", "solver", "publisher")}


def toml_value(value: object) -> str:
    """A JSON scalar as a TOML value."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    raise ValueError(f"a matcher setting must be a number, a boolean or a string: {value!r}")


def load_config(rate: float, seconds: float, **kw) -> LoadConfig:
    return LoadConfig(vehicles=vehicles_for(rate), rate=float(rate), duration_s=seconds, **kw)


# -- profiling ------------------------------------------------------------------


def profiling_python(directory: Path, services: list[str]) -> str:
    """A stand-in for the Python interpreter that runs the named services under cProfile
    (profile written to ``directory/<service>.prof`` when the service exits on SIGTERM)
    and anything else unchanged. Used as ``Stack(python=...)``."""
    directory.mkdir(parents=True, exist_ok=True)
    cases = "".join(
        f'  *" service {s} "*) exec "{sys.executable}" -m cProfile '
        f'-o "{directory}/{s}.prof" "$@" ;;\n'
        for s in services
    )
    script = directory / "python-profiled"
    script.write_text(f'#!/bin/sh\ncase " $* " in\n{cases}esac\nexec "{sys.executable}" "$@"\n')
    script.chmod(0o755)
    return str(script)


def top_costs(prof: Path, n: int = 20) -> list[dict]:
    """The ``n`` functions with the most own time (tottime), with their cumulative time."""
    st = pstats.Stats(str(prof))
    total = st.total_tt  # type: ignore[attr-defined]
    rows = []
    for (file, line, func), (_cc, ncalls, tt, ct, _callers) in st.stats.items():  # type: ignore[attr-defined]
        rows.append(
            {
                "function": f"{Path(file).name}:{line}({func})",
                "path": file,
                "ncalls": ncalls,
                "tottime_s": tt,
                "cumtime_s": ct,
                "share_of_total": tt / total if total else 0.0,
            }
        )
    rows.sort(key=lambda r: -r["tottime_s"])
    return rows[:n]


def top_cumulative(prof: Path, n: int = 25, under: str = str(ROOT)) -> list[dict]:
    """The project's own functions (under the repository) with the most cumulative time."""
    st = pstats.Stats(str(prof))
    total = st.total_tt  # type: ignore[attr-defined]
    rows = [
        {
            "function": f"{Path(file).relative_to(under)}:{line}({func})",
            "ncalls": ncalls,
            "cumtime_s": ct,
            "share_of_total": ct / total if total else 0.0,
        }
        for (file, line, func), (_cc, ncalls, _tt, ct, _c) in st.stats.items()  # type: ignore[attr-defined]
        if file.startswith(under) and "/.venv/" not in file and func != "<module>"
    ]
    rows.sort(key=lambda r: -r["cumtime_s"])
    return rows[:n]


def print_profile(service: str, costs: list[dict], cumulative: list[dict]) -> None:
    print(f"\n{service} under cProfile: top own time (tottime)")
    for r in costs:
        print(
            f"  {r['tottime_s']:7.2f} s {100 * r['share_of_total']:5.1f}%  "
            f"{r['ncalls']:>9} calls  {r['function']}"
        )
    print(f"{service}: project functions by cumulative time")
    for r in cumulative:
        print(
            f"  {r['cumtime_s']:7.2f} s {100 * r['share_of_total']:5.1f}%  "
            f"{r['ncalls']:>9} calls  {r['function']}"
        )


# -- stack helpers ------------------------------------------------------------------


@dataclass
class ProcCpu:
    """CPU seconds of the stack's router process (not a service: no stats queryable)."""

    stack: Stack

    def router_cpu(self) -> float:
        p = self.stack.procs.get("router")
        if p is None or p.popen is None:
            return 0.0
        try:
            t = psutil.Process(p.popen.pid).cpu_times()
            return t.user + t.system
        except psutil.Error:
            return 0.0


def step(session, stack: Stack, cfg: LoadConfig, drain_timeout: float, progress: bool) -> dict:
    """One load step: the loadtest report, the router's CPU, the machine's load."""
    cpu = ProcCpu(stack)
    la0, r0 = load_average(), cpu.router_cpu()
    r = run_load(session, cfg, drain_timeout=drain_timeout, progress=progress)
    elapsed = r["load_s"] + r["drain_s"]
    r["router"] = {"cpu_s": cpu.router_cpu() - r0}
    r["router"]["cpu_share"] = r["router"]["cpu_s"] / max(elapsed, 1e-9)
    r["load_average_before"], r["load_average_after"] = la0, load_average()
    return r


def verdict(r: dict, rate: float) -> list[str]:
    """Why a step fails (empty: it passes)."""
    why = []
    if not r["zero_loss"]:
        why.append("loss or not drained: " + json.dumps(r["losses"]))
    if r["failed"]:
        why.append(f"{r['failed']} observations never acknowledged")
    if r["accepted_per_s"] < 0.9 * rate:
        why.append(f"fleet got only {r['accepted_per_s']:.0f} obs/s acknowledged")
    p99 = r["latency_s"]["p99"]
    if p99 is None or p99 >= P99_MAX_S:
        why.append(f"p99 latency {p99 if p99 is None else round(p99, 3)} s >= {P99_MAX_S} s")
    return why


def summary(r: dict) -> dict:
    keep = (
        "target_per_s",
        "accepted_per_s",
        "sustained_per_s",
        "load_s",
        "drain_s",
        "zero_loss",
        "failed",
        "retries",
        "deltas_per_s",
        "latency_s",
        "ack_latency_s",
        "losses",
        "services",
        "loadgen",
        "router",
        "load_average_before",
        "load_average_after",
    )
    return {k: r[k] for k in keep} | {"vehicles": r["config"]["vehicles"]}


def print_step(r: dict, why: list[str]) -> None:
    lat = r["latency_s"]
    cpu = ", ".join(
        f"{s} {100 * v['cpu_share']:.0f}%"
        for s, v in [*r["services"].items(), ("loadgen", r["loadgen"]), ("router", r["router"])]
    )
    per_obs = ", ".join(
        f"{s} {v['cpu_us_per_obs']:.0f}"
        for s, v in r["services"].items()
        if v.get("cpu_us_per_obs") is not None
    )
    p = [lat[k] if lat[k] is not None else float("nan") for k in ("p50", "p95", "p99")]
    print(
        f"{r['target_per_s']:>8.0f} obs/s target: accepted {r['accepted_per_s']:8.0f}/s, "
        f"sustained {r['sustained_per_s']:8.0f}/s, latency p50/p95/p99 "
        f"{p[0]:.3f}/{p[1]:.3f}/{p[2]:.3f} s, drain {r['drain_s']:.1f} s, "
        f"{'zero loss' if r['zero_loss'] else 'LOSS'} -> {'PASS' if not why else 'FAIL'}",
        flush=True,
    )
    print(f"          cpu (of one core): {cpu}; load average {r['load_average_after']}")
    print(f"          cpu us per observation: {per_obs}")
    for w in why:
        print(f"          {w}")


# -- raw Zenoh reference ------------------------------------------------------------------


def reference_payload(cfg: LoadConfig) -> tuple[bytes, int]:
    """A real upload payload of the load generator, of the median size."""
    _world, pool = build_pool(cfg)
    sizes = sorted(len(p) for parts in pool for p in parts)
    median = sizes[len(sizes) // 2]
    for payload, n in upload_payloads(pool, "load-ref-00000"):
        if n == median:
            return payload, n
    raise AssertionError("unreachable: the median size is in the pool")


def raw_zenoh(stack: Stack, payload: bytes, n_obs: int, seconds: float) -> dict:
    """bench_zenoh's request/reply and pub/sub through the stack's router, same payload."""
    child = subprocess.Popen(
        [sys.executable, bench_zenoh.__file__, "--serve", stack.listen],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
    )
    out: dict = {"payload_bytes": len(payload), "obs_per_payload": n_obs}
    try:
        assert child.stdout is not None and child.stdout.readline().strip() == b"ready"
        time.sleep(0.5)
        with open_session(stack.bus) as s:
            for th in (1, 4, 16):
                q = bench_zenoh.bench_query(s, payload, seconds, th)
                q["obs_per_s"] = q["requests_per_s"] * n_obs
                out[f"query_threads_{th}"] = q
                print(
                    f"raw request/reply {th:>2} threads: {q['requests_per_s']:7.0f} req/s = "
                    f"{q['obs_per_s']:9.0f} obs/s (p99 {q['p99_ms']:.1f} ms)",
                    flush=True,
                )
            p = bench_zenoh.bench_pub(s, payload, seconds)
            p["obs_per_s"] = p["messages_per_s"] * n_obs
            out["pubsub"] = p
            print(
                f"raw pub/sub BLOCK: {p['messages_per_s']:7.0f} msg/s = {p['obs_per_s']:9.0f}"
                f" obs/s, lost {p['lost']}",
                flush=True,
            )
    finally:
        if child.stdin:
            child.stdin.close()
        try:
            child.wait(10)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait(5)
    out["query_obs_per_s"] = max(out[f"query_threads_{t}"]["obs_per_s"] for t in (1, 4, 16))
    return out


# -- main ------------------------------------------------------------------


def profile_service(
    service: str,
    rate: float,
    seconds: float,
    drain_timeout: float,
    workdir: Path,
    admission: dict[str, list[str]],
) -> dict:
    """The load step at ``rate`` again, on a fresh stack with the services' arguments
    ``admission`` (:func:`fleet_admission`), ``service`` under cProfile."""
    prof_dir = workdir / "profile"
    python = profiling_python(prof_dir, [service])
    print(f"\nprofiling {service} at {rate:.0f} obs/s for {seconds:.0f} s (fresh stack) ...")
    with Stack(workdir / "stack-profiled", python=python, extra_service_args=admission) as st:
        st.start_all()
        with open_session(st.bus) as s:
            r = run_load(s, load_config(rate, seconds), drain_timeout, progress=False)
        st.stop_all(timeout=60.0)  # cProfile writes its file when the service exits
    prof = prof_dir / f"{service}.prof"
    if not prof.exists():
        return {"service": service, "error": f"no profile written ({prof})"}
    costs, cumulative = top_costs(prof), top_cumulative(prof)
    print_profile(service, costs, cumulative)
    return {
        "service": service,
        "rate": rate,
        "observations": r["chain"]["matcher_received"],
        "cpu_s_per_1000_obs": 1000
        * r["services"][service]["cpu_s"]
        / max(r["chain"]["matcher_received"], 1),
        "top_tottime": costs,
        "top_cumulative": cumulative,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short steps, 1k-5k obs/s only")
    ap.add_argument("--seconds", type=float, help="load per step (default 20; quick 6)")
    ap.add_argument("--rates", type=float, nargs="+", help="the ladder (obs/s)")
    ap.add_argument("--drain-timeout", type=float, default=120.0)
    ap.add_argument(
        "--retries",
        type=int,
        default=1,
        help="a failing step is run again this many times before the ladder stops "
        "(the machine may be shared)",
    )
    ap.add_argument(
        "--profile",
        metavar="SERVICE",
        help="profile this service ('auto': the bottleneck; 'none': skip; default: auto "
        "when the goal is missed, none with --quick)",
    )
    ap.add_argument(
        "--linger-s",
        type=float,
        help="the stage services' batch linger (s; default: theirs, [NAME.batching] linger_s)",
    )
    ap.add_argument(
        "--publish-interval-s",
        type=float,
        help="the publisher's coalescing interval (s; default: its own, [publisher] interval_s)",
    )
    ap.add_argument(
        "--matcher-set",
        metavar="KEY=JSON",
        action="append",
        default=[],
        help="a matcher setting for the stack (dotted for nested: gate.chi2_gate=12; "
        "repeatable), e.g. tick_lag_s=60",
    )
    ap.add_argument("--progress", action="store_true", help="live progress lines")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--data-dir", type=Path, help="keep the stack's state and logs here")
    args = ap.parse_args()
    seconds = args.seconds or (6.0 if args.quick else 20.0)
    rates = args.rates or (RATES[:3] if args.quick else RATES)
    profile = args.profile or ("none" if args.quick else "auto")
    matcher_set = parse_settings(args.matcher_set)
    out: dict = {
        "machine": bench_zenoh.machine(),
        "load_average_start": load_average(),
        "seconds_per_step": seconds,
        "goal_obs_per_s": GOAL,
        "p99_max_s": P99_MAX_S,
        "linger_s": args.linger_s,
        "publish_interval_s": args.publish_interval_s,
        "matcher_settings": matcher_set,
        "steps": [],
    }
    print(json.dumps(out["machine"]), "load average", out["load_average_start"], flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        work = args.data_dir or Path(tmp)
        admit = fleet_admission(work, args.linger_s, args.publish_interval_s, matcher_set)
        with Stack(work / "stack", extra_service_args=admit) as st:
            st.start_all()
            payload, n = reference_payload(load_config(rates[0], seconds))
            out["raw_zenoh"] = raw_zenoh(st, payload, n, 2.0 if args.quick else 5.0)
            best = None
            failing = None
            with open_session(st.bus) as s:
                for rate in rates:
                    for attempt in range(1 + args.retries):
                        cfg = load_config(rate, seconds)
                        r = step(s, st, cfg, args.drain_timeout, args.progress)
                        why = verdict(r, rate)
                        print_step(r, why)
                        out["steps"].append(
                            summary(r) | {"passed": not why, "why": why, "attempt": attempt + 1}
                        )
                        if not why:
                            break
                    if why:
                        failing = r
                        break
                    best = r
        raw = out["raw_zenoh"]["query_obs_per_s"]
        best_rate = best["sustained_per_s"] if best else 0.0
        out["best"] = {
            "target_per_s": best["target_per_s"] if best else None,
            "sustained_per_s": best_rate,
            "p99_s": best["latency_s"]["p99"] if best else None,
            "raw_query_obs_per_s": raw,
            "raw_pubsub_obs_per_s": out["raw_zenoh"]["pubsub"]["obs_per_s"],
            "ratio_to_raw_query": best_rate / raw if raw else None,
            "ratio_to_goal": best_rate / GOAL,
        }
        b = out["best"]
        print(
            f"\nhighest passing step: {b['target_per_s']} obs/s target, sustained "
            f"{best_rate:.0f} obs/s with zero loss, p99 {b['p99_s']} s; raw Zenoh "
            f"request/reply with the same payloads {raw:.0f} obs/s: ratio "
            f"{b['ratio_to_raw_query']:.4f}; goal {GOAL} obs/s: {100 * b['ratio_to_goal']:.1f}%",
            flush=True,
        )
        if profile == "auto" and best_rate < GOAL and failing is not None:
            profile = max(failing["services"], key=lambda s: failing["services"][s]["cpu_share"])
        if profile not in ("none", "auto"):
            rate = failing["target_per_s"] if failing else rates[-1]
            out["profile"] = profile_service(
                profile, rate, seconds, args.drain_timeout, work, admit
            )
    out["load_average_end"] = load_average()
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
