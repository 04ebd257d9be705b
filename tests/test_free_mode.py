"""Free-space mode (issue 16, item 2): the robot plans only inside perceived convex free
cells, stands inside one, and heads for the frontier when the goal is beyond them."""

from __future__ import annotations

import math

import numpy as np
import pytest

from onboard.high_level.tracking import collision as col
from onboard.contracts.binary_messages import CELL_FREE, CELL_OCCUPIED, CELL_UNKNOWN, OccupancyGrid
from onboard.high_level.planning.graph_planner import GraphPlanner
from onboard.contracts.params import PerceptionParams, PlannerParams
from onboard.perception.decomposition import decompose_free_space
from onboard.perception.occupancy import OccupancyMap
from onboard.perception.segmentation import OCCUPIED, TRAVERSABLE
from onboard.high_level.planning.seen_space import SeenSpace
from sim_twin.lockstep import LockstepRunner, RunConfig

RES = 0.05
ORIGIN = (-2.0, -3.0)
SHAPE = (120, 160)  # rows along y (6 m), columns along x (8 m)
ROBOT_RADIUS = 0.13
FREE = PerceptionParams(mode="free")
NO_POINTS = (np.zeros((0, 3)), np.zeros(0, dtype=np.int8))


def xy_of(grid_shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    rows, cols = grid_shape
    return np.meshgrid(ORIGIN[0] + (np.arange(cols) + 0.5) * RES, ORIGIN[1] + (np.arange(rows) + 0.5) * RES)


def cell_of(grid, x: float, y: float) -> tuple[int, int]:
    return int((y - grid.origin[1]) / grid.resolution), int((x - grid.origin[0]) / grid.resolution)


def what_the_robot_knows_at_its_start(hopped: float = 0.0) -> OccupancyGrid:
    """Free: the ground around the robot at the origin (its stand disc) and a fan the camera
    saw ahead of it from 0.35 m on; the camera's blind sides beside the robot unknown; a
    post seen on its near face at (1.5, 0.6); everything else unknown. With ``hopped`` [m],
    the robot has since hopped that far along x, where it stands now freed too."""
    x, y = xy_of(SHAPE)
    cells = np.full(SHAPE, CELL_UNKNOWN, dtype=np.uint8)
    fan = (x > 0.35) & (np.abs(y) < 0.9 * (x - 0.1)) & (np.hypot(x, y) < 3.0)
    stood = (np.hypot(x, y) <= FREE.stand_radius_m) | (np.hypot(x - hopped, y) <= FREE.stand_radius_m)
    cells[fan | stood] = CELL_FREE
    cells[(np.abs(x - 1.5) < 0.06) & (np.abs(y - 0.6) < 0.2)] = CELL_OCCUPIED
    return OccupancyGrid(cells, RES, ORIGIN)


def free_planner(grid: OccupancyGrid, goal: tuple[float, float], start=(0.0, 0.0)) -> GraphPlanner:
    cells, _ = decompose_free_space(grid.cells == CELL_FREE, grid.resolution, grid.origin, FREE, start=start,
                                    must_cover=(start, goal))
    planner = GraphPlanner(PlannerParams(), ROBOT_RADIUS)
    planner.set_free_cells([c.vertices for c in cells])
    planner.set_seen(SeenSpace.from_grid(grid), required=False)
    planner.set_goal(goal)
    return planner


def test_the_frontier_is_where_seen_free_ground_meets_the_unknown_not_a_wall() -> None:
    x, y = xy_of(SHAPE)
    cells = np.full(SHAPE, CELL_UNKNOWN, dtype=np.uint8)
    cells[(x > -1.0) & (x < 1.0) & (np.abs(y) < 1.0)] = CELL_FREE
    cells[(x > 1.0) & (x < 1.1) & (np.abs(y) < 1.0)] = CELL_OCCUPIED  # a wall closes the east side
    front = SeenSpace.from_grid(OccupancyGrid(cells, RES, ORIGIN)).frontier()
    assert len(front) > 0
    # every frontier cell borders the unknown: the west, north and south edges of the free box
    assert np.all((front[:, 0] < -0.9) | (np.abs(front[:, 1]) > 0.9))
    assert not np.any((front[:, 0] > 0.9) & (np.abs(front[:, 1]) < 0.9))  # beside the wall: nothing new to see
    # free up to the grid's edge: beyond it nothing is known
    edge = SeenSpace(np.ones((4, 5), dtype=bool), RES, (0.0, 0.0), np.zeros((4, 5), dtype=bool)).frontier()
    assert len(edge) == 4 * 5 - 2 * 3

    # A 10 cm strip of unknown at the wall's foot (cells flickering between a noisy hit and a
    # miss) is no frontier for a robot 26 cm wide: nothing it could go to fits there
    cells[(x > 0.9) & (x < 1.0) & (np.abs(y) < 1.0)] = CELL_UNKNOWN
    strip = SeenSpace.from_grid(OccupancyGrid(cells, RES, ORIGIN))
    assert np.any((strip.frontier()[:, 0] > 0.8) & (np.abs(strip.frontier()[:, 1]) < 0.8))
    assert not np.any((strip.frontier(0.26)[:, 0] > 0.8) & (np.abs(strip.frontier(0.26)[:, 1]) < 0.8))
    # free ground seen behind the wall borders the unknown, but is no way on from the robot's side
    cells[(x > 1.1) & (x < 1.5) & (np.abs(y) < 0.3)] = CELL_FREE
    behind = SeenSpace.from_grid(OccupancyGrid(cells, RES, ORIGIN))
    assert np.any(behind.frontier(0.26)[:, 0] > 1.1)
    assert not np.any(behind.frontier(0.26, here=(0.0, 0.0))[:, 0] > 1.1)
    assert len(behind.frontier(0.26, here=(0.0, 0.0))) > 0
    assert len(behind.frontier(0.26, here=(3.0, 0.0))) == 0  # the robot on no free cell: no way on at all


def test_free_mode_grid_keeps_what_it_saw_and_frees_the_ground_in_sight_where_the_robot_stands() -> None:
    kept, faded = OccupancyMap(FREE), OccupancyMap(PerceptionParams(mode="obstacles"))
    ground = np.array([[1.5, 0.0, 0.0]])
    for m in (kept, faded):
        m.integrate(ground, np.array([TRAVERSABLE], dtype=np.int8), (0.0, 0.0), 0.0)
        m.integrate(*NO_POINTS, (0.0, 0.0), 10 * FREE.decay_half_life_s)
    assert kept.grid().cells[cell_of(kept.grid(), 1.5, 0.0)] == CELL_FREE  # the world of a run stands still
    assert faded.grid().cells[cell_of(faded.grid(), 1.5, 0.0)] == CELL_UNKNOWN  # obstacle mode forgets as before
    # seen occupied once: occupied at once, however free it was
    post = np.array([[1.5, 0.0, 0.3], [1.5, 0.01, 0.6]])
    kept.integrate(post, np.array([OCCUPIED, OCCUPIED], dtype=np.int8), (0.0, 0.0), 11 * FREE.decay_half_life_s)
    assert kept.grid().cells[cell_of(kept.grid(), 1.5, 0.0)] == CELL_OCCUPIED

    # Standing at (3, 1) next to a wall seen on its near face only (x = 3.3, its inside unknown):
    # the ground around the robot is free out to stand_radius_m, but not past the wall
    stand = OccupancyMap(FREE)
    wall = np.array([[3.3, y, z] for y in np.arange(0.6, 1.45, 0.025) for z in (0.3, 0.6)])
    stand.integrate(wall, np.full(len(wall), OCCUPIED, dtype=np.int8), (2.0, 1.0), 0.0)
    stand.integrate(*NO_POINTS, (2.0, 1.0), 0.1, footprint_xy=(3.0, 1.0))
    g = stand.grid()
    assert g.cells[cell_of(g, 3.0 - 0.45, 1.0)] == CELL_FREE  # behind the robot, never seen
    assert g.cells[cell_of(g, 3.0, 1.0 + 0.45)] == CELL_FREE  # beside it
    assert g.cells[cell_of(g, 3.0, 1.0 + 0.6)] == CELL_UNKNOWN  # beyond stand_radius_m
    assert g.cells[cell_of(g, 3.3, 1.0)] == CELL_OCCUPIED  # what was seen occupied stays so
    assert g.cells[cell_of(g, 3.4, 1.0)] == CELL_UNKNOWN  # the wall's inside: behind its seen face


def test_from_the_robots_own_region_the_planner_heads_for_the_frontier_when_the_goal_is_unseen() -> None:
    # At the start the cells around the robot and those the camera saw ahead overlap too thinly
    # for the regular graph: the first plan leaves the start toward the frontier as far as they let it
    first = free_planner(what_the_robot_knows_at_its_start(), goal=(5.0, 0.0))
    assert first.start_margin(np.zeros(2)) == pytest.approx(first.margin)  # the robot stands deep in a cell of its own
    assert first.plan(np.zeros(2), np.zeros(2), 0) is not None
    assert first.frontier_goal is not None and first.frontier_goal[0] > 0.1
    # a hop on, where it stood is free too, and the plan reaches the frontier
    hop = 0.15
    grid = what_the_robot_knows_at_its_start(hopped=hop)
    planner = free_planner(grid, goal=(5.0, 0.0), start=(hop, 0.0))
    start = np.array([hop, 0.0])
    assert planner.start_margin(start) == pytest.approx(planner.margin)
    ref = planner.plan(start, np.zeros(2), 0)
    assert ref is not None and not ref.hold
    assert planner.stats.frontier_plans == 1 and planner.frontier_goal is not None
    end = planner.path.states[-1]
    assert np.allclose(end[2:], 0.0, atol=planner.params.goal_speed_tol)  # it stops there, at rest
    assert np.array_equal(end[:2], planner.frontier_goal)
    assert math.dist(end[:2], (5.0, 0.0)) < 5.0 - 1.0  # well on the way to the goal
    seen = SeenSpace.from_grid(grid)  # near a frontier over free ground (4-connected cells: sqrt(2) allowed)
    reach = math.sqrt(2.0) * (planner.margin + planner.params.frontier_reach)
    assert seen.distance_through_free(seen.frontier(2 * ROBOT_RADIUS, start), end[None, :2])[0] <= reach
    # every segment inside one free cell, the margin deep; the camera turned along the path
    assert np.all(col.free_cell_of(col.hull_set(planner.path.control_points), planner.cells, planner.margin) >= 0)
    assert ref.yaw is not None and math.cos(ref.yaw) > 0


def test_with_the_goal_in_the_known_free_cells_the_path_ends_at_the_goal() -> None:
    planner = free_planner(what_the_robot_knows_at_its_start(hopped=0.15), goal=(2.2, -0.3), start=(0.15, 0.0))
    assert planner.plan(np.array([0.15, 0.0]), np.zeros(2), 0) is not None
    assert planner.frontier_goal is None and planner.stats.frontier_plans == 0
    assert np.allclose(planner.path.states[-1], [2.2, -0.3, 0.0, 0.0])


def test_no_free_cell_no_path_and_no_frontier_without_a_seen_space() -> None:
    planner = GraphPlanner(PlannerParams(), ROBOT_RADIUS)
    planner.set_free_cells([])  # before the first view nothing is known free
    planner.set_goal((3.0, 0.0))
    assert planner.plan(np.zeros(2), np.zeros(2), 0) is None


def test_free_mode_lockstep_forest_heads_into_the_unseen_toward_the_goal() -> None:
    runner = LockstepRunner(RunConfig("forest", seed=0, duration_s=8.0, estimator="truth", perception="depth",
                                      perception_params=FREE))
    plug = runner.planner
    goal_distance = math.dist(runner.scenario.start, runner.scenario.target())
    metrics = runner.run().metrics
    assert metrics["collisions"] == 0 and metrics["falls"] == 0
    assert plug.planner.stats.frontier_plans > 0  # the goal, 6 m off, lies beyond what was seen
    assert metrics["final_goal_error_m"] < goal_distance - 0.8  # it moved toward it (before: 0 of 10 runs moved)


def test_the_frontier_headed_for_keeps_an_advantage_as_the_views_shift_the_costs() -> None:
    """A corridor with walls along its sides, unknown beyond both ends, the goal unseen to the
    north and a little east: from the middle the east end is the better frontier; 0.4 m west
    of the middle the west end is, by less than frontier_hysteresis."""
    x, y = xy_of(SHAPE)
    cells = np.full(SHAPE, CELL_UNKNOWN, dtype=np.uint8)
    cells[(np.abs(x) < 1.8) & (np.abs(y) < 0.5)] = CELL_FREE
    cells[(np.abs(x) < 1.8) & (np.abs(y) >= 0.5) & (np.abs(y) < 0.6)] = CELL_OCCUPIED
    grid = OccupancyGrid(cells, RES, ORIGIN)
    goal, west_of_middle = (0.6, 2.5), (-0.4, 0.0)

    fresh = free_planner(grid, goal, start=west_of_middle)
    assert fresh.plan(np.array(west_of_middle), np.zeros(2), 0) is not None
    assert fresh.frontier_goal[0] < -1.0  # on its own, the west end

    heading_east = free_planner(grid, goal, start=(0.0, 0.0))
    assert heading_east.plan(np.zeros(2), np.zeros(2), 0) is not None
    assert heading_east.frontier_goal[0] > 1.0
    assert heading_east.plan(np.array(west_of_middle), np.zeros(2), 0) is not None
    assert heading_east.frontier_goal[0] > 1.0  # still east: no turning back and forth
    heading_east.set_goal((-0.6, 2.5))  # a new goal: its frontier is chosen afresh
    assert heading_east.plan(np.array(west_of_middle), np.zeros(2), 0) is not None
    assert heading_east.frontier_goal[0] < -1.0
