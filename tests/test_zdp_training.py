"""The thesis's Algorithm 2 (offline/ilqr.py, offline/mlp_training.py, offline/zdp_training.py,
archer train zdp): iLQR with box bounds, the optimal input's gradient, the invariance loss and
its gradient, training, and the written weights driving the robot in the twin."""

from __future__ import annotations

import copy
import dataclasses
import importlib.util
import itertools
import json
import math

import numpy as np
import pytest

from offline import ilqr
from offline import mlp_training as mt
from offline import zdp_training as zt
from onboard.contracts.params import ControlParams
from robot_description.params import hopper_model

# --- iLQR on a pendulum: cheap, nonlinear, and its torque bound binds ---------------------------

DT, GRAV_OVER_L, DAMP = 0.05, 9.81, 0.1  # [s], [1/s^2], [1/s]


class Pendulum:
    """x = (angle from upright [rad], rate [rad/s]), u = torque / inertia [rad/s^2]; explicit Euler."""

    def step(self, x, u):
        th, om = x[:, 0], x[:, 1]
        return np.column_stack((th + DT * om, om + DT * (GRAV_OVER_L * np.sin(th) - DAMP * om + u[:, 0])))

    def jacobians(self, x, u):
        n = x.shape[0]
        a = np.zeros((n, 2, 2))
        a[:, 0, 0] = 1.0
        a[:, 0, 1] = DT
        a[:, 1, 0] = DT * GRAV_OVER_L * np.cos(x[:, 0])
        a[:, 1, 1] = 1.0 - DT * DAMP
        b = np.zeros((n, 2, 1))
        b[:, 1, 0] = DT
        return a, b


Q, R, P = np.diag([10.0, 1.0]), np.eye(1) * 0.1, np.diag([100.0, 10.0])
HORIZON = 30


def _solve(x0, lo, hi, iterations=30):
    dyn = Pendulum()
    u0 = np.zeros((x0.shape[0], HORIZON, 1))
    x_init = ilqr.rollout(dyn, x0, u0)
    return ilqr.ilqr(dyn, x_init, u0, Q, R, P, np.array([lo]), np.array([hi]),
                     ilqr.IlqrSettings(iterations=iterations, converged_rel=1e-12))


def test_box_qp_is_the_exact_minimiser():
    rng = np.random.default_rng(0)
    n = 50
    a = rng.normal(size=(n, 2, 2))
    h = a @ np.transpose(a, (0, 2, 1)) + 0.1 * np.eye(2)
    g = rng.normal(size=(n, 2)) * 3.0
    lo, hi = -np.ones((n, 2)), np.ones((n, 2))
    d, free = ilqr.box_qp(h, g, lo, hi)
    assert np.all(d >= lo - 1e-12) and np.all(d <= hi + 1e-12)
    grid = np.array(list(itertools.product(np.linspace(-1, 1, 201), repeat=2)))  # brute force on a 0.01 grid
    obj = 0.5 * np.einsum("gi,nij,gj->ng", grid, h, grid) + g @ grid.T
    best = obj.min(axis=1)
    mine = 0.5 * np.einsum("ni,nij,nj->n", d, h, d) + np.einsum("ni,ni->n", g, d)
    assert np.all(mine <= best + 1e-9)
    assert np.array_equal(free, (np.abs(d) < 1.0 - 1e-9))  # free exactly where not on a bound


def test_ilqr_lowers_the_cost_and_keeps_the_box():
    x0 = np.array([[0.6, 0.0], [-0.3, 1.0], [0.05, 0.0]])
    res = _solve(x0, -4.0, 4.0)
    hist = res.cost_history
    assert np.all(np.diff(hist, axis=0) <= 1e-12)  # never worse
    assert np.all(hist[-1] < 0.5 * hist[0])  # far better than doing nothing (it falls over)
    assert np.all(res.u >= -4.0) and np.all(res.u <= 4.0)
    assert not res.free[0, 0, 0]  # the big swing-up needs the whole torque at first: on the bound
    assert np.all(res.gains[~res.free] == 0.0)


def test_feedback_gain_is_the_optimal_inputs_gradient_where_no_bound_is_active():
    x0 = np.array([0.05, -0.1])
    h = 1e-5
    rows = [x0] + [x0 + s * h * e for e in np.eye(2) for s in (1.0, -1.0)]
    res = _solve(np.array(rows), -4.0, 4.0)
    assert res.free[0, 0, 0]
    fd = np.array([(res.u[1 + 2 * j, 0, 0] - res.u[2 + 2 * j, 0, 0]) / (2 * h) for j in range(2)])
    # iLQR's gain drops the dynamics' curvature (Gauss-Newton): exact up to that
    assert np.allclose(res.gains[0, 0, 0], fd, rtol=0.02, atol=1e-3)


# --- the network's arithmetic ------------------------------------------------------------------


def test_backprop_and_input_jacobian_match_finite_differences():
    rng = np.random.default_rng(1)
    w = mt.init_weights((4, 16, 16, 2), rng)
    x = rng.normal(size=(5, 4))
    g_out = rng.normal(size=(5, 2))
    out, acts = mt.forward(w, x)
    grads = mt.backward(w, acts, g_out)
    h = 1e-6
    for k, idx in (("W0", (3, 1)), ("b1", (7,)), ("W2", (1, 5)), ("b2", (0,))):
        wp, wm = copy.deepcopy(w), copy.deepcopy(w)
        wp[k][idx] += h
        wm[k][idx] -= h
        fd = (np.sum(g_out * mt.forward(wp, x)[0]) - np.sum(g_out * mt.forward(wm, x)[0])) / (2 * h)
        assert fd == pytest.approx(grads[k][idx], rel=1e-5, abs=1e-8)
    jac = mt.input_jacobian(w, acts)
    for j in range(4):
        e = np.zeros(4)
        e[j] = h
        fd = (mt.forward(w, x + e)[0] - mt.forward(w, x - e)[0]) / (2 * h)
        assert np.allclose(jac[:, :, j], fd, atol=1e-6)


# --- Algorithm 2 on the reduced hopper ---------------------------------------------------------


@pytest.fixture(scope="module")
def hopper_problem():
    params = ControlParams()
    settings = zt.Alg2Settings(pretrain_steps=300, horizon=3)  # a hop shorter than the default: faster, same algorithm
    problem = zt.make_problem(params, hopper_model("indoor"), settings)
    from services.cli.train_zdp_alg2 import raibert_policy

    scales = zt.Scales.for_problem(problem)
    w, _ = zt.pretrain(problem, raibert_policy(params), scales, settings, np.random.default_rng(0))
    return problem, scales, w


def test_hopper_ilqr_gain_is_the_gradient_of_the_optimal_impact_attitude(hopper_problem):
    problem, _, _ = hopper_problem
    converged = dataclasses.replace(problem, ilqr=dataclasses.replace(problem.ilqr, iterations=30))
    z = np.array([0.1, -0.05, 0.2, 0.1])
    eta = np.array([-0.03, 0.01])
    h = 1e-3  # [rad]
    etas = [eta] + [eta + s * h * e for e in np.eye(2) for s in (1.0, -1.0)]
    sol = zt.solve_batch(converged, np.array(etas), np.tile(z, (5, 1)))
    assert sol.ok.all() and sol.free0[0].all()
    assert np.all(np.abs(sol.v0) <= problem.bound)
    fd = np.column_stack([(sol.v0[1 + 2 * j] - sol.v0[2 + 2 * j]) / (2 * h) for j in range(2)])
    assert np.allclose(sol.dv0_deta0[0], fd, rtol=0.02, atol=0.01)
    assert np.all(sol.cost <= sol.cost_initial + 1e-12)


def test_the_box_binds_and_its_inputs_have_no_gradient(hopper_problem):
    problem, _, _ = hopper_problem
    z = np.array([[0.2, 0.0, 0.5, 0.0]])  # far out and moving away: the LQR asks for more tilt than allowed
    sol = zt.solve_batch(problem, np.zeros((1, 2)), z)
    assert sol.ok[0] and not sol.free0[0, 0]
    assert sol.v0[0, 0] == pytest.approx(-problem.bound)
    assert np.all(sol.dv0_deta0[0, 0] == 0.0)


def test_invariance_loss_gradient_matches_a_directional_difference(hopper_problem):
    problem, scales, w = hopper_problem
    z = zt.sample_domain(problem, 4, np.random.default_rng(5))

    def loss(weights):
        sol = zt.solve_batch(problem, zt.policy(weights, scales, z), z)
        return zt.invariance_loss(weights, scales, z, sol)

    l0, grads, _ = loss(w)
    norm = math.sqrt(sum(float((g * g).sum()) for g in grads.values()))
    eps = 1e-3  # along the unit gradient direction
    lp = loss({k: w[k] + eps * grads[k] / norm for k in w})[0]
    lm = loss({k: w[k] - eps * grads[k] / norm for k in w})[0]
    assert (lp - lm) / (2 * eps) == pytest.approx(norm, rel=0.1)


def test_a_few_iterations_lower_the_invariance_loss_on_a_fixed_batch(hopper_problem):
    problem, scales, w0 = hopper_problem
    w = copy.deepcopy(w0)
    z = zt.sample_domain(problem, 8, np.random.default_rng(7))
    opt = mt.Adam()
    losses = [zt.train_iteration(w, opt, problem, scales, z, 3e-4)[0] for _ in range(3)]
    assert losses[-1] < 0.7 * losses[0]


# --- the command: weights the controller loads, and the robot hops on them ----------------------


def test_archer_train_zdp_writes_weights_the_controller_flies(tmp_path):
    from robot_description.controller import build_controller, load_policy_weights
    from services.cli.main import main
    from sim_twin.lockstep import LockstepRunner, RunConfig

    out = tmp_path / "alg2.npz"
    assert main(["train", "zdp", "--iterations", "2", "--batch", "4", "--horizon", "2", "--pretrain-steps", "100",
                 "--validation", "2", "--validate-every", "0", "--workers", "0", "--out", str(out), "--json"]) == 0
    w = load_policy_weights(str(out))
    meta = json.loads(str(w["meta_settings"]))
    assert meta["settings"]["batch"] == 4 and meta["settings"]["horizon"] == 2
    assert w["meta_loss_history"].shape == (2,) and np.isfinite(w["meta_loss_history"]).all()
    assert w["meta_validation_loss"].shape == (2,)
    assert (tmp_path / "alg2_loss.png").stat().st_size > 0
    params = dataclasses.replace(ControlParams(), policy="mlp", mlp_weights=str(out))
    assert build_controller("indoor", params)._mlp.n_in == 4
    res = LockstepRunner(RunConfig(scenario="hop-in-place", seed=0, duration_s=2.0, control_params=params)).run()
    assert res.metrics["falls"] == 0 and res.metrics["hops"] >= 4


@pytest.mark.parametrize("engine", ["local", pytest.param("ray", marks=pytest.mark.skipif(
    importlib.util.find_spec("ray") is None, reason="Ray is the optional extra .[cluster]"))])
def test_the_batch_solved_on_the_campaigns_pool_is_the_batch_solved_in_process(hopper_problem, engine):
    """On a local pool and on a private Ray instance (``archer train zdp --ray local``); Ray is not
    imported here first: imported before the pool, it would fix its node address off loopback."""
    from services.cli.campaign_pool import LocalPool, RayPool
    from services.cli.train_zdp_alg2 import PoolSolver

    problem, scales, w = hopper_problem
    short = dataclasses.replace(problem, horizon=2)
    z = zt.sample_domain(problem, 4, np.random.default_rng(11))
    eta0 = zt.policy(w, scales, z)
    here = zt.solve_batch(short, eta0, z)
    with (LocalPool(2) if engine == "local" else RayPool("local", 2)) as pool:
        there = PoolSolver(pool, 2)(short, eta0, z)
    for f in ("v0", "z1", "dv0_deta0", "dz1_deta0", "free0", "ok", "cost"):
        assert np.array_equal(getattr(here, f), getattr(there, f)), f


def test_compare_metrics_time_to_goal_and_overshoot():
    from services.cli.zdp_compare import ARRIVE_M, scenario_metrics
    from sim_twin import scenarios as sc

    t = np.arange(0.0, 10.0, 0.01)
    x = np.interp(t, [0.0, 5.0, 7.0, 10.0], [0.0, 2.3, 2.0, 2.0])  # past the 2 m goal by 0.3 m, back at t = 7 s
    com = np.column_stack((x, np.zeros_like(t), np.zeros_like(t)))
    got = scenario_metrics("setpoint", None, t, com, (2.0, 0.0), 10.0)
    assert got["overshoot_m"] == pytest.approx(0.3, abs=0.01)
    back = t[np.flatnonzero(np.abs(x - 2.0) > ARRIVE_M)[-1] + 1]
    assert got["time_to_goal_s"] == pytest.approx(back)
    push = sc.make("push", seed=0)
    bump = np.where((t > push.FIRST) & (t < push.FIRST + 0.5), 0.25, 0.0)  # out 0.25 m for 0.5 s after the push
    got = scenario_metrics("push", push, t, np.column_stack((bump, 0 * t, 0 * t)), (0.0, 0.0), 10.0)
    assert got["overshoot_m"] == pytest.approx(0.25) and got["pushes"] == 1
    assert got["time_to_goal_s"] == pytest.approx(0.5, abs=0.02)
