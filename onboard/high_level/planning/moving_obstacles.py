"""Obstacles that move (issue 28; thesis 7.2: people kick the obstacles around the lab).

An obstacle comes with its velocity (``Polytope.velocity``). The planner cuts its graph in time:
a curve ``d`` metres from the robot cannot be reached before ``d / v_max``, so it is cut against each
moving obstacle swept along its velocity over the window from then until the robot has crossed the
band of curves that far out (``obstacle_band_m``) plus the part of the plan it commits to
(``obstacle_sweep_s``): where the obstacle can be while the robot can be there. Travel is capped at
``obstacle_sweep_max_m`` (a kick stops). When that leaves no way (the robot stands in an
obstacle's way, or the sweeps close a gap), it plans again with shorter windows, down to the
obstacles where they will be at the earliest time (``SWEEP_LEVELS``); when even that fails and one
comes at the robot, it steps out of its way (:func:`evasion_directions`) rather than hop in place
until it arrives. Static obstacles are cut exactly as given.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

SWEEP_LEVELS = (1.0, 0.5, 0.0)  # shares of the horizon tried in turn when the longer sweep leaves no path
STILL = 1e-6  # [m/s] slower than this an obstacle is static


def hull_order(poly: np.ndarray, displacement: np.ndarray) -> np.ndarray:
    """Indices into ``[poly; poly + displacement]`` of their convex hull, counter-clockwise (``poly``
    (k, 2) convex). For a non-zero displacement they depend on its direction only: a convex polygon
    swept along a segment keeps the vertices its direction picks, however long the segment."""
    pts = np.concatenate([poly, poly + displacement])
    p = pts.tolist()

    def half(seq: list[int]) -> list[int]:
        out: list[int] = []
        for i in seq:
            while len(out) >= 2 and ((p[out[-1]][0] - p[out[-2]][0]) * (p[i][1] - p[out[-2]][1])
                                     - (p[out[-1]][1] - p[out[-2]][1]) * (p[i][0] - p[out[-2]][0])) <= 1e-12:
                out.pop()
            out.append(i)
        return out

    order = np.lexsort((pts[:, 1], pts[:, 0])).tolist()
    lower, upper = half(order), half(order[::-1])
    return np.array(lower[:-1] + upper[:-1], dtype=np.int64)


def swept(poly: np.ndarray, displacement: np.ndarray) -> np.ndarray:
    """The convex hull of ``poly`` ((k, 2), convex) and ``poly`` shifted by ``displacement`` [m], counter-clockwise."""
    return np.concatenate([poly, poly + displacement])[hull_order(poly, displacement)]


def check_velocities(velocities: object, count: int) -> np.ndarray:
    """``(count, 2)`` finite velocities [m/s], or ValueError."""
    vel = np.asarray(velocities, dtype=float)
    if vel.size == 0:
        vel = vel.reshape(0, 2)
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


def sweep_orders(polygons: list[np.ndarray], velocities: np.ndarray) -> list[np.ndarray | None]:
    """Each polygon's :func:`hull_order` along its velocity (None for a still one): computed once per
    world, every band's sweep of it is then a few array operations."""
    return [hull_order(np.asarray(poly, dtype=float), np.array([vx, vy])) if math.hypot(vx, vy) >= STILL else None
            for poly, (vx, vy) in zip(polygons, velocities.tolist())]


def band_polygons(polygons: list[np.ndarray], velocities: np.ndarray, orders: list[np.ndarray | None],
                  windows: np.ndarray, max_m: float) -> list[list[np.ndarray]]:
    """Per time window ``[t0, t1]`` of ``windows`` ((n, 2) [s]), each moving polygon over it: the hull
    of where it is at both ends (by its :func:`sweep_orders` entry), its travel capped at ``max_m`` [m]
    (a kick stops); still ones are left out. Each hull is ``swept(poly + v t0, v (t1 - t0))``, to the bit."""
    windows = np.asarray(windows, dtype=float).reshape(-1, 2)
    out: list[list[np.ndarray]] = [[] for _ in range(len(windows))]
    for poly, (vx, vy), order in zip(polygons, velocities.tolist(), orders):
        if order is None:
            continue
        cap = max_m / math.hypot(vx, vy)
        a, b = np.minimum(windows[:, 0], cap), np.minimum(windows[:, 1], cap)
        v = np.array([vx, vy])
        start = poly[None] + a[:, None, None] * v  # (n, k, 2): where it is at t0
        shifted = (order >= len(poly)).astype(float)  # the hull's vertices from the copy at t1
        hulls = start[:, order % len(poly)] + ((b - a)[:, None] * shifted)[..., None] * v
        for w in range(len(windows)):
            out[w].append(hulls[w] if b[w] > a[w] else start[w])
    return out


@nb.njit(cache=True)
def _bands(aabb, ox, oy, band_m):  # pragma: no cover - compiled
    out = np.empty(aabb.shape[0], dtype=np.int64)
    for e in range(aabb.shape[0]):
        dx = max(aabb[e, 0] - ox, ox - aabb[e, 2], 0.0)
        dy = max(aabb[e, 1] - oy, oy - aabb[e, 3], 0.0)
        out[e] = int(math.hypot(dx, dy) / band_m)
    return out


def curve_bands(aabb: np.ndarray, origin: np.ndarray, band_m: float) -> np.ndarray:
    """Distance band of each curve's box ``(E, 4)`` from ``origin``: ``floor(d / band_m)`` with ``d`` [m]
    the box's distance (no point of the curve is nearer). One compiled pass: the planner bands every
    edge of its graph at each replan among moving obstacles."""
    return _bands(np.ascontiguousarray(aabb, dtype=float), float(origin[0]), float(origin[1]), float(band_m))


def moving(velocities: np.ndarray | None) -> bool:
    """Whether any obstacle moves."""
    return velocities is not None and bool(np.any(np.hypot(velocities[:, 0], velocities[:, 1]) >= STILL))


EVADE_M = 0.6  # [m] how far an evasion steps out of an oncoming obstacle's way
EVADE_TURNS = (0.0, math.pi / 4, -math.pi / 4, math.pi / 2, -math.pi / 2, math.pi)  # tried in turn, from across its way


def threat(position: np.ndarray, polygons: list[np.ndarray], velocities: np.ndarray, reach: float) -> int | None:
    """The moving obstacle nearest ``position`` among those coming toward it within ``reach`` [m] of its
    centre (vertex distance: a bound for convex polygons); None when none comes."""
    best, best_d = None, math.inf
    p = np.asarray(position, dtype=float)[:2]
    for k, (poly, (vx, vy)) in enumerate(zip(polygons, velocities.tolist())):
        if math.hypot(vx, vy) < STILL:
            continue
        c = poly.mean(axis=0)
        if vx * (p[0] - c[0]) + vy * (p[1] - c[1]) <= 0.0:  # moving away
            continue
        d = float(np.min(np.hypot(*(poly - p).T)))
        if d <= reach and d < best_d:
            best, best_d = k, d
    return best


def evasion_directions(position: np.ndarray, centre: np.ndarray, velocity: np.ndarray) -> list[np.ndarray]:
    """Unit directions to step out of an obstacle's way, best first: across its way on the side the
    robot is on, then turned from that (never first toward where it goes)."""
    v = np.asarray(velocity, dtype=float) / math.hypot(*velocity)
    across = np.array([-v[1], v[0]])
    if float(across @ (np.asarray(position, dtype=float)[:2] - centre)) < 0.0:
        across = -across
    # turned away from the obstacle's motion first (positive turns toward +v are tried after)
    sign = 1.0 if across[0] * v[1] - across[1] * v[0] > 0 else -1.0  # the 2D cross product's sign
    out = []
    for turn in EVADE_TURNS:
        a = sign * turn
        c, s = math.cos(a), math.sin(a)
        out.append(np.array([c * across[0] - s * across[1], s * across[0] + c * across[1]]))
    return out
