"""The clipped ZDP against plain LQR / Raibert / the MLP on a 2 m setpoint (thesis Fig. 5.22).

Runs the twin's ``setpoint`` scenario in lockstep once per policy (``ControlParams.policy``)
with the onboard estimator on noisy sensors. ``--reference step`` replaces the scenario's
smooth cubic by the bare goal from t = 0 (the thesis's figure: "tracking a setpoint 2 m
away"); ``smooth`` keeps the scenario's reference. Per policy: falls (and when), time to
arrive within 0.10 m of the goal and stay, overshoot past the goal, final error, RMS
tracking error at impacts, peak wheel speed.
"""

from __future__ import annotations

import argparse
import dataclasses
import math

from onboard.contracts.params import ControlParams
from sim_twin.lockstep import LockstepRunner, RunConfig

POLICIES = ("zdp", "lqr", "raibert", "mlp")
ARRIVE_M = 0.10


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--reference", choices=("step", "smooth"), default="step")
    parser.add_argument("--estimator", choices=("kalman", "truth"), default="kalman")
    parser.add_argument("--duration", type=float, default=20.0)
    parser.add_argument("--seed", type=int, default=0)


def run_policy(policy: str, args: argparse.Namespace) -> dict:
    cfg = RunConfig(scenario="setpoint", estimator=args.estimator, seed=args.seed, duration_s=args.duration,
                    control_params=dataclasses.replace(ControlParams(), policy=policy))
    runner = LockstepRunner(cfg)
    goal = runner.scenario.target()
    if args.reference == "step":
        runner.step_reference()
    res = runner.run()
    d = res.metrics
    arrive = None
    heading = math.atan2(goal[1], goal[0])
    overshoot = -math.inf
    for t, c in zip(res.trace.t, res.trace.com, strict=True):
        err = math.hypot(c[0] - goal[0], c[1] - goal[1])
        if err <= ARRIVE_M:
            arrive = t if arrive is None else arrive
        else:
            arrive = None
        along = c[0] * math.cos(heading) + c[1] * math.sin(heading)
        overshoot = max(overshoot, along - math.hypot(*goal))
    return {
        "falls": d["falls"],
        "fall_time_s": d["fall_time_s"],
        "arrive_s": arrive,
        "overshoot_m": round(overshoot, 3),
        "final_error_m": d["final_goal_error_m"],
        "rms_tracking_error_m": d["rms_tracking_error_m"],
        "max_wheel_speed_rad_s": d["max_wheel_speed_rad_s"],
    }


def measure(args: argparse.Namespace) -> dict:
    out: dict = {"reference": args.reference, "estimator": args.estimator}
    for policy in POLICIES:
        for key, value in run_policy(policy, args).items():
            out[f"{policy}_{key}"] = value
    return out
