"""An independent oracle for the graph planner: OMPL's RRTConnect in the same world.

The graph planner (:mod:`onboard.high_level.planning.graph_planner`) plans a double integrator; RRTConnect here
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

from onboard.geometry import polygons as pg

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

