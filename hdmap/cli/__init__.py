"""The ``hdmap`` command: one entry point, one subcommand per job.

Each subcommand module exposes ``add_arguments(parser)`` and ``run(args) -> int``;
this module only wires them (CLI entry -> orchestration -> domain).
"""

from __future__ import annotations

import argparse
import importlib
import sys

from hdmap.runtime.orphan import watch_parent

# name -> (module, help). Modules are imported lazily so `hdmap --help` stays fast.
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("hdmap.cli.demo", "run the main job on embedded defaults"),
    "vehicle-demo": ("hdmap.cli.vehicle_demo", "the vehicle side alone: rays of one drive"),
    "router": ("hdmap.cli.router", "run a Zenoh router"),
    "service": ("hdmap.cli.service", "run one service (ingest, matcher, solver, publisher)"),
    "up": ("hdmap.cli.up", "router + one of each service, until Ctrl-C"),
    "status": ("hdmap.cli.status", "live services, their regions and counters"),
    "export": ("hdmap.cli.export", "the published map of an area as GeoJSON, OSM XML or CSV"),
    "dashboard": ("hdmap.cli.dashboard", "a live web page of the map and the services' health"),
    "region": ("hdmap.cli.region", "split a live region into sub-regions, or merge regions"),
    "eval": (
        "hdmap.cli.eval",
        "evaluations (paper simulation, fleet, map changes, localisation against the map)",
    ),
    "loadtest": ("hdmap.cli.loadtest", "a simulated fleet against a running stack"),
    "calibrate-gnss": (
        "hdmap.cli.calibrate",
        "the solver's shared-error floor from a fix-minus-truth GNSS log",
    ),
    "calibrate-map": (
        "hdmap.cli.calibrate_map",
        "the solver's map floor from surveyed signs against the live map",
    ),
}


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The parser; with ``only``, just that subcommand's module is imported."""
    parser = argparse.ArgumentParser(prog="hdmap", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module, help_text) in SUBCOMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if only is None or name == only:
            try:
                mod = importlib.import_module(module)
            except ModuleNotFoundError as e:  # an install without the extras this one needs
                p.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
                p.set_defaults(_run=_needs_extras(name, e.name or "?"))
                continue
            mod.add_arguments(p)
            p.set_defaults(_run=mod.run)
    return parser


def _needs_extras(name: str, missing: str):
    def run(_args: argparse.Namespace) -> int:
        print(
            f"hdmap {name}: needs {missing!r}, which this install lacks; the base install is "
            "the onboard side: pip install 'hdmap[server]' (services, operations) or "
            "'hdmap[sim]' (evaluations, demo)",
            file=sys.stderr,
        )
        return 2

    return run


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    only = argv[0] if argv and argv[0] in SUBCOMMANDS else None
    args = build_parser(only).parse_args(argv)
    watch_parent()  # a stack's child ends with its starter (hdmap.runtime.orphan)
    try:
        return int(args._run(args) or 0)
    except BrokenPipeError:  # `hdmap ... | head`: the reader left, not an error of ours
        sys.stderr.close()
        return 0


if __name__ == "__main__":
    sys.exit(main())
