"""Bezier MPC on the nonlinear system of thesis section 6.1, with a tracking low level.

    x1' = x2,    x2' = sin(x1) + x2^3 + u + w(t)

Goal: drive the state to the origin with ``|x1| <= 2.5``, ``|x2| <= 1`` and ``|u| <= u_max``
for all time (thesis Figure 6.2). The high level is the Bezier MPC of eq. 6.12 over the
planning model without ``w`` (Lipschitz input bounds, Lemma 6.1 / Theorem 6.2, references
on each segment); it replans every segment ``tau`` from the measured state. The low level
tracks the current Bezier segment by feedback linearization with PD on the error, at
1 kHz, against the disturbance ``w``. The planning limits are tightened by the tube the
low level keeps (dual-norm tightening), so the closed loop stays inside the true limits.

For comparison the same low level alone (PD to the origin, no plan) violates both the
state and the input limit. Run: ``.venv/bin/python examples/nonlinear_bezier_mpc.py``.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass

import numpy as np

from onboard.geometry import bezier as bz
from onboard.high_level.tracking import reachability as rc
from onboard.high_level.tracking.bezier_mpc import BezierMpc, MpcWeights

X1_MAX = 2.5  # state limits of the closed loop
X2_MAX = 1.0
U_MAX = 6.0  # actuator limit of the closed loop
U_PLAN = 4.0  # planning input bound: the rest is left to the tracking feedback
TUBE = (0.02, 0.1)  # tracking error bound the low level keeps on (x1, x2) under W_AMP
W_AMP = 0.3  # disturbance amplitude on x2'
KP, KD = 400.0, 40.0  # low-level PD gains (critically damped, 20 rad/s)
DT = 1e-3  # [s] low-level period
TAU = 0.2  # [s] segment duration
HORIZON = 10  # segments (2 s)
DIVERGED = 10.0  # |x| past this (four times the state limit) ends a run: it has left every limit for good


def drift(x: np.ndarray) -> np.ndarray:
    return (np.sin(x[..., 0]) + x[..., 1] ** 3)[..., None]


def planning_model() -> rc.PlanningModel:
    # |d f / d x1| <= 1, |d f / d x2| = 3 x2^2 <= 3 X2_MAX^2 on the state set
    return rc.PlanningModel(1, 2, drift=drift, lipschitz_drift=np.array([[1.0, 3.0 * X2_MAX**2]]), name="section_6_1")


def disturbance(t: float) -> float:
    return W_AMP * np.sin(3.0 * t)


def plant_step(x: np.ndarray, u: float, t: float) -> np.ndarray:
    """One RK4 step of the true system (with the disturbance)."""

    def fx(xx, tt):
        return np.array([xx[1], np.sin(xx[0]) + xx[1] ** 3 + u + disturbance(tt)])

    k1 = fx(x, t)
    k2 = fx(x + 0.5 * DT * k1, t + 0.5 * DT)
    k3 = fx(x + 0.5 * DT * k2, t + 0.5 * DT)
    k4 = fx(x + DT * k3, t + DT)
    return x + DT / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)


def nominal_reference(x0: np.ndarray, steps: int) -> np.ndarray:
    """A slow, feasible first guess: the planning model under a gentle linearizing PD."""
    ref = [x0.copy()]
    x = x0.copy()
    for _ in range(steps):
        for _ in range(int(round(TAU / DT))):
            v = -1.0 * x[0] - 2.0 * x[1]
            u = np.clip(v - np.sin(x[0]) - x[1] ** 3, -0.5 * U_PLAN, 0.5 * U_PLAN)
            x = x + DT * np.array([x[1], np.sin(x[0]) + x[1] ** 3 + u])
        ref.append(x.copy())
    return np.array(ref)


@dataclass
class RunLog:
    t: np.ndarray
    x: np.ndarray  # (T, 2) closed-loop states
    u: np.ndarray  # (T,) applied inputs
    planned: list[np.ndarray]  # control points of every segment that was tracked
    planned_max_input: float  # largest planning input over all tracked segments, densely sampled
    replans: int
    certified: int

    @property
    def max_abs(self) -> dict[str, float]:
        return {"x1": float(np.abs(self.x[:, 0]).max()), "x2": float(np.abs(self.x[:, 1]).max()), "u": float(np.abs(self.u).max())}


def run_bezier_mpc(x0: np.ndarray, duration: float, backend: str = "osqp", track: bool = True) -> RunLog:
    """The Bezier MPC replanning every segment; ``track=False`` applies each plan's own input with
    no low level under it (thesis Figure 6.2, 'MPC only'): the disturbance then moves the state off
    the plan, and a replan that finds no certified plan from there ends the run early."""
    model = planning_model()
    limits = rc.box_limits(model, U_PLAN, [-X1_MAX + TUBE[0], -X2_MAX + TUBE[1]], [X1_MAX - TUBE[0], X2_MAX - TUBE[1]])
    reach = rc.BezierReachability(model, limits, TAU, refinement=2)
    mpc = BezierMpc(
        reach, HORIZON, MpcWeights(state=(1.0, 0.1), terminal=(10.0, 1.0), effort=1e-3),
        trust_region=[0.3, 0.3], terminal="free", backend=backend, polish=False,
        unit_rows=False, eps=1e-5, max_iter=20000,
    )  # fmt: skip
    ref = nominal_reference(x0, HORIZON)
    x = x0.copy()
    t = 0.0
    ts, xs, us, planned = [], [], [], []
    certified = replans = 0
    pending: list[np.ndarray] = []  # remaining segments of the last certified plan
    steps_per_seg = int(round(TAU / DT))
    origin = np.zeros_like(ref)
    while t < duration - 1e-9:
        # eq. 6.12: cost to the origin, trust region around a feasible reference
        sol = mpc.solve(x, ref, target=origin, warm_start=ref)
        replans += 1
        if sol.ok:
            certified += 1
            pending = list(sol.control_points)
            ref = np.vstack([sol.waypoints[1:], nominal_reference(sol.waypoints[-1], 1)[1:]])
        else:
            if not pending and not track:
                break  # the MPC alone lost its plan: what happened so far is the result
            if not pending:
                raise RuntimeError(f"no certified plan from {x}: {sol.status}")
            ref = np.vstack([ref[1:], nominal_reference(ref[-1], 1)[1:]])
        plan = pending.pop(0)
        planned.append(plan)
        q = plan[None]
        dq = bz.derivative_points(q, TAU, 1)
        ddq = bz.derivative_points(q, TAU, 2)
        for k in range(steps_per_seg):
            s = k * DT
            qd = bz.evaluate(q, TAU, s)[0, 0]
            vd = bz.evaluate(dq, TAU, s)[0, 0]
            ad = bz.evaluate(ddq, TAU, s)[0, 0]
            if track:  # feedback linearization of the known model, PD on the tracking error
                u = ad - np.sin(x[0]) - x[1] ** 3 - KP * (x[0] - qd) - KD * (x[1] - vd)
            else:  # the plan's own input: what the planning model says the curve needs
                u = ad - np.sin(qd) - vd**3
            ts.append(t)
            xs.append(x.copy())
            us.append(u)
            x = plant_step(x, u, t)
            t += DT
            if not np.all(np.abs(x) < DIVERGED):
                break
        if not np.all(np.abs(x) < DIVERGED):
            break  # open loop on an unstable system (x2' grows with x2^3): the state is gone
    planned_arr = np.array(planned)
    tt = np.linspace(0.0, TAU, 200)
    xq = bz.state_values(planned_arr, TAU, 2, tt)
    aq = bz.evaluate(bz.derivative_points(planned_arr, TAU, 2), TAU, tt)
    u_plan = model.input(xq, aq)
    return RunLog(np.array(ts), np.array(xs), np.array(us), planned, float(np.abs(u_plan).max()), replans, certified)


def run_low_level_only(x0: np.ndarray, duration: float) -> RunLog:
    """The same linearizing PD aimed straight at the origin (thesis Figure 6.2, 'CLF only')."""
    x = x0.copy()
    ts, xs, us = [], [], []
    t = 0.0
    while t < duration - 1e-9:
        u = -np.sin(x[0]) - x[1] ** 3 - KP * x[0] - KD * x[1]
        ts.append(t)
        xs.append(x.copy())
        us.append(u)
        x = plant_step(x, u, t)
        t += DT
    return RunLog(np.array(ts), np.array(xs), np.array(us), [], np.nan, 0, 0)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--x1", type=float, default=2.0, help="initial x1")
    parser.add_argument("--x2", type=float, default=0.0, help="initial x2")
    parser.add_argument("--duration", type=float, default=8.0, help="[s]")
    args = parser.parse_args(argv)
    x0 = np.array([args.x1, args.x2])
    mpc = run_bezier_mpc(x0, args.duration)
    ll = run_low_level_only(x0, args.duration)
    limits = {"x1": X1_MAX, "x2": X2_MAX, "u": U_MAX}
    for name, log in (("bezier mpc + low level", mpc), ("low level only", ll)):
        worst = log.max_abs
        inside = all(worst[k] <= limits[k] for k in limits)
        print(
            f"{name:24s} max|x1|={worst['x1']:.3f} (<= {X1_MAX})  max|x2|={worst['x2']:.3f} (<= {X2_MAX})  "
            f"max|u|={worst['u']:.2f} (<= {U_MAX})  final |x|={np.linalg.norm(log.x[-1]):.3f}  within limits: {inside}"
        )
    print(f"planning input, densely sampled: {mpc.planned_max_input:.3f} (<= {U_PLAN}); "
          f"replans {mpc.replans}, certified {mpc.certified}")  # fmt: skip
    ok = all(mpc.max_abs[k] <= limits[k] for k in limits) and mpc.planned_max_input <= U_PLAN + 1e-9
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
