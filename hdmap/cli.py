"""The ``hdmap`` command: one entry point, one subcommand per job.

Each subcommand module exposes ``add_arguments(parser)`` and ``run(args) -> int``;
this module only wires them (CLI entry -> orchestration -> domain).
"""

from __future__ import annotations

import argparse
import importlib
import sys

# name -> (module, help). Modules are imported lazily so `hdmap --help` stays fast.
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("hdmap.commands.demo", "run the main job on embedded defaults"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="hdmap", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module, help_text) in SUBCOMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        mod = importlib.import_module(module)
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(args._run(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
