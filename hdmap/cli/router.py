"""``hdmap router``: a Zenoh router opened by the eclipse-zenoh wheel."""

from __future__ import annotations

import argparse
import json
import logging
import signal
import threading

import zenoh

from hdmap.cli.common import setup_logging
from hdmap.runtime.bus import DEFAULT_ENDPOINT, BusConfig, open_session, zenoh_config

log = logging.getLogger("hdmap.router")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help=f"endpoint to listen on (repeatable; overrides the --zenoh-config file's; "
        f"default: the file's, else {DEFAULT_ENDPOINT})",
    )
    p.add_argument("--zenoh-config", metavar="FILE", help="Zenoh JSON5 config loaded first")


def configured_listen(cfg: BusConfig) -> tuple[str, ...]:
    """The router's listen endpoints after the file and the overrides (for the log)."""
    try:
        value = json.loads(zenoh_config(cfg).get_json("listen/endpoints"))
    except (ValueError, zenoh.ZError):
        return ()
    if isinstance(value, dict):  # per-mode form {router: [...], peer: [...]}
        value = value.get("router", [])
    return tuple(str(e) for e in value) if isinstance(value, list) else ()


def run(args: argparse.Namespace) -> int:
    setup_logging()
    listen = tuple(args.listen) or (() if args.zenoh_config else (DEFAULT_ENDPOINT,))
    cfg = BusConfig(mode="router", connect=(), listen=listen, config_file=args.zenoh_config)
    stop = threading.Event()
    for s in (signal.SIGTERM, signal.SIGINT):
        signal.signal(s, lambda *_: stop.set())
    listen = configured_listen(cfg) or listen
    with open_session(cfg) as session:
        log.info("router %s listening on %s", session.zid(), ", ".join(listen))
        print(f"router listening on {', '.join(listen)}", flush=True)
        while not stop.wait(0.5):
            pass
    log.info("router stopped")
    return 0
