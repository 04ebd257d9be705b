"""Bezier MPC (thesis 6.12 / 7.2): certified solutions, backend agreement, messages."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from onboard.geometry import bezier as bz
from onboard.high_level.tracking import bezier_mpc as bm
from onboard.high_level.tracking import reachability as rc
from onboard.contracts.messages import ComReference, decode, encode

FAST = settings(max_examples=15, deadline=None)
SAMPLES = 100  # dense samples per segment

V_MAX, A_MAX, TUBE = 0.6, 1.0, 0.05
# converged answers always certify with physical rows and an absolute tolerance
ACCURATE = {"unit_rows": False, "eps": 1e-5, "max_iter": 50000}
WEIGHTS = bm.MpcWeights(state=(1.0, 1.0, 0.1, 0.1), terminal=(10.0, 10.0, 1.0, 1.0), effort=0.01, path=1.0)


def di_reach(tau: float = 0.1, order: int = 3) -> rc.BezierReachability:
    md = rc.double_integrator(2)
    lim = rc.box_limits(md, A_MAX, [-np.inf, -np.inf, -V_MAX, -V_MAX], [np.inf, np.inf, V_MAX, V_MAX], tube=TUBE)
    return rc.BezierReachability(md, lim, tau, order=order)


def sine_reference(seed: int, N: int, tau: float) -> np.ndarray:
    """A smooth path well inside the limits: speeds <= V_MAX/2, accelerations <= A_MAX/3."""
    rng = np.random.default_rng(seed)
    t = np.arange(N + 1) * tau
    w = rng.uniform(0.2, 0.8, size=2)
    amp = np.minimum(0.5 * V_MAX / w, A_MAX / 3 / w**2)
    phase = rng.uniform(0, 2 * np.pi, size=2)
    pos = amp * np.sin(np.outer(t, w) + phase) + rng.uniform(-1, 1, size=2)
    vel = amp * w * np.cos(np.outer(t, w) + phase)
    return np.concatenate([pos, vel], axis=1)


def planes_around(seed: int, ref: np.ndarray, max_planes: int, clearance: float):
    """Random halfspaces that every reference segment clears by ``clearance`` + tube."""
    rng = np.random.default_rng(seed + 1)
    N = len(ref) - 1
    a = rng.normal(size=(N, max_planes, 2))
    a /= np.linalg.norm(a, axis=-1, keepdims=True)
    pts = np.stack([ref[:-1, :2], ref[1:, :2]], axis=1)  # (N, 2, 2)
    b = np.einsum("khd,kjd->khj", a, pts).max(axis=-1) + clearance + TUBE * np.sqrt(2) + 0.05
    unused = rng.random(size=(N, max_planes)) < 0.3
    b[unused] = np.inf
    return a, b


def dense_plane_violation(sol: bm.MpcSolution, a: np.ndarray, b: np.ndarray) -> float:
    t = np.linspace(0, sol.tau, SAMPLES)
    pos = bz.evaluate(sol.control_points, sol.tau, t)  # (N, S, 2)
    lhs = np.einsum("khd,ksd->khs", a, pos)
    rhs = b - np.linalg.norm(a, ord=1, axis=-1) * TUBE  # inf-norm tube: dual is the 1-norm
    with np.errstate(invalid="ignore"):
        return float(np.nanmax(lhs - rhs[..., None]))


def check_dynamics_and_continuity(sol: bm.MpcSolution, reach: rc.BezierReachability) -> None:
    C = sol.control_points
    ends = bz.state_values(C, sol.tau, 2, np.array([0.0, sol.tau]))  # (N, 2, 4)
    np.testing.assert_allclose(ends[1:, 0], ends[:-1, 1], atol=1e-9)
    np.testing.assert_allclose(ends[:, 0], sol.waypoints[:-1], atol=1e-9)
    np.testing.assert_allclose(ends[-1, 1], sol.waypoints[-1], atol=1e-9)


@FAST
@given(seed=st.integers(0, 2**32 - 1), backend=st.sampled_from(["osqp", "piqp"]), order=st.sampled_from([3, 4, 5]))
def test_double_integrator_solutions_satisfy_constraints_when_densely_sampled(seed, backend, order):
    N, tau, P = 20, 0.1, 3
    reach = di_reach(tau, order)
    mpc = bm.BezierMpc(reach, N, WEIGHTS, trust_region=[0.3, 0.3, 0.4, 0.4], init_radius=[0.02, 0.02, 0.0, 0.0], max_planes=P, backend=backend, **ACCURATE)
    ref = sine_reference(seed, N, tau)
    a, b = planes_around(seed, ref, P, clearance=0.0)
    x_init = ref[0] + np.array([0.01, -0.01, 0.0, 0.0])
    # a shifted target pulls the trajectory toward the planes and the limits
    target = ref.copy()
    target[:, :2] += 0.2
    target[-1] = ref[-1]
    sol = mpc.solve(x_init, target, (a, b), warm_start=ref)
    assert sol.ok, (sol.status, sol.max_violation)
    assert np.all(reach.violation(sol.control_points, SAMPLES) <= 0.0)
    assert dense_plane_violation(sol, a, b) <= 0.0
    assert np.all(np.abs(sol.waypoints[0] - x_init) <= np.array([0.02, 0.02, 0, 0]) + 1e-6)
    np.testing.assert_allclose(sol.waypoints[-1], ref[-1], atol=1e-5)
    assert np.all(np.abs(sol.waypoints[1:-1] - target[1:-1]) <= np.array([0.3, 0.3, 0.4, 0.4]) + 1e-9)
    check_dynamics_and_continuity(sol, reach)


@FAST
@given(seed=st.integers(0, 2**32 - 1), order=st.sampled_from([3, 5]))
def test_osqp_and_piqp_agree(seed, order):
    N, tau, P = 15, 0.1, 2
    reach = di_reach(tau, order)
    ref = sine_reference(seed, N, tau)
    a, b = planes_around(seed, ref, P, clearance=0.0)
    target = ref.copy()
    target[1:-1, :2] += 0.15
    sols = {}
    for backend in ("osqp", "piqp"):
        mpc = bm.BezierMpc(reach, N, WEIGHTS, trust_region=[0.3, 0.3, 0.4, 0.4], max_planes=P, backend=backend, **{**ACCURATE, "eps": 1e-6})
        sols[backend] = mpc.solve(ref[0], target, (a, b))
    o, q = sols["osqp"], sols["piqp"]
    assert o.ok and q.ok
    np.testing.assert_allclose(o.waypoints, q.waypoints, atol=1e-3)
    np.testing.assert_allclose(o.control_points, q.control_points, atol=1e-3)
    assert o.objective == pytest.approx(q.objective, rel=1e-3, abs=1e-4)


def section61_reach(u_max: float) -> rc.BezierReachability:
    v_max = 1.5
    md = rc.PlanningModel(1, 2, drift=lambda x: (np.sin(x[..., 0]) + x[..., 1] ** 3)[..., None], lipschitz_drift=np.array([[1.0, 3 * v_max**2]]))
    lim = rc.box_limits(md, u_max, [-3.0, -v_max], [3.0, v_max])
    return rc.BezierReachability(md, lim, 0.2, refinement=2)


@FAST
@given(seed=st.integers(0, 2**32 - 1), backend=st.sampled_from(["osqp", "piqp"]))
def test_nonlinear_model_solutions_are_feasible_for_the_true_dynamics(seed, backend):
    reach = section61_reach(u_max=4.0)
    N = 10
    # reference: the system itself under a small smooth input, sampled every tau
    rng = np.random.default_rng(seed)
    x = np.array([rng.uniform(-1.5, 1.5), rng.uniform(-0.5, 0.5)])
    ref = [x.copy()]
    h = 0.002
    u0, w = rng.uniform(-0.5, 0.5), rng.uniform(0.5, 2.0)
    for k in range(N):
        for i in range(int(round(reach.tau / h))):
            t = k * reach.tau + i * h
            u = u0 * np.cos(w * t) - np.sin(x[0]) - x[1] ** 3 - 0.8 * x[1]  # damped, stays slow
            x = x + h * np.array([x[1], np.sin(x[0]) + x[1] ** 3 + u])
        ref.append(x.copy())
    ref = np.array(ref)
    assume(np.all(reach.test(ref[:-1], ref[1:])))
    mpc = bm.BezierMpc(reach, N, bm.MpcWeights(state=(1.0, 0.1), terminal=(1.0, 0.1), effort=1e-3), trust_region=[0.2, 0.3], backend=backend, **ACCURATE)
    target = np.zeros_like(ref)  # drive toward the origin (thesis section 6.1)
    target[-1] = ref[-1]
    target[0] = ref[0]
    sol = mpc.solve(ref[0], target, warm_start=ref)
    # the trust region keeps it near the feasible reference: centre it there
    sol_ref = mpc.solve(ref[0], ref, warm_start=ref)
    assert sol_ref.ok, (sol_ref.status, sol_ref.max_violation)
    for s in (sol, sol_ref):
        if s.ok:
            assert np.all(reach.violation(s.control_points, SAMPLES) <= 0.0)


def test_infeasible_start_is_reported_not_raised():
    reach = di_reach()
    mpc = bm.BezierMpc(reach, 10, WEIGHTS)
    ref = np.zeros((11, 4))
    sol = mpc.solve(np.array([0.0, 0.0, 3 * V_MAX, 0.0]), ref)  # far over the speed limit
    assert not sol.ok
    msg = sol.to_com_reference(t_ref_ns=5)
    assert msg.hold
    with pytest.raises(ValueError):
        mpc.solve(np.array([np.nan, 0, 0, 0]), ref)
    with pytest.raises(ValueError):
        mpc.solve(np.zeros(4), np.zeros((5, 4)))


def test_bad_planes_and_settings_are_rejected():
    reach = di_reach()
    with pytest.raises(ValueError):
        bm.BezierMpc(reach, 10, WEIGHTS, init_radius=[1e-6, 0, 0, 0])
    with pytest.raises(ValueError):
        bm.BezierMpc(reach, 10, bm.MpcWeights(state=(1.0,), terminal=(1.0,)))
    with pytest.raises(ValueError):
        bm.BezierMpc(reach, 10, WEIGHTS, backend="nope")
    mpc = bm.BezierMpc(reach, 10, WEIGHTS, max_planes=2)
    with pytest.raises(ValueError):
        mpc.solve(np.zeros(4), np.zeros((11, 4)), (np.zeros((10, 3, 2)), np.zeros((10, 3))))
    with pytest.raises(ValueError):
        mpc.solve(np.zeros(4), np.zeros((11, 4)), (np.full((10, 2, 2), np.nan), np.zeros((10, 2))))


def test_per_tick_updates_reuse_the_setup_and_warm_start():
    reach = di_reach()
    N = 30
    mpc = bm.BezierMpc(reach, N, WEIGHTS, trust_region=[0.3, 0.3, 0.4, 0.4], max_planes=2, **ACCURATE)
    pattern = (mpc._A.indices.copy(), mpc._A.indptr.copy())
    ref = sine_reference(3, N + 5, 0.1)
    a, b = planes_around(3, ref, 2, 0.0)
    iters = []
    for tick in range(5):
        window = ref[tick : tick + N + 1]
        sol = mpc.solve(window[0], window, (a[tick : tick + N], b[tick : tick + N]))
        assert sol.ok
        iters.append(sol.iterations)
        assert np.array_equal(mpc._A.indices, pattern[0]) and np.array_equal(mpc._A.indptr, pattern[1])
    again = mpc.solve(window[0], window, (a[4 : 4 + N], b[4 : 4 + N]))  # same data: warm start is the answer
    assert again.iterations <= 25  # OSQP's first termination check
    np.testing.assert_allclose(again.waypoints, sol.waypoints, atol=1e-4)


def test_unconverged_answers_are_only_ok_when_they_are_feasible():
    reach = di_reach()
    N = 20
    ref = sine_reference(11, N, 0.1)
    a, b = planes_around(11, ref, 2, 0.0)
    target = ref.copy()
    target[1:-1, :2] += 0.3
    for max_iter in (1, 3, 10, 30):
        mpc = bm.BezierMpc(reach, N, WEIGHTS, trust_region=[0.3, 0.3, 0.4, 0.4], max_planes=2, max_iter=max_iter, polish=False)
        sol = mpc.solve(ref[0], target, (a, b))
        if sol.ok:
            assert np.all(reach.violation(sol.control_points, SAMPLES) <= 0.0)
            assert dense_plane_violation(sol, a, b) <= 0.0
        else:
            assert sol.max_violation > 0.0 or sol.equality_residual > 0.0


def test_solution_becomes_a_com_reference_message():
    reach = di_reach()
    N = 10
    mpc = bm.BezierMpc(reach, N, WEIGHTS)
    ref = sine_reference(5, N, 0.1)
    sol = mpc.solve(ref[0], ref)
    assert sol.ok
    msg = decode(encode(sol.to_com_reference(t_ref_ns=123, stamp_ns=100)), ComReference)
    assert not msg.hold and msg.t_ref_ns == 123 and len(msg.segments) == N
    assert msg.segments[3].t0 == pytest.approx(0.3) and msg.segments[3].duration == pytest.approx(0.1)
    np.testing.assert_allclose(msg.segments[3].control_points, sol.control_points[3])
    # evaluating the whole trajectory matches per-segment evaluation
    t = np.array([0.0, 0.05, 0.35, sol.duration])
    np.testing.assert_allclose(sol.evaluate(t)[2], bz.evaluate(sol.control_points[3], 0.1, 0.05), atol=1e-12)
    np.testing.assert_allclose(sol.evaluate(t)[-1], sol.waypoints[-1, :2], atol=1e-9)
    np.testing.assert_allclose(sol.evaluate(t, 1)[0], sol.waypoints[0, 2:], atol=1e-9)


@FAST
@given(seed=st.integers(0, 2**32 - 1))
def test_default_fast_settings_certify_most_ticks_and_only_feasible_ones(seed):
    """Defaults (unit rows, early stop, polish): ok answers are feasible; most ticks are ok."""
    reach = di_reach()
    N, P = 20, 2
    mpc = bm.BezierMpc(reach, N, WEIGHTS, trust_region=[0.3, 0.3, 0.4, 0.4], init_radius=[0.02, 0.02, 0.0, 0.0], max_planes=P)
    ref = sine_reference(seed, N + 10, 0.1)
    a, b = planes_around(seed, ref, P, 0.0)
    oks = []
    for tick in range(10):
        w = ref[tick : tick + N + 1]
        sol = mpc.solve(w[0] + np.array([0.01, 0.0, 0.0, 0.0]), w, (a[tick : tick + N], b[tick : tick + N]), shift=1 if tick else 0)
        oks.append(sol.ok)
        if sol.ok:
            assert np.all(reach.violation(sol.control_points, SAMPLES) <= 0.0)
            assert dense_plane_violation(sol, a[tick : tick + N], b[tick : tick + N]) <= 0.0
    assert np.mean(oks) >= 0.7


def test_solving_prints_nothing(capfd):
    """A service's stdout (and `archer plan --json`) must not get solver chatter."""
    reach = di_reach()
    ref = sine_reference(2, 10, 0.1)
    for backend in ("osqp", "piqp"):
        mpc = bm.BezierMpc(reach, 10, WEIGHTS, terminal="free", init_radius=[0.02, 0.02, 0.05, 0.05], backend=backend)
        assert mpc.solve(ref[0], ref).ok
    out, err = capfd.readouterr()
    assert out == "" and err == ""


@FAST
@given(seed=st.integers(0, 2**32 - 1))
def test_both_polish_solvers_give_the_active_set_optimum(seed):
    """The polish's dense range-space solve (P well conditioned) and its sparse KKT
    factorization (any P) agree, and the answer holds its active rows with equality."""
    reach = di_reach()
    N, P = 20, 2
    mpc = bm.BezierMpc(reach, N, WEIGHTS, trust_region=[0.3, 0.3, 0.4, 0.4], init_radius=[0.02, 0.02, 0.0, 0.0], max_planes=P)
    assert mpc._polisher.P_inv is not None  # positive weights: the dense path
    ref = sine_reference(seed, N, 0.1)
    a, b = planes_around(seed, ref, P, 0.0)
    target = ref.copy()
    target[1:-1, :2] += 0.2
    mpc.solve(ref[0], target, (a, b))
    rng = np.random.default_rng(seed)
    A = mpc._A
    rows = np.unique(np.concatenate([[0, 1, 2, 3], rng.choice(mpc.n_rows, 12, replace=False)]))
    Aa = A.tocsr()[rows].toarray()
    assume(np.linalg.matrix_rank(Aa) == len(rows))  # independent rows: one answer
    q = rng.normal(size=mpc.nvar)
    rhs = rng.normal(size=len(rows)) * 0.1
    dense = mpc._polisher.solve_kkt(A, rows, q, rhs)
    P_inv, mpc._polisher.P_inv = mpc._polisher.P_inv, None
    sparse = mpc._polisher.solve_kkt(A, rows, q, rhs)
    mpc._polisher.P_inv = P_inv
    assert dense is not None and sparse is not None
    np.testing.assert_allclose(Aa @ dense, rhs, atol=1e-8)
    np.testing.assert_allclose(dense, sparse, atol=1e-6)
    # a row twice (dependent rows, consistent right-hand side): the same answer
    twice = mpc._polisher.solve_kkt(A, np.append(rows, rows[-1]), q, np.append(rhs, rhs[-1]))
    np.testing.assert_allclose(twice, dense, atol=1e-6)


def test_an_ill_conditioned_cost_polishes_with_the_sparse_kkt_system():
    weights = bm.MpcWeights(state=(1.0, 1.0, 0.0, 0.0), terminal=(1.0, 1.0, 0.0, 0.0))  # no velocity cost
    mpc = bm.BezierMpc(di_reach(), 10, weights, trust_region=[0.3, 0.3, 0.4, 0.4])
    assert mpc._polisher.P_inv is None
    ref = sine_reference(4, 10, 0.1)
    assert mpc.solve(ref[0], ref).ok


def _octagon_mpc(**kw) -> bm.BezierMpc:
    """The planner's refinement MPC shape: the speed octagon's diagonal rows are single-waypoint rows."""
    from onboard.high_level.planning.bezier_graph import speed_limits

    reach = rc.BezierReachability(rc.double_integrator(2), speed_limits(A_MAX, V_MAX, tube=TUBE, tube_norm=2), 0.1)
    return bm.BezierMpc(reach, 20, WEIGHTS, trust_region=[0.3, 0.3, np.inf, np.inf], init_radius=[0.02, 0.02, 0.0, 0.0],
                        **kw)


def test_a_start_past_the_speed_bound_is_refused_at_once_with_its_reason():
    """A measured speed past the speed octagon (a push): no answer exists, and it is said at once,
    not after the solver's whole iteration budget."""
    mpc = _octagon_mpc()
    ref = sine_reference(0, 20, 0.1)
    assert mpc.solve(ref[0], ref).ok  # the same problem from a start inside the bound
    fast = ref[0].copy()
    fast[2:] = 0.95 * V_MAX  # each axis within the bound, the diagonal far past it
    sol = mpc.solve(fast, ref)
    assert not sol.ok and "initial state" in sol.status and sol.iterations == 0


def test_a_time_limit_ends_the_solve_with_its_reason():
    mpc = _octagon_mpc(time_limit_s=1e-7, polish=False)
    ref = sine_reference(1, 20, 0.1)
    target = ref.copy()
    target[1:-1, :2] += 0.2  # away from the warm start: many iterations' work
    sol = mpc.solve(ref[0], ref, target=target)
    assert "time limit" in sol.status
    with pytest.raises(ValueError, match="time_limit_s"):
        _octagon_mpc(time_limit_s=-1.0)


def test_an_infeasible_verdict_is_returned_without_polishing_its_certificate():
    """OSQP's ``y`` after "primal infeasible" is a certificate, not a dual: polishing it made every
    row active (1808 rows, 20 s of least squares in the overhead bench); the verdict is the answer."""
    verdicts = 0
    for seed in range(6):
        mpc = _octagon_mpc(max_planes=1)
        verdict, polished_after = [], []  # each ADMM pass's status; the status each polish followed
        real_solve, real_polish = mpc._solver.solve, mpc._polisher.polish
        mpc._solver.solve = lambda **kw: verdict.append(res := real_solve(**kw)) or res
        mpc._polisher.polish = lambda *args: polished_after.append(str(verdict[-1].info.status)) or real_polish(*args)
        mpc._row_outside_box = lambda *args: False  # the test before the solve would refuse it: off, the solver meets it
        ref = sine_reference(seed, 20, 0.1)
        a = np.zeros((20, 1, 2))
        a[:, 0, 0] = 1.0
        b = np.full((20, 1), np.inf)
        b[19, 0] = min(ref[19, 0], ref[20, 0]) - 3.0  # the last segment 3 m behind where it must end
        sol = mpc.solve(ref[0], ref, (a, b))
        assert not sol.ok
        verdicts += any("infeasible" in str(r.info.status) for r in verdict)
        assert not [status for status in polished_after if "infeasible" in status]
    assert verdicts >= 3  # OSQP says so on most of these (6 of 6 here): the rule was exercised


def test_a_path_end_behind_an_obstacle_face_is_refused_before_the_solve():
    """The planner pins the last knot to the graph path (7.2e); an obstacle that moved onto it
    leaves a face that knot breaks: no answer exists, said at once (the solver spent its whole
    budget, twice, on each such tick of the sliding scenarios)."""
    for seed in range(5):
        mpc = _octagon_mpc(max_planes=1, terminal="equal")
        ref = sine_reference(seed, 20, 0.1)
        a = np.zeros((20, 1, 2))
        a[19, 0, 0] = 1.0
        b = np.full((20, 1), np.inf)
        b[19, 0] = ref[20, 0] + 0.1  # the face 0.1 m past the pinned end (the tube tightens it by 0.05): it may be kept
        assert mpc.solve(ref[0], ref, (a, b)).ok
        b[19, 0] = ref[20, 0] + 0.04  # the face moved 6 cm: the pinned end is 1 cm past it once tightened
        sol = mpc.solve(ref[0], ref, (a, b))
        assert not sol.ok and "holds nowhere" in sol.status and sol.iterations == 0, sol.status


def test_a_polish_with_more_active_rows_than_variables_gives_up():
    """More active rows than variables are not a vertex: no polish (it would cost rows^3)."""
    mpc = _octagon_mpc(max_planes=2)
    ref = sine_reference(3, 20, 0.1)
    assert mpc.solve(ref[0], ref).ok
    A = mpc._A
    ls, us = np.full(mpc.n_rows, -1.0), np.full(mpc.n_rows, 1.0)
    assert mpc.n_rows > mpc.nvar
    every_row = np.ones(mpc.n_rows)
    assert mpc._polisher.polish(np.zeros(mpc.nvar), every_row, A, ls, us, np.zeros(mpc.nvar)) is None
    few_rows = np.zeros(mpc.n_rows)
    few_rows[:4] = 1.0  # the same polish on a real active set answers
    assert mpc._polisher.polish(np.zeros(mpc.nvar), few_rows, A, ls, us, np.zeros(mpc.nvar)) is not None
