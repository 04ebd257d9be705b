"""The geometric MPC (thesis 5.3): its Lie-algebra linearization against finite differences
of the Pinocchio dynamics, its mode schedule, and its QP across OSQP and PIQP."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pinocchio as pin
import pytest

from onboard.low_level.planning import geometric_mpc as gm
from onboard.geometry import quaternion as qt
from onboard.contracts.params import GeometricMpcParams
from robot_description.hopper_dynamics import HopperDynamics, stance_half_period
from robot_description.params import FOOT_JOINT, robot_params

VARIANT = "sim15nm"


@pytest.fixture(scope="module")
def dyn() -> HopperDynamics:
    return HopperDynamics(VARIANT)


def _state(rng: np.random.Generator, stance: bool) -> np.ndarray:
    """A tilted, turning, moving state; in stance the spring compressed."""
    x = np.zeros(21)
    x[0:3] = rng.normal(0.0, 0.1, 3) + [0.0, 0.0, 0.5]
    x[3:7] = qt.mul(qt.from_euler(*rng.normal(0.0, 0.2, 3)), (1.0, 0.0, 0.0, 0.0))
    x[7:10] = rng.normal(0.0, 1.0, 3)
    x[10] = 0.03 if stance else 0.02
    x[11:14] = rng.normal(0.0, 0.5, 3)
    x[14:17] = rng.normal(0.0, 1.0, 3)
    x[17:20] = rng.normal(0.0, 50.0, 3)
    x[20] = rng.normal(0.0, 0.3) if stance else 0.0
    return x


@pytest.mark.parametrize("mode", [gm.FLIGHT, gm.STANCE])
def test_flow_jacobians_match_finite_differences_in_the_lie_algebra(dyn, mode):
    """A (eq. 5.20: d z_dot / d(dp, eta, ...), eta the attitude perturbation q exp(eta)) and B."""
    rng = np.random.default_rng(1)
    for _ in range(3):
        x = _state(rng, mode == gm.STANCE)
        u = rng.normal(0.0, 2.0, 3)
        f, a, b = dyn.flow(mode, x, u)
        eps = 1e-6
        fd_a = np.column_stack([
            (dyn.flow(mode, dyn.retract(x, eps * e), u)[0] - dyn.flow(mode, dyn.retract(x, -eps * e), u)[0]) / (2 * eps)
            for e in np.eye(gm.STATE_DIM)
        ])
        fd_b = np.column_stack([(dyn.flow(mode, x, u + eps * e)[0] - dyn.flow(mode, x, u - eps * e)[0]) / (2 * eps) for e in np.eye(3)])
        scale = 1.0 + np.abs(fd_a).max()
        assert np.abs(a - fd_a).max() < 1e-5 * scale, np.unravel_index(np.abs(a - fd_a).argmax(), a.shape)
        assert np.abs(b - fd_b).max() < 1e-5 * (1.0 + np.abs(fd_b).max())
        assert np.abs(fd_a[:, 3:6]).max() > 1e-2  # the attitude columns carry something to check


def test_flight_falls_freely_with_the_foot_held_and_stance_rests_on_the_spring(dyn):
    rng = np.random.default_rng(2)
    model, data = dyn.model, dyn.data
    g = robot_params(VARIANT).gravity
    for _ in range(3):
        x = _state(rng, stance=False)
        a = dyn.acceleration(gm.FLIGHT, x, rng.normal(0.0, 5.0, 3))
        assert abs(a[9]) < 1e-9  # the cable holds the spring
        pin.centerOfMass(model, data, dyn.configuration(x), x[11:], a)
        assert np.allclose(data.acom[0], [0.0, 0.0, -g], atol=1e-9)  # whatever the wheels do
    rest = np.zeros(21)
    rest[3] = 1.0
    rest[10] = robot_params(VARIANT).sprung_mass * g / dyn.spring_k  # the static compression
    assert np.abs(dyn.acceleration(gm.STANCE, rest, np.zeros(3))).max() < 1e-9


def _tip_velocity(dyn: HopperDynamics, x: np.ndarray) -> np.ndarray:
    foot = dyn.model.getJointId(FOOT_JOINT)
    pin.forwardKinematics(dyn.model, dyn.data, dyn.configuration(x), x[11:])
    return pin.getVelocity(dyn.model, dyn.data, foot, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED).linear


@pytest.mark.parametrize("edge", [gm.TOUCHDOWN, gm.LIFTOFF])
def test_jump_jacobians_match_finite_differences(dyn, edge):
    rng = np.random.default_rng(3)
    x = _state(rng, stance=edge == gm.LIFTOFF)
    if edge == gm.TOUCHDOWN:
        x[13] = -1.5  # falling
    x_plus, d = dyn.jump(edge, x)
    eps = 1e-6
    fd = np.column_stack([
        (dyn.difference(x_plus, dyn.jump(edge, dyn.retract(x, eps * e))[0]) - dyn.difference(x_plus, dyn.jump(edge, dyn.retract(x, -eps * e))[0])) / (2 * eps)
        for e in np.eye(gm.STATE_DIM)
    ])
    assert np.abs(d - fd).max() < 1e-5 * (1.0 + np.abs(fd).max())
    if edge == gm.TOUCHDOWN:
        assert np.abs(_tip_velocity(dyn, x)).max() > 1.0
        assert np.abs(_tip_velocity(dyn, x_plus)).max() < 1e-9  # plastic: the tip stops
    else:
        assert abs(x_plus[20]) < 1e-12  # the stop locks the foot
    assert np.array_equal(x_plus[:11], x[:11])  # impacts change velocities only


# --- mode schedule ----------------------------------------------------------------------------


def test_time_to_liftoff_matches_the_oscillator_it_models():
    omega, g = 46.0, 9.81
    rest = g / omega**2
    for l0, ld0 in [(0.0, 1.5), (0.03, 0.0), (0.04, -0.5), (0.01, -1.0)]:
        t = gm.time_to_liftoff(l0, ld0, omega, g, nominal=-1.0)
        y0 = l0 - rest
        l_t = rest + y0 * math.cos(omega * t) + ld0 / omega * math.sin(omega * t)
        ld_t = -omega * y0 * math.sin(omega * t) + ld0 * math.cos(omega * t)
        assert abs(l_t) < 1e-9 and ld_t < 0.0  # back at full extension, extending
        assert 0.0 < t < 2 * math.pi / omega
    assert gm.time_to_liftoff(rest, 0.0, omega, g, nominal=0.07) == 0.07  # at rest: never lifts off


def test_mode_schedule_follows_the_predicted_impacts():
    p = GeometricMpcParams()
    knots = gm.mode_schedule(gm.FLIGHT, 0.13, p, flight_time=0.3, stance_time=0.065)
    assert len(knots) == p.horizon
    kinds = [k.kind for k in knots]
    td = kinds.index(gm.TOUCHDOWN)
    assert set(kinds[:td]) == {gm.FLIGHT} and knots[td].t == pytest.approx(0.13)
    lo = kinds.index(gm.LIFTOFF)
    assert set(kinds[td + 1 : lo]) == {gm.STANCE}
    assert knots[lo].t - knots[td].t == pytest.approx(0.065)
    assert all(k.h <= p.stance_step_s + 1e-12 for k in knots[td + 1 : lo])
    assert all(k.h >= p.min_step_s for k in knots if not k.is_jump)
    # an impact due now comes first
    assert gm.mode_schedule(gm.FLIGHT, 0.0, p, 0.3, 0.065)[0].kind == gm.TOUCHDOWN


# --- the QP -----------------------------------------------------------------------------------


def _problem(dyn: HopperDynamics, seed: int, mode: str):
    rng = np.random.default_rng(seed)
    p = GeometricMpcParams()
    x0 = _state(rng, mode == gm.STANCE)
    x0[13] = -1.0 if mode == gm.FLIGHT else x0[13]
    x0[17:20] *= 0.1
    event = 0.12 if mode == gm.FLIGHT else gm.time_to_liftoff(x0[10], x0[20], 46.0, 9.81, 0.065)
    knots = gm.mode_schedule(mode, event, p, 0.3, stance_half_period(VARIANT))
    targets = np.tile(x0[0:3] + [0.2, -0.1, 0.0], (p.horizon + 1, 1))
    z_ref = gm.reference_states(x0[3:7], targets, np.zeros((p.horizon + 1, 3)), (1.0, 0.0, 0.0, 0.0))
    return p, x0, knots, z_ref


COST_AGREEMENT_EPS = 10  # the two objectives agree to this many relative solver tolerances


def _qp_point(sol: gm.GmpcSolution) -> np.ndarray:
    return np.concatenate([sol.z.ravel(), sol.u.ravel()])


def _qp_objective(mpc: gm.GeometricMpc, w: np.ndarray, z_ref: np.ndarray) -> float:
    """The QP's own objective at w, 1/2 w'Pw + q'w, with the q that ``solve`` builds from z_ref."""
    q = np.concatenate([-2.0 * (mpc.q_diag * z_ref).ravel(), np.zeros(w.size - z_ref.size)])
    return float(0.5 * w @ (mpc.P @ w) + q @ w)


@pytest.mark.parametrize("mode", [gm.FLIGHT, gm.STANCE])
@pytest.mark.parametrize("limit", [15.0, 1.5])
def test_osqp_and_piqp_agree_on_a_feasible_answer(dyn, mode, limit):
    """One SQP iteration: both solvers answer the very same QP (a second iteration would
    linearize about two slightly different first answers).

    What two correct solvers must agree on, from their own tolerances rather than one CPU's
    last bits: each answer satisfies the constraints; the costs agree; and the answers are
    close in the QP's own metric. The QP is strongly convex (P > 0), so a feasible w whose
    objective is within g of the optimum lies within ||w - w*||_P <= sqrt(2 g) of it
    (f(w) - f* >= 1/2 (w - w*)'P(w - w*) at a constrained optimum), and the two answers within
    sqrt(2 g_osqp) + sqrt(2 g_piqp). PIQP's dual objective bounds f* from below (weak
    duality); each solver stops with its gap within eps (absolute and relative), which the
    lower bound may miss by as much, and OSQP's answer, feasible to its residual tolerance only,
    may lie below f*: g = |f(w) - dual| + eps (1 + |dual|). The costs agree to
    COST_AGREEMENT_EPS solver tolerances (measured: 2.5e-5 relative at most, eps 1e-5). The inputs, weighted
    only weight_input, are the least determined part of w: a max-norm bound on them of
    1.5e-3 N m held on one CPU (4e-4 measured) and not on an AVX-512 one (6.9e-3).
    """
    for seed in range(3):
        p, x0, knots, z_ref = _problem(dyn, seed, mode)
        p = dataclasses.replace(p, sqp_iterations=1)
        # ADMM needs thousands of iterations on these stiff equality rows (the reason PIQP is the default)
        mpcs = {"osqp": gm.GeometricMpc(dyn, dataclasses.replace(p, max_qp_iter=40_000), limit, "osqp"),
                "piqp": gm.GeometricMpc(dyn, p, limit, "piqp")}
        sols = {b: mpc.solve(x0, knots, z_ref) for b, mpc in mpcs.items()}
        for b, sol in sols.items():
            assert sol.ok, (b, sol.status)
            assert np.abs(sol.u).max() <= limit + 1e-9  # the input set
            assert np.allclose(sol.z[0], gm.lift(x0, sol.q0), atol=1e-6)  # z_0 = z(t), xi_0 = 0
            assert sol.dynamics_residual < 1e-4
            jumps = [k for k, knot in enumerate(knots) if knot.is_jump]
            assert np.all(sol.u[jumps] == 0.0)
        info = mpcs["piqp"]._solver.result.info
        w = {b: _qp_point(s) for b, s in sols.items()}
        f = {b: _qp_objective(mpcs[b], w[b], z_ref) for b in sols}
        assert f["piqp"] == pytest.approx(info.primal_obj, rel=1e-9)  # the objective recomputed is the solver's
        slack = p.eps * (1.0 + abs(info.dual_obj))
        # ADMM's answer is feasible only to its residual tolerance: its objective may lie below f*
        gap = {b: abs(f[b] - info.dual_obj) + slack for b in sols}
        assert abs(f["osqp"] - f["piqp"]) <= COST_AGREEMENT_EPS * p.eps * abs(f["piqp"])
        dw = w["osqp"] - w["piqp"]
        assert math.sqrt(dw @ (mpcs["piqp"].P @ dw)) <= math.sqrt(2 * gap["osqp"]) + math.sqrt(2 * gap["piqp"])
        if limit == 1.5:
            assert np.abs(sols["piqp"].u).max() > 0.99 * limit  # the bound is active: the test checks a clipped answer


def test_the_answer_moves_toward_the_target_and_its_setpoint_is_the_first_knot(dyn):
    p, x0, knots, z_ref = _problem(dyn, 0, gm.FLIGHT)
    mpc = gm.GeometricMpc(dyn, p, 15.0)
    sol = mpc.solve(x0, knots, z_ref)
    assert sol.ok and len(sol.qp_iterations) == p.sqp_iterations
    q_d, w_d, u_ff = sol.setpoint(knots[0].h)
    assert qt.angle_between(q_d, qt.mul(sol.q0, qt.exp(sol.z[1, gm.XI]))) < 1e-9  # q0 exp(xi_1)
    assert np.allclose(w_d, sol.z[1, gm.OMEGA]) and np.allclose(u_ff, sol.u[0])
    # high in the air, tilted and still, the orientation weighted alone: the plan stands it upright
    p_up = GeometricMpcParams(weight_position=0.0, weight_velocity=0.0)
    tilted = np.zeros(21)
    tilted[2], tilted[10] = 1.5, 0.02
    tilted[3:7] = qt.from_euler(0.3, -0.2, 0.1)
    flight = gm.mode_schedule(gm.FLIGHT, p_up.horizon * p_up.flight_step_s, p_up, 0.3, 0.065)
    assert all(k.kind == gm.FLIGHT for k in flight)
    upright = gm.reference_states(tilted[3:7], np.zeros((p_up.horizon + 1, 3)), np.zeros((p_up.horizon + 1, 3)),
                                  qt.from_axis_yaw((0.0, 0.0, 1.0), qt.yaw_of(tilted[3:7])))
    sol = gm.GeometricMpc(dyn, p_up, 15.0).solve(tilted, flight, upright)
    assert sol.ok
    tilt = [qt.tilt(qt.mul(sol.q0, qt.exp(z[gm.XI]))) for z in sol.z]
    assert tilt[0] > 0.3 and np.all(np.diff(tilt) < 0.0) and tilt[-1] < 0.3 * tilt[0], tilt


def test_bad_input_is_refused_not_solved(dyn):
    p, x0, knots, z_ref = _problem(dyn, 1, gm.FLIGHT)
    mpc = gm.GeometricMpc(dyn, p, 15.0)
    bad = x0.copy()
    bad[12] = math.nan
    sol = mpc.solve(bad, knots, z_ref)
    assert not sol.ok and sol.status == "non-finite input" and np.all(np.isnan(sol.u))
    ref = z_ref.copy()
    ref[3, 0] = math.inf
    assert not mpc.solve(x0, knots, ref).ok
    # an iteration cap too small to converge: refused with the solver's own status
    starved = gm.GeometricMpc(dyn, GeometricMpcParams(max_qp_iter=1), 15.0, "osqp")
    sol = starved.solve(x0, knots, z_ref)
    assert not sol.ok and "max" in sol.status.lower()
    assert mpc.solve(x0, knots, z_ref).ok  # and the solver works again after refusals


def test_the_tilt_bound_holds_the_plan_and_both_backends_agree_on_it(dyn):
    """Moving sideways at 1.2 m/s toward the held place the plan leans 0.26 rad; bounded at
    0.1 rad (the rows linearized about the present attitude) it stays there."""
    x0 = np.zeros(21)
    x0[2], x0[3], x0[10], x0[11], x0[13] = 0.55, 1.0, 0.02, 1.2, -1.0
    held = np.tile([0.0, 0.0, 0.55], (GeometricMpcParams().horizon + 1, 1))
    z_ref = gm.reference_states(x0[3:7], held, np.zeros_like(held), (1.0, 0.0, 0.0, 0.0))

    def max_tilt(p: GeometricMpcParams, backend: str) -> tuple[float, gm.GmpcSolution]:
        knots = gm.mode_schedule(gm.FLIGHT, 0.12, p, 0.3, 0.065)
        sol = gm.GeometricMpc(dyn, p, 15.0, backend).solve(x0, knots, z_ref)
        assert sol.ok, sol.status
        return max(qt.tilt(qt.mul(sol.q0, qt.exp(z[gm.XI]))) for z in sol.z), sol

    free, _ = max_tilt(GeometricMpcParams(), "piqp")
    bounded = GeometricMpcParams(tilt_max_plan=0.1)
    held_piqp, sol_piqp = max_tilt(bounded, "piqp")
    held_osqp, sol_osqp = max_tilt(dataclasses.replace(bounded, max_qp_iter=40_000), "osqp")
    assert free > 0.2 and held_piqp < 0.1 * 1.01 and held_osqp < 0.1 * 1.01
    assert np.abs(sol_piqp.u - sol_osqp.u).max() < 1e-2
