"""Arguments and setup shared by the commands that join the bus."""

from __future__ import annotations

import argparse
import logging
import math
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


def add_progress_argument(p: argparse.ArgumentParser) -> None:
    """``--no-progress``: no progress line (:mod:`hdmap.ops.progress`)."""
    p.add_argument(
        "--no-progress",
        action="store_true",
        help="no progress line on stderr (also HDMAP_NO_PROGRESS=1); on a terminal it is "
        "redrawn in place, elsewhere (CI logs) a line every 10 %%",
    )


def bus_unreachable(command: str, bus: BusConfig, exc: Exception) -> int:
    """One line on stderr for a bus that cannot be reached (no router there), not a
    traceback; the exit status to return (2)."""
    where = ", ".join(bus.connect) or "the configured endpoints"
    print(f"{command}: cannot reach the bus at {where}: {exc}", file=sys.stderr)
    return 2


def setup_logging(level: str = "INFO") -> None:
    logging.basicConfig(
        level=getattr(logging, level.upper(), logging.INFO),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )


def non_negative_int(text: str) -> int:
    """An argument type: a whole number >= 0."""
    try:
        n = int(text)
    except ValueError:
        n = -1
    if n < 0:
        raise argparse.ArgumentTypeError(f"need a whole number >= 0, got {text!r}")
    return n


def positive_int(text: str) -> int:
    """An argument type: a whole number >= 1."""
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"need a whole number >= 1, got {text!r}")
    return n


def non_negative_float(text: str) -> float:
    """An argument type: a finite number >= 0."""
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not (math.isfinite(v) and v >= 0.0):
        raise argparse.ArgumentTypeError(f"need a finite number >= 0, got {text!r}")
    return v


def positive_float(text: str) -> float:
    """An argument type: a finite number > 0."""
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not (math.isfinite(v) and v > 0.0):
        raise argparse.ArgumentTypeError(f"need a finite number > 0, got {text!r}")
    return v


def seed_list(text: str) -> list[int]:
    """An argument type: distinct comma-separated ints (``0,1,2``)."""
    try:
        seeds = [int(s) for s in text.split(",") if s.strip()]
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"not a comma-separated list of ints: {text!r}") from exc
    if not seeds or len(set(seeds)) != len(seeds):
        raise argparse.ArgumentTypeError(f"need distinct seeds, got {text!r}")
    return seeds
