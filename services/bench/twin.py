"""Twin speed: physics step, the twin's own per-tick cost, and lockstep real-time factors with the stack.

``archer bench twin [--duration S] [--scenario NAME] [--planner-scenario NAME] [--json]`` prints:

- ``compiled_modules``: how many of the tick's modules run compiled (``setup.py``, mypyc);
- ``mj_step_us``: one physics step of the robot hopping (mean);
- ``twin_tick_us`` / ``twin_realtime_factor``: a lockstep tick with no stack (truth estimate, passive
  controller): physics, sensors, actuation, metrics and the loop;
- ``stack_tick_us`` / ``stack_realtime_factor``: the same with the onboard estimator (on the noisy
  sensors) and the low level, on ``--scenario`` (default hop-in-place);
- with ``--planner-scenario``: ``planner_realtime_factor`` with the graph planner in the loop too.
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
    parser.add_argument("--planner-scenario", default="", help="also run this scenario with the graph planner (e.g. forest)")


def _mj_step_us(steps: int = 5000) -> float:
    model = tm.load_model()
    data = mujoco.MjData(model)
    data.qpos[2] = rd.robot_params().leg_length + 0.1  # drops and bounces: contacts come and go
    t0 = time.perf_counter()
    for _ in range(steps):
        mujoco.mj_step(model, data)
    return (time.perf_counter() - t0) / steps * 1e6


def measure(args: argparse.Namespace) -> dict:
    out: dict[str, float | int | str] = {"compiled_modules": len(compiled_modules()), "mj_step_us": round(_mj_step_us(), 2)}
    twin = run(RunConfig(scenario="hop-in-place", duration_s=args.duration, estimator="truth", controller="passive")).metrics
    out["twin_tick_us"] = twin["tick_us_mean"]
    out["twin_realtime_factor"] = twin["realtime_factor"]
    stack = run(RunConfig(scenario=args.scenario, duration_s=args.duration, estimator="kalman", planner="scenario")).metrics
    out["stack_scenario"] = args.scenario
    out["stack_tick_us"] = stack["tick_us_mean"]
    out["stack_realtime_factor"] = stack["realtime_factor"]
    out["stack_hops"] = stack["hops"]
    out["stack_falls"] = stack["falls"]
    if args.planner_scenario:
        planned = run(RunConfig(scenario=args.planner_scenario, duration_s=args.duration, estimator="kalman", planner="graph")).metrics
        out["planner_scenario"] = args.planner_scenario
        out["planner_tick_us"] = planned["tick_us_mean"]
        out["planner_realtime_factor"] = planned["realtime_factor"]
    return out
