"""``archer sim``: run a scenario on the digital twin with the onboard stack in the loop.

``--mode lockstep`` (default) steps physics and stack together on simulated time, as fast as the
machine goes, deterministically per seed. With ``--json`` the last line of stdout is one JSON
object of metrics (see :mod:`sim_twin.lockstep` for their definitions).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

from services.config import ConfigError, load_params
from sim_twin import model as tm
from sim_twin import scenarios as sc
from sim_twin import stack as st
from sim_twin.lockstep import RunConfig, run

MODES = ("lockstep",)
PROGRESS_MIN_S = 10.0  # [s of sim] shorter runs get no progress bar
BAR_WIDTH = 30


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", required=True, choices=list(sc.SCENARIOS), help="what to run")
    parser.add_argument("--seed", type=int, default=0, help="seeds every random choice (sensor noise, world, pushes)")
    parser.add_argument("--duration", type=float, default=None, help="simulated seconds (default: the scenario's)")
    parser.add_argument("--mode", choices=MODES, default="lockstep", help="lockstep: as fast as possible, deterministic")
    parser.add_argument("--variant", choices=tm.VARIANTS, default=tm.DEFAULT_VARIANT, help="robot model variant")
    parser.add_argument("--estimator", choices=st.ESTIMATORS, default="kalman",
                        help="kalman: the onboard estimator on the twin's sensors; truth: the twin's true state")
    parser.add_argument("--planner", choices=st.PLANNERS, default="auto",
                        help="scenario: the scenario's own reference; graph: the onboard planner; auto: graph when there are obstacles")
    parser.add_argument("--controller", choices=st.CONTROLLERS, default="lowlevel", help="passive: no torque (physics only)")
    parser.add_argument("--obstacles", type=int, default=None, help="forest: number of obstacles")
    parser.add_argument("--config", default=None, help="TOML file overriding onboard.params sections")
    parser.add_argument("--no-noise", action="store_true", help="sensors read the true state")
    parser.add_argument("--keep-going", action="store_true", help="do not stop at the first fall")
    parser.add_argument("--json", action="store_true", help="print the metrics as one JSON object (last stdout line)")
    parser.add_argument("--record", default=None, metavar="FILE.mcap", help="write every message to an MCAP file")
    parser.add_argument("--plot", default=None, metavar="FILE.png", help="write a PNG summary")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


class _Progress:
    """A progress bar on stderr: redrawn in place on a terminal, a line per 10 % otherwise."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self.tty = sys.stderr.isatty()
        self.t0 = time.perf_counter()
        self.last_decile = -1

    def __call__(self, sim_t: float, total: float) -> None:
        if not self.enabled or total <= 0:
            return
        frac = min(1.0, sim_t / total)
        wall = time.perf_counter() - self.t0
        rtf = sim_t / wall if wall > 0 else math.inf
        text = f"[{'#' * int(frac * BAR_WIDTH):<{BAR_WIDTH}}] {sim_t:7.1f}/{total:.1f} s sim  {rtf:5.1f}x real time"
        if self.tty:
            sys.stderr.write("\r" + text + ("\n" if frac >= 1.0 else ""))
            sys.stderr.flush()
        elif int(frac * 10) > self.last_decile:
            self.last_decile = int(frac * 10)
            print(text, file=sys.stderr, flush=True)


def build_config(args: argparse.Namespace) -> RunConfig:
    params = load_params(args.config)
    twin = params["twin"]
    if args.no_noise:
        from onboard.params import with_overrides

        twin = with_overrides(twin, {"noise": False})
    return RunConfig(
        scenario=args.scenario,
        seed=args.seed,
        duration_s=args.duration,
        variant=args.variant,
        estimator=args.estimator,
        planner=args.planner,
        controller=args.controller,
        obstacles=args.obstacles,
        twin=twin,
        safety=params["safety"] if args.config else None,
        estimator_params=params.get("estimator"),
        planner_params=params.get("planner"),
        control_params=params.get("control"),
        stop_on_fall=not args.keep_going,
        record=bool(args.record),
    )


def run_lockstep(args: argparse.Namespace) -> dict:
    cfg = build_config(args)
    duration = cfg.duration_s if cfg.duration_s is not None else sc.SCENARIOS[cfg.scenario](cfg.seed, cfg.obstacles).default_duration_s
    progress = _Progress(enabled=not args.quiet and duration >= PROGRESS_MIN_S)
    result = run(cfg, progress)
    if args.record:
        from sim_twin.record import write_mcap

        result.metrics["recorded_messages"] = write_mcap(args.record, result.messages)
    if args.plot:
        from sim_twin.plot import plot_run

        plot_run(result, args.plot)
    return result.metrics


def run_sim(args: argparse.Namespace) -> int:
    try:
        metrics = run_lockstep(args)
    except (ValueError, ConfigError) as exc:
        print(f"archer sim: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(metrics))
    else:
        width = max(len(k) for k in metrics)
        for key, value in metrics.items():
            print(f"{key:<{width}}  {value}")
    return 0
