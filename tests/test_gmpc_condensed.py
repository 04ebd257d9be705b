"""The geometric MPC's fast path (issue 29): the QP condensed onto its inputs and solved by an
active-set method, the knots' exponentials compiled; PIQP on the full sparse QP is the
cross-check, at the stack's knots and at the thesis's (Table 5.3)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import piqp
import pytest
import scipy.linalg

from onboard.contracts.params import GMPC_THESIS_KNOTS, GeometricMpcParams, with_overrides
from onboard.low_level.planning import box_qp, gmpc_kernels
from onboard.low_level.planning import geometric_mpc as gm
from robot_description.hopper_dynamics import HopperDynamics, stance_half_period
from test_geometric_mpc import VARIANT, _problem, _qp_objective, _qp_point

COST_AGREEMENT_EPS = 10  # relative solver tolerances, as between OSQP and PIQP (tests/test_geometric_mpc.py)


@pytest.fixture(scope="module")
def dyn() -> HopperDynamics:
    return HopperDynamics(VARIANT)


def _thesis(p: GeometricMpcParams) -> GeometricMpcParams:
    return with_overrides(p, GMPC_THESIS_KNOTS)


@pytest.mark.parametrize("knots", ["default", "thesis"])
@pytest.mark.parametrize("mode", [gm.FLIGHT, gm.STANCE])
@pytest.mark.parametrize("limit", [15.0, 1.5])
def test_the_condensed_qp_and_piqp_agree_on_the_same_qp(dyn, knots, mode, limit):
    """One SQP iteration, so both answer the very same QP. The condensed answer satisfies the
    dynamics exactly (the states are the dynamics' own rollout of its inputs) and its box KKT
    conditions to ``eps``; PIQP's answer is within its own tolerances. The bound is the one
    between OSQP and PIQP (tests/test_geometric_mpc.py): the QP is strongly convex, a feasible
    w within g of the optimum lies within ||w - w*||_P <= sqrt(2 g), g from PIQP's dual
    objective plus its tolerance."""
    for seed in range(3):
        p, x0, _, z_ref = _problem(dyn, seed, mode)
        if knots == "thesis":
            p = _thesis(p)
        p = dataclasses.replace(p, sqp_iterations=1)
        event = 0.12 if mode == gm.FLIGHT else gm.time_to_liftoff(x0[10], x0[20], 46.0, 9.81, 0.065)
        schedule = gm.mode_schedule(mode, event, p, 0.3, stance_half_period(VARIANT))
        mpcs = {b: gm.GeometricMpc(dyn, p, limit, b) for b in ("condensed", "piqp")}
        sols = {b: mpc.solve(x0, schedule, z_ref) for b, mpc in mpcs.items()}
        for b, sol in sols.items():
            assert sol.ok, (b, sol.status)
            assert np.abs(sol.u).max() <= limit + 1e-9
            assert np.allclose(sol.z[0], gm.lift(x0, sol.q0), atol=1e-9)
            assert np.all(sol.u[[k for k, knot in enumerate(schedule) if knot.is_jump]] == 0.0)
        assert sols["condensed"].dynamics_residual < 1e-9  # exact up to rounding, not to a solver tolerance
        info = mpcs["piqp"]._solver.result.info
        w = {b: _qp_point(s) for b, s in sols.items()}
        f = {b: _qp_objective(mpcs["piqp"], w[b], z_ref) for b in sols}
        slack = p.eps * (1.0 + abs(info.dual_obj))
        gap = {b: abs(f[b] - info.dual_obj) + slack for b in sols}
        assert abs(f["condensed"] - f["piqp"]) <= COST_AGREEMENT_EPS * p.eps * abs(f["piqp"])
        dw = w["condensed"] - w["piqp"]
        assert math.sqrt(dw @ (mpcs["piqp"].P @ dw)) <= math.sqrt(2 * gap["condensed"]) + math.sqrt(2 * gap["piqp"])
        if limit == 1.5:
            assert np.abs(sols["condensed"].u).max() > 0.99 * limit  # an active bound: the active set did work


def test_the_thesis_knots_are_table_5_3s():
    p = _thesis(GeometricMpcParams())
    assert (p.horizon, p.sqp_iterations, p.flight_step_s, p.stance_step_s) == (20, 2, 0.01, 0.001)
    knots = gm.mode_schedule(gm.FLIGHT, 0.05, p, 0.3, 0.065)
    flows = [k for k in knots if not k.is_jump]
    assert len(knots) == 20 and knots[5].kind == gm.TOUCHDOWN
    assert all(math.isclose(k.h, 0.01) for k in flows[:5]) and all(math.isclose(k.h, 0.001) for k in flows[5:])


def test_two_sqp_iterations_agree_across_backends(dyn):
    """The full solve (two SQP iterations, the second linearized about the first's answer):
    the condensed and PIQP plans agree closely in the first knots, those the low level acts on."""
    for mode in (gm.FLIGHT, gm.STANCE):
        p, x0, knots, z_ref = _problem(dyn, 4, mode)
        a = gm.GeometricMpc(dyn, p, 15.0, "condensed").solve(x0, knots, z_ref)
        b = gm.GeometricMpc(dyn, p, 15.0, "piqp").solve(x0, knots, z_ref)
        assert a.ok and b.ok
        assert np.abs(a.u[:3] - b.u[:3]).max() < 1e-2  # N m (the inputs are the least determined part)
        assert np.abs(a.z[:4, gm.XI] - b.z[:4, gm.XI]).max() < 1e-4  # rad


def test_the_tilt_rows_send_the_qp_to_piqp(dyn):
    mpc = gm.GeometricMpc(dyn, GeometricMpcParams(tilt_max_plan=0.1), 15.0, "condensed")
    assert mpc.backend == "piqp"


@pytest.mark.parametrize("norm", [0.0, 0.3, 4.4, 39.0, 175.0])
def test_the_compiled_exponential_matches_scipys(norm):
    rng = np.random.default_rng(int(norm * 10))
    m = rng.normal(size=(24, 24))
    m[20:] = 0.0  # the augmented system's zero rows
    if norm:
        m *= norm / np.abs(m).sum(axis=0).max()
    else:
        m[:] = 0.0
    ref = scipy.linalg.expm(m)
    assert np.abs(gmpc_kernels.expm(m) - ref).max() <= 1e-12 * max(1.0, np.abs(ref).max())


def test_the_box_qp_finds_the_minimizer_and_certifies_it():
    """Random strictly convex QPs (not M-matrices, some variables fixed) against PIQP's dense
    solver at a tight tolerance; every answer carries its KKT certificate."""
    rng = np.random.default_rng(7)
    for _ in range(100):
        n = int(rng.integers(1, 61))
        m = rng.normal(size=(n, n))
        h = m @ m.T + 1e-2 * np.eye(n)
        g = rng.normal(size=n) * 10.0
        lo, hi = -np.ones(n), np.ones(n)
        fixed = rng.random(n) < 0.1
        lo[fixed] = hi[fixed] = 0.0
        res = box_qp.solve(h, g, lo, hi, 1e-9)
        assert res.status == box_qp.SOLVED and res.kkt_residual <= 1e-9 and res.iterations <= 12
        assert np.all(res.x >= lo) and np.all(res.x <= hi) and np.all(res.x[fixed] == 0.0)
        ref = piqp.DenseSolver()
        ref.settings.eps_abs = ref.settings.eps_rel = 1e-11
        ref.setup(h, g, None, None, None, None, None, lo, hi)
        ref.solve()
        f = lambda x: 0.5 * x @ h @ x + g @ x  # noqa: E731
        assert f(res.x) <= f(np.clip(ref.result.x, lo, hi)) + 1e-9 * (1.0 + abs(f(res.x)))


def test_the_box_qp_refuses_what_it_cannot_certify():
    h = np.array([[1.0, 0.0], [0.0, -1.0]])  # not positive definite
    res = box_qp.solve(h, np.ones(2), -np.ones(2), np.ones(2), 1e-9)
    assert res.status != box_qp.SOLVED
    # a cycle cut short: the iteration cap is the verdict, never an uncertified answer
    rng = np.random.default_rng(1)
    m = rng.normal(size=(30, 30))
    res = box_qp.solve(m @ m.T + 1e-3 * np.eye(30), rng.normal(size=30) * 100.0, -np.ones(30), np.ones(30), 1e-9, max_iter=1)
    assert res.status == "max iterations"
