"""Pendulum swing-up by a graph over Bezier reachable polytopes (thesis Figure 6.6).

Nodes are sampled uniformly over the pendulum state ``[theta, omega]`` (theta = 0
hanging, +-pi upright). Node ``i`` connects to node ``j`` when ``x_j`` lies in the
forward reachable polytope of ``x_i`` (Theorem 6.2 with Corollary 6.3: a k-refinement
with references on the zero-input flow of ``x_i``), i.e. when the Bezier curve between
them needs at most ``u_max`` of torque and keeps ``|omega| <= omega_max`` for all time.
Candidate pairs come from a k-d tree around each node's drift endpoint. Dijkstra then
finds the fewest segments from hanging at rest to upright at rest. Tighter torque
limits need more pumping: the path gets longer (the thesis's observation).

Every curve on the returned path is re-checked by dense sampling against the true
pendulum equation. Run: ``.venv/bin/python examples/pendulum_swingup.py [--plot out.png]``.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from onboard.geometry import bezier as bz
from onboard.high_level.tracking import reachability as rc

GRAVITY = 9.81  # [m/s^2]
MASS = 0.5  # [kg]
LENGTH = 0.5  # [m]: m g l = 2.45 N m is what holding the pendulum level takes
DAMPING = 0.0  # [1/s]
BROAD_PHASE_RADIUS = 1.5  # in units of the input's reach: covers the box [-1, 1]^2 with room


@dataclass(frozen=True)
class SwingupResult:
    u_max: float
    found: bool
    segments: int  # curves on the path (duration = segments * tau)
    nodes: int
    edges: int
    build_s: float
    path: np.ndarray  # (segments + 1, 2) states
    curves: np.ndarray  # (segments, p + 1, 1) control points of theta
    tau: float
    max_torque: float  # densely sampled, through the pendulum equation [N m]
    max_speed: float  # [rad/s]


def torque_along(curves: np.ndarray, tau: float, samples: int = 400) -> tuple[np.ndarray, np.ndarray]:
    """Torque needed by each curve (pendulum equation) and its speed, densely sampled."""
    t = np.linspace(0.0, tau, samples)
    th = bz.evaluate(curves, tau, t)[..., 0]
    om = bz.evaluate(bz.derivative_points(curves, tau, 1), tau, t)[..., 0]
    al = bz.evaluate(bz.derivative_points(curves, tau, 2), tau, t)[..., 0]
    torque = MASS * LENGTH**2 * (al + GRAVITY / LENGTH * np.sin(th) + DAMPING * om)
    return torque, om


def swing_up(
    u_max: float,
    nodes: int = 20000,
    tau: float = 0.15,
    omega_max: float = 10.0,
    refinement: int = 4,
    seed: int = 0,
) -> SwingupResult:
    t_start = time.perf_counter()
    model = rc.pendulum(MASS, LENGTH, GRAVITY, DAMPING)
    limits = rc.box_limits(model, u_max, [-np.inf, -omega_max], [np.inf, omega_max])
    reach = rc.BezierReachability(model, limits, tau, refinement=refinement)
    rng = np.random.default_rng(seed)
    lo = np.array([-math.pi - 0.3, -omega_max])
    hi = np.array([math.pi + 0.3, omega_max])
    start = np.array([0.0, 0.0])
    goals = np.array([[math.pi, 0.0], [-math.pi, 0.0]])
    X = np.vstack([start, goals, rng.uniform(lo, hi, size=(nodes, 2))])
    # broad phase: the curve must end near the drift endpoint; scale axes to the torque's reach
    drift_end = rc._drift_flow(model, X, np.array([tau]))[:, 0]
    # (the input moves the end at most a tau^2 / 2 in theta and a tau in omega off the flow)
    accel = u_max / (MASS * LENGTH**2)
    scale = np.array([2.0 / (accel * tau**2), 1.0 / (accel * tau)])
    tree = cKDTree(X * scale)
    cand = tree.query_ball_point(drift_end * scale, r=BROAD_PHASE_RADIUS)
    i = np.repeat(np.arange(len(X)), [len(c) for c in cand])
    j = np.concatenate([np.asarray(c, dtype=np.int64) for c in cand])
    keep = i != j
    i, j = i[keep], j[keep]
    table = reach.edge_table(X)
    ok = table.test_pairs(i, j)
    i, j = i[ok], j[ok]
    graph = csr_matrix((np.ones(len(i)), (i, j)), shape=(len(X), len(X)))
    dist, pred = dijkstra(graph, directed=True, indices=0, return_predecessors=True)
    goal = 1 + int(np.argmin(dist[1:3]))
    build_s = time.perf_counter() - t_start
    if not np.isfinite(dist[goal]):
        return SwingupResult(u_max, False, 0, len(X), len(i), build_s, np.zeros((0, 2)), np.zeros((0, 4, 1)), tau, 0.0, 0.0)
    path = [goal]
    while path[-1] != 0:
        path.append(int(pred[path[-1]]))
    states = X[path[::-1]]
    curves = reach.curve(states[:-1], states[1:])
    torque, omega = torque_along(curves, tau)
    return SwingupResult(
        u_max=u_max, found=True, segments=len(states) - 1, nodes=len(X), edges=len(i), build_s=build_s,
        path=states, curves=curves, tau=tau,
        max_torque=float(np.abs(torque).max()), max_speed=float(np.abs(omega).max()),
    )  # fmt: skip


def plot(results: list[SwingupResult], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(results), 1, figsize=(7, 3.2 * len(results)), squeeze=False)
    for ax, res in zip(axes[:, 0], results):
        if res.found:
            t = np.linspace(0, res.tau, 50)
            th = bz.evaluate(res.curves, res.tau, t)[..., 0]
            om = bz.evaluate(bz.derivative_points(res.curves, res.tau, 1), res.tau, t)[..., 0]
            ax.plot(th.T, om.T, color="tab:blue", lw=1)
            ax.plot(res.path[:, 0], res.path[:, 1], ".", color="k", ms=3)
        ax.set_title(f"u_max = {res.u_max} N m: {res.segments} segments ({res.segments * res.tau:.2f} s)")
        ax.set_xlabel("theta [rad]")
        ax.set_ylabel("omega [rad/s]")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


# (u_max [N m], nodes, tau [s]): tighter limits shrink each reachable polytope, so they
# need denser nodes and shorter segments to stay connected
PRESETS = ((5.0, 4000, 0.15), (1.0, 20000, 0.15), (0.75, 40000, 0.1))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--u-max", type=float, help="one torque limit [N m] (default: the three presets)")
    parser.add_argument("--nodes", type=int, default=20000)
    parser.add_argument("--tau", type=float, default=0.15, help="segment duration [s]")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--plot", help="write a figure like thesis Figure 6.6")
    args = parser.parse_args(argv)
    runs = PRESETS if args.u_max is None else ((args.u_max, args.nodes, args.tau),)
    results = [swing_up(u, nodes=n, tau=tau, seed=args.seed) for u, n, tau in runs]
    for r in results:
        print(
            f"u_max {r.u_max:5.2f} N m: found={r.found} segments={r.segments} ({r.segments * r.tau:.2f} s) "
            f"nodes={r.nodes} edges={r.edges} build={r.build_s:.1f} s "
            f"max |torque| on path={r.max_torque:.3f} N m, max |omega|={r.max_speed:.2f} rad/s"
        )
    if args.plot:
        plot(results, args.plot)
    sound = all(r.max_torque <= r.u_max + 1e-9 for r in results if r.found)
    return 0 if sound and all(r.found for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
