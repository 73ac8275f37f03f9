"""Attacks under honest load: one attacker (issue #17) against a loadtest of honest vehicles.

For each attack of :mod:`fleetsim.attacks` (``restart``, ``parked``, ``spread``,
``tokens``, ``snapshots``, ``sybil``, ``wildcard``, ``future``, ``newcomers``), side by
side in one run, each on a fresh stack (hdmap.ops.stack.Stack: a router and the four
services as processes on 127.0.0.1, a random free port, multicast scouting off): the
honest fleet of the load generator (``--vehicles`` at ``--rate`` obs/s for ``--seconds``,
then the drain) WITHOUT and then WITH the attacker running for exactly the honest load
(:func:`fleetsim.attack_run. run_under_attack`), in a process of its own
(:class:`fleetsim.attack_run.AttackProcess`: its CPU is not the measuring process's GIL).
Reported for the honest vehicles: sent, acked, applied (observations the matcher took in,
less the attacker's acknowledged ones), lost (the chain's losses with the attacker's
acknowledged rows counted; must be 0), drained (the loadtest's quiet-chain check, bounded
by ``--drain-timeout``), p50/p99 latency (ingest receipt -> landmark update at a
subscribed vehicle) and p99_with / p99_without (target <= 2); for the attacker what it
sent and how it was answered, and the services' refusal counters (``rejected.*``,
``pending_evicted``, ``passes_quarantined``, ...). The control ``cpu``
(:class:`fleetsim.attack_run.CpuBurner`) sends nothing and keeps one core of the machine
busy: its ratio is what an attacker's own CPU does on this machine.

    .venv/bin/python benchmarks/bench_hostile.py [--quick] [--json FILE] [--attacks spread]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import machine, machine_line, write_json
from fleetsim.attack_run import (
    CONTROL,
    AttackProcess,
    CpuBurner,
    SubscriberCrowd,
    run_under_attack,
)
from fleetsim.attacks import ATTACK_NAMES, attack_identity
from fleetsim.loadgen import LoadConfig
from hdmap.ops.security import generate
from hdmap.ops.stack import Stack, free_port
from hdmap.runtime.bus import open_session

RATIO_MAX = 2.0
"""Target: the honest p99 latency with the attacker at most this times the one without."""


def load_average() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def one_run(
    attack: str,
    with_attacker: bool,
    cfg: LoadConfig,
    drain_timeout: float,
    attacker_cpus: frozenset[int] | None = None,
    secure: bool = False,
    crowd: int = 0,
) -> dict:
    """One honest load on a fresh stack, with or without ``attack``; its summary.
    ``attacker_cpus``: the attacker's CPUs (``--pin``: this process, the stack and the
    honest fleet keep the others). ``secure``: the stack in secured mode (TLS, mTLS, the
    router's ACL); the honest fleet on the operator's session, the attacker
    authenticated as the one vehicle of :func:`fleetsim.attacks.attack_identity`.
    ``crowd``: that many more subscribed vehicles, each a session of its own, in a process
    of their own (:class:`fleetsim.attack_run.SubscriberCrowd`), through the whole run."""
    la0 = load_average()
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory() as tmp:
        dep, attacker_bus = None, None
        if secure:
            identity = "cpu-control" if attack == CONTROL else attack_identity(attack)
            dep = generate(
                Path(tmp) / "secure", [identity, "crowd"], f"tls/127.0.0.1:{free_port()}"
            )
            attacker_bus = dep.bus(identity)
        where = {"listen": dep.endpoint, "security": dep} if dep is not None else {}
        with Stack(Path(tmp) / "stack", **where) as st:
            st.start_all()
            attacks: list = []
            if with_attacker:
                attacks = [
                    CpuBurner(cfg.duration_s, attacker_cpus)
                    if attack == CONTROL
                    else AttackProcess(
                        attack, attacker_bus or st.bus, cfg.duration_s, cpus=attacker_cpus
                    )
                ]
            crowd_run = None
            if crowd:
                crowd_run = SubscriberCrowd(crowd, st.bus if dep is None else dep.bus("crowd"), cfg)
                crowd_run.start()
            try:
                with open_session(st.bus) as session:
                    r = run_under_attack(session, cfg, attacks, drain_timeout=drain_timeout)
            finally:
                if crowd_run is not None:
                    crowd_run.stop()
                    crowd_run.join(30.0)
            st.stop_all()
    h = r["honest"]
    return {
        "attack": attack,
        "with_attacker": with_attacker,
        "sent": h["sent"],
        "acked": h["acked"],
        "failed": h["failed"],
        "applied": h["applied"],
        "lost": h["lost"],
        "losses": h["losses"],
        "drained": h["drained"],
        "zero_loss": h["zero_loss"],
        "latency_s": h["latency_s"],
        "latency_samples": h["latency_samples"],
        "ack_latency_s": h["ack_latency_s"],
        "accepted_per_s": r["accepted_per_s"],
        "load_s": r["load_s"],
        "drain_s": r["drain_s"],
        "started_quiet": r["started_quiet"],
        "attacker": r["attacks"][0] if r["attacks"] else None,
        "crowd": crowd_run.report().as_dict() if crowd_run is not None else None,
        "attack_failures": r["attack_failures"],
        "refusals": r["refusals"],
        "services_cpu_s": {s: round(v["cpu_s"], 2) for s, v in r["services"].items()},
        "wall_s": time.monotonic() - t0,
        "load_average_before": la0,
        "load_average_after": load_average(),
    }


def _f(v: float | None, digits: int = 3) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def print_run(x: dict) -> None:
    lat = x["latency_s"]
    mode = "with" if x["with_attacker"] else "without"
    line = (
        f"{x['attack']:>9} {mode:>7}: sent {x['sent']:6d} acked {x['acked']:6d} applied "
        f"{x['applied']:6.0f} lost {x['lost']:3.0f} {'drained' if x['drained'] else 'NOT DRAINED'}"
        f"  latency p50 {_f(lat['p50'])} s p99 {_f(lat['p99'])} s  drain {x['drain_s']:5.1f} s"
        f"  ({x['wall_s']:.0f} s; load average {x['load_average_after']})"
    )
    print(line, flush=True)
    if x.get("crowd"):
        print(f"{'':>18}crowd: {x['crowd']['client']}, {x['crowd']['replies']} deltas taken")
    a = x["attacker"]
    if a is not None:
        print(
            f"{'':>18}attacker {a['client']}: {a['requests']} requests, {a['observations']} obs,"
            f" acked {a['accepted']}, rows rejected {a['rejected']}, refused {a['refused']},"
            f" unanswered {a['unanswered']}; errors {a['errors']}",
            flush=True,
        )
        counts = {s: c for s, c in x["refusals"].items() if c}
        print(f"{'':>18}services: {counts}", flush=True)


def _outcome(passed: bool | None) -> str:
    return "control" if passed is None else "PASS" if passed else "FAIL"


def verdict(without: dict, with_: dict) -> dict:
    """The pair's figures: p99 ratio and whether the honest chain held."""
    p0, p1 = without["latency_s"]["p99"], with_["latency_s"]["p99"]
    ratio = p1 / p0 if p0 and p1 is not None else None
    ok = bool(
        without["zero_loss"]
        and with_["zero_loss"]
        and ratio is not None
        and ratio <= RATIO_MAX
        and with_["failed"] == 0
    )
    return {"p99_without_s": p0, "p99_with_s": p1, "p99_ratio": ratio, "passed": ok}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="4 vehicles, 500 obs/s, 6 s a run")
    ap.add_argument("--vehicles", type=int, help="honest vehicles (default 10; quick 4)")
    ap.add_argument("--rate", type=float, help="honest obs/s in all (default 1000; quick 500)")
    ap.add_argument("--seconds", type=float, help="honest load per run (default 20; quick 6)")
    names = [*ATTACK_NAMES, CONTROL]
    ap.add_argument("--attacks", nargs="+", choices=names, default=names)
    ap.add_argument("--drain-timeout", type=float, default=300.0)
    ap.add_argument("--json", type=Path)
    ap.add_argument(
        "--pin",
        action="store_true",
        help="the attacker on the last CPU, everything else (stack, honest fleet) on the "
        "others, in both runs of a pair: the attacker's own CPU then costs the honest side "
        "nothing, as from another host",
    )
    ap.add_argument(
        "--secure",
        action="store_true",
        help="each stack in secured mode (TLS, mTLS, the router's ACL): the attacker "
        "authenticated as one vehicle, the honest fleet on the operator's session",
    )
    ap.add_argument(
        "--subscribers", type=int, help="subscribed readers that measure (default 2; quick 1)"
    )
    ap.add_argument(
        "--crowd",
        type=int,
        default=0,
        help="that many more subscribed vehicles, a session each, in a process of their own",
    )
    a = ap.parse_args(argv)
    attacker_cpus: frozenset[int] | None = None
    if a.pin:
        cpus = sorted(os.sched_getaffinity(0))
        if len(cpus) < 2:
            ap.error("--pin needs at least 2 CPUs")
        attacker_cpus = frozenset(cpus[-1:])
        os.sched_setaffinity(0, set(cpus[:-1]))  # the stack's processes inherit it
    cfg = LoadConfig(
        vehicles=a.vehicles or (4 if a.quick else 10),
        rate=a.rate or (500.0 if a.quick else 1000.0),
        duration_s=a.seconds or (6.0 if a.quick else 20.0),
        subscribers=a.subscribers or (1 if a.quick else 2),
    )
    m = machine()
    print(machine_line(m), flush=True)
    print(
        f"honest load: {cfg.vehicles} vehicles, {cfg.rate:.0f} obs/s, {cfg.duration_s:.0f} s a "
        f"run, {cfg.subscribers} subscribed readers; each run on a fresh "
        f"{'secured ' if a.secure else ''}stack"
        + (f", {a.crowd} more subscribed vehicles (sessions)" if a.crowd else ""),
        flush=True,
    )
    out: dict = {
        "machine": m,
        "config": {
            "vehicles": cfg.vehicles,
            "rate": cfg.rate,
            "seconds": cfg.duration_s,
            "subscribers": cfg.subscribers,
            "drain_timeout_s": a.drain_timeout,
            "attacker_cpus": sorted(attacker_cpus) if attacker_cpus else None,
            "secure": a.secure,
            "crowd": a.crowd,
        },
        "ratio_max": RATIO_MAX,
        "attacks": [],
    }
    t0 = time.monotonic()
    for i, name in enumerate(a.attacks, 1):
        print(f"[{i}/{len(a.attacks)}] {name}", flush=True)
        runs = []
        for with_attacker in (False, True):
            runs.append(
                one_run(name, with_attacker, cfg, a.drain_timeout, attacker_cpus, a.secure, a.crowd)
            )
            print_run(runs[-1])
        v = verdict(*runs)
        if name == CONTROL:  # no attack: what one busy local core does to the ratio
            v["passed"] = None
        print(
            f"{'':>18}p99 with / without = {_f(v['p99_ratio'], 2)} (target <= {RATIO_MAX:g})"
            f" -> {_outcome(v['passed'])}",
            flush=True,
        )
        out["attacks"].append({"attack": name, **v, "without": runs[0], "with": runs[1]})
    out["seconds"] = time.monotonic() - t0
    print(f"\n{'attack':>9} {'lost':>9} {'p99 without':>11} {'p99 with':>9} {'ratio':>6}")
    for x in out["attacks"]:
        lost = f"{x['without']['lost']:.0f}/{x['with']['lost']:.0f}"
        print(
            f"{x['attack']:>9} {lost:>9} {_f(x['p99_without_s']):>11} {_f(x['p99_with_s']):>9} "
            f"{_f(x['p99_ratio'], 2):>6} {_outcome(x['passed'])}"
        )
    print(f"total {out['seconds']:.0f} s", flush=True)
    write_json(a.json, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
