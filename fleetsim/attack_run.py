"""Attacks under an honest load (issue #17): the load generator's honest fleet
(:mod:`fleetsim.loadgen`) with attacks of :mod:`fleetsim.attacks` running exactly as long
(:func:`run_under_attack`), and what the services and the honest vehicles say about it
(:func:`service_refusals`, :func:`honest_accounting`). Used by
``benchmarks/bench_hostile.py`` and ``tests/integration/test_hostile_load.py``.
"""

from __future__ import annotations

import multiprocessing
import os
import queue
import sys
import threading
import time
from collections import Counter
from contextlib import ExitStack
from dataclasses import replace

import zenoh

from fleetsim import loadgen
from fleetsim.attacks import Attack, AttackReport, make_attack, stop_all
from fleetsim.loadgen import LoadConfig
from fleetsim.loadtest import report
from fleetsim.world import demo_town
from hdmap.ops.quiesce import wait_quiet
from hdmap.ops.status import collect
from hdmap.runtime.bus import open_session
from schemas import Stats, keys


def run_under_attack(
    session: zenoh.Session,
    cfg: LoadConfig,
    attacks: list[Attack] | list[AttackProcess],
    drain_timeout: float = 120.0,
    quiet_timeout: float = 60.0,
) -> dict:
    """The load generator's honest fleet (:mod:`fleetsim.loadgen`) for ``cfg.duration_s``
    with ``attacks`` running from the moment every honest vehicle has one upload
    acknowledged (an established fleet, known to ingest; at most 10 s or half the load)
    to the end of the load, then the drain; the loadtest's report
    (:func:`fleetsim.loadtest.report`) with ``attacks`` (each :class:`AttackReport`) and
    ``honest`` (:func:`honest_accounting`). With no attacks it is the loadtest's run.

    Bounded: the initial wait for a quiet chain by ``quiet_timeout``, the load by its
    duration, vehicles' and attacks' last requests by their timeouts, the drain by
    ``drain_timeout``."""
    run_id = cfg.run_id or loadgen.new_run_id()
    cfg = replace(cfg, run_id=run_id)
    world, pool = loadgen.build_pool(cfg)
    tiles = loadgen.town_tiles_with_halo(world)
    counters = loadgen.Counters()
    started_quiet = wait_quiet(session, timeout=quiet_timeout)
    before = collect(session)
    stop = threading.Event()
    vehicles = [
        loadgen.Vehicle(i, session, pool, cfg, counters, stop, run_id) for i in range(cfg.vehicles)
    ]
    readers: list[loadgen.Reader] = []
    t0 = time.monotonic()
    try:
        readers = [loadgen.Reader(session, tiles, counters) for _ in range(cfg.subscribers)]
        for v in vehicles:
            v.start()
        # the honest fleet is established (known to ingest) before the attack starts
        warm = time.monotonic() + min(10.0, cfg.duration_s / 2)
        while time.monotonic() < warm and not all(v.acked_uploads for v in vehicles):
            stop.wait(0.05)
        for a in attacks:
            a.start()
        stop.wait(max(0.0, cfg.duration_s - (time.monotonic() - t0)))
    finally:
        stop.set()
        stop_all(attacks)
        deadline = time.monotonic() + cfg.max_attempts * (cfg.upload_timeout_s + 2.0) + 5.0
        for v in vehicles:
            if v.is_alive():
                v.join(max(0.1, deadline - time.monotonic()))
        load_s = time.monotonic() - t0
        if sys.exc_info()[0] is not None:
            for r in readers:
                r.close()
    try:
        drained = wait_quiet(session, timeout=drain_timeout)
    finally:
        drain_s = time.monotonic() - t0 - load_s
        time.sleep(0.5)  # the last deltas in flight to the readers
        for r in readers:
            r.close()
    after = collect(session)
    out = report(cfg, counters, before, after, load_s, drain_s, drained, started_quiet)
    reports = [a.report() for a in attacks]
    out["attacks"] = [r.as_dict() for r in reports]
    out["attack_failures"] = [a.failure for a in attacks if a.failure]
    out["honest"] = honest_accounting(out, reports)
    out["refusals"] = service_refusals(before, after)
    return out


WATCHED = ("pending_evicted", "passes_quarantined", "init_skipped_quarantined", "rate_limited")
GAUGES = ("passes_in_quarantine", "quarantine.")
"""Prefixes of the service counters where an attack shows (with every ``rejected`` reason)."""


def service_refusals(before: list[Stats], after: list[Stats]) -> dict[str, dict[str, float]]:
    """Per service, what changed between two stats snapshots in its ``rejected`` reasons
    (``rejected.<reason>``) and its counters starting with one of :data:`WATCHED`, and
    the gauges of :data:`GAUGES` at the end (``quarantine.<vehicle>``: its passes in
    quarantine); zeros left out."""

    def flat(stats: list[Stats]) -> dict[str, dict[str, float]]:
        out: dict[str, dict[str, float]] = {}
        for s in stats:
            d = out.setdefault(s.service, {})
            for k, v in s.counters.items():
                if k.startswith(WATCHED):
                    d[k] = d.get(k, 0.0) + float(v)
            for k, v in s.rejected.items():
                d[f"rejected.{k}"] = d.get(f"rejected.{k}", 0.0) + float(v)
        return out

    b, a = flat(before), flat(after)
    delta = {
        svc: {k: v - b.get(svc, {}).get(k, 0.0) for k, v in sorted(vals.items())}
        for svc, vals in sorted(a.items())
    }
    for s in after:
        for k, v in s.counters.items():
            if k.startswith(GAUGES):
                q = delta.setdefault(s.service, {})
                q[k] = q.get(k, 0.0) + float(v)
    return {svc: {k: v for k, v in d.items() if v} for svc, d in delta.items()}


def honest_accounting(r: dict, attacks: list[AttackReport]) -> dict:
    """The honest vehicles' figures of a report of :func:`run_under_attack`: ``sent``,
    ``acked``, ``failed``, ``applied`` (observations the matcher took in, less those the
    attackers got acknowledged), ``lost`` (the sum of the chain's losses, with the
    attackers' acknowledged rows counted on the acknowledged side: 0 when every
    acknowledged observation, honest or not, was applied exactly once), ``drained``,
    ``zero_loss`` and the latency percentiles."""
    attacker_acked = sum(a.accepted for a in attacks)
    losses = dict(r["losses"])
    losses["ingest_vs_acked"] += attacker_acked
    lost = sum(abs(v) for v in losses.values())
    return {
        "sent": r["sent"],
        "acked": r["accepted"],
        "failed": r["failed"],
        "rejected": r["rejected"],
        "applied": r["chain"]["matcher_received"] - attacker_acked,
        "attacker_acked": attacker_acked,
        "losses": losses,
        "lost": lost,
        "drained": r["drained"],
        "zero_loss": bool(r["drained"] and lost == 0 and r["failed"] == 0),
        "latency_s": r["latency_s"],
        "latency_samples": r["latency_samples"],
        "ack_latency_s": r["ack_latency_s"],
    }


def _pin(cpus: frozenset[int] | None) -> None:
    if cpus:
        os.sched_setaffinity(0, cpus)


def _attack_main(
    name: str, bus, duration_s: float, fast: bool, cpus: frozenset[int] | None, stop, out
) -> None:
    """Child process: run one attack until its duration or ``stop``; put its report."""
    _pin(cpus)
    attack = make_attack(name, bus, duration_s, fast)
    attack.start()
    while attack.is_alive() and not stop.wait(0.1):
        pass
    attack.stop()
    attack.join(40.0)
    out.put((attack.report().as_dict(), attack.failure))


def _spin(duration_s: float, cpus: frozenset[int] | None, stop, out) -> None:
    """Child process: keep one CPU busy until ``duration_s`` or ``stop``; report nothing."""
    _pin(cpus)
    end = time.monotonic() + duration_s
    while not stop.is_set() and time.monotonic() < end:
        sum(range(10_000))
    out.put((AttackReport(CONTROL, "local-cpu").as_dict(), ""))


class AttackProcess:
    """An attack of :func:`fleetsim.attacks.make_attack` in a process of its own (spawned,
    not forked: the parent holds Zenoh sessions), with the interface of an
    :class:`~fleetsim.attacks.Attack` that :func:`run_under_attack` uses. Run this way the
    attacker's CPU is a separate process, as an attacker on the network is, instead of
    threads holding the GIL of the process that measures the honest vehicles' latency.
    ``cpus``: the CPUs the attacker may run on (None: any)."""

    def __init__(
        self,
        name: str,
        bus,
        duration_s: float,
        fast: bool = False,
        cpus: frozenset[int] | None = None,
    ):
        self._spawn(name, _attack_main, (name, bus, duration_s, fast, cpus))

    def _spawn(self, name: str, target, args: tuple) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._stop = ctx.Event()
        self._out = ctx.Queue()
        self._proc = ctx.Process(
            target=target, args=(*args, self._stop, self._out), name=f"attack-{name}", daemon=True
        )
        self.name_ = name
        self.failure = ""
        self._report: AttackReport | None = None

    def start(self) -> None:
        self._proc.start()

    def stop(self) -> None:
        self._stop.set()

    def is_alive(self) -> bool:
        return self._proc.is_alive()

    def join(self, timeout: float | None = None) -> None:
        if self._report is None:
            try:
                d, self.failure = self._out.get(timeout=timeout)
                self._report = AttackReport(**{**d, "errors": Counter(d["errors"])})
            except queue.Empty:
                self.failure = self.failure or "no report from the attack process"
        self._proc.join(5.0)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(5.0)

    def report(self) -> AttackReport:
        if self._report is None:
            self.join(45.0)
        return self._report or AttackReport(self.name_, "?")


def _crowd_main(
    n: int, bus, cfg: LoadConfig, cpus: frozenset[int] | None, ready, stop, out
) -> None:
    """Child process: ``n`` subscribed vehicles until ``stop``, each a session of its own
    subscribed to every delta key of the load's town (:func:`fleetsim.loadgen.
    town_tiles_with_halo`). Each subscriber keeps one sample in a ring (Zenoh drops older
    ones in Rust, so the crowd's own CPU stays small), drained every 0.1 s; ``ready`` is
    set once all are declared. Reports the samples taken as ``replies``."""
    _pin(cpus)
    tiles = loadgen.town_tiles_with_halo(
        demo_town(cfg.seed, n_signs=cfg.n_signs, n_blocks=cfg.n_blocks)
    )
    taken = 0
    with ExitStack() as es:
        subs = []
        for _ in range(n):
            s = es.enter_context(open_session(bus))
            for t in tiles:
                subs.append(s.declare_subscriber(keys.map_delta(t), zenoh.handlers.RingChannel(1)))
        ready.set()
        while not stop.wait(0.1):
            for sub in subs:
                while sub.try_recv() is not None:
                    taken += 1
        for sub in subs:
            sub.undeclare()
    out.put((AttackReport(CROWD, f"{n} subscribers", replies=taken).as_dict(), ""))


class SubscriberCrowd(AttackProcess):
    """Background, not an attack: ``n`` subscribed vehicles in a process of their own
    (:func:`_crowd_main`), each with its own session, so that the router fans every delta
    out ``n`` times more; :meth:`start` returns once they are all subscribed (bounded by
    ``timeout_s``)."""

    def __init__(
        self,
        n: int,
        bus,
        cfg: LoadConfig,
        cpus: frozenset[int] | None = None,
        timeout_s: float = 120.0,
    ):
        ctx = multiprocessing.get_context("spawn")
        self._ready, self.timeout_s = ctx.Event(), timeout_s
        self._spawn(CROWD, _crowd_main, (n, bus, cfg, cpus, self._ready))

    def start(self) -> None:
        super().start()
        if not self._ready.wait(self.timeout_s):
            self.stop()
            self.join(10.0)
            raise RuntimeError(f"the subscriber crowd was not ready in {self.timeout_s:g} s")


class CpuBurner(AttackProcess):
    """The control of an attack: a process that keeps one core busy for ``duration_s``
    and sends nothing. What it does to the honest p99 is what any attacker running on
    the same machine does by its CPU alone (on the 2-core benchmark machine, a lot)."""

    def __init__(self, duration_s: float, cpus: frozenset[int] | None = None):
        self._spawn(CONTROL, _spin, (duration_s, cpus))


CROWD = "crowd"
"""The name of :class:`SubscriberCrowd` in its report."""

CONTROL = "cpu"
"""The name of :class:`CpuBurner` in the benchmark's list of attacks."""
