"""``--perception depth`` in the lockstep runner: the planner's world comes from the
depth camera through onboard.perception, not from the scenario's ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from onboard.perception.geometry import polygon_from_points, polygons_overlap
from sim_twin.lockstep import LockstepRunner, RunConfig
from sim_twin.perception_plug import PerceivedGraphPlannerPlug, make_planner


def test_planner_world_comes_from_the_depth_camera():
    runner = LockstepRunner(RunConfig("forest", seed=1, duration_s=1.5, estimator="truth", perception="depth"))
    plug = runner.planner
    assert isinstance(plug, PerceivedGraphPlannerPlug)
    assert len(plug.planner.obstacles.offsets) <= 1  # knows nothing before the first view
    result = runner.run()
    assert result.metrics["planner"] == "graph+perception"
    assert plug.loop.view.map.views >= 5  # 5 Hz camera, 1.5 s
    assert plug.loop.sets >= 5
    assert plug.polygons > 0
    truth = [polygon_from_points(np.array(p.vertices)) for p in runner.scenario.polytopes().polytopes]
    perceived, _ = plug.loop.view.polytopes()
    # What the planner plans around sits on real trees.
    assert sum(any(polygons_overlap(p, t) for t in truth) for p in perceived) >= 0.7 * len(perceived)
    assert result.metrics["collisions"] == 0


def test_unknown_perception_or_planner_refused():
    runner_cfg = RunConfig("forest", seed=0)
    scenario = LockstepRunner(runner_cfg).scenario
    from robot_description import params as rd

    robot = rd.robot_params()
    with pytest.raises(ValueError, match="perception"):
        make_planner("auto", "lidar", scenario, robot)
    with pytest.raises(ValueError, match="graph planner"):
        make_planner("scenario", "depth", scenario, robot)


def test_a_camera_message_of_the_wrong_type_is_refused_by_name():
    from robot_description import params as rd

    scenario = LockstepRunner(RunConfig("forest", seed=0)).scenario
    plug = make_planner("graph", "depth", scenario, rd.robot_params())
    with pytest.raises(TypeError, match="depth: expected a DepthImage, got str"):
        plug.feed("depth", "not a frame")
    with pytest.raises(TypeError, match="color: expected a ColorImage"):
        plug.feed("color", b"\x00" * 16)
