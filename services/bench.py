"""``archer bench SUBJECT``: speed measurements that print figures.

Each subject module exposes ``add_arguments(parser)`` and ``measure(args) -> dict``;
the figures are printed as one JSON object (``--json``) or as aligned text.
"""

from __future__ import annotations

import argparse
import importlib
import json

BENCHES: dict[str, str] = {
    "messaging": "services.bench_messaging",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="subject", required=True, metavar="SUBJECT")
    for subject, module_name in BENCHES.items():
        module = importlib.import_module(module_name)
        p = sub.add_parser(subject, help=(module.__doc__ or "").strip().splitlines()[0])
        p.add_argument("--json", action="store_true", help="print one JSON object")
        module.add_arguments(p)
        p.set_defaults(_measure=module.measure)


def run(args: argparse.Namespace) -> int:
    figures = args._measure(args)
    if args.json:
        print(json.dumps(figures))
    else:
        width = max(len(k) for k in figures)
        for key, value in figures.items():
            print(f"{key:<{width}}  {value}")
    return 0
