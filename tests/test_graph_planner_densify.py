"""Densification of the Bezier graph after a failed search (onboard/high_level/planning/densify.py), its report in
`archer plan`, and completeness against an independent oracle (OMPL's RRTConnect)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from onboard.geometry import bezier as bz
from onboard.high_level.planning import bezier_graph as bg
from onboard.high_level.tracking import collision as col
from onboard.high_level.planning import densify as dn
from onboard.high_level.planning import graph_planner as gp
from onboard.contracts.params import PlannerParams
from services.bench.ompl_oracle import RrtConnectOracle
from services.bench.planner import compare_queries
from services.cli.plan import parse_scene, plan_scene

RADIUS = 0.13
# margin 0.23 m; without a clock the rounds of a call are unbounded here (lockstep bounds them)
PARAMS = PlannerParams(nodes=300, rest_grid=0.0, tube=0.1, densify_max_rounds=10_000)
MARGIN = RADIUS + PARAMS.tube
BOUNDS = (0.0, 0.0, 4.0, 4.0)
START = np.array([0.8, 0.8])
GOAL = np.array([3.2, 3.2])
SEED = 0  # the bench world of `archer bench planner --oracle ompl` (its first queries include misses of the bare graph)


def wall_with_gap(width: float) -> list[np.ndarray]:
    """A wall across the whole region at x = 2 m with one gap of ``width`` [m] centred at y = 1.7 m."""
    lo, hi = 1.7 - width / 2, 1.7 + width / 2
    return [np.array([[1.9, -0.5], [2.1, -0.5], [2.1, lo], [1.9, lo]]),
            np.array([[1.9, hi], [2.1, hi], [2.1, 4.5], [1.9, 4.5]])]


def planner_for(obstacles: list[np.ndarray], **changes) -> gp.GraphPlanner:
    params = dataclasses.replace(PARAMS, **changes)
    planner = gp.GraphPlanner(params, RADIUS, bounds=BOUNDS, nodes=params.nodes)
    planner.set_obstacles(obstacles)
    planner.set_goal(GOAL, 0.1)
    return planner


def path_clearance(planner: gp.GraphPlanner) -> float:
    ctrl = planner.path.control_points
    pts = np.einsum("sk,ekd->esd", bz.bernstein(ctrl.shape[1] - 1, np.linspace(0, 1, 200)), ctrl).reshape(1, -1, 2)
    return float(col.samples_clearance(pts, planner.obstacles, reach=MARGIN + 1.0)[0])


def test_densification_passes_a_gap_the_graph_misses_and_the_graph_is_reused():
    gap = 2 * MARGIN + 0.04
    assert planner_for(wall_with_gap(gap), densify_budget_s=0.0).plan(START, (0, 0)) is None  # the graph alone misses it
    planner = planner_for(wall_with_gap(gap))
    ref = planner.plan(START, (0, 0))  # no clock: until a path or the finest resolution
    assert ref is not None
    report = planner.last_densify
    assert report is not None and report.found and report.reason == "" and report.rounds >= 1
    assert planner.graph.densified == report.nodes_added > 0
    assert planner.graph.n_nodes == planner.graph.spec.total_nodes + report.nodes_added
    assert planner.stats.densify_plans == 1 and planner.stats.densify_rounds == report.rounds
    assert path_clearance(planner) > MARGIN  # densified edges are cut like the others
    xs = planner.path.states[:, 0]
    assert xs.min() < 2.0 < xs.max()
    # the next plan in the region searches the densified graph: no new densification
    graph = planner.graph
    assert planner.plan(START + 0.05, (0, 0)) is not None
    assert planner.graph is graph and planner.last_densify is None and planner.stats.densify_plans == 1


def test_closed_gap_is_unreachable_at_the_finest_resolution():
    planner = planner_for(wall_with_gap(2 * MARGIN - 0.02))
    assert planner.plan(START, (0, 0)) is None
    report = planner.last_densify
    assert report.reason == dn.UNREACHABLE and not report.found
    bounded = planner_for(wall_with_gap(2 * MARGIN - 0.02), densify_max_rounds=2)
    assert bounded.plan(START, (0, 0)) is None  # lockstep's bound: so many rounds, then no path for now
    assert bounded.last_densify.reason == dn.BUDGET_SPENT and bounded.last_densify.rounds == 2
    assert report.rounds >= 1 and report.finest_grid == pytest.approx(planner._densifier.levels[-1])
    assert report.finest_grid >= PARAMS.densify_min_grid
    # a replan of the same world and goal keeps the answer without densifying again
    nodes = planner.graph.n_nodes
    assert planner.plan(START, (0, 0)) is None
    assert planner.last_densify is report and planner.stats.densify_plans == 1 and planner.graph.n_nodes == nodes
    planner.set_goal(GOAL + 0.1, 0.1)  # a new question: densified again (nothing left to add there)
    assert planner.plan(START, (0, 0)) is None
    assert planner.stats.densify_plans == 2 and planner.last_densify.reason == dn.UNREACHABLE
    # RRTConnect cannot pass either: the two see the same clearance
    oracle = RrtConnectOracle(BOUNDS, wall_with_gap(2 * MARGIN - 0.02), MARGIN)
    assert oracle.solve(START, GOAL, 0.3) is None
    assert RrtConnectOracle(BOUNDS, wall_with_gap(2 * MARGIN + 0.04), MARGIN).solve(START, GOAL, 1.0) is not None


def test_budget_and_node_limit_stop_densification():
    ticks = iter(range(1000))
    planner = planner_for(wall_with_gap(2 * MARGIN + 0.04), densify_budget_s=0.5)
    assert planner.plan(START, (0, 0), clock=lambda: float(next(ticks))) is None  # each reading 1 s later
    assert planner.last_densify.reason == dn.BUDGET_SPENT and planner.last_densify.rounds == 0
    assert planner.graph.densified == 0
    planner = planner_for(wall_with_gap(2 * MARGIN + 0.04), densify_max_nodes=3)
    assert planner.plan(START, (0, 0)) is None
    assert planner.last_densify.reason == dn.NODE_LIMIT and planner.graph.densified == 3
    planner = planner_for(wall_with_gap(2 * MARGIN - 0.02), densify_max_edges=1)  # the memory bound: one round passes it
    assert planner.plan(START, (0, 0)) is None
    assert planner.last_densify.reason == dn.EDGE_LIMIT and planner.last_densify.rounds == 1
    assert planner.last_densify.edges_added > 0
    planner = planner_for(wall_with_gap(2 * MARGIN + 0.04), densify_budget_s=0.0)
    assert planner.plan(START, (0, 0)) is None and planner.last_densify is None


def test_an_extended_graph_is_the_graph_sorted_and_built_whole():
    planner = planner_for(wall_with_gap(2 * MARGIN + 0.04))
    planner.plan(START, (0, 0))  # builds the graph (and densifies it)
    graph = planner.graph
    lattice = np.array([[x, y, 0.0, 0.0] for x in (1.95, 2.0, 2.05) for y in (1.6, 1.7, 1.8)])
    grown, old_at, new_at = dn.extend_graph(graph, lattice, np.full(len(lattice), 0.1))
    assert grown.n_nodes == graph.n_nodes + len(lattice) and grown.densified == graph.densified + len(lattice)
    assert len(old_at) == graph.n_edges and len(new_at) == grown.n_edges - graph.n_edges > 0
    np.testing.assert_array_equal(grown.src[old_at], graph.src)
    np.testing.assert_array_equal(grown.dst[old_at], graph.dst)
    np.testing.assert_array_equal(grown.control_points[old_at], graph.control_points)
    assert np.all((grown.src[new_at] >= graph.n_nodes) | (grown.dst[new_at] >= graph.n_nodes))  # each has a new end
    keys = grown.src * grown.n_nodes + grown.dst
    assert np.all(np.diff(keys) > 0)  # sorted by source, then destination; no edge twice
    np.testing.assert_array_equal(np.diff(grown.indptr), np.bincount(grown.src, minlength=grown.n_nodes))
    whole = bg.assemble(grown.spec, grown.nodes, grown.src, grown.dst, grown.control_points, grown.cost, grown.reachability)
    for name in ("points", "aabb", "radius", "axes"):
        np.testing.assert_array_equal(getattr(grown.hulls, name), getattr(whole.hulls, name), err_msg=name)
    np.testing.assert_array_equal(grown.cost, bz.path_length_bound(grown.control_points))
    obstacles = planner.obstacles
    np.testing.assert_array_equal(col.cut_obstacles(grown.hulls, obstacles, MARGIN), col.cut_obstacles(whole.hulls, obstacles, MARGIN))


def test_a_densified_graph_is_never_written_to_the_cache(tmp_path):
    scene = {"bounds": [[0, 0], [4, 4]], "obstacles": [p.tolist() for p in wall_with_gap(2 * MARGIN + 0.04)],
             "start": START.tolist(), "goal": GOAL.tolist(), "robot_radius": RADIUS, "tube": 0.1, "nodes": 300,
             "densify_budget_s": 30.0}
    out = plan_scene(parse_scene(json.dumps(scene), PARAMS), tmp_path)
    assert out["path"] is True and out["found"] is True and out["no_path_reason"] is None
    assert out["densified"]["rounds"] >= 1 and out["densified"]["nodes_added"] > 0
    assert out["nodes"] == 300 + out["densified"]["nodes_added"]
    (cached,) = tmp_path.glob("*.npz")
    before = cached.read_bytes()
    again = plan_scene(parse_scene(json.dumps(scene), PARAMS), tmp_path)
    assert again["graph_cached"] is True and again["densified"]["nodes_added"] == out["densified"]["nodes_added"]
    assert cached.read_bytes() == before  # the base graph, not the densified one
    spec = bg.spec_from_params(dataclasses.replace(PARAMS, tube=0.1), (0.0, 0.0, 4.0, 4.0), nodes=300)
    planner = planner_for(wall_with_gap(2 * MARGIN + 0.04))
    planner.plan(START, (0, 0))
    with pytest.raises(bg.PlanningError):
        planner.graph.to_arrays()
    assert bg.build_graph(spec).n_nodes == 300
    closed = dict(scene, obstacles=[p.tolist() for p in wall_with_gap(2 * MARGIN - 0.02)])
    out = plan_scene(parse_scene(json.dumps(closed), PARAMS), tmp_path)
    assert out["path"] is False and out["no_path_reason"] == dn.UNREACHABLE
    out = plan_scene(parse_scene(json.dumps(dict(closed, densify_budget_s=0.0)), PARAMS), tmp_path)
    assert out["path"] is False and out["no_path_reason"] == "densification off" and out["densified"] is None


def test_segment_clearance_is_exact():
    from services.bench.planner import random_obstacles

    rng = np.random.default_rng(4)
    oracle = RrtConnectOracle((0.0, 0.0, 5.0, 5.0), random_obstacles(rng, 60, 5.0), MARGIN)
    for _ in range(300):
        a = rng.uniform(0, 5, 2)
        b = a + rng.normal(0, 0.4, 2)
        pts = a + np.linspace(0, 1, 4001)[:, None] * (b - a)
        sampled = min(max(float(col.samples_clearance(pts[None], oracle.obstacles, reach=oracle.reach)[0]), 0.0), oracle.reach)
        assert oracle.clearance(a, b) == pytest.approx(sampled, abs=2e-3)


def test_every_query_rrtconnect_solves_we_solve():
    """8 seeded queries in the planner bench's world (10 m, 150 obstacles, 5000 random nodes, no
    rest lattice): every query RRTConnect solves in 1 s, the graph planner solves after
    densifying for at most 5 s of wall clock (a shared machine: the budget leaves room)."""
    out = compare_queries(side=10.0, obstacle_count=150, nodes=5000, queries=8, seed=SEED, rrt_s=1.0, budget_s=5.0,
                          robot_radius=RADIUS, tube=0.1)
    assert out["rrt_solved"] >= 6
    assert out["missed_before"] >= 1  # the graph alone misses some: densification is what is tested
    assert out["missed_after"] == 0, [r for r in out["records"] if r["rrt"] and not r["ours_after"]]
    assert out["path_clearance_min"] > out["margin_m"]
