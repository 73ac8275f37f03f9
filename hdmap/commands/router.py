"""``hdmap router``: a Zenoh router opened by the eclipse-zenoh wheel."""

from __future__ import annotations

import argparse
import logging
import signal
import threading

from hdmap.bus import DEFAULT_ENDPOINT, BusConfig, open_session
from hdmap.commands.common import setup_logging

log = logging.getLogger("hdmap.router")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help=f"endpoint to listen on (repeatable; default {DEFAULT_ENDPOINT})",
    )
    p.add_argument("--zenoh-config", metavar="FILE", help="Zenoh JSON5 config loaded first")


def run(args: argparse.Namespace) -> int:
    setup_logging()
    listen = tuple(args.listen) or (DEFAULT_ENDPOINT,)
    cfg = BusConfig(mode="router", connect=(), listen=listen, config_file=args.zenoh_config)
    stop = threading.Event()
    for s in (signal.SIGTERM, signal.SIGINT):
        signal.signal(s, lambda *_: stop.set())
    with open_session(cfg) as session:
        log.info("router %s listening on %s", session.zid(), ", ".join(listen))
        print(f"router listening on {', '.join(listen)}", flush=True)
        while not stop.wait(0.5):
            pass
    log.info("router stopped")
    return 0
