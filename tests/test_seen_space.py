"""Unknown is not free: the robot is committed only over ground the camera saw free, and the
planner turns the camera to where it is going (issue 16, item 1)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from onboard.contracts.binary_messages import CELL_FREE, CELL_OCCUPIED, CELL_UNKNOWN, OccupancyGrid
from onboard.high_level.planning.graph_planner import GraphPlanner
from onboard.contracts.reference import sample_reference
from onboard.low_level.controller import turn_toward
from onboard.contracts.params import PlannerParams
from onboard.high_level.planning.seen_space import SeenSpace
from sim_twin import scenarios as sc
from sim_twin.lockstep import LockstepRunner, RunConfig

RES = 0.05
ORIGIN = (-2.0, -2.0)  # a 4 m x 4 m grid centred on the origin
ROBOT_RADIUS = 0.13


def grid_with(fill: int, unknown_box: tuple[float, float, float, float] | None = None, value: int = CELL_UNKNOWN) -> OccupancyGrid:
    cells = np.full((80, 80), fill, dtype=np.uint8)
    if unknown_box is not None:
        x0, x1, y0, y1 = unknown_box
        c0, c1 = int((x0 - ORIGIN[0]) / RES), int((x1 - ORIGIN[0]) / RES)
        r0, r1 = int((y0 - ORIGIN[1]) / RES), int((y1 - ORIGIN[1]) / RES)
        cells[r0:r1, c0:c1] = value
    return OccupancyGrid(stamp_ns=0, seq=0, resolution=RES, origin=ORIGIN, cells=cells)


def test_a_disc_is_seen_only_when_every_cell_under_it_was_seen_free() -> None:
    line = np.array([[0.0, 0.0], [0.3, 0.0], [0.6, 0.0], [0.9, 0.0]])
    here = (0.0, 0.0)
    assert SeenSpace.from_grid(grid_with(CELL_FREE)).first_unseen(line, ROBOT_RADIUS, here, 0.2) is None
    # a strip of unknown across the line at x = 0.35..0.7: the disc of the second sample
    # (x = 0.3, reaching 0.43) is the first to cover it
    strip = SeenSpace.from_grid(grid_with(CELL_FREE, (0.35, 0.7, -1.0, 1.0)))
    assert strip.first_unseen(line, ROBOT_RADIUS, here, 0.2) == 1
    assert SeenSpace.from_grid(grid_with(CELL_FREE, (0.5, 0.7, -1.0, 1.0))).first_unseen(line, ROBOT_RADIUS, here, 0.2) == 2
    assert strip.first_unseen(line[:1], ROBOT_RADIUS, here, 0.2) is None
    # occupied is not free either; and beyond the grid nothing was seen
    wall = SeenSpace.from_grid(grid_with(CELL_FREE, (0.35, 0.7, -1.0, 1.0), CELL_OCCUPIED))
    assert wall.first_unseen(line, ROBOT_RADIUS, here, 0.2) == 1
    assert SeenSpace.from_grid(grid_with(CELL_FREE)).first_unseen([[1.95, 0.0]], ROBOT_RADIUS, here, 0.2) == 0
    # the robot's own region counts as seen: it hops there (the camera's blind zone beside it)
    blind_beside = SeenSpace.from_grid(grid_with(CELL_FREE, (-0.2, 0.2, -0.2, 0.2)))
    assert blind_beside.first_unseen(line[:1], ROBOT_RADIUS, here, 0.25) is None
    assert blind_beside.first_unseen(line[:1], ROBOT_RADIUS, here, 0.0) == 0
    with pytest.raises(ValueError):
        blind_beside.first_unseen([[math.nan, 0.0]], ROBOT_RADIUS, here, 0.2)


def planner_going_east() -> GraphPlanner:
    planner = GraphPlanner(PlannerParams(nodes=600), ROBOT_RADIUS)  # the rest lattice: a path that heads east
    planner.set_obstacles([])
    planner.set_goal((1.5, 0.0))
    return planner


def test_a_perceived_world_commits_the_robot_only_over_seen_ground_and_points_the_camera() -> None:
    start, rest = np.zeros(2), np.zeros(2)
    known = planner_going_east()  # a world given whole: references pass unchanged
    ref = known.plan(start, rest, 0)
    assert ref is not None and not ref.hold and ref.yaw is None and known.stats.unseen_holds == 0

    perceived = planner_going_east()
    perceived.set_seen(None)  # before the first view: committed nowhere
    held = perceived.plan(start, rest, 0)
    assert held is not None and held.hold and perceived.stats.unseen_holds == 1
    # turned toward where the path will be heading_lookahead_s on, or a multiple of it where that is
    # nearer than heading_min_m (a path from rest starts slowly): eastward, the way to the goal
    prm, t = perceived.params, perceived.params.heading_lookahead_s
    while math.hypot(*sample_reference(perceived.path_reference(0), t)[:2]) < prm.heading_min_m:
        t += prm.heading_lookahead_s
    ahead = sample_reference(perceived.path_reference(0), t)
    assert held.yaw == pytest.approx(math.atan2(ahead[1], ahead[0])) and math.cos(held.yaw) > 0

    perceived.set_seen(SeenSpace.from_grid(grid_with(CELL_FREE)))
    going = perceived.refine(start, rest, 0)
    assert going is not None and not going.hold and math.cos(going.yaw) > 0

    # unknown ground within the first commit_s of the path: hold; beyond it: go (optimistic)
    near = SeenSpace.from_grid(grid_with(CELL_FREE, (0.2, 0.4, -1.0, 1.0)))
    perceived.set_seen(near)
    assert perceived.refine(start, rest, 0).hold
    far = SeenSpace.from_grid(grid_with(CELL_FREE, (1.2, 1.4, -1.0, 1.0)))
    perceived.set_seen(far)
    assert not perceived.refine(start, rest, 0).hold

    perceived.set_seen(None, required=False)  # back to a world given whole
    assert not perceived.refine(start, rest, 0).hold


def test_the_heading_turns_the_short_way_at_a_bounded_rate() -> None:
    assert turn_toward(0.0, 1.0, 0.1) == pytest.approx(0.1)
    assert turn_toward(0.0, 0.05, 0.1) == pytest.approx(0.05)
    assert turn_toward(3.0, -3.0, 0.1) == pytest.approx(3.1)  # across +-pi, not the long way back
    assert turn_toward(-3.0, 3.0, 0.1) == pytest.approx(-3.1)


def test_the_robot_looks_before_it_steps_sideways_and_goes_round_a_post_it_could_not_see() -> None:
    runner = LockstepRunner(RunConfig(sc.BlindSide.name, seed=0, perception="depth", estimator="truth", planner="graph"))
    result = runner.run()
    m = result.metrics
    assert m["collisions"] == 0 and m["falls"] == 0
    assert m["goal_reached"]
    assert m["planner_unseen_holds"] > 0  # it did wait for the camera
