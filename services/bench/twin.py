"""Twin speed: physics step, the twin's own per-tick cost, and lockstep real-time factors with the stack.

``archer bench twin [--duration S] [--scenario NAME] [--planner-scenario A,B] [--planner-duration S] [--json]`` prints:

- ``compiled_modules``: how many of the tick's modules run compiled (``setup.py``, mypyc);
- ``mj_step_us``: one physics step of the robot hopping (mean);
- ``twin_tick_us`` / ``twin_realtime_factor``: a lockstep tick with no stack (truth estimate, passive
  controller): physics, sensors, actuation, metrics and the loop;
- ``stack_tick_us`` / ``stack_realtime_factor``: the same with the onboard estimator (on the noisy
  sensors) and the low level, on ``--scenario`` (default hop-in-place);
- with ``--planner-scenario A[,B]``: each scenario with the graph planner in the loop too, for its whole
  default duration (``--planner-duration`` to shorten it): what one campaign run costs, the graph build
  included (``planner_runs``: per scenario ``sim_s``, ``tick_us``, ``realtime_factor``, ``goal_reached``).

The figures are wall-clock: run it on a machine with nothing else busy.
"""

from __future__ import annotations

import argparse
import time

import mujoco

from robot_description import params as rd
from sim_twin import model as tm
from sim_twin.compiled import compiled_modules
from sim_twin.lockstep import RunConfig, run


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--duration", type=float, default=10.0, help="simulated seconds per lockstep run")
    parser.add_argument("--scenario", default="hop-in-place", help="scenario of the stack run")
    parser.add_argument("--planner-scenario", default="",
                        help="also run these scenarios (comma-separated) with the graph planner (e.g. forest,maze)")
    parser.add_argument("--planner-duration", type=float, default=None,
                        help="simulated seconds of each planner run (default: the scenario's own, as a campaign runs it)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the planner runs")


def _mj_step_us(steps: int = 5000) -> float:
    model = tm.load_model()
    data = mujoco.MjData(model)
    data.qpos[2] = rd.robot_params().leg_length + 0.1  # drops and bounces: contacts come and go
    t0 = time.perf_counter()
    for _ in range(steps):
        mujoco.mj_step(model, data)
    return (time.perf_counter() - t0) / steps * 1e6


def measure(args: argparse.Namespace) -> dict:
    out: dict[str, object] = {"compiled_modules": len(compiled_modules()), "mj_step_us": round(_mj_step_us(), 2)}
    twin = run(RunConfig(scenario="hop-in-place", duration_s=args.duration, estimator="truth", controller="passive")).metrics
    out["twin_tick_us"] = twin["tick_us_mean"]
    out["twin_realtime_factor"] = twin["realtime_factor"]
    stack = run(RunConfig(scenario=args.scenario, duration_s=args.duration, estimator="kalman", planner="scenario")).metrics
    out["stack_scenario"] = args.scenario
    out["stack_tick_us"] = stack["tick_us_mean"]
    out["stack_realtime_factor"] = stack["realtime_factor"]
    out["stack_hops"] = stack["hops"]
    out["stack_falls"] = stack["falls"]
    runs = {}
    for name in filter(None, (n.strip() for n in args.planner_scenario.split(","))):
        planned = run(RunConfig(scenario=name, seed=args.seed, duration_s=args.planner_duration, estimator="kalman",
                                planner="graph")).metrics
        runs[name] = {"sim_s": planned["sim_time_s"], "tick_us": planned["tick_us_mean"],
                      "realtime_factor": planned["realtime_factor"], "goal_reached": planned.get("goal_reached")}
    if runs:
        out["planner_runs"] = runs
    return out
