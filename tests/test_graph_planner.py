"""Bezier graph planner: build, cache arrays, cut, search and refine on scenes with known answers."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from onboard.geometry import bezier as bz
from onboard.high_level.tracking import collision as col
from onboard.geometry import polygons as pg
from onboard.high_level.planning import bezier_graph as bg
from onboard.high_level.planning import graph_planner as gp
from onboard.high_level.planning.planner_world import START_SLACK
from onboard.high_level.tracking import reachability as reach
from onboard.contracts.params import PlannerParams

PARAMS = PlannerParams(nodes=1500)
ROBOT_RADIUS = 0.13
BOUNDS = (0.0, 0.0, 6.0, 6.0)


def _box(cx: float, cy: float, hx: float, hy: float) -> np.ndarray:
    return np.array([[cx - hx, cy - hy], [cx + hx, cy - hy], [cx + hx, cy + hy], [cx - hx, cy + hy]])


@pytest.fixture(scope="module")
def graph() -> bg.BezierGraph:
    return bg.build_graph(bg.spec_from_params(PARAMS, BOUNDS))


def _planner(graph: bg.BezierGraph, **kw) -> gp.GraphPlanner:
    planner = gp.GraphPlanner(dataclasses.replace(PARAMS, **kw), ROBOT_RADIUS, bounds=BOUNDS)
    planner.set_graph(graph)
    return planner


def _state_at(planner: gp.GraphPlanner, t: float) -> np.ndarray:
    """``[px, py, vx, vy]`` of the planner's current path ``t`` [s] after its start."""
    return bg.path_states(planner.path.control_points, planner.path.tau, np.array([t]))[0]


def _dense(ctrl: np.ndarray, samples: int = 100) -> np.ndarray:
    return bz.evaluate(ctrl, 1.0, np.linspace(0.0, 1.0, samples))


# --- build ------------------------------------------------------------------------------


def test_edges_are_exactly_the_pairs_the_test_accepts():
    spec = bg.spec_from_params(PARAMS, (0.0, 0.0, 2.0, 2.0), nodes=250)
    g = bg.build_graph(spec)
    test = spec.reachability()
    i, j = np.meshgrid(np.arange(g.n_nodes), np.arange(g.n_nodes), indexing="ij")
    off = i != j
    ok = test.test(g.nodes[i[off]], g.nodes[j[off]])
    brute = set(zip(i[off][ok].tolist(), j[off][ok].tolist()))
    assert set(zip(g.src.tolist(), g.dst.tolist())) == brute  # the k-d tree pruning drops nothing
    assert len(brute) > 100


def test_edges_are_dynamically_feasible_and_costed_by_property_2_49(graph):
    test = graph.reachability
    rng = np.random.default_rng(0)
    pick = rng.choice(graph.n_edges, 400, replace=False)
    ctrl = graph.control_points[pick]
    assert np.all(test.violation(ctrl) <= 1e-9)  # speed and acceleration bounds, densely sampled
    # Endpoints are the nodes (position and velocity).
    states = np.stack([bg.path_states(c[None], graph.spec.tau, np.array([0.0, graph.spec.tau])) for c in ctrl])
    assert np.allclose(states[:, 0], graph.nodes[graph.src[pick]])
    assert np.allclose(states[:, 1, :2], graph.nodes[graph.dst[pick], :2])
    # The cost bounds the arc length from above and the chord from below.
    pts = np.stack([_dense(c, 400) for c in ctrl])
    arc = np.linalg.norm(np.diff(pts, axis=1), axis=2).sum(axis=1)
    assert np.all(graph.cost[pick] >= arc - 1e-9)
    assert np.all(graph.cost[pick] >= np.linalg.norm(ctrl[:, -1] - ctrl[:, 0], axis=1) - 1e-12)
    assert np.all(np.diff(graph.src) >= 0) and graph.indptr[-1] == graph.n_edges


def test_graph_arrays_round_trip_and_key_covers_every_field(graph):
    arrays = graph.to_arrays()
    again = bg.BezierGraph.from_arrays(graph.spec, arrays)
    assert np.array_equal(again.src, graph.src) and np.array_equal(again.control_points, graph.control_points)
    keys = {graph.spec.key()}
    for change in ({"nodes": 1499}, {"v_max": 0.6}, {"a_max": 1.1}, {"tau": 1.4}, {"seed": 1},
                   {"sampling": "grid"}, {"grid_velocities": 5}, {"bounds": (0.0, 0.0, 6.0, 6.5)}, {"rest_grid": 0.5}):
        keys.add(dataclasses.replace(graph.spec, **change).key())
    assert len(keys) == 10
    other = dataclasses.replace(graph.spec, seed=5)
    with pytest.raises(gp.PlanningError, match="another spec"):
        bg.BezierGraph.from_arrays(other, arrays)
    broken = dict(arrays, src=arrays["src"][::-1])
    with pytest.raises(gp.PlanningError, match="inconsistent"):
        bg.BezierGraph.from_arrays(graph.spec, broken)


def test_grid_sampling_has_the_requested_node_count_and_resting_nodes():
    spec = bg.spec_from_params(dataclasses.replace(PARAMS, sampling="grid", rest_grid=0.0), (0.0, 0.0, 3.0, 2.0), nodes=700)
    nodes = bg.sample_nodes(spec)
    assert nodes.shape == (700, 4)
    assert np.any(np.all(nodes[:, 2:] == 0.0, axis=1))
    assert np.all(bg.within_speed_bound(nodes[:, 2:], spec.v_max))
    diagonal = nodes[np.abs(np.abs(nodes[:, 2]) - np.abs(nodes[:, 3])) < 1e-12]
    assert np.max(np.hypot(diagonal[:, 2], diagonal[:, 3])) == pytest.approx(spec.v_max)  # the box's corners pulled in


def test_the_planned_speed_is_bounded_in_every_direction_not_per_axis():
    spec = bg.spec_from_params(dataclasses.replace(PARAMS, rest_grid=0.0), (0.0, 0.0, 3.0, 2.0), nodes=4000)
    speeds = np.hypot(*bg.sample_nodes(spec)[:, 2:].T)
    corner = spec.v_max / math.cos(math.pi / 8)  # the octagon's vertices
    assert np.max(speeds) <= corner * (1 + 1e-12) and np.max(speeds) > 0.95 * corner  # the octagon filled
    assert np.allclose(bg.limit_speed(np.array([1.0, 1.0]), spec.v_max), [spec.v_max * math.sqrt(0.5)] * 2)
    assert np.array_equal(bg.limit_speed(np.array([0.1, -0.05]), spec.v_max), [0.1, -0.05])
    # every edge's velocity control points stay in the octagon, diagonal included
    test = spec.reachability()
    model, inf, v = test.model, math.inf, spec.v_max
    box = reach.BezierReachability(model, reach.box_limits(model, spec.a_max, [-inf, -inf, -v, -v], [inf, inf, v, v]), spec.tau)
    x0 = np.array([0.0, 0.0, 0.0, 0.0])
    fast_diagonal = np.array([0.4, 0.4, 0.3, 0.3])  # ends at 0.42 m/s > v_max
    assert box.test(x0, fast_diagonal) and not test.test(x0, fast_diagonal)
    assert test.test(x0, np.array([0.3, 0.3, 0.2, 0.2]))


def test_rest_lattice_joins_neighbours_by_straight_segments():
    spec = bg.spec_from_params(dataclasses.replace(PARAMS, rest_grid=0.25), (0.0, 0.0, 2.0, 1.0), nodes=100)
    g = bg.build_graph(spec)
    assert g.n_nodes == 100 + 9 * 5 == spec.total_nodes
    lattice = np.arange(100, g.n_nodes)
    assert np.all(g.nodes[lattice, 2:] == 0.0)
    # Each lattice node reaches its lattice neighbours 0.25 m away; those segments are straight.
    sel = np.isin(g.src, lattice) & np.isin(g.dst, lattice)
    steps = g.nodes[g.dst[sel], :2] - g.nodes[g.src[sel], :2]
    assert np.any(np.all(np.isclose(steps, [0.25, 0.0]), axis=1)) and np.any(np.all(np.isclose(steps, [0.0, -0.25]), axis=1))
    ctrl = g.control_points[sel]
    d = ctrl[:, -1] - ctrl[:, 0]
    cross = d[:, None, 0] * (ctrl[..., 1] - ctrl[:, :1, 1]) - d[:, None, 1] * (ctrl[..., 0] - ctrl[:, :1, 0])
    assert np.allclose(cross, 0.0, atol=1e-12)


def test_bad_specs_are_rejected():
    with pytest.raises(gp.PlanningError):
        bg.GraphSpec((0.0, 0.0, -1.0, 1.0), 100, 0.5, 1.0, 1.5)
    with pytest.raises(gp.PlanningError):
        bg.GraphSpec((0.0, 0.0, 1.0, float("nan")), 100, 0.5, 1.0, 1.5)
    with pytest.raises(gp.PlanningError):
        bg.GraphSpec((0.0, 0.0, 1.0, 1.0), 100, 0.5, 1.0, 1.5, sampling="random")


# --- search -----------------------------------------------------------------------------


def test_astar_matches_dijkstra(graph):
    rng = np.random.default_rng(1)
    free = rng.random(graph.n_edges) > 0.3
    W = csr_matrix((graph.cost[free], (graph.src[free], graph.dst[free])), shape=(graph.n_nodes,) * 2)
    for _ in range(5):
        a, b = rng.choice(graph.n_nodes, 2, replace=False)
        best = dijkstra(W, indices=a)[b]
        goal_costs = np.full(graph.n_nodes, np.inf)
        goal_costs[b] = 0.0
        res = bg.search(graph, free, graph.nodes[a], np.array([a]), np.array([0.0]), graph.nodes[b], goal_costs,
                        0.0, {}, {})
        if math.isinf(best):
            assert res is None
            continue
        assert res is not None and res.cost == pytest.approx(best)
        assert res.nodes[0] == a and res.nodes[-1] == b
        # Consecutive segments join in position and velocity.
        assert np.allclose(res.states[1:-1], bg.path_states(res.control_points, res.tau, res.tau * np.arange(1, len(res.states) - 1)))


# --- plan: hand-made scenes ---------------------------------------------------------------


def _assert_clear(planner: gp.GraphPlanner, polys: list[np.ndarray], ctrl: np.ndarray) -> None:
    samples = np.stack([_dense(c, 200) for c in ctrl])
    clearance = col.samples_clearance(samples, pg.pack_polygons(polys), reach=1.0)
    assert np.all(clearance > planner.margin), f"clearance {clearance.min()} <= margin {planner.margin}"


def test_open_field_path_is_nearly_straight(graph):
    planner = _planner(graph)
    planner.set_obstacles([])
    planner.set_goal((5.0, 5.0), 0.1)
    ref = planner.plan((1.0, 1.0), (0.0, 0.0), stamp_ns=123)
    assert ref is not None and not ref.hold and ref.t_ref_ns == 123
    path = planner.path
    assert np.allclose(path.states[0], [1.0, 1.0, 0.0, 0.0]) and np.allclose(path.states[-1], [5.0, 5.0, 0.0, 0.0])
    length = float(bz.path_length_bound(path.control_points).sum())
    assert length < 1.35 * math.dist((1, 1), (5, 5))
    assert path.cost == pytest.approx(length + PARAMS.time_weight * path.duration)
    assert [s.t0 for s in ref.segments] == pytest.approx([k * PARAMS.segment_s for k in range(len(ref.segments))])


def test_wall_with_one_gap_is_passed_through_the_gap(graph):
    # A wall across the region at x = 3 with a 1.2 m gap centred at y = 4.5.
    polys = [_box(3.0, 1.95, 0.1, 1.95), _box(3.0, 5.55, 0.1, 0.45)]
    planner = _planner(graph)
    planner.set_obstacles(polys)
    planner.set_goal((5.0, 1.0), 0.1)
    assert planner.plan((1.0, 1.0), (0.0, 0.0)) is not None
    ctrl = planner.path.control_points
    _assert_clear(planner, polys, ctrl)
    pts = np.concatenate([_dense(c) for c in ctrl])
    crossing = pts[np.argmin(np.abs(pts[:, 0] - 3.0))]
    assert 3.9 + planner.margin - 0.05 <= crossing[1] <= 5.1 - planner.margin + 0.05


def test_closed_wall_has_no_path_and_a_hold_reference(graph):
    planner = _planner(graph)
    planner.set_obstacles([_box(3.0, 3.0, 0.1, 3.2)])
    planner.set_goal((5.0, 1.0), 0.1)
    assert planner.plan((1.0, 1.0), (0.0, 0.0)) is None
    assert planner.stats.no_path == 1
    hold = planner.hold_reference((1.0, 1.0), stamp_ns=7)
    assert hold.hold and hold.segments[0].control_points[0] == [1.0, 1.0]


def test_goal_inside_obstacle_has_no_path(graph):
    planner = _planner(graph)
    planner.set_obstacles([_box(5.0, 5.0, 0.5, 0.5)])
    planner.set_goal((5.0, 5.0), 0.1)
    assert planner.plan((1.0, 1.0), (0.0, 0.0)) is None


def test_random_scenes_plans_keep_clear_under_dense_sampling(graph):
    rng = np.random.default_rng(5)
    found = 0
    for _ in range(6):
        polys = []
        for _ in range(25):
            c = rng.uniform(1.5, 4.5, 2)
            th = rng.uniform(0, math.pi)
            R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
            polys.append(c + _box(0.0, 0.0, *rng.uniform(0.05, 0.3, 2)) @ R.T)
        planner = _planner(graph)
        planner.set_obstacles(polys)
        planner.set_goal((5.5, 5.5), 0.1)
        if planner.plan((0.5, 0.5), (0.1, 0.0)) is None:
            continue
        found += 1
        _assert_clear(planner, polys, planner.path.control_points)
        # Every segment is dynamically feasible, the joins included.
        assert np.all(graph.reachability.violation(planner.path.control_points) <= 1e-9)
    assert found >= 4


def test_tube_growth_recuts_with_a_larger_margin(graph):
    planner = _planner(graph)
    planner.set_obstacles([_box(3.0, 3.0, 0.5, 0.5)])
    planner.set_goal((5.0, 5.0), 0.1)
    planner.plan((1.0, 1.0), (0.0, 0.0))
    before, version = planner.stats.edges_free, planner.world_version
    planner.set_tube(0.3)
    assert planner.world_version == version + 1 and planner.needs_replan((1.0, 1.0), 0, 1.0)
    planner.plan((1.0, 1.0), (0.0, 0.0))
    assert planner.stats.edges_free < before and planner.margin == pytest.approx(ROBOT_RADIUS + 0.3)
    with pytest.raises(gp.PlanningError):
        planner.set_tube(float("nan"))


def test_free_cells_mode_keeps_every_segment_in_one_cell(graph):
    # An L of two overlapping free rectangles; everything else is occupied.
    cells = [_box(3.0, 1.2, 2.8, 1.0), _box(4.8, 3.0, 1.0, 2.8)]
    planner = _planner(graph)
    planner.set_free_cells(cells)
    planner.set_goal((4.8, 5.0), 0.1)
    assert planner.plan((0.8, 1.2), (0.0, 0.0)) is not None
    packed = pg.pack_polygons(cells)
    inside = col.free_cell_of(col.hull_set(planner.path.control_points), packed, planner.margin)
    assert np.all(inside >= 0)
    wps = planner.waypoints()
    assert len(wps.sets) == len(wps.points) and all(len(s.vertices) == 4 for s in wps.sets)


def test_bad_inputs_are_rejected(graph):
    planner = _planner(graph)
    with pytest.raises(gp.PlanningError, match="not convex"):
        planner.set_obstacles([[[0, 0], [2, 0], [1, 0.2], [2, 2], [0, 2]]])
    with pytest.raises(gp.PlanningError):
        planner.set_goal((float("nan"), 1.0))
    with pytest.raises(gp.PlanningError, match="no goal"):
        planner.plan((1.0, 1.0), (0.0, 0.0))
    planner.set_goal((5.0, 5.0))
    with pytest.raises(gp.PlanningError):
        planner.plan((1.0, float("inf")), (0.0, 0.0))


def test_waypoint_sets_contain_their_segments_and_keep_the_margin(graph):
    polys = [_box(3.0, 3.0, 0.6, 0.6), _box(1.8, 4.2, 0.3, 0.3)]
    planner = _planner(graph)
    planner.set_obstacles(polys)
    planner.set_goal((5.0, 5.0), 0.1)
    assert planner.plan((1.0, 1.0), (0.0, 0.0)) is not None
    wps = planner.waypoints(stamp_ns=5)
    assert len(wps.points) == len(planner.path.states) == len(wps.sets)
    for ctrl, s in zip(planner.path.control_points, wps.sets):
        A, b = np.array(s.A), np.array(s.b)
        assert np.all(ctrl @ A.T <= b + 1e-9)  # the segment lies in its set
        # Every point of the set keeps the margin from every obstacle.
        verts = np.array(s.vertices)
        cand = np.random.default_rng(0).uniform(verts.min(axis=0), verts.max(axis=0), (4000, 2))
        inside = cand[np.all(cand @ A.T <= b, axis=1)]
        clearance = col.samples_clearance(inside[:, None, :], pg.pack_polygons(polys), reach=5.0)
        assert clearance.min() >= planner.margin - 1e-8


def test_moving_obstacle_triggers_a_replan_around_it(graph):
    planner = _planner(graph)
    planner.set_obstacles([_box(3.0, 5.0, 0.3, 0.3)])
    planner.set_goal((5.0, 3.0), 0.1)
    assert planner.plan((1.0, 3.0), (0.0, 0.0), stamp_ns=0) is not None
    assert not planner.needs_replan((1.0, 3.0), 0, 0.3)
    # The obstacle moves onto the path: the world changed, the old path now collides.
    mid = _dense(planner.path.control_points[len(planner.path.control_points) // 2], 3)[1]
    moved = [_box(mid[0], mid[1], 0.3, 0.3)]
    planner.set_obstacles(moved)
    assert planner.needs_replan((1.0, 3.0), 0, 0.3)
    old = planner.path.control_points
    samples = np.stack([_dense(c, 100) for c in old])
    assert col.samples_clearance(samples, pg.pack_polygons(moved), reach=1.0).min() <= planner.margin
    assert planner.plan((1.0, 3.0), (0.0, 0.0), stamp_ns=100_000_000) is not None
    _assert_clear(planner, moved, planner.path.control_points)
    assert not planner.needs_replan((1.0, 3.0), 100_000_000, 0.3)


def test_a_perceived_world_that_changes_keeps_a_path_still_clear(graph):
    # perception refits its obstacles from every view: a world that moved beside the path keeps it
    # (replanned at every view, a hopper's reference restarted from rest and it crept)
    planner = _planner(graph)
    planner.set_obstacles([_box(3.0, 5.2, 0.3, 0.3)])
    planner.set_goal((5.0, 3.0), 0.1)
    assert planner.plan((1.0, 3.0), (0.0, 0.0), stamp_ns=0) is not None
    planner.set_obstacles([_box(3.02, 5.21, 0.31, 0.3)])
    assert not planner.needs_replan((1.0, 3.0), 0, 0.3)
    mid = _dense(planner.path.control_points[len(planner.path.control_points) // 2], 3)[1]
    planner.set_obstacles([_box(3.02, 5.21, 0.31, 0.3), _box(mid[0], mid[1], 0.2, 0.2)])
    assert planner.needs_replan((1.0, 3.0), 0, 0.3)


def test_free_cells_that_change_replan(graph):
    planner = _planner(graph)
    planner.set_free_cells([_box(3.0, 3.0, 2.8, 1.0)])
    planner.set_goal((5.0, 3.0), 0.1)
    assert planner.plan((1.0, 3.0), (0.0, 0.0), stamp_ns=0) is not None
    planner.set_free_cells([_box(3.0, 3.0, 2.8, 1.1)])  # still holds the path, but the cells are new
    assert planner.needs_replan((1.0, 3.0), 0, 0.3)
    # and the replan starts where the robot is (its cells are fitted around it), not on the old path
    stamp = 1_500_000_000
    on_path = _state_at(planner, stamp * 1e-9)
    near = on_path[:2] + (0.0, 0.5 * planner.tube)
    assert planner.plan(near, (0.0, 0.0), stamp_ns=stamp) is not None
    start = _state_at(planner, 0.0)
    assert np.allclose(start, [near[0], near[1], 0.0, 0.0])


def test_a_replan_starts_where_the_path_is_while_the_robot_keeps_to_its_tube(graph):
    planner = _planner(graph)
    planner.set_goal((5.0, 3.0), 0.1)
    assert planner.plan((1.0, 3.0), (0.0, 0.0), stamp_ns=0) is not None
    stamp = 1_500_000_000
    on_path = _state_at(planner, stamp * 1e-9)
    assert math.hypot(*on_path[2:]) > 0.05  # under way: the stitch keeps its speed
    near = on_path[:2] + (0.0, 0.8 * planner.tube)
    assert planner.plan(near, (0.0, 0.0), stamp_ns=stamp) is not None
    first = planner.path.control_points[0]
    start = _state_at(planner, 0.0)
    assert np.allclose(first[0], on_path[:2]) and np.allclose(start[2:], on_path[2:])
    # off by more than the tube: the robot's own state
    far = _state_at(planner, 1.0)[:2] + (0.0, 1.5 * planner.tube)
    assert planner.plan(far, (0.0, 0.0), stamp_ns=stamp + 1_000_000_000) is not None
    start = _state_at(planner, 0.0)
    assert np.allclose(start, [far[0], far[1], 0.0, 0.0])


def test_a_start_inside_the_margin_may_leave_keeping_its_clearance(graph):
    planner = _planner(graph)
    wall = _box(2.0, 3.0, 0.1, 1.0)
    planner.set_obstacles([wall])
    planner.set_goal((5.0, 3.0), 0.1)
    start = (2.1 + 0.18, 3.0)  # 0.18 m from the wall: inside the 0.23 m margin, outside the robot
    assert planner.start_margin(start) == pytest.approx(0.18 - START_SLACK)
    assert planner.plan(start, (0.0, 0.0)) is not None
    samples = np.stack([_dense(c, 200) for c in planner.path.control_points])
    clearance = col.samples_clearance(samples, pg.pack_polygons([wall]), reach=1.0)
    assert clearance[0] >= 0.18 - START_SLACK and np.all(clearance[1:] > planner.margin)
    # Touching the wall already: no way out that keeps the robot clear.
    assert planner.start_margin((2.1 + 0.05, 3.0)) == ROBOT_RADIUS
    assert planner.plan((2.1 + 0.05, 3.0), (0.0, 0.0)) is None
