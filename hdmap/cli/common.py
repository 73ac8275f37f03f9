"""Arguments and setup shared by the commands that join the bus."""

from __future__ import annotations

import argparse
import logging
import sys

from hdmap.runtime.bus import DEFAULT_ENDPOINT, BusConfig


def add_bus_arguments(p: argparse.ArgumentParser, mode: str = "client") -> None:
    p.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help=f"Zenoh endpoint to connect to (repeatable; default: the --zenoh-config "
        f"file's, else {DEFAULT_ENDPOINT})",
    )
    p.add_argument("--zenoh-config", metavar="FILE", help="Zenoh JSON5 config loaded first")
    p.set_defaults(_bus_mode=mode)


def bus_from_args(args: argparse.Namespace) -> BusConfig:
    """``--connect`` overrides the config file's endpoints; with neither, the default one."""
    config_file = getattr(args, "zenoh_config", None)
    connect = tuple(args.connect) or (() if config_file else (DEFAULT_ENDPOINT,))
    return BusConfig(mode=args._bus_mode, connect=connect, config_file=config_file)


def setup_logging(level: str = "INFO") -> None:
    logging.basicConfig(
        level=getattr(logging, level.upper(), logging.INFO),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
