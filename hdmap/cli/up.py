"""``hdmap up``: a router and one instance of each service, supervised, until Ctrl-C/SIGTERM.

Each service is isolated: one that fails to start or stops later does not stop the
others (:class:`hdmap.ops.stack.Supervisor`: a crash is restarted with backoff, a
permanent fault such as a corrupt database is reported with its file and left stopped).
"""

from __future__ import annotations

import argparse
import signal
import threading
from pathlib import Path

from hdmap.ops.stack import SERVICE_NAMES, Stack, Supervisor
from hdmap.runtime.bus import DEFAULT_ENDPOINT


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--listen", default=DEFAULT_ENDPOINT, help="router endpoint")
    p.add_argument("--data-dir", default="var", help="state directory (default ./var)")
    p.add_argument("--region", action="append", default=[], metavar="QUADKEY_PREFIX")
    p.add_argument(
        "--config",
        metavar="FILE",
        help="services config (TOML, deploy/services.toml shows every key) for every service: "
        "each reads its own [name] table",
    )
    p.add_argument(
        "--secure",
        action="store_true",
        help="TLS + authentication + ACL with a test PKI generated in <data-dir>/secure/ "
        "(the listen endpoint becomes tls/; see deploy/secure/README.md)",
    )
    p.add_argument(
        "--auth",
        choices=["mtls", "usrpwd"],
        default="mtls",
        help="with --secure: client certificates (default) or user/password",
    )
    p.add_argument(
        "--vehicle",
        action="append",
        default=[],
        metavar="ID",
        help="with --secure: a vehicle to issue credentials for (repeatable; default veh-1..3)",
    )


def run(args: argparse.Namespace) -> int:
    stop = threading.Event()
    for s in (signal.SIGTERM, signal.SIGINT):
        signal.signal(s, lambda *_: stop.set())
    region = tuple(args.region)
    security = None
    if args.secure:
        from hdmap.ops.security import generate, tls_endpoint

        vehicles = args.vehicle or ["veh-1", "veh-2", "veh-3"]
        root = Path(args.data_dir).resolve() / "secure"
        try:
            security = generate(root, vehicles, tls_endpoint(args.listen), args.auth)
        except ValueError as exc:
            raise SystemExit(f"hdmap up --secure: {exc}") from None
    extra: dict[str, list[str]] = {}
    if args.config:
        config = Path(args.config).resolve()
        if not config.is_file():
            raise SystemExit(f"hdmap up --config {args.config}: no such file")
        extra = {name: ["--config", str(config)] for name in SERVICE_NAMES}
    with Stack(
        Path(args.data_dir), listen=args.listen, security=security, extra_service_args=extra
    ) as stack:
        stack.start_all(region, isolate=True)  # the supervisor below reports who did not
        print(
            f"hdmap up: router on {stack.listen}; services {', '.join(SERVICE_NAMES)}; "
            f"state in {Path(args.data_dir).resolve()}; Ctrl-C stops",
            flush=True,
        )
        if security is not None:
            op = security.service_config("operator")
            print(
                f"hdmap up: secured ({security.auth}, ACL default deny); router config "
                f"{security.router_config}\n"
                f"  vehicle credentials: {security.root}/vehicle-<id>.json5 for "
                f"{', '.join(security.vehicles)} (CA and keys in {security.pki})\n"
                f"  status: hdmap status --zenoh-config {op} --connect {stack.listen}",
                flush=True,
            )
        supervisor = Supervisor(stack)
        while not stop.is_set():
            for line in supervisor.check():
                print(f"hdmap up: {line}", flush=True)
            stop.wait(0.5)
        print("hdmap up: stopping", flush=True)
    if supervisor.stopped:  # the operator must see that part of the region was down
        for name, why in sorted(supervisor.stopped.items()):
            print(f"hdmap up: {name} had stopped on a permanent fault: {why}", flush=True)
        return 1
    return 0
