"""The ``hdmap`` command as users run it: ``up``, ``status``, ``router``, and the bus options.

Each command runs as a subprocess on 127.0.0.1 (free ports, multicast scouting off).
Whatever a test starts is killed in a ``finally`` block, with every descendant, also
on failure; every wait is bounded; nothing asserts on timing.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import signal
import socket
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import psutil
import pytest

from hdmap.cli.common import add_bus_arguments, bus_from_args
from hdmap.ops.stack import SERVICE_NAMES, Proc, Stack, endpoint_port, free_port
from hdmap.runtime.bus import DEFAULT_ENDPOINT, BusConfig, open_session, zenoh_config
from tests.support import wait_until
from tests.support.processes import running

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[2]


def hdmap(*args: str) -> list[str]:
    return [sys.executable, "-m", "hdmap.cli", *args]


def listening(endpoint: str) -> bool:
    with contextlib.suppress(OSError), socket.create_connection(endpoint_port(endpoint), 0.5):
        return True
    return False


def status(*bus_args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        hdmap("status", "--timeout", "5", *bus_args),
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=60,
    )


def services_listed(out: str) -> dict[str, list[str]]:
    """``hdmap status`` text -> {service: [instance, ...]} of entries with counters."""
    found: dict[str, list[str]] = {}
    lines = out.splitlines()
    for i, line in enumerate(lines):
        parts = line.split()
        if line[:1].strip() and len(parts) >= 3 and parts[2].startswith("region="):
            counters = [x for x in lines[i + 1 : i + 4] if x.startswith("    ") and x.split()]
            if counters:
                found.setdefault(parts[0], []).append(parts[1])
    return found


def children_by_role(pid: int) -> dict[str, psutil.Process]:
    """The router and service processes under ``hdmap up`` by role (one each expected)."""
    out: dict[str, psutil.Process] = {}
    for c in psutil.Process(pid).children(recursive=True):
        with contextlib.suppress(psutil.Error):
            argv = c.cmdline()
            if "hdmap.cli" in argv and len(argv) > argv.index("hdmap.cli") + 1:
                rest = argv[argv.index("hdmap.cli") + 1 :]
                role = rest[1] if rest[0] == "service" and len(rest) > 1 else rest[0]
                assert role not in out, (role, argv)
                out[role] = c
    return out


def write_json5(path: Path, doc: dict) -> Path:
    path.write_text(json.dumps(doc))  # JSON is JSON5
    return path


def test_up_runs_the_stack_until_sigterm_and_leaves_no_process(tmp_path):
    ep = f"tcp/127.0.0.1:{free_port()}"
    data = tmp_path / "var"
    log = tmp_path / "up.log"
    cfg = tmp_path / "services.toml"
    cfg.write_text("[publisher]\ninterval_s = 0.25\n")
    argv = hdmap("up", "--listen", ep, "--data-dir", str(data), "--config", str(cfg))
    with running(argv, log) as up:
        listed: dict[str, list[str]] = {}

        def all_listed() -> bool:
            nonlocal listed
            assert up.poll() is None, log.read_text()
            if not listening(ep):
                return False
            res = status("--connect", ep)
            listed = services_listed(res.stdout) if res.returncode == 0 else {}
            return set(SERVICE_NAMES) <= set(listed)

        assert wait_until(all_listed, 90.0, 0.5), (listed, log.read_text())
        assert all(len(v) == 1 for v in listed.values()), listed
        instances = sorted(i for v in listed.values() for i in v)

        # a Zenoh config file alone says where to connect (no default endpoint added)
        conf = write_json5(tmp_path / "client.json5", {"connect": {"endpoints": [ep]}})
        res = status("--zenoh-config", str(conf))
        assert res.returncode == 0, res.stderr
        assert sorted(i for v in services_listed(res.stdout).values() for i in v) == instances

        kids = children_by_role(up.pid)
        assert sorted(kids) == sorted(["router", *SERVICE_NAMES]), kids
        for name in SERVICE_NAMES:  # --config reaches every service
            argv_of = kids[name].cmdline()
            assert argv_of[argv_of.index("--config") + 1] == str(cfg.resolve()), argv_of

        # a service that dies is restarted (same instance: its id is kept in the data dir)
        kids["ingest"].kill()

        def ingest_back() -> bool:
            assert up.poll() is None, log.read_text()
            again = children_by_role(up.pid).get("ingest")
            if again is None or again.pid == kids["ingest"].pid:
                return False
            res = status("--connect", ep)
            return services_listed(res.stdout).get("ingest") == listed["ingest"]

        assert wait_until(ingest_back, 60.0, 0.5), log.read_text()
        assert "hdmap up: ingest-all exited" in log.read_text()
        children = list(children_by_role(up.pid).values())
        assert len(children) == 1 + len(SERVICE_NAMES)

        up.send_signal(signal.SIGTERM)
        assert up.wait(60) == 0, log.read_text()
        _gone, alive = psutil.wait_procs(children, timeout=10)
        assert not alive, alive
        strays = []
        for p in psutil.process_iter(["cmdline"]):
            with contextlib.suppress(psutil.Error):
                if str(data) in " ".join(p.info["cmdline"] or []) and p.status() != "zombie":
                    strays.append(p)
        assert not strays, strays
        assert not listening(ep)
    text = log.read_text()
    assert f"hdmap up: router on {ep}" in text and "hdmap up: stopping" in text


def roundtrip(ep: str) -> bool:
    """Two client sessions through the router at ``ep``: a put reaches a subscriber."""
    got = threading.Event()
    bus = BusConfig(mode="client", connect=(ep,))
    with open_session(bus) as a, open_session(bus) as b:
        sub = a.declare_subscriber("hdmap/test/ping", lambda _s: got.set())
        try:
            deadline = time.monotonic() + 20
            while not got.is_set() and time.monotonic() < deadline:
                b.put("hdmap/test/ping", b"1")
                got.wait(0.2)
        finally:
            sub.undeclare()
    return got.is_set()


def test_router_listens_and_sessions_connect_through_it(tmp_path):
    ep = f"tcp/127.0.0.1:{free_port()}"
    log = tmp_path / "router.log"
    with running(hdmap("router", "--listen", ep), log) as router:
        assert wait_until(lambda: listening(ep) or router.poll() is not None, 30.0, 0.1)
        assert router.poll() is None, log.read_text()
        assert roundtrip(ep)
        router.send_signal(signal.SIGTERM)
        assert router.wait(30) == 0, log.read_text()
    assert f"router listening on {ep}" in log.read_text()


def test_router_listen_overrides_the_zenoh_config_file(tmp_path):
    in_file, on_cli = (f"tcp/127.0.0.1:{free_port()}" for _ in range(2))
    conf = write_json5(tmp_path / "router.json5", {"listen": {"endpoints": [in_file]}})
    for argv, ep, not_ep in [
        (["--listen", on_cli, "--zenoh-config", str(conf)], on_cli, in_file),
        (["--zenoh-config", str(conf)], in_file, DEFAULT_ENDPOINT),  # the file's, no default
    ]:
        log = tmp_path / f"router-{endpoint_port(ep)[1]}.log"
        with running(hdmap("router", *argv), log) as router:
            assert wait_until(lambda ep=ep: listening(ep) or router.poll() is not None, 30.0, 0.1)
            assert router.poll() is None, log.read_text()
            assert roundtrip(ep)
            conns = psutil.Process(router.pid).net_connections("tcp")
            ports = {c.laddr.port for c in conns if c.status == psutil.CONN_LISTEN}
            assert endpoint_port(ep)[1] in ports and endpoint_port(not_ep)[1] not in ports
            router.send_signal(signal.SIGTERM)
            assert router.wait(30) == 0, log.read_text()
        assert f"router listening on {ep}" in log.read_text()


def test_bus_from_args_keeps_the_config_files_endpoints(tmp_path):
    conf = write_json5(tmp_path / "c.json5", {"connect": {"endpoints": ["tcp/127.0.0.1:17999"]}})
    p = argparse.ArgumentParser()
    add_bus_arguments(p)

    def endpoints(*argv: str) -> list[str]:
        cfg = bus_from_args(p.parse_args(list(argv)))
        return json.loads(zenoh_config(cfg).get_json("connect/endpoints"))

    assert endpoints("--zenoh-config", str(conf)) == ["tcp/127.0.0.1:17999"]
    assert endpoints("--zenoh-config", str(conf), "--connect", "tcp/127.0.0.1:1") == [
        "tcp/127.0.0.1:1"
    ]
    assert endpoints() == [DEFAULT_ENDPOINT]
    assert endpoints("--connect", "tcp/127.0.0.1:2", "--connect", "tcp/127.0.0.1:3") == [
        "tcp/127.0.0.1:2",
        "tcp/127.0.0.1:3",
    ]


# Counts its SIGTERMs in a file; exits 1 s after the first (like a service draining).
TERM_COUNTER = textwrap.dedent(
    """
    import signal, sys, time
    out = sys.argv[1]
    terms = []
    def on_term(*_):
        terms.append(time.monotonic())
        with open(out, "a") as f:
            f.write("TERM\\n")
    signal.signal(signal.SIGTERM, on_term)
    open(out + ".ready", "w").close()
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not (terms and time.monotonic() > terms[0] + 1.0):
        time.sleep(0.05)
    """
)


def test_stack_stop_all_sends_sigterm_once(tmp_path):
    st = Stack(tmp_path / "stack")
    script = tmp_path / "term_counter.py"
    script.write_text(TERM_COUNTER)
    try:
        for name in ("router", "ingest-all", "matcher-all"):
            out = tmp_path / f"{name}.terms"
            p = Proc(name, [sys.executable, str(script), str(out)], tmp_path / f"{name}.log")
            p.popen = subprocess.Popen(p.argv)
            st.procs[name] = p
        for name in st.procs:
            assert wait_until(lambda n=name: (tmp_path / f"{n}.terms.ready").exists(), 30.0)
        st.stop_all(timeout=30.0)
        for name, p in st.procs.items():
            assert not p.alive
            assert (tmp_path / f"{name}.terms").read_text().splitlines() == ["TERM"], name
    finally:
        for p in st.procs.values():
            if p.popen is not None and p.popen.poll() is None:
                p.popen.kill()
                p.popen.wait(10)


def test_up_killed_outright_leaves_no_process(tmp_path):
    """SIGKILL gives ``hdmap up`` no chance to stop its router and services: they notice
    they were orphaned (hdmap.runtime.orphan) and stop themselves, releasing the port."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    log = tmp_path / "up.log"
    with running(hdmap("up", "--listen", ep, "--data-dir", str(tmp_path / "var")), log) as up:
        roles: dict[str, psutil.Process] = {}

        def all_started() -> bool:
            nonlocal roles
            assert up.poll() is None, log.read_text()
            roles = children_by_role(up.pid)
            return listening(ep) and set(SERVICE_NAMES) | {"router"} <= set(roles)

        assert wait_until(all_started, 90.0, 0.5), (sorted(roles), log.read_text())
        up.kill()
        up.wait(10)

        def gone(p: psutil.Process) -> bool:
            with contextlib.suppress(psutil.NoSuchProcess):
                return p.status() == psutil.STATUS_ZOMBIE
            return True

        assert wait_until(lambda: all(gone(p) for p in roles.values()), 60.0, 0.5), {
            r: p.pid for r, p in roles.items() if not gone(p)
        }
        assert wait_until(lambda: not listening(ep), 30.0, 0.5)


def test_status_without_a_router_says_so_in_one_line():
    res = status("--connect", f"tcp/127.0.0.1:{free_port()}")
    assert res.returncode == 2, res
    assert "hdmap status: cannot reach the bus at tcp/127.0.0.1:" in res.stderr
    assert "Traceback" not in res.stderr, res.stderr
