"""``hdmap service NAME``: run one service in this process until SIGTERM/SIGINT."""

from __future__ import annotations

import argparse
import importlib
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from hdmap.cli.common import add_bus_arguments, bus_from_args, setup_logging
from hdmap.geo.tiles import DEFAULT_ZOOM, valid_quadkey
from hdmap.runtime.config import EXIT_CONFIG, ConfigError, from_mapping, load_toml
from hdmap.runtime.log_policy import GapPolicy, RetentionPolicy
from hdmap.runtime.metrics import MetricsConfig
from hdmap.runtime.service import Batching, ServiceOptions, run_until_signalled

log = logging.getLogger(__name__)

# name -> (module, service class, config class)
SERVICES: dict[str, tuple[str, str, str]] = {
    "ingest": ("services.ingest.service", "IngestService", "IngestConfig"),
    "matcher": ("services.matcher.service", "MatcherService", "MatcherConfig"),
    "solver": ("services.solver.service", "SolverService", "SolverConfig"),
    "publisher": ("services.publisher.service", "PublisherService", "PublisherConfig"),
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("name", choices=sorted(SERVICES))
    p.add_argument(
        "--region",
        action="append",
        default=[],
        metavar="QUADKEY_PREFIX",
        help="tiles this instance owns (repeatable; default: all)",
    )
    p.add_argument("--data-dir", default="var", help="state directory (default ./var)")
    p.add_argument(
        "--shard",
        default="0/1",
        metavar="I/N",
        help="ingest only: serve the vehicles of shard I of N (by a hash of their id)",
    )
    p.add_argument("--instance", help="stable instance id (default: kept in the data dir)")
    p.add_argument(
        "--sync",
        choices=["normal", "full"],
        default="normal",
        help="SQLite durability: normal survives crashes, full survives power loss",
    )
    p.add_argument("--zoom", type=int, default=DEFAULT_ZOOM, help="tile zoom of the deployment")
    p.add_argument("--config", metavar="FILE", help="TOML file; the [NAME] table configures it")
    p.add_argument("--log-level", default="INFO")
    p.add_argument(
        "--metrics-port",
        type=int,
        metavar="PORT",
        help="serve Prometheus metrics on http://HOST:PORT/metrics (0: off; default: the "
        "config file's [NAME.metrics] port, else off)",
    )
    p.add_argument(
        "--metrics-host",
        metavar="HOST",
        help="address the metrics endpoint binds (default: [NAME.metrics] host, else "
        "127.0.0.1: it has no authentication)",
    )
    add_bus_arguments(p)


def service_config(name: str, table: Mapping[str, Any]) -> tuple[Batching, Any]:
    """A service's ``[NAME]`` table of a services config file as its batching (the
    ``[NAME.batching]`` subtable: the runtime's, :class:`Batching`) and its own typed
    config; a bad key or value is a :class:`ConfigError` naming it."""
    own = dict(table)
    batching = from_mapping(Batching, own.pop("batching", {}), f"{name}.batching")
    own.pop("gaps", None)  # the runtime's too: gap_policy
    own.pop("retention", None)  # and retention_policy
    own.pop("metrics", None)  # and metrics_config
    module, _cls, cfg_name = SERVICES[name]
    return batching, from_mapping(getattr(importlib.import_module(module), cfg_name), own, name)


def parse_shard(text: str) -> tuple[int, int]:
    """``I/N`` as (I, N), with 0 <= I < N; else a :class:`ConfigError` naming it.

    >>> parse_shard("1/2")
    (1, 2)
    """
    i, sep, n = text.partition("/")
    if sep and i.isdigit() and n.isdigit() and 0 <= int(i) < int(n) <= 1024:
        return int(i), int(n)
    raise ConfigError(f"--shard {text!r}: expected I/N with 0 <= I < N <= 1024")


def gap_policy(name: str, table: Mapping[str, Any]) -> GapPolicy:
    """The ``[NAME.gaps]`` subtable of a service's table (:class:`GapPolicy`)."""
    return from_mapping(GapPolicy, table.get("gaps", {}), f"{name}.gaps")


def retention_policy(name: str, table: Mapping[str, Any]) -> RetentionPolicy:
    """The ``[NAME.retention]`` subtable of a service's table (:class:`RetentionPolicy`)."""
    return from_mapping(RetentionPolicy, table.get("retention", {}), f"{name}.retention")


def metrics_config(
    name: str, table: Mapping[str, Any], port: int | None = None, host: str | None = None
) -> MetricsConfig:
    """The ``[NAME.metrics]`` subtable of a service's table (:class:`MetricsConfig`), with
    ``--metrics-port`` / ``--metrics-host`` (when given) over it.

    >>> metrics_config("ingest", {"metrics": {"port": 9101}}, host="0.0.0.0")
    MetricsConfig(port=9101, host='0.0.0.0')
    """
    cfg = from_mapping(MetricsConfig, table.get("metrics", {}), f"{name}.metrics")
    over = {"port": port, "host": host}
    return from_mapping(MetricsConfig, {k: v for k, v in over.items() if v is not None}, base=cfg)


def build(args: argparse.Namespace):
    for r in args.region:
        if not valid_quadkey(r):
            raise ConfigError(f"--region {r!r}: not a quadkey prefix (digits 0-3)")
    module, cls_name, _cfg = SERVICES[args.name]
    table = load_toml(args.config).get(args.name, {}) if args.config else {}
    batching, config = service_config(args.name, table)
    shard = parse_shard(args.shard)
    if shard[1] > 1 and args.name != "ingest":
        raise ConfigError(f"--shard {args.shard}: only ingest is sharded (the others by --region)")
    opts = ServiceOptions(
        batching=batching,
        gaps=gap_policy(args.name, table),
        retention=retention_policy(args.name, table),
        metrics=metrics_config(
            args.name,
            table,
            getattr(args, "metrics_port", None),
            getattr(args, "metrics_host", None),
        ),
        region=tuple(args.region),
        data_dir=Path(args.data_dir),
        bus=bus_from_args(args),
        instance=args.instance,
        sync=args.sync,
        zoom=args.zoom,
        shard=shard,
    )
    return getattr(importlib.import_module(module), cls_name)(opts, config)


def run(args: argparse.Namespace) -> int:
    """Run the service until signalled; a refused configuration (a bad key or value, an
    unreadable file, a bad region) is one error line and :data:`EXIT_CONFIG`, which
    ``hdmap up`` does not restart."""
    setup_logging(args.log_level)
    try:
        service = build(args)
    except (ConfigError, OSError) as exc:
        log.error("%s: configuration refused: %s", args.name, exc)
        return EXIT_CONFIG
    return run_until_signalled(service)
