"""Arguments and setup shared by the commands that join the bus."""

from __future__ import annotations

import argparse
import logging
import sys

from hdmap.bus import DEFAULT_ENDPOINT, BusConfig


def add_bus_arguments(p: argparse.ArgumentParser, mode: str = "client") -> None:
    p.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help=f"Zenoh endpoint to connect to (repeatable; default {DEFAULT_ENDPOINT})",
    )
    p.add_argument("--zenoh-config", metavar="FILE", help="Zenoh JSON5 config loaded first")
    p.set_defaults(_bus_mode=mode)


def bus_from_args(args: argparse.Namespace) -> BusConfig:
    base = BusConfig(mode=args._bus_mode, config_file=getattr(args, "zenoh_config", None))
    return base.with_connect(args.connect)


def setup_logging(level: str = "INFO") -> None:
    logging.basicConfig(
        level=getattr(logging, level.upper(), logging.INFO),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
