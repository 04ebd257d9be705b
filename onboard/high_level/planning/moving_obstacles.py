"""Obstacles that move (issue 28; thesis 7.2: people kick the obstacles around the lab).

An obstacle comes with its velocity (``Polytope.velocity``). Over the part of a plan the robot
commits to it may travel ``speed x horizon``; the planner cuts its graph against each moving
obstacle swept along its velocity over that horizon (the convex hull of the polygon where it is and
where it will be), capped at a distance (a kick does not go on for ever). When that leaves no way
(the robot stands in an obstacle's sweep, or the sweeps close a gap), it plans again with shorter
sweeps, down to the obstacles where they are now (``SWEEP_LEVELS``): a way out of the sweep now
beats hopping in place until the obstacle arrives. Static obstacles are left exactly as given.
"""

from __future__ import annotations

import math

import numpy as np

SWEEP_LEVELS = (1.0, 0.5, 0.0)  # shares of the horizon tried in turn when the longer sweep leaves no path
STILL = 1e-6  # [m/s] slower than this an obstacle is static


def swept(poly: np.ndarray, displacement: np.ndarray) -> np.ndarray:
    """The convex hull of ``poly`` ((k, 2), convex) and ``poly`` shifted by ``displacement`` [m], counter-clockwise."""
    pts = np.concatenate([poly, poly + displacement])
    order = np.lexsort((pts[:, 1], pts[:, 0]))
    pts = pts[order].tolist()

    def half(seq: list) -> list:
        out: list = []
        for p in seq:
            while len(out) >= 2 and ((out[-1][0] - out[-2][0]) * (p[1] - out[-2][1])
                                     - (out[-1][1] - out[-2][1]) * (p[0] - out[-2][0])) <= 1e-12:
                out.pop()
            out.append(p)
        return out

    lower, upper = half(pts), half(pts[::-1])
    return np.array(lower[:-1] + upper[:-1], dtype=float)


def check_velocities(velocities: object, count: int) -> np.ndarray:
    """``(count, 2)`` finite velocities [m/s], or ValueError."""
    vel = np.asarray(velocities, dtype=float)
    if vel.shape != (count, 2) or not np.all(np.isfinite(vel)):
        raise ValueError(f"velocities must be {count} finite [vx, vy], got shape {vel.shape}")
    return vel


def sweep_obstacles(polygons: list[np.ndarray], velocities: np.ndarray, horizon_s: float, max_m: float) -> list[np.ndarray]:
    """Each polygon swept along its velocity over ``horizon_s`` [s], at most ``max_m`` [m]; static ones as given."""
    out = []
    for poly, (vx, vy) in zip(polygons, velocities.tolist()):
        speed = math.hypot(vx, vy)
        if speed < STILL or horizon_s <= 0.0:
            out.append(poly)
            continue
        t = min(horizon_s, max_m / speed)
        out.append(swept(np.asarray(poly, dtype=float), np.array([vx * t, vy * t])))
    return out


def moving(velocities: np.ndarray | None) -> bool:
    """Whether any obstacle moves."""
    return velocities is not None and bool(np.any(np.hypot(velocities[:, 0], velocities[:, 1]) >= STILL))
