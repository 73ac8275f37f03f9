"""``hdmap up``: a router and one instance of each service, supervised, until Ctrl-C/SIGTERM."""

from __future__ import annotations

import argparse
import signal
import threading
import time
from pathlib import Path

from hdmap.bus import DEFAULT_ENDPOINT
from hdmap.stack import SERVICE_NAMES, Stack, tail


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--listen", default=DEFAULT_ENDPOINT, help="router endpoint")
    p.add_argument("--data-dir", default="var", help="state directory (default ./var)")
    p.add_argument("--region", action="append", default=[], metavar="QUADKEY_PREFIX")


def run(args: argparse.Namespace) -> int:
    stop = threading.Event()
    for s in (signal.SIGTERM, signal.SIGINT):
        signal.signal(s, lambda *_: stop.set())
    region = tuple(args.region)
    with Stack(Path(args.data_dir), listen=args.listen) as stack:
        stack.start_all(region)
        print(
            f"hdmap up: router on {stack.listen}; services {', '.join(SERVICE_NAMES)}; "
            f"state in {Path(args.data_dir).resolve()}; Ctrl-C stops",
            flush=True,
        )
        while not stop.wait(1.0):
            for name, proc in list(stack.procs.items()):
                if not proc.alive and not stop.is_set():
                    print(
                        f"hdmap up: {name} exited ({proc.popen.returncode if proc.popen else '?'})"
                        f"; restarting. Last log lines:\n{tail(proc.log_path, 10)}",
                        flush=True,
                    )
                    time.sleep(min(5.0, 0.5 * (proc.restarts + 1)))
                    stack.restart(name)
        print("hdmap up: stopping", flush=True)
    return 0
