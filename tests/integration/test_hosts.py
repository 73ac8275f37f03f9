"""The pipeline across hosts (issue 20): three network namespaces this test makes stand
for three machines, linked to a router's namespace by veth pairs on their own subnets
(no loopback between them; random subnet, random port, scouting off).

- ``r``: the router, listening on its three links;
- ``a``: ingest (where vehicles upload);
- ``b``: matcher, solver, publisher (the region's mapping services);
- the test process stays in the host's namespace, on the third link, as a vehicle and
  an operator.

The pipeline builds its log across the links; then the link to ``b`` goes down for a few
seconds while the vehicle keeps uploading (ingest acknowledges; the mapping host is cut
off) and comes back: the matcher catches up and receives every acknowledged observation
once. Needs ``ip netns`` (root, or CAP_SYS_ADMIN and CAP_NET_ADMIN): skipped otherwise,
saying so. Every namespace and process is removed by the test, also on failure.
"""

from __future__ import annotations

import os
import random
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass

import pytest

from hdmap.ops.quiesce import totals
from hdmap.ops.stack import Stack, free_port
from hdmap.ops.status import collect
from hdmap.runtime.bus import BusConfig, open_session
from tests.support import wait_until
from tests.support.uploads import upload

pytestmark = pytest.mark.integration

N = 20


def ip(*args: str, ns: str | None = None) -> None:
    cmd = ["ip", *args] if ns is None else ["ip", "netns", "exec", ns, "ip", *args]
    subprocess.run(cmd, check=True, capture_output=True, timeout=20)


@dataclass
class Hosts:
    names: dict[str, str]
    """role (r, a, b) -> namespace."""
    addr: dict[str, str]
    """role (a, b, host) -> the router's address on that link; ``<role>-peer``: theirs."""
    router_if: dict[str, str]
    """role (a, b, host) -> the router's end of the link (in namespace ``r``)."""


def _can_make_namespaces() -> str:
    """'' if this process may make network namespaces, else why not."""
    if os.geteuid() != 0:
        return "network namespaces need root (or CAP_SYS_ADMIN and CAP_NET_ADMIN)"
    name = f"hdprobe{os.getpid()}"
    try:
        ip("netns", "add", name)
    except (OSError, subprocess.CalledProcessError) as exc:
        return f"ip netns add failed: {getattr(exc, 'stderr', b'') or exc}"
    ip("netns", "del", name)
    return ""


@pytest.fixture
def hosts() -> Iterator[Hosts]:
    why = _can_make_namespaces()
    if why:
        pytest.skip(why)
    tag = f"{os.getpid() % 10000}{random.randrange(100, 999)}"
    net = random.randrange(64, 250)  # 10.<net>.<link>.0/30 per link
    names = {role: f"hd{tag}{role}" for role in ("r", "a", "b")}
    links = {"a": 1, "b": 2, "host": 3}
    made: list[str] = []
    host_links: list[str] = []
    try:
        for ns in names.values():
            ip("netns", "add", ns)
            made.append(ns)
            ip("link", "set", "lo", "up", ns=ns)
        addr: dict[str, str] = {}
        router_if: dict[str, str] = {}
        for role, k in links.items():
            r_if, o_if = f"hr{tag}{k}", f"ho{tag}{k}"
            ip("link", "add", r_if, "type", "veth", "peer", "name", o_if)
            if role == "host":
                host_links.append(o_if)
            ip("link", "set", r_if, "netns", names["r"])
            ip("addr", "add", f"10.{net}.{k}.1/30", "dev", r_if, ns=names["r"])
            ip("link", "set", r_if, "up", ns=names["r"])
            other = None if role == "host" else names[role]
            if other is not None:
                ip("link", "set", o_if, "netns", other)
            ip("addr", "add", f"10.{net}.{k}.2/30", "dev", o_if, ns=other)
            ip("link", "set", o_if, "up", ns=other)
            router_if[role] = r_if
            addr[role] = f"10.{net}.{k}.1"
            addr[f"{role}-peer"] = f"10.{net}.{k}.2"
        yield Hosts(names, addr, router_if)
    finally:
        for link in host_links:  # the host's end (the rest goes with the namespaces)
            subprocess.run(["ip", "link", "del", link], capture_output=True, timeout=20)
        for ns in made:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=20)


def matcher_received(s) -> float:
    return totals(collect(s, 2.0)).get("matcher", {}).get("received", -1)


def test_the_pipeline_across_hosts_survives_a_cut_link(hosts, tmp_path):
    port = free_port()
    at = {role: f"tcp/{hosts.addr[role]}:{port}" for role in ("a", "b", "host")}
    stack = Stack(
        tmp_path / "stack",
        listen=at["host"],
        router_listen=(at["a"], at["b"]),
        netns={
            "router": hosts.names["r"],
            "ingest-all": hosts.names["a"],
            "matcher-all": hosts.names["b"],
            "solver-all": hosts.names["b"],
            "publisher-all": hosts.names["b"],
        },
        connect_for={
            "ingest-all": at["a"],
            "matcher-all": at["b"],
            "solver-all": at["b"],
            "publisher-all": at["b"],
        },
    )
    try:
        stack.start_all()
        with open_session(BusConfig(mode="client", connect=(at["host"],))) as s:
            acked = 0
            for k in range(10):
                assert len(upload(s, "veh-1", k + 1, k * N, N).accepted) == N
                acked += N
            assert wait_until(lambda: matcher_received(s) == acked, 60.0)

            r_if = hosts.router_if["b"]
            ip("link", "set", r_if, "down", ns=hosts.names["r"])
            try:
                for k in range(10, 30):  # b is cut off; a still takes uploads
                    assert len(upload(s, "veh-1", k + 1, k * N, N).accepted) == N
                    acked += N
                    time.sleep(0.1)
                seen = totals(collect(s, 2.0))  # the operator reaches a, not b
                assert "ingest" in seen and "matcher" not in seen, sorted(seen)
            finally:
                ip("link", "set", r_if, "up", ns=hosts.names["r"])
            assert wait_until(lambda: matcher_received(s) == acked, 90.0), (
                matcher_received(s),
                acked,
            )
            time.sleep(1.0)
            t = totals(collect(s, 2.0))
            assert t["matcher"]["received"] == acked  # once each
            assert t["ingest"]["log_entries"] == t["matcher"]["entries_applied"]
    finally:
        stack.stop_all()
