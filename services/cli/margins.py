"""``archer margins --out DIR``: how far each model error may grow before the robot misses its goal
and before it falls (:mod:`offline.margins`), for one or more controller configs side by side.

Each factor alone on its ladder (``--model-error name=value``), the stack nominal, lockstep with the
Kalman estimator; the runs go through the campaign engine (``DIR/runs.jsonl``: a second start
resumes, a local pool or ``--ray``), then ``DIR/margins.md`` (the table), ``margins.png`` (worst
goal error per rung, a cross where a run fell) and ``margins.json``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from offline import margins as mg
from robot_description import params as rd


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, type=Path, help="campaign folder (runs.jsonl, margins.md/.png/.json)")
    parser.add_argument("--factors", default=",".join(lad.factor for lad in mg.LADDERS),
                        help="comma list of factors (default: every ladder)")
    parser.add_argument("--scenario", default="hop-in-place,setpoint", help="comma list of scenarios run on every rung")
    parser.add_argument("--seeds", default="0-1", help="seeds of every rung (archer campaign's syntax)")
    parser.add_argument("--config", default="", help="comma list of controller config TOML files compared side by side "
                        "(an empty entry: the defaults)")
    parser.add_argument("--variant", choices=rd.VARIANTS, default=rd.DEFAULT_VARIANT)
    parser.add_argument("--workers", type=int, default=2, help="local worker processes")
    parser.add_argument("--ray", default=None, metavar="ADDRESS", help="run on this Ray cluster")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from services.cli import campaign

    try:
        ladders = [mg.ladder(f.strip()) for f in args.factors.split(",") if f.strip()]
        configs = [c.strip() for c in args.config.split(",")] or [""]
        for c in configs:
            if c and not Path(c).is_file():
                raise ValueError(f"--config {c}: no such file")
        scenarios = [s.strip() for s in args.scenario.split(",") if s.strip()]
        specs = mg.specs(ladders, scenarios, campaign.parse_seeds(args.seeds), configs, args.variant)
        for spec in {(s["scenario"], s["options"]["model-error"], s["options"].get("config")): s for s in specs}.values():
            campaign.sim_arguments(spec)  # archer sim accepts every run before any starts
    except ValueError as exc:
        print(f"archer margins: {exc}")
        return 2
    records = campaign.sweep(specs, args.out, args.workers, args.ray, progress=not args.quiet)
    results = mg.margins(list(records.values()), ladders, configs)
    md, png = mg.write(results, configs, args.out)
    print(md.read_text(), end="")
    print(f"{len(records)} runs; wrote {md}, {png}")
    return 0
