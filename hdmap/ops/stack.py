"""Start and stop a router plus services as separate processes (``hdmap up``, tests, evals).

Every process is a child of the :class:`Stack`; leaving the ``with`` block (also on
an exception) stops them all: SIGTERM, then SIGKILL after a grace period.

A service process that exits with :data:`~hdmap.runtime.store.EXIT_CORRUPT` stopped on a
permanent fault (its database is corrupt): :attr:`Proc.permanent`, and
:func:`stop_reason` finds the line it logged. ``start_all(isolate=True)`` starts the
others even so (``hdmap up``'s fault isolation).

With ``security`` (a :class:`hdmap.ops.security.SecureDeployment`) the router and each
service load their generated Zenoh config (TLS, authentication, ACL), the router
listens on ``tls/`` and :attr:`Stack.bus` is the ``operator`` identity.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from hdmap.geo.tiles import region_label
from hdmap.runtime.bus import BusConfig, open_session
from hdmap.runtime.config import EXIT_CONFIG
from hdmap.runtime.orphan import PARENT_ENV
from hdmap.runtime.shards import shard_label
from hdmap.runtime.store import EXIT_CORRUPT
from schemas import keys

if TYPE_CHECKING:
    from hdmap.ops.security import SecureDeployment

SERVICE_NAMES = ("ingest", "matcher", "solver", "publisher")


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def endpoint_port(endpoint: str) -> tuple[str, int]:
    """'tcp/127.0.0.1:7447' -> ('127.0.0.1', 7447)."""
    host, port = endpoint.split("/", 1)[1].rsplit(":", 1)
    return host.strip("[]"), int(port)


PERMANENT_EXITS = (EXIT_CORRUPT, EXIT_CONFIG)
"""Exit codes :class:`Supervisor` does not restart."""


@dataclass
class Proc:
    name: str
    argv: list[str]
    log_path: Path
    popen: subprocess.Popen | None = None
    restarts: int = 0

    @property
    def alive(self) -> bool:
        return self.popen is not None and self.popen.poll() is None

    @property
    def returncode(self) -> int | None:
        """The exit code once the process has ended (None while it runs or before it started)."""
        return None if self.popen is None else self.popen.poll()

    @property
    def permanent(self) -> bool:
        """Whether it ended on a permanent fault (:data:`EXIT_CORRUPT`: a corrupt database,
        :data:`EXIT_CONFIG`: a refused configuration): restarting it fails the same way
        until an operator repairs its data or its config."""
        return self.returncode in PERMANENT_EXITS


@dataclass
class Stack:
    """A router and services on one machine, each its own process."""

    data_dir: Path
    listen: str = ""
    extra_service_args: dict[str, list[str]] = field(default_factory=dict)
    python: str = sys.executable
    procs: dict[str, Proc] = field(default_factory=dict)
    security: SecureDeployment | None = None
    """Secure mode: per-process Zenoh configs (TLS, auth, ACL) from hdmap.ops.security."""
    netns: dict[str, str] = field(default_factory=dict)
    """Process name (``router``, ``ingest-all``, ...) -> the network namespace it runs in
    (``ip netns exec``): other hosts, as tests make them."""
    connect_for: dict[str, str] = field(default_factory=dict)
    """Process name -> the router endpoint it connects to (default :attr:`listen`)."""
    router_listen: tuple[str, ...] = ()
    """More endpoints the router listens on (one per network it is on)."""

    def __post_init__(self) -> None:
        self.data_dir = Path(self.data_dir)
        if not self.listen:
            self.listen = f"tcp/127.0.0.1:{free_port()}"
        if self.security is not None and self.listen.startswith("tcp/"):
            self.listen = "tls/" + self.listen.removeprefix("tcp/")
        (self.data_dir / "logs").mkdir(parents=True, exist_ok=True)

    @property
    def bus(self) -> BusConfig:
        if self.security is not None:
            return self.security.bus("operator").with_connect([self.listen])
        return BusConfig(mode="client", connect=(self.listen,))

    def _zenoh_config(self, identity: str | None) -> list[str]:
        """``--zenoh-config FILE`` of a process in secure mode (router: identity None)."""
        if self.security is None:
            return []
        if identity is None:
            return ["--zenoh-config", str(self.security.router_config)]
        return ["--zenoh-config", str(self.security.client_config(identity))]

    def _cli(self, *args: str) -> list[str]:
        return [self.python, "-m", "hdmap.cli", *args]

    def _spawn(self, proc: Proc) -> Proc:
        log = open(proc.log_path, "ab")
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        env[PARENT_ENV] = str(os.getpid())  # the child ends if this process dies
        argv = proc.argv
        if (ns := self.netns.get(proc.name)) is not None:
            argv = ["ip", "netns", "exec", ns, *argv]  # execs: the same process, its pid
        proc.popen = subprocess.Popen(
            argv, stdout=log, stderr=subprocess.STDOUT, env=env, start_new_session=True
        )
        log.close()
        self.procs[proc.name] = proc
        return proc

    def start_router(self, timeout: float = 20.0) -> Proc:
        p = self._spawn(
            Proc(
                "router",
                self._cli(
                    "router",
                    *(a for e in (self.listen, *self.router_listen) for a in ("--listen", e)),
                    *self._zenoh_config(None),
                ),
                self.data_dir / "logs" / "router.log",
            )
        )
        return self._wait_listening(p, timeout)

    def restart_router(self, timeout: float = 20.0) -> Proc:
        """Restart the router (SIGTERM if still alive) on the same endpoint; wait until it
        listens. Services and clients reconnect by themselves."""
        self.restart("router")
        return self._wait_listening(self.procs["router"], timeout)

    def _wait_listening(self, p: Proc, timeout: float) -> Proc:
        host, port = endpoint_port(self.listen)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if not p.alive:
                raise RuntimeError(f"router exited: see {p.log_path}")
            with contextlib.suppress(OSError), socket.create_connection((host, port), 0.2):
                return p
            time.sleep(0.05)
        raise TimeoutError(f"router not listening on {self.listen} after {timeout} s")

    def service_key(
        self, name: str, region: tuple[str, ...] = (), shard: tuple[int, int] = (0, 1)
    ) -> str:
        return f"{name}-{region_label(region)}{shard_label(shard)}"

    def start_service(
        self,
        name: str,
        region: tuple[str, ...] = (),
        *extra: str,
        shard: tuple[int, int] = (0, 1),
    ) -> Proc:
        key = self.service_key(name, region, shard)
        connect = self.connect_for.get(key, self.listen)
        argv = self._cli("service", name, "--connect", connect, "--data-dir", str(self.data_dir))
        argv += self._zenoh_config(name)
        for r in region:
            argv += ["--region", r]
        if shard[1] > 1:
            argv += ["--shard", f"{shard[0]}/{shard[1]}"]
        argv += self.extra_service_args.get(name, []) + list(extra)
        old = self.procs.get(key)
        p = Proc(
            key,
            argv,
            self.data_dir / "logs" / f"{key}.log",
            restarts=(old.restarts + 1) if old else 0,
        )
        return self._spawn(p)

    def start_all(
        self, region: tuple[str, ...] = (), timeout: float = 60.0, isolate: bool = False
    ) -> list[str]:
        """Start the router and one of each service; wait until they are ready.

        A service that exits meanwhile raises :class:`RuntimeError`, unless ``isolate``:
        then the others are still waited for, and the names of those that exited are
        returned (the caller decides about them: ``hdmap up`` restarts a crashed one and
        leaves one stopped on a permanent fault stopped). The router must come up.
        """
        self.start_router()
        for name in SERVICE_NAMES:
            self.start_service(name, region)
        return self.wait_ready(
            [self.service_key(n, region) for n in SERVICE_NAMES], timeout, isolate
        )

    def wait_ready(
        self, names: list[str], timeout: float = 60.0, isolate: bool = False
    ) -> list[str]:
        """Until each named service has its liveliness token up (bounded); the names that
        exited instead (only with ``isolate``; without it, one exiting raises)."""
        deadline = time.monotonic() + timeout
        exited: list[str] = []
        names = list(names)
        with open_session(self.bus) as s:
            while True:
                alive = {
                    "-".join(str(r.ok.key_expr).split("/")[-3:-1])
                    for r in s.liveliness().get(f"{keys.ROOT}/alive/**", timeout=2.0)
                    if r.ok
                }
                missing = [n for n in names if n not in alive]
                if not missing:
                    return exited
                for n in missing:
                    p = self.procs.get(n)
                    if p is not None and not p.alive:
                        if not isolate:
                            raise RuntimeError(f"{n} exited: {tail(p.log_path)}")
                        exited.append(n)
                        names.remove(n)
                if time.monotonic() > deadline:
                    raise TimeoutError(f"services not ready after {timeout} s: {missing}")
                time.sleep(0.1)

    def send_signal(self, name: str, sig: int) -> None:
        p = self.procs[name]
        if p.alive and p.popen is not None:
            p.popen.send_signal(sig)

    def stop(self, name: str, timeout: float = 15.0, sig: int = signal.SIGTERM) -> int | None:
        """Stop one process (SIGTERM, then SIGKILL after ``timeout``); its exit code."""
        p = self.procs.get(name)
        if p is None or p.popen is None:
            return None
        if p.alive:
            p.popen.send_signal(sig)
        return self._reap(p, timeout)

    @staticmethod
    def _reap(p: Proc, timeout: float) -> int | None:
        """Wait for a signalled process to exit; SIGKILL it after ``timeout``."""
        if p.popen is None:
            return None
        try:
            p.popen.wait(max(timeout, 0.0))
        except subprocess.TimeoutExpired:
            p.popen.kill()
            p.popen.wait(5)
        return p.popen.returncode

    def kill(self, name: str) -> None:
        self.stop(name, timeout=5.0, sig=signal.SIGKILL)

    def restart(self, name: str) -> Proc:
        p = self.procs[name]
        if p.alive:
            self.stop(name)
        p.restarts += 1
        return self._spawn(p)

    def stop_all(self, timeout: float = 15.0) -> None:
        """SIGTERM every service at once (each once), wait, then the router."""
        services = [self.procs[n] for n in self.procs if n != "router"]
        for p in services:
            if p.alive and p.popen is not None:
                p.popen.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + timeout
        for p in services:
            self._reap(p, deadline - time.monotonic())
        self.stop("router", timeout)

    def __enter__(self) -> Stack:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop_all()


@dataclass
class Supervisor:
    """What ``hdmap up`` does about processes of ``stack`` that ended, one :meth:`check` at
    a time: a process that crashed (any other exit code, a signal) is restarted after a
    backoff of 0.5 s times (its restarts so far + 1), at most ``max_backoff_s``; one that stopped
    on a permanent fault (:attr:`Proc.permanent`: a corrupt database) is not restarted,
    since it would fail the same way: it is listed in :attr:`stopped` with its reason
    until the operator repairs its data and starts ``hdmap up`` again. The others keep
    running either way."""

    stack: Stack
    max_backoff_s: float = 5.0
    stopped: dict[str, str] = field(default_factory=dict)
    """Process name -> why it stopped for good (its logged error line)."""
    _due: dict[str, float] = field(default_factory=dict, init=False, repr=False)
    """Process name -> when to restart it (monotonic s)."""

    def check(self, now: float | None = None) -> list[str]:
        """Look at every process once: restart those whose backoff has passed; one line
        (or a few) to report per process that ended since the last check."""
        now = time.monotonic() if now is None else now
        report: list[str] = []
        for name, proc in list(self.stack.procs.items()):
            if proc.alive or name in self.stopped:
                continue
            if proc.permanent:
                self.stopped[name] = stop_reason(proc)
                report.append(
                    f"{name} stopped on a permanent fault (exit {proc.returncode}; not "
                    f"restarted, the others keep running): {self.stopped[name]}"
                )
                continue
            due = self._due.get(name)
            if due is None:
                self._due[name] = now + min(self.max_backoff_s, 0.5 * (proc.restarts + 1))
                report.append(
                    f"{name} exited ({proc.returncode}); restarting. Last log lines:\n"
                    f"{tail(proc.log_path, 10)}"
                )
            elif now >= due:
                del self._due[name]
                self.stack.restart(name)
        return report


def stop_reason(p: Proc) -> str:
    """Why a process ended, in one line: the message of the last error line of its log (a
    service stopped on a corrupt database logs one naming the file and the cause), else
    its last line."""
    lines = [ln for ln in tail(p.log_path, 50).splitlines() if ln.strip()]
    errors = [ln for ln in lines if " ERROR " in ln or "Error" in ln]
    line = (errors or lines or ["(empty log)"])[-1].strip()
    if " ERROR " in line:  # '<time> ERROR <logger>: <message>' (hdmap.cli.common)
        line = line.split(" ERROR ", 1)[1]
        logger, sep, message = line.partition(": ")
        line = message if sep and " " not in logger else line
    return line


def tail(path: Path, n: int = 30) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-n:])
    except OSError:
        return "(no log)"
