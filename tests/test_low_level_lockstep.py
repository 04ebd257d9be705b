"""The low level on the MuJoCo twin in lockstep: hundreds of hops in place, a 2 m setpoint
with the onboard estimator on noisy sensors, a moving reference tracked without a standing error,
and the stale-reference fallback.

Long runs (3000 hops, every scenario, the ZDP/LQR comparison) are for reports:
``archer sim --scenario NAME --json``.
"""

from __future__ import annotations

import math

from onboard.contracts.params import ControlParams, SafetyLimits
from sim_twin.lockstep import LockstepRunner, RunConfig, run

LIMITS = SafetyLimits()


def test_hundreds_of_hops_in_place_without_a_fall():
    res = run(RunConfig(scenario="hop-in-place", estimator="truth", duration_s=80.0))
    m = res.metrics
    assert m["falls"] == 0
    assert "time_to_goal_s" not in m  # nowhere to go
    assert m["hops"] >= 200
    assert m["final_goal_error_m"] < 0.05
    assert m["max_wheel_speed_rad_s"] < LIMITS.wheel_speed_max
    assert m["max_tracking_error_m"] < 0.05


def test_setpoint_two_metres_with_the_kalman_estimator():
    runner = LockstepRunner(RunConfig(scenario="setpoint", estimator="kalman", seed=3))
    res = runner.run()
    m = res.metrics
    ctrl = runner.controller.ctrl
    assert 0.0 < ctrl.saturation_fraction < 0.3  # the PD saturates at times, not always
    assert m["falls"] == 0
    assert m["goal_reached"] and m["final_goal_error_m"] <= 0.10
    # the pace: the first time the CoM came within the goal's tolerance, no sooner than the robot's
    # top speed allows and within the run (a run that never got there reports None)
    goal = runner.scenario.goal()
    to_go = math.dist(runner.scenario.start, goal.position) - goal.tolerance
    assert to_go / runner.robot.hop_speed_max < m["time_to_goal_s"] <= m["sim_time_s"]
    assert m["max_wheel_speed_rad_s"] < LIMITS.wheel_speed_max
    assert m["rms_tracking_error_m"] < 0.10


def test_the_cruise_lean_keeps_the_robot_on_a_moving_reference():
    """The ZDP's error law alone leans back against the hop map's growing speed only from an error, so it
    cruises off a moving reference; with the hop map's cruise lean fed forward the robot stays on it:
    the square's RMS tracking 0.070 -> 0.043 m (seed 0, lockstep), the wheels no faster."""
    runs = {ff: run(RunConfig(scenario="square", estimator="kalman", seed=0, control_params=ControlParams(cruise_feedforward=ff))).metrics
            for ff in (0.0, 1.0)}
    assert all(m["falls"] == 0 and m["goal_reached"] for m in runs.values())
    assert runs[1.0]["rms_tracking_error_m"] < 0.8 * runs[0.0]["rms_tracking_error_m"]
    assert runs[1.0]["max_wheel_speed_rad_s"] <= runs[0.0]["max_wheel_speed_rad_s"] * 1.05


def test_dead_planner_falls_back_to_hopping_in_place():
    runner = LockstepRunner(RunConfig(scenario="setpoint", estimator="truth", duration_s=8.0))
    ref = runner.planner.reference
    frozen = {"stamp": None}

    def update(now_ns, state):  # the planner publishes until 2 s, then dies
        if now_ns <= 2_000_000_000:
            ref.stamp_ns = now_ns
            frozen["stamp"] = now_ns
        else:
            ref.stamp_ns = frozen["stamp"]
        return ref

    runner.planner.update = update
    res = runner.run()
    ctrl = runner.controller.ctrl
    assert res.metrics["falls"] == 0
    assert ctrl.supervisor.counts.get("reference_stale") == 1
    assert ctrl.holding
    # it stopped near where it was when the planner died, far from the 2 m goal
    x_final = res.trace.com[-1][0]
    assert 0.0 < x_final < 1.0
    assert res.metrics["final_goal_error_m"] > 1.0

