"""The ``archer`` command line.

Each subcommand lives in its own module exposing ``add_arguments(parser)`` and
``run(args) -> int``; this table is the only place that lists them.
"""

from __future__ import annotations

import argparse
import importlib
import sys

COMMANDS: dict[str, tuple[str, str]] = {
    # name: (module, one-line help)
    "run": ("services.cmd_run", "run one service (estimator, control, planner, perception, hardware, twin, recorder, router)"),
    "topics": ("services.cmd_introspect", "print the topic table"),
    "echo": ("services.cmd_introspect", "print decoded live messages on a topic"),
    "status": ("services.cmd_introspect", "list live services and their status"),
    "bench": ("services.bench", "measure speed: messaging, control, estimator, mpc, planner, perception"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="archer", description="ARCHER hopping-robot onboard stack")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module_name, help_text) in COMMANDS.items():
        module = importlib.import_module(module_name)
        p = sub.add_parser(name, help=help_text, description=help_text)
        adder = getattr(module, f"add_{name}_arguments", None) or module.add_arguments
        adder(p)
        p.set_defaults(_runner=getattr(module, f"run_{name}", None) or module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args._runner(args) or 0)
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
