"""Issue #17's attacks, all at once, while honest vehicles load a real stack.

A router and the four services run as processes (the ``stack`` fixture stops them, also
on failure). A short honest load (:func:`fleetsim.attack_run.run_under_attack`) runs with
every attack of :mod:`fleetsim.attacks` concurrently, each from its own client (the stuck
passes fast enough to reach the matcher's budget within the load, spread uploads of 1,000
tiles). The honest chain must drain with zero loss, and each attack must show where the
services say it was refused, quarantined or counted. Counts only, never timings; every
wait is bounded (the load, the requests' timeouts, the drain, pytest-timeout).
"""

from __future__ import annotations

import threading

import pytest

from fleetsim.attack_run import run_under_attack
from fleetsim.attacks import ATTACK_NAMES, attack_identity, make_attack
from fleetsim.loadgen import LoadConfig
from hdmap.ops.security import generate
from hdmap.ops.stack import SERVICE_NAMES, Stack, free_port
from hdmap.ops.status import collect
from hdmap.runtime.bus import open_session

pytestmark = [pytest.mark.integration, pytest.mark.timeout(180)]

CFG = LoadConfig(
    vehicles=4,
    rate=500.0,
    duration_s=15.0,
    batch=250,
    subscribers=1,
    pool_passes=12,
    upload_timeout_s=10.0,
)


class StatusWatch(threading.Thread):
    """What the status client sees, once a second until stopped (bounded by ``rounds``)."""

    def __init__(self, bus, rounds: int = 60):
        super().__init__(daemon=True)
        self.bus, self.rounds = bus, rounds
        self.stop = threading.Event()
        self.seen: list[list[tuple[str, str]]] = []

    def run(self) -> None:
        with open_session(self.bus) as s:
            for _ in range(self.rounds):
                self.seen.append(sorted((x.service, x.instance) for x in collect(s, 2.0)))
                if self.stop.wait(1.0):
                    return


def run_watched(bus, attacks: list) -> tuple[dict, dict, StatusWatch]:
    """The honest load under ``attacks`` with the status client watching; the report,
    the attacks' reports by name and the watch."""
    watch = StatusWatch(bus)
    watch.start()
    try:
        with open_session(bus) as session:
            r = run_under_attack(session, CFG, attacks, drain_timeout=90.0)
    finally:
        watch.stop.set()
        watch.join(10.0)
    assert not r["attack_failures"]
    return r, {a["name"]: a for a in r["attacks"]}, watch


def test_honest_chain_holds_under_every_attack(stack):
    stack.start_all()
    attacks = [make_attack(n, stack.bus, CFG.duration_s, fast=True) for n in ATTACK_NAMES]
    r, by_name, watch = run_watched(stack.bus, attacks)

    # The honest vehicles: everything sent acknowledged, and applied exactly once.
    h = r["honest"]
    assert h["drained"] and h["failed"] == 0 and h["rejected"] == 0
    assert h["acked"] == h["sent"] > 0
    assert h["applied"] == h["acked"], h
    assert h["lost"] == 0 and h["zero_loss"], h["losses"]
    assert r["deltas"] > 0 and r["latency_samples"] > 0

    ingest = r["refusals"].get("ingest", {})
    matcher = r["refusals"].get("matcher", {})
    publisher = r["refusals"].get("publisher", {})

    # (1) Passes that never make a landmark: recorded, then evicted past the pass's
    # budget and quarantined (both of them, by vehicle).
    for name in ("restart", "parked"):
        a = by_name[name]
        assert a["accepted"] == a["observations"] > 0 and a["refused"] == 0, a
        assert matcher.get(f"quarantine.{a['client']}", 0) >= 1, matcher
    assert matcher.get("pending_evicted.pass", 0) > 0, matcher
    assert matcher.get("passes_quarantined", 0) >= 2, matcher

    # (2) Uploads over many tiles: rows past the upload's first tiles refused one by one
    # (obs.lat, ingest's max_tiles), counted; the rest recorded.
    spread = by_name["spread"]
    assert spread["requests"] > 0 and 0 < spread["accepted"] < spread["observations"], spread
    assert spread["accepted"] + spread["rejected"] == spread["observations"], spread
    assert ingest.get("rejected.obs.lat", 0) >= spread["rejected"], ingest

    # (3) Forged wildcard tokens: the status client saw the four services, one instance
    # each, every time it looked during the attack.
    assert by_name["tokens"]["requests"] > 0
    assert watch.seen
    for seen in watch.seen:
        assert sorted(s for s, _i in seen) == sorted(SERVICE_NAMES), seen

    # (4) Snapshot queries. One client id flooding its own snapshot key: refused with
    # `rate` past its burst (snapshot.client), counted. A new id each query (Sybil): never
    # refused per client (only the total budget can hold it), answered. Queries on
    # hdmap/v1/**: the publisher refuses a snapshot naming no tile, ingest an upload key
    # naming no vehicle; both counted.
    snaps = by_name["snapshots"]
    assert snaps["errors"].get("snapshot.client", 0) > 0, snaps
    assert publisher.get("rejected.snapshot.client", 0) >= snaps["errors"]["snapshot.client"]
    assert snaps["replies"] > snaps["refused"] > 0, snaps  # its burst was served
    sybil = by_name["sybil"]
    assert sybil["replies"] > 0 and "snapshot.client" not in sybil["errors"], sybil
    wild = by_name["wildcard"]
    assert wild["requests"] > 0 and wild["errors"].get("tile", 0) > 0, wild
    assert publisher.get("rejected.snapshot.tile", 0) >= wild["errors"]["tile"], publisher
    assert ingest.get("rejected.batch.key", 0) > 0, ingest

    # (5) Dated in the future: rows within ingest's 300 s skew window recorded, those a
    # year ahead rejected one by one (obs.t), counted; the batch's sent_at (2096) passes.
    fut = by_name["future"]
    assert fut["requests"] > 0 and fut["refused"] == 0, fut
    assert fut["rejected"] == fut["errors"].get("obs.t", 0) > 0, fut
    assert fut["accepted"] + fut["rejected"] == fut["observations"], fut
    assert ingest.get("rejected.obs.t", 0) == fut["rejected"], ingest

    # No service restarted or crashed on any of it.
    for name in SERVICE_NAMES:
        assert stack.procs[stack.service_key(name)].alive, name
    for log in (stack.data_dir / "logs").glob("*.log"):
        assert "Traceback" not in log.read_text(errors="replace"), log


SECURED_ATTACKS = ("snapshots", "sybil", "newcomers", "wildcard", "tokens")
"""The attacks that claim ids or keys other than their own: in secured mode each runs
authenticated as one vehicle of the deployment (:func:`fleetsim.attacks.attack_identity`)."""


def test_secured_mode_stops_forged_ids_at_the_router_under_load(tmp_path):
    """Secured mode (mTLS, the router's ACL) under the same honest load: what an attacker
    sends under ids or keys it was not given (a new snapshot client id each query, a new
    vehicle id each upload, ``hdmap/v1/**``, wildcard tokens) never reaches a service,
    and its own snapshot key is limited per client; the honest chain drains with zero
    loss. The honest fleet runs on the operator's session."""
    identities = [attack_identity(n) for n in SECURED_ATTACKS]
    dep = generate(tmp_path / "secure", identities, f"tls/127.0.0.1:{free_port()}")
    st = Stack(tmp_path / "stack", listen=dep.endpoint, security=dep)
    try:
        st.start_all()
        attacks = [
            make_attack(n, dep.bus(attack_identity(n)), CFG.duration_s, fast=True)
            for n in SECURED_ATTACKS
        ]
        r, by_name, watch = run_watched(st.bus, attacks)
        h = r["honest"]
        assert h["drained"] and h["failed"] == 0 and h["acked"] == h["sent"] > 0, h
        assert h["applied"] == h["acked"] and h["lost"] == 0 and h["zero_loss"], h["losses"]
        ingest = r["refusals"].get("ingest", {})
        publisher = r["refusals"].get("publisher", {})

        # Forged ids and keys: denied at the router, no reply at all, nothing counted by
        # a service (it never saw them).
        for name in ("sybil", "newcomers", "wildcard"):
            a = by_name[name]
            assert a["requests"] > 0 and a["unanswered"] == a["requests"], a
            assert a["replies"] == 0 and a["accepted"] == 0, a
        assert "rejected.snapshot.total" not in publisher, publisher
        assert "rejected.snapshot.tile" not in publisher, publisher
        assert "rejected.vehicle.new" not in ingest and "rejected.batch.key" not in ingest
        # Its own snapshot key: served within its burst, then refused per client.
        snaps = by_name["snapshots"]
        assert snaps["replies"] > snaps["refused"] > 0, snaps
        assert publisher.get("rejected.snapshot.client", 0) >= snaps["errors"]["snapshot.client"]
        # Wildcard tokens: declared, seen by no one (the ACL denies liveliness to vehicles).
        assert by_name["tokens"]["requests"] > 0
        assert watch.seen
        for seen in watch.seen:
            assert sorted(s for s, _i in seen) == sorted(SERVICE_NAMES), seen
        for name in SERVICE_NAMES:
            assert st.procs[st.service_key(name)].alive, name
    finally:
        st.stop_all()
