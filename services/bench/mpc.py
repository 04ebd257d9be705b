"""The 50-node planner MPC (thesis eq. 7.2) in a receding-horizon loop, and the edge test rate.

MPC: the CoM double integrator with the planner's limits, knot spacing, horizon, trust
region, tube and halfspace budget (``PlannerParams``), tracking a serpentine reference
past circular obstacles. Each tick is what the planner's refine step does: the measured
state moves along the reference with a tracking error inside the tube, the window
advances by whole knots with time, every segment gets halfspaces to its nearest
obstacles computed from the previous solution (so the constraint matrix changes values
every tick), then one :meth:`BezierMpc.solve` (update, warm start, solve, certify). The
figure is the wall time of that call. PIQP solves the same ticks for comparison.

Edge test: ``EdgeTable.test_pairs`` (compiled, early exit) over random node pairs of
the planner graph's segment, and the plain matrix form ``F @ [x_i; x_j] <= G``.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from onboard.high_level.tracking import reachability as rc
from onboard.high_level.planning.bezier_graph import speed_limits
from onboard.high_level.tracking.bezier_mpc import BezierMpc, MpcWeights
from onboard.contracts.params import PlannerParams
from services.planner import REFINE_BUDGET_SHARE

# The planner's refine weights (onboard.high_level.planning.graph_planner): path length dominates tracking.
WEIGHTS = MpcWeights(state=(1.0, 1.0, 0.1, 0.1), terminal=(10.0, 10.0, 1.0, 1.0), effort=0.01, path=50.0)
TICK_S = 0.01  # refine period at 100 Hz
OBSTACLE_RADIUS = 0.3  # [m]
OBSTACLE_CLEARANCE = 0.45  # [m] obstacle centres at least this far from the reference
NOISE_M = 0.002  # [m] position estimate noise per tick


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--ticks", type=int, default=600, help="MPC ticks per backend")
    parser.add_argument("--max-iter", type=int, default=BezierMpc.max_iter, help="OSQP iteration cap (the planner's; the thesis used 50)")
    parser.add_argument("--time-limit-ms", type=float, default=1e3 * REFINE_BUDGET_SHARE / PlannerParams().refine_hz,
                        help="OSQP's time limit per attempt, as the planner service sets it (0: none)")
    parser.add_argument("--nodes", type=int, default=5000, help="graph nodes for the edge test")
    parser.add_argument("--pairs", type=int, default=2_000_000, help="node pairs per edge-test batch")
    parser.add_argument("--seed", type=int, default=0)


def _reference(t: np.ndarray, v: float) -> np.ndarray:
    """Serpentine at up to 0.75 v: x advances at 0.6 v, y weaves at up to 0.45 v; states [x, y, vx, vy].
    Inside the speed octagon with the tube's tightening and the tracking error's speed (at up to
    0.8 v forward and 0.6 v across, 1 v in all, it left it: 12 % of ticks had no answer)."""
    w = 0.5
    amp = 0.45 * v / w
    x, vx = 0.6 * v * t, np.full_like(t, 0.6 * v)
    y, vy = amp * np.sin(w * t), amp * w * np.cos(w * t)
    return np.stack([x, y, vx, vy], axis=-1)


def _obstacles(rng: np.random.Generator, v: float, duration: float) -> np.ndarray:
    """Circle centres along the route, clear of the reference by OBSTACLE_CLEARANCE + radius."""
    path = _reference(np.linspace(0, duration, 2000), v)[:, :2]
    centres = []
    while len(centres) < int(duration):
        c = path[rng.integers(len(path))] + rng.normal(size=2) * 0.8
        if np.min(np.linalg.norm(path - c, axis=1)) > OBSTACLE_CLEARANCE + OBSTACLE_RADIUS:
            centres.append(c)
    return np.array(centres)


def _halfspaces(ctrl: np.ndarray, centres: np.ndarray, count: int, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Per segment, ``count`` halfspaces facing its nearest obstacles (unused: b = inf)."""
    mid = ctrl.mean(axis=1)  # (N, 2)
    d = centres[None, :, :] - mid[:, None, :]  # (N, O, 2)
    dist = np.linalg.norm(d, axis=-1)
    near = np.argsort(dist, axis=1)[:, :count]
    a = np.take_along_axis(d, near[..., None], axis=1) / np.take_along_axis(dist, near, axis=1)[..., None]
    c = centres[near]  # (N, count, 2)
    b = np.einsum("nkd,nkd->nk", a, c) - OBSTACLE_RADIUS - margin
    far = np.take_along_axis(dist, near, axis=1) > 3.0
    b[far] = np.inf
    a[far] = 0.0
    return a, b


def _mpc_loop(mpc: BezierMpc, prm: PlannerParams, centres: np.ndarray, ticks: int, seed: int) -> dict[str, object]:
    rng = np.random.default_rng(seed)
    N, dt = prm.mpc_horizon, prm.mpc_dt
    times_ms, iters, oks, refused = [], [], [], {}
    last = None
    for tick in range(ticks):
        t = tick * TICK_S
        j0 = int(t / dt)
        knots = (j0 + np.arange(N + 1)) * dt
        ref = _reference(knots, prm.v_max)
        # tracking error: a slow swing inside the tube plus estimate noise
        err = 0.6 * prm.tube * np.array([math.sin(1.3 * t), math.cos(0.9 * t)]) + rng.normal(size=2) * NOISE_M
        x = ref[0] + np.concatenate([err, 0.6 * prm.tube * np.array([1.3 * math.cos(1.3 * t), -0.9 * math.sin(0.9 * t)])])
        warm = ref.copy()
        shift = 0
        if last is not None and 0 <= j0 - last[0] <= N:
            shift = j0 - last[0]
            warm[: N + 1 - shift] = last[1][shift:]
        ctrl = mpc.reach.curve(warm[:-1], warm[1:])
        a, b = _halfspaces(ctrl, centres, mpc.max_planes, margin=0.0)
        t0 = time.perf_counter()
        sol = mpc.solve(x, ref, (a, b), shift=shift)
        times_ms.append((time.perf_counter() - t0) * 1e3)
        iters.append(sol.iterations)
        oks.append(sol.ok)
        if not sol.ok:
            refused[sol.status] = refused.get(sol.status, 0) + 1
        last = (j0, sol.waypoints) if sol.ok else None
    return {"times": np.array(times_ms), "iters": np.array(iters), "ok": np.array(oks), "refused": refused}


def _build_mpc(prm: PlannerParams, backend: str, max_iter: int, time_limit_s: float = 0.0) -> BezierMpc:
    inf = math.inf
    md = rc.double_integrator(2)
    reach = rc.BezierReachability(md, speed_limits(prm.a_max, prm.v_max, tube=prm.tube, tube_norm=2), prm.mpc_dt)
    return BezierMpc(
        reach, prm.mpc_horizon, WEIGHTS, trust_region=[prm.mpc_trust, prm.mpc_trust, inf, inf],
        init_radius=[prm.tube, prm.tube, 0.0, 0.0], max_planes=prm.halfspaces, backend=backend, max_iter=max_iter,
        time_limit_s=time_limit_s,
    )  # fmt: skip


def _edge_rate(prm: PlannerParams, nodes: int, pairs: int, seed: int) -> dict[str, float]:
    md = rc.double_integrator(2)
    reach = rc.BezierReachability(md, speed_limits(prm.a_max, prm.v_max, tube=prm.tube), prm.segment_s)
    rng = np.random.default_rng(seed)
    side = math.sqrt(nodes) * 0.3  # about the planner's node density
    X = rng.uniform([0, 0, -prm.v_max, -prm.v_max], [side, side, prm.v_max, prm.v_max], size=(nodes, 4))
    i = rng.integers(0, nodes, pairs)
    j = rng.integers(0, nodes, pairs)
    table = reach.edge_table(X)
    table.test_pairs(i[:10], j[:10])  # compile outside the timing
    t0 = time.perf_counter()
    ok = table.test_pairs(i, j)
    t_table = time.perf_counter() - t0
    chunk = 200_000
    t0 = time.perf_counter()
    ok_mm = np.concatenate([
        np.all(reach.F @ np.concatenate([X[i[s : s + chunk]], X[j[s : s + chunk]]], axis=1).T <= reach.G_const[:, None], axis=0)
        for s in range(0, pairs, chunk)
    ])  # fmt: skip
    t_mm = time.perf_counter() - t0
    if not np.array_equal(ok, ok_mm):
        raise RuntimeError("edge table and matrix form disagree")
    return {
        "edge_tests_per_s": round(pairs / t_table),
        "edge_tests_per_s_matmul": round(pairs / t_mm),
        "edge_rows": int(reach.F.shape[0]),
        "edge_accept_fraction": round(float(ok.mean()), 5),
    }


def measure(args: argparse.Namespace) -> dict[str, object]:
    prm = PlannerParams()
    rng = np.random.default_rng(args.seed)
    duration = args.ticks * TICK_S + prm.mpc_horizon * prm.mpc_dt
    centres = _obstacles(rng, prm.v_max, duration)
    osqp_mpc = _build_mpc(prm, "osqp", args.max_iter, args.time_limit_ms / 1e3)
    runs = {"osqp": _mpc_loop(osqp_mpc, prm, centres, args.ticks, args.seed)}
    runs["piqp"] = _mpc_loop(_build_mpc(prm, "piqp", args.max_iter), prm, centres, args.ticks, args.seed)
    o, q = runs["osqp"], runs["piqp"]
    mean_ms = float(o["times"].mean())
    figures: dict[str, object] = {
        "horizon": prm.mpc_horizon,
        "variables": osqp_mpc.nvar,
        "constraints": osqp_mpc.n_rows,
        "ticks": args.ticks,
        "solve_ms_p50": round(float(np.percentile(o["times"], 50)), 3),
        "solve_ms_p99": round(float(np.percentile(o["times"], 99)), 3),
        "solve_ms_max": round(float(o["times"].max()), 3),
        "rate_hz": round(1000.0 / mean_ms, 1),
        "iterations_p50": int(np.percentile(o["iters"], 50)),
        "iterations_p99": int(np.percentile(o["iters"], 99)),
        "certified_fraction": round(float(o["ok"].mean()), 4),
        "refused": o["refused"],  # every tick not certified, by the solver's stated reason
        "time_limit_ms": args.time_limit_ms,
        "piqp_solve_ms_p50": round(float(np.percentile(q["times"], 50)), 3),
        "piqp_solve_ms_p99": round(float(np.percentile(q["times"], 99)), 3),
        "piqp_certified_fraction": round(float(q["ok"].mean()), 4),
        "piqp_refused": q["refused"],
    }
    figures.update(_edge_rate(prm, args.nodes, args.pairs, args.seed))
    return figures
