"""``archer bench planner``: Bezier graph build, cut, search and refine on a random clutter.

A square world (side ``--world``, default sized for about 50 nodes per square metre)
with ``--obstacles`` random convex obstacles (rotated rectangles), ``--nodes`` graph
nodes, the default planner parameters. Prints:

- ``nodes``, ``edges``, ``build_ms`` (sampling, pruning, edge test, control points);
- ``cut_ms_p50``/``cut_ms_p99``: the whole graph cut against every obstacle inflated by
  robot radius plus tube (``--repeat`` times, obstacles moved a little each time, as
  when the world changes), with ``pack_ms_p50`` (validating and packing the obstacles)
  apart; ``cut_cpu_ms_p50``: the process CPU time of one cut (all threads), the figure
  that a shared, loaded machine distorts least; ``threads``: numba threads;
- ``search_ms_p50``: start and goal joined to the graph and A*, random free start/goal
  pairs until ``--queries`` paths are found (``paths_found`` of ``queries`` tried);
- ``refine_ms_p50``/``refine_ms_p99``: one refine call at ``refine_hz`` along the path: an
  SQP iteration of the MPC (eq. 7.2) when a knot passed (``refine_solves``), else the last
  solution again (``refine_reused``); ``refine_solve_ms_p50``/``_p99``: the calls that solved;
- ``unsound_edges``: kept edges whose densely sampled curve (``--samples`` points) comes
  within the margin of an obstacle (must be 0); ``missed_edges``: cut edges whose dense
  samples all keep the margin (the convex-hull test's conservatism).

``--oracle ompl``: instead of the above, OMPL's RRTConnect (``--oracle-time`` each, 1 s by
default) against the graph planner on ``--queries`` random start/goal pairs at rest, the
graph planner densifying a failed search for at most ``--densify-budget`` (see
:mod:`services.bench.ompl_oracle` for how the two see the same problem): ``rrt_solved``,
``ours_before`` / ``ours_after`` (solved before / after densification), ``missed_after``
(solved by RRTConnect, not by us), densification rounds, nodes and time, and each query.

500 obstacles in the 10 m world that 5000 nodes get leave little room for a robot of
0.26 m with its tube (most edges are cut, many start/goal pairs have no path): the
figures are the thesis's problem size (5000 nodes, about 50,000 edges, 500 obstacles).
"""

from __future__ import annotations

import argparse
import math
import time

import numba
import numpy as np

from onboard.geometry import bezier as bz
from onboard.high_level.tracking import collision as col
from onboard.geometry import polygons as pg
from onboard.high_level.planning import bezier_graph as bg
from onboard.high_level.planning import graph_planner as gp
from onboard.contracts.params import PlannerParams
from services.bench.ompl_oracle import RrtConnectOracle

NODES_PER_M2 = 50.0  # default world sizing: thesis density (5000 nodes, about 10 edges each)
OBSTACLE_HALF_SIZE = (0.03, 0.12)  # [m] half sides of the random rectangles
JITTER = 0.01  # [m] obstacle motion between timed cuts
QUERY_ATTEMPTS = 10  # random start/goal pairs tried per wanted path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--nodes", type=int, default=5000, help="graph nodes")
    parser.add_argument("--obstacles", type=int, default=500, help="random convex obstacles")
    parser.add_argument("--world", type=float, default=0.0, help="world side [m] (0: sized by --nodes)")
    parser.add_argument("--repeat", type=int, default=30, help="timed cuts")
    parser.add_argument("--queries", type=int, default=20, help="timed searches (random start and goal)")
    parser.add_argument("--refines", type=int, default=1000, help="timed refine calls (at refine_hz along each path found)")
    parser.add_argument("--samples", type=int, default=100, help="dense samples per edge for the soundness check")
    parser.add_argument("--robot-radius", type=float, default=0.13, help="[m]")
    parser.add_argument("--tube", type=float, default=PlannerParams().tube, help="[m] low-level tube planned with")
    parser.add_argument("--rest-grid", type=float, default=0.0, help="[m] rest-lattice spacing (0: none, exactly --nodes nodes)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--oracle", choices=["ompl"], help="compare with OMPL's RRTConnect (needs the test extra)")
    parser.add_argument("--oracle-time", type=float, default=1.0, help="[s] RRTConnect's time per query")
    parser.add_argument("--densify-budget", type=float, default=PlannerParams().densify_budget_s,
                        help="[s] densification after a failed search (0: none)")


def random_obstacles(rng: np.random.Generator, count: int, side: float) -> list[np.ndarray]:
    out = []
    for _ in range(count):
        c = rng.uniform(0.0, side, 2)
        hx, hy = rng.uniform(*OBSTACLE_HALF_SIZE, 2)
        th = rng.uniform(0.0, math.pi)
        R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
        out.append(c + np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]]) @ R.T)
    return out


def _pct(values: list[float], q: float) -> float:
    return round(float(np.percentile(values, q)), 3)


def _free_point(rng: np.random.Generator, side: float, obstacles: pg.PolygonSet, margin: float) -> np.ndarray:
    while True:
        p = rng.uniform(0.5, side - 0.5, 2)
        if col.samples_clearance(p[None, None, :], obstacles, reach=margin + 0.5)[0] > margin + 0.05:
            return p


def measure(args: argparse.Namespace) -> dict:
    side = args.world if args.world > 0 else math.sqrt(args.nodes / NODES_PER_M2)
    if args.oracle == "ompl":
        return compare_queries(side, args.obstacles, args.nodes, args.queries, args.seed, args.oracle_time,
                               args.densify_budget, args.robot_radius, args.tube, args.rest_grid)
    params = PlannerParams(nodes=args.nodes, rest_grid=args.rest_grid, tube=args.tube)
    rng = np.random.default_rng(args.seed)
    # Warm the compiled kernels on a small problem so that timings exclude compilation.
    warm = gp.GraphPlanner(params, args.robot_radius, bounds=(0.0, 0.0, 2.0, 2.0), nodes=200)
    warm.set_obstacles(random_obstacles(rng, 5, 2.0))
    warm.set_goal((1.8, 1.8))
    warm.plan((0.2, 0.2), (0.0, 0.0))
    warm.refine((0.2, 0.2), (0.0, 0.0), 0)
    col.cut_obstacles(col.hull_set(np.zeros((gp.col.PARALLEL_MIN, 4, 2))), warm.obstacles, 0.1)

    spec = bg.spec_from_params(params, (0.0, 0.0, side, side), nodes=args.nodes, seed=args.seed)
    t0 = time.perf_counter()
    graph = bg.build_graph(spec)
    build_ms = (time.perf_counter() - t0) * 1e3

    polys = random_obstacles(rng, args.obstacles, side)
    planner = gp.GraphPlanner(params, args.robot_radius, bounds=spec.bounds, nodes=args.nodes)
    planner.set_graph(graph)
    margin = planner.margin
    cut_ms, cut_cpu_ms, pack_ms = [], [], []
    for k in range(args.repeat):
        moved = [p + rng.normal(0.0, JITTER, 2) for p in polys] if k else polys
        t0 = time.perf_counter()
        packed = pg.pack_polygons(moved)
        t1 = time.perf_counter()
        c1 = time.process_time()
        col.cut_obstacles(graph.hulls, packed, margin)
        c2 = time.process_time()
        t2 = time.perf_counter()
        pack_ms.append((t1 - t0) * 1e3)
        cut_ms.append((t2 - t1) * 1e3)
        cut_cpu_ms.append((c2 - c1) * 1e3)
    obstacles = pg.pack_polygons(polys)
    blocked = col.cut_obstacles(graph.hulls, obstacles, margin)

    # Soundness against dense sampling of every edge's true curve.
    Z = bz.bernstein(graph.control_points.shape[1] - 1, np.linspace(0.0, 1.0, args.samples))
    unsound = missed = 0
    chunk = 20000
    for a in range(0, graph.n_edges, chunk):
        samples = np.einsum("sk,ekd->esd", Z, graph.control_points[a:a + chunk])
        clearance = col.samples_clearance(samples, obstacles, reach=margin + 0.01)
        unsound += int(np.sum(~blocked[a:a + chunk] & (clearance <= margin)))
        missed += int(np.sum(blocked[a:a + chunk] & (clearance > margin)))

    planner.set_obstacles(polys)
    planner.cut()
    search_ms, refine_ms, solve_ms = [], [], []
    found = attempts = 0
    # Random free start and goal; searches that find no path are timed too.
    while found < args.queries and attempts < QUERY_ATTEMPTS * args.queries:
        attempts += 1
        start = _free_point(rng, side, obstacles, margin)
        goal = _free_point(rng, side, obstacles, margin)
        planner.set_goal(goal, 0.1)
        t0 = time.perf_counter()
        ref = planner.plan(start, (0.0, 0.0), 0)
        search_ms.append((time.perf_counter() - t0) * 1e3)
        if ref is None:
            continue
        found += 1
        for j in range(max(args.refines // args.queries, 1)):
            t_ns = int(j * 1e9 / params.refine_hz)
            expect = bg.path_states(planner.path.control_points, planner.path.tau, np.array([t_ns * 1e-9]))[0]
            solves = planner.stats.refines
            t0 = time.perf_counter()
            planner.refine(expect[:2], expect[2:], t_ns)
            refine_ms.append((time.perf_counter() - t0) * 1e3)
            if planner.stats.refines > solves:
                solve_ms.append(refine_ms[-1])
    return {
        "nodes": graph.n_nodes,
        "edges": graph.n_edges,
        "obstacles": args.obstacles,
        "world_m": round(side, 3),
        "margin_m": round(margin, 3),
        "build_ms": round(build_ms, 1),
        "cut_ms_p50": _pct(cut_ms, 50),
        "cut_ms_p99": _pct(cut_ms, 99),
        "cut_cpu_ms_p50": _pct(cut_cpu_ms, 50),
        "pack_ms_p50": _pct(pack_ms, 50),
        "threads": numba.get_num_threads(),
        "edges_free": int((~blocked).sum()),
        "search_ms_p50": _pct(search_ms, 50),
        "refine_ms_p50": _pct(refine_ms, 50) if refine_ms else None,
        "refine_ms_p99": _pct(refine_ms, 99) if refine_ms else None,
        "refine_solve_ms_p50": _pct(solve_ms, 50) if solve_ms else None,
        "refine_solve_ms_p99": _pct(solve_ms, 99) if solve_ms else None,
        "refine_solves": planner.stats.refines,
        "refine_reused": planner.stats.refine_reused,
        "refine_failures": planner.stats.refine_failures,
        "unsound_edges": unsound,
        "missed_edges": missed,
        "paths_found": found,
        "queries": attempts,
    }


# --- against an oracle ---------------------------------------------------------------------


def compare_queries(side: float, obstacle_count: int, nodes: int, queries: int, seed: int, rrt_s: float,
                    budget_s: float, robot_radius: float, tube: float, rest_grid: float = 0.0,
                    samples: int = 50) -> dict:
    """RRTConnect against the graph planner on ``queries`` random free start/goal pairs (at
    rest) in a ``side`` [m] square with ``obstacle_count`` random obstacles (the planner bench's).

    Each query gets the same base graph (``nodes`` uniform random nodes, ``rest_grid``), so
    a densification never helps a later query. ``ours_before``: solved by the first search;
    ``ours_after``: solved after densifying for at most ``budget_s`` on the wall clock.
    ``missed``: queries RRTConnect solved and we did not. Our paths are sampled densely
    (``samples`` per segment) and their least clearance reported (must exceed the margin).
    """
    rng = np.random.default_rng(seed)
    polys = random_obstacles(rng, obstacle_count, side)
    params = PlannerParams(nodes=nodes, rest_grid=rest_grid, tube=tube, densify_budget_s=budget_s)
    bounds = (0.0, 0.0, side, side)
    base = bg.build_graph(bg.spec_from_params(params, bounds, nodes=nodes, seed=seed))
    planner = gp.GraphPlanner(params, robot_radius, bounds=bounds, nodes=nodes)
    planner.set_obstacles(polys)
    margin = planner.margin
    oracle = RrtConnectOracle(bounds, polys, margin, seed)
    Z = bz.bernstein(base.control_points.shape[1] - 1, np.linspace(0.0, 1.0, samples))
    records = []
    for _ in range(queries):
        start = _free_point(rng, side, planner.obstacles, margin)
        goal = _free_point(rng, side, planner.obstacles, margin)
        t0 = time.perf_counter()
        rrt = oracle.solve(start, goal, rrt_s)
        rrt_ms = (time.perf_counter() - t0) * 1e3
        planner.set_graph(base)  # every query from the same base graph
        planner.set_goal(goal, 0.1)
        t0 = time.perf_counter()
        ref = planner.plan(start, (0.0, 0.0), 0, clock=time.perf_counter)
        plan_ms = (time.perf_counter() - t0) * 1e3
        report = planner.last_densify
        clearance = None
        if ref is not None:
            pts = np.einsum("sk,ekd->esd", Z, planner.path.control_points).reshape(1, -1, 2)
            clearance = float(col.samples_clearance(pts, planner.obstacles, reach=margin + 1.0)[0])
        records.append({
            "start": start.tolist(), "goal": goal.tolist(), "rrt": rrt is not None, "rrt_ms": round(rrt_ms, 1),
            "ours_before": ref is not None and report is None, "ours_after": ref is not None, "plan_ms": round(plan_ms, 1),
            "densify_rounds": report.rounds if report else 0, "densify_nodes": report.nodes_added if report else 0,
            "densify_ms": round(report.spent_s * 1e3, 1) if report else 0.0,
            "no_path_reason": None if ref is not None else (report.reason if report else "densification off"),
            "path_clearance": clearance,
        })
    densified = [r for r in records if r["densify_rounds"] or r["densify_ms"]]
    clearances = [r["path_clearance"] for r in records if r["path_clearance"] is not None]
    return {
        "world_m": side, "obstacles": obstacle_count, "nodes": nodes, "rest_grid": rest_grid, "margin_m": round(margin, 3),
        "queries": queries, "rrt_time_s": rrt_s, "densify_budget_s": budget_s,
        "rrt_solved": sum(r["rrt"] for r in records),
        "ours_before": sum(r["ours_before"] for r in records),
        "ours_after": sum(r["ours_after"] for r in records),
        "missed_before": sum(r["rrt"] and not r["ours_before"] for r in records),
        "missed_after": sum(r["rrt"] and not r["ours_after"] for r in records),
        "ours_only": sum(r["ours_after"] and not r["rrt"] for r in records),
        "densified_queries": len(densified),
        "densify_rounds_max": max((r["densify_rounds"] for r in records), default=0),
        "densify_nodes_max": max((r["densify_nodes"] for r in records), default=0),
        "densify_ms_max": max((r["densify_ms"] for r in records), default=0.0),
        "path_clearance_min": round(min(clearances), 4) if clearances else None,
        "records": records,
    }
