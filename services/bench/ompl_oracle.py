"""An independent oracle for the graph planner: OMPL's RRTConnect in the same world.

The graph planner (:mod:`onboard.graph_planner`) plans a double integrator; RRTConnect here
plans a point in R^2, the robot as a disc. The comparison is fair when both see the same
problem:

- **the same world**: the state space is the planning region (the graph keeps every curve
  inside it; OMPL samples inside it, and a segment between two states inside a box stays
  inside), the same convex obstacles;
- **the same clearance**: a state is valid iff its distance to every obstacle exceeds the
  planner's margin (robot radius plus tube), and a motion iff the whole segment's does,
  checked exactly (segment to convex polygon), not by OMPL's sampled motion check, which
  could pass a segment that clips a corner; every path RRTConnect returns is checked again
  before it counts as solved;
- **dynamics out of the way**: the queries start and end at rest. Between two states at
  rest a double integrator can follow any straight segment (stop, go, stop), so every
  polyline RRTConnect finds is a dynamically feasible path at the speed and acceleration
  bounds too, only slower; an "unsolved" query of the graph planner is therefore a
  question of its graph's resolution, not of its dynamics.

Needs ``ompl`` (the ``test`` extra: OMPL's own Python bindings), imported on first use.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from onboard import polygons as pg

VERIFY_SLACK = 1e-9  # [m] a returned path must keep the margin to within this (rounding)


@nb.njit(cache=True)
def _point_segment(px, py, ax, ay, bx, by):  # pragma: no cover - compiled
    dx, dy = bx - ax, by - ay
    d2 = dx * dx + dy * dy
    t = 0.0 if d2 <= 0.0 else min(max(((px - ax) * dx + (py - ay) * dy) / d2, 0.0), 1.0)
    return math.hypot(ax + t * dx - px, ay + t * dy - py)


@nb.njit(cache=True)
def _cross(ax, ay, bx, by, cx, cy):  # pragma: no cover - compiled
    return (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)


@nb.njit(cache=True)
def segment_clearance(ax, ay, bx, by, verts, offsets, normals, face_offsets, aabb, reach):  # pragma: no cover - compiled
    """Exact least distance [m] from segment a-b to the packed convex polygons (0 when it
    meets one); polygons whose box is farther than ``reach`` are skipped (result at most ``reach``)."""
    best = reach
    lox, hix = min(ax, bx) - reach, max(ax, bx) + reach
    loy, hiy = min(ay, by) - reach, max(ay, by) + reach
    for k in range(offsets.shape[0] - 1):
        if aabb[k, 0] > hix or aabb[k, 2] < lox or aabb[k, 1] > hiy or aabb[k, 3] < loy:
            continue
        s, e = offsets[k], offsets[k + 1]
        inside_a = True
        inside_b = True
        for v in range(s, e):
            if normals[v, 0] * ax + normals[v, 1] * ay > face_offsets[v]:
                inside_a = False
            if normals[v, 0] * bx + normals[v, 1] * by > face_offsets[v]:
                inside_b = False
        if inside_a or inside_b:
            return 0.0
        n = e - s
        for i in range(n):
            x0, y0 = verts[s + i, 0], verts[s + i, 1]
            x1, y1 = verts[s + (i + 1) % n, 0], verts[s + (i + 1) % n, 1]
            if (_cross(ax, ay, bx, by, x0, y0) * _cross(ax, ay, bx, by, x1, y1) < 0
                    and _cross(x0, y0, x1, y1, ax, ay) * _cross(x0, y0, x1, y1, bx, by) < 0):
                return 0.0  # the segment crosses this face
            d = min(_point_segment(x0, y0, ax, ay, bx, by), _point_segment(ax, ay, x0, y0, x1, y1),
                    _point_segment(bx, by, x0, y0, x1, y1))
            if d < best:
                best = d
    return best


class RrtConnectOracle:
    """RRTConnect (OMPL) for a disc of radius ``margin`` [m] among convex ``obstacles`` in ``bounds``."""

    def __init__(self, bounds: tuple[float, float, float, float], obstacles: list[np.ndarray], margin: float,
                 seed: int = 0) -> None:
        from ompl import base as ob
        from ompl import util as ou

        ou.setLogLevel(ou.LOG_NONE)
        ou.RNG.setSeed(int(seed) + 1)  # OMPL's seed must be > 0; set before its first sampler exists
        self.obstacles = pg.pack_polygons(obstacles)
        self.margin = float(margin)
        self.reach = self.margin + 1.0
        self.space = ob.RealVectorStateSpace(2)
        box = ob.RealVectorBounds(2)
        box.setLow(0, bounds[0])
        box.setLow(1, bounds[1])
        box.setHigh(0, bounds[2])
        box.setHigh(1, bounds[3])
        self.space.setBounds(box)

    def clearance(self, a: tuple[float, float], b: tuple[float, float]) -> float:
        """Exact clearance [m] of segment ``a``-``b`` (at most ``margin + 1``)."""
        o = self.obstacles
        return segment_clearance(float(a[0]), float(a[1]), float(b[0]), float(b[1]), o.vertices, o.offsets, o.normals,
                                 o.face_offsets, o.aabb, self.reach)

    def segment_free(self, a: tuple[float, float], b: tuple[float, float]) -> bool:
        return self.clearance(a, b) > self.margin

    def solve(self, start: np.ndarray, goal: np.ndarray, time_s: float) -> np.ndarray | None:
        """RRTConnect's path ``(K, 2)`` from ``start`` to ``goal`` within ``time_s`` [s], checked
        exactly against the margin; None when it found none."""
        from ompl import base as ob
        from ompl import geometric as og

        setup = og.SimpleSetup(self.space)
        setup.setStateValidityChecker(lambda s: self.segment_free((s[0], s[1]), (s[0], s[1])))
        info = setup.getSpaceInformation()
        oracle = self

        class ExactMotion(ob.MotionValidator):
            def checkMotion(self, s1, s2, *rest):  # noqa: N802 - OMPL's name
                return oracle.segment_free((s1[0], s1[1]), (s2[0], s2[1]))

        validator = ExactMotion(info)
        info.setMotionValidator(validator)
        a = self.space.allocState()
        a[0], a[1] = float(start[0]), float(start[1])
        b = self.space.allocState()
        b[0], b[1] = float(goal[0]), float(goal[1])
        setup.setStartAndGoalStates(a, b)
        setup.setPlanner(og.RRTConnect(info))
        setup.solve(float(time_s))
        if not setup.haveExactSolutionPath():
            return None
        path = setup.getSolutionPath()
        points = np.array([[path.getState(i)[0], path.getState(i)[1]] for i in range(path.getStateCount())])
        for p, q in zip(points[:-1], points[1:]):
            if self.clearance(p, q) <= self.margin - VERIFY_SLACK:
                raise AssertionError(f"RRTConnect returned a segment {p} -> {q} closer than the margin")
        return points


# --- the comparison ------------------------------------------------------------------------


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
    import time

    from onboard import bezier as bz
    from onboard import bezier_graph as bg
    from onboard import collision as col
    from onboard import graph_planner as gp
    from onboard.params import PlannerParams
    from services.bench.planner import _free_point, random_obstacles

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
