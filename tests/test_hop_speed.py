"""The speed a robot sustains hopping (``RobotParams.hop_speed_max``) bounds what it is asked to do:
the scenarios' references and the planner's speed bound (issue 16: the outdoor robot fell on
every scenario at the indoor robot's speed; its wheels gathered momentum hop by hop)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from onboard.contracts.params import PlannerParams
from robot_description import params as rd
from sim_twin import scenarios as sc
from sim_twin.lockstep import LockstepRunner, RunConfig


def _peak_speed(scenario: sc.Scenario) -> float:
    t_end = scenario.segments[-1].t0 + scenario.segments[-1].duration
    t = np.linspace(0.0, t_end, 2001)
    xy = np.array([sc.sample_reference(scenario.segments, float(ti)) for ti in t])
    return float(np.max(np.hypot(*np.diff(xy, axis=0).T) / np.diff(t)))


def test_the_heavier_robot_is_asked_to_go_slower_than_it_can_hop() -> None:
    indoor, outdoor = rd.robot_params("indoor"), rd.robot_params("outdoor")
    assert outdoor.hop_speed_max < indoor.hop_speed_max
    assert rd.robot_params("sim15nm").hop_speed_max == indoor.hop_speed_max
    # the indoor robot's references and planner are as they were; the outdoor one's are capped
    assert sc.cruise_speed_for(indoor) == sc.REF_SPEED
    assert rd.planner_params_for(PlannerParams(), indoor) == PlannerParams()
    assert rd.planner_params_for(PlannerParams(), outdoor).v_max == outdoor.hop_speed_max
    slow = dataclasses.replace(PlannerParams(), v_max=0.1)
    assert rd.planner_params_for(slow, outdoor) is slow  # a slower bound of the user's stays
    for robot in (indoor, outdoor):
        setpoint = sc.make("setpoint", seed=3, cruise_speed=sc.cruise_speed_for(robot))
        assert _peak_speed(setpoint) <= robot.hop_speed_max * (1 + 1e-3)
    # the run is given the time its way takes
    assert sc.make("forest", cruise_speed=sc.cruise_speed_for(outdoor)).default_duration_s > sc.make("forest").default_duration_s
    with pytest.raises(ValueError, match="cruise speed"):
        sc.make("setpoint", cruise_speed=0.0)


def test_the_outdoor_robot_reaches_a_setpoint_at_its_speed_and_saturates_a_wheel_at_the_indoor_speed(monkeypatch) -> None:
    run = LockstepRunner(RunConfig("setpoint", seed=1, variant="outdoor", estimator="kalman")).run()
    m = run.metrics
    assert m["falls"] == 0 and m["goal_reached"]
    assert m["max_wheel_speed_rad_s"] < 300.0
    # the same robot on the indoor robot's reference: a wheel gathers momentum hop by hop
    monkeypatch.setattr(sc, "cruise_speed_for", lambda robot: sc.REF_SPEED)
    faster = LockstepRunner(RunConfig("setpoint", seed=1, variant="outdoor", estimator="kalman", duration_s=5.0)).run().metrics
    assert faster["max_wheel_speed_rad_s"] > 1.5 * m["max_wheel_speed_rad_s"]
