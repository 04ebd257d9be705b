"""Bezier reachable polytopes (thesis ch. 6): soundness against dense sampling."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from onboard.geometry import bezier as bz
from onboard.high_level.tracking import reachability as rc

FAST = settings(max_examples=25, deadline=None)
SAMPLES = 300  # dense samples per curve for the soundness checks


def section61_model(v_max: float) -> rc.PlanningModel:
    """x2' = sin(x1) + x2^3 + u (thesis section 6.1); Lipschitz on |x2| <= v_max."""

    def drift(x):
        return (np.sin(x[..., 0]) + x[..., 1] ** 3)[..., None]

    return rc.PlanningModel(1, 2, drift=drift, lipschitz_drift=np.array([[1.0, 3 * v_max**2]]))


def di_limits(v_max: float, a_max: float, pos: float = np.inf, tube: float = 0.0, tube_norm=np.inf):
    md = rc.double_integrator(2)
    return md, rc.box_limits(md, a_max, [-pos, -pos, -v_max, -v_max], [pos, pos, v_max, v_max], tube, tube_norm)


def near_pairs(rng, lo, hi, spread, count):
    x0 = rng.uniform(lo, hi, size=(count, len(lo)))
    return x0, x0 + rng.normal(size=x0.shape) * spread


@FAST
@given(
    seed=st.integers(0, 2**32 - 1),
    v_max=st.floats(0.2, 2.0),
    a_max=st.floats(0.2, 4.0),
    tau=st.floats(0.1, 1.0),
    tube=st.floats(0.0, 0.3),
    tube_norm=st.sampled_from([1, 2, np.inf]),
    order_extra=st.integers(0, 3),
    refinement=st.integers(1, 4),
    elevate=st.integers(0, 3),
)
def test_double_integrator_accepted_pairs_are_feasible(seed, v_max, a_max, tau, tube, tube_norm, order_extra, refinement, elevate):
    md, lim = di_limits(v_max, a_max, pos=2.0, tube=tube, tube_norm=tube_norm)
    p = 3 + order_extra
    R = rc.BezierReachability(md, lim, tau, order=p, refinement=refinement, check_order=p + elevate)
    rng = np.random.default_rng(seed)
    lo, hi = np.array([-2, -2, -v_max, -v_max]), np.array([2, 2, v_max, v_max])
    x0, xT = near_pairs(rng, lo, hi, np.array([v_max * tau, v_max * tau, a_max * tau, a_max * tau]) / 2, 3000)
    ok = R.test(x0, xT)
    assume(ok.sum() >= 1)
    C = R.curve(x0[ok], xT[ok])
    assert np.all(R.violation(C, SAMPLES) <= 1e-9)
    # independent check: positions stay in the box shrunk by the tube, speed and accel bounded
    t = np.linspace(0, tau, SAMPLES)
    pos = bz.evaluate(C, tau, t)
    vel = bz.evaluate(bz.derivative_points(C, tau, 1), tau, t)
    acc = bz.evaluate(bz.derivative_points(C, tau, 2), tau, t)
    shrink = tube  # unit axis rows: every dual norm of e_i is 1
    assert np.abs(pos).max() <= 2.0 - shrink + 1e-9
    assert np.abs(vel).max() <= v_max + 1e-9
    assert np.abs(acc).max() <= a_max + 1e-9


@FAST
@given(
    seed=st.integers(0, 2**32 - 1),
    u_max=st.floats(0.5, 6.0),
    tau=st.floats(0.1, 0.5),
    refinement=st.integers(1, 6),
    reference=st.sampled_from(["drift", "start"]),
)
def test_pendulum_accepted_pairs_are_feasible(seed, u_max, tau, refinement, reference):
    md = rc.pendulum(mass=1.0, length=1.0, damping=0.1)
    lim = rc.box_limits(md, u_max, [-np.inf, -6.0], [np.inf, 6.0])
    R = rc.BezierReachability(md, lim, tau, refinement=refinement, reference=reference)
    rng = np.random.default_rng(seed)
    x0 = rng.uniform([-4, -5], [4, 5], size=(3000, 2))
    flow = rc._drift_flow(md, x0, np.array([tau]))[:, 0]
    xT = flow + rng.normal(size=x0.shape) * np.array([0.3, 1.0]) * u_max * tau**2
    ok = R.test(x0, xT)
    assume(ok.sum() >= 1)
    C = R.curve(x0[ok], xT[ok])
    assert np.all(R.violation(C, SAMPLES) <= 1e-9)
    # independent input check through the pendulum equation itself
    t = np.linspace(0, tau, SAMPLES)
    th = bz.evaluate(C, tau, t)[..., 0]
    om = bz.evaluate(bz.derivative_points(C, tau, 1), tau, t)[..., 0]
    al = bz.evaluate(bz.derivative_points(C, tau, 2), tau, t)[..., 0]
    torque = 1.0 * (al + 9.81 * np.sin(th) + 0.1 * om)
    assert np.abs(torque).max() <= u_max + 1e-9
    assert np.abs(om).max() <= 6.0 + 1e-9


@FAST
@given(seed=st.integers(0, 2**32 - 1), u_max=st.floats(1.0, 10.0), refinement=st.integers(1, 4), order_extra=st.integers(0, 2))
def test_section61_system_accepted_pairs_are_feasible(seed, u_max, refinement, order_extra):
    v_max = 1.5
    md = section61_model(v_max)
    lim = rc.box_limits(md, u_max, [-3.0, -v_max], [3.0, v_max])
    R = rc.BezierReachability(md, lim, 0.3, order=3 + order_extra, refinement=refinement)
    rng = np.random.default_rng(seed)
    x0, xT = near_pairs(rng, np.array([-3, -v_max]), np.array([3, v_max]), np.array([0.2, 0.5]), 3000)
    ok = R.test(x0, xT)
    assume(ok.sum() >= 1)
    C = R.curve(x0[ok], xT[ok])
    t = np.linspace(0, 0.3, SAMPLES)
    x1 = bz.evaluate(C, 0.3, t)[..., 0]
    x2 = bz.evaluate(bz.derivative_points(C, 0.3, 1), 0.3, t)[..., 0]
    a = bz.evaluate(bz.derivative_points(C, 0.3, 2), 0.3, t)[..., 0]
    u = a - np.sin(x1) - x2**3
    assert np.abs(u).max() <= u_max + 1e-9
    assert np.abs(x1).max() <= 3 + 1e-9 and np.abs(x2).max() <= v_max + 1e-9


def test_double_integrator_matrix_shape_and_constant_velocity_segments():
    md, lim = di_limits(v_max=1.0, a_max=2.0)
    R = rc.BezierReachability(md, lim, 0.5)
    assert R.F.shape[1] == 8 and R.G_const is not None
    x0 = np.array([0.0, 0.0, 0.9, 0.0])
    assert R.test(x0, np.array([0.45, 0.0, 0.9, 0.0]))  # cruising at 0.9 m/s for 0.5 s
    assert not R.test(x0, np.array([0.6, 0.0, 0.9, 0.0]))  # needs to exceed 1 m/s in between
    assert not R.test(np.array([0.0, 0.0, 1.1, 0.0]), np.array([0.55, 0.0, 1.1, 0.0]))  # over the limit
    # rest to rest: the cubic's peak acceleration is 6 d / tau^2 <= 2 -> d <= 1/12 m
    rest = np.zeros(4)
    assert R.test(rest, np.array([0.08, 0.0, 0.0, 0.0]))
    assert not R.test(rest, np.array([0.09, 0.0, 0.0, 0.0]))


def test_tube_tightening_uses_the_dual_norm():
    md = rc.double_integrator(2)
    A = np.array([[1.0, 1.0, 0.0, 0.0]])  # x + y <= 1
    for norm, dual in ((np.inf, 2.0), (2, np.sqrt(2.0)), (1, 1.0)):
        lim = rc.ReachLimits(u_max=1.0, state_A=A, state_b=np.array([1.0]), tube=0.1, tube_norm=norm)
        assert lim.tightened_b(2)[0] == pytest.approx(1.0 - 0.1 * dual)
        R = rc.BezierReachability(md, lim, 0.5)
        inside = 0.5 * (1.0 - 0.1 * dual) - 1e-6
        assert R.test(np.array([inside, inside, 0, 0]), np.array([inside, inside, 0, 0]))
        assert not R.test(np.array([inside + 1e-4, inside + 1e-4, 0, 0]), np.array([inside, inside, 0, 0]))


def test_refinement_and_elevation_only_add_pairs():
    md, lim = di_limits(v_max=1.0, a_max=1.0, pos=1.0, tube=0.05)
    rng = np.random.default_rng(2)
    x0, xT = near_pairs(rng, np.array([-1, -1, -1, -1]), np.array([1, 1, 1, 1]), 0.1, 20000)
    xT[:, :2] += 0.5 * x0[:, 2:]  # drift the end position with the start velocity
    base = rc.BezierReachability(md, lim, 0.5).test(x0, xT)
    finer = rc.BezierReachability(md, lim, 0.5, refinement=4).test(x0, xT)
    elevated = rc.BezierReachability(md, lim, 0.5, check_order=8).test(x0, xT)
    assert base.sum() > 100
    assert np.all(finer[base]) and finer.sum() > base.sum()
    assert np.all(elevated[base]) and elevated.sum() > base.sum()


def test_forward_backward_polytopes_and_edge_table_agree_with_the_test():
    md, lim = di_limits(v_max=0.6, a_max=1.0)
    R = rc.BezierReachability(md, lim, 0.5)
    rng = np.random.default_rng(3)
    nodes = rng.uniform([-1, -1, -0.6, -0.6], [1, 1, 0.6, 0.6], size=(300, 4))
    i, j = rng.integers(0, 300, size=(2, 50000))
    direct = R.test(nodes[i], nodes[j])
    A, b = R.forward_polytope(nodes[i])
    assert np.array_equal(np.all(nodes[j] @ A.T <= b, axis=1), direct)
    A, b = R.backward_polytope(nodes[j])
    assert np.array_equal(np.all(nodes[i] @ A.T <= b, axis=1), direct)
    table = R.edge_table(nodes)
    assert np.array_equal(table.test_pairs(i, j), direct)
    succ = table.successors(7)
    assert np.array_equal(succ, np.flatnonzero(R.test(np.tile(nodes[7], (300, 1)), nodes)))
    with pytest.raises(IndexError):
        table.test_pairs(np.array([0]), np.array([300]))


def test_reach_radius_bounds_every_accepted_pair_and_is_attained():
    md, lim = di_limits(v_max=0.6, a_max=1.0)
    R = rc.BezierReachability(md, lim, 0.5)
    radius = R.reach_radius()
    assert radius == pytest.approx([0.3, 0.3], abs=1e-6)  # v_max * tau: cruising at the limit
    assert R.test(np.array([0, 0, 0.6, 0]), np.array([0.3 - 1e-9, 0, 0.6, 0]))
    rng = np.random.default_rng(4)
    x0, xT = near_pairs(rng, np.array([-1, -1, -0.6, -0.6]), np.array([1, 1, 0.6, 0.6]), 0.3, 50000)
    ok = R.test(x0, xT)
    assert np.all(np.abs(xT[ok, :2] - x0[ok, :2]) <= radius + 1e-9)


def test_pendulum_free_flow_is_reachable_and_references_follow_the_drift():
    md = rc.pendulum(1.0, 1.0)
    lim = rc.box_limits(md, 1.0, [-np.inf, -8.0], [np.inf, 8.0])
    R = rc.BezierReachability(md, lim, 0.2, refinement=4)
    x0 = np.array([[0.5, 0.0], [2.0, 1.0], [-1.0, -2.0]])
    flow = rc._drift_flow(md, x0, np.array([0.2]))[:, 0]
    assert np.all(R.test(x0, flow))
    assert not np.any(R.test(x0, flow + np.array([0.0, 0.8])))  # 0.8 rad/s more needs ~4 N m
    refs = R.references(x0)
    assert refs.shape == (3, 4, 2)
    np.testing.assert_allclose(refs[:, 0], rc._drift_flow(md, x0, np.array([0.025]))[:, 0], atol=1e-9)
    back = R.references(flow, "backward")
    np.testing.assert_allclose(back, refs, atol=1e-6)  # the same flow traced backwards


def test_escaping_drift_gives_no_edge_instead_of_an_error():
    md = rc.PlanningModel(1, 2, drift=lambda x: (x[..., 1] ** 3 * 1e6)[..., None], lipschitz_drift=np.array([[0.0, 1e9]]))
    lim = rc.box_limits(md, 1.0, [-1.0, -np.inf], [1.0, np.inf])
    R = rc.BezierReachability(md, lim, 0.5)
    assert not R.test(np.array([0.0, 5.0]), np.array([0.1, 5.0]))


def test_bad_configurations_are_rejected():
    md = rc.double_integrator(2)
    with pytest.raises(ValueError):  # tube larger than the position box
        rc.BezierReachability(md, rc.box_limits(md, 1.0, [-0.1] * 4, [0.1] * 4, tube=0.2), 0.5)
    with pytest.raises(ValueError):
        rc.PlanningModel(1, 2, drift=lambda x: x[..., :1])  # no Lipschitz bound
    with pytest.raises(ValueError):
        rc.PlanningModel(1, 2, lipschitz_drift=np.array([[-1.0, 0.0]]))
    with pytest.raises(ValueError):  # state-dependent gain without a deviation box
        md2 = rc.PlanningModel(1, 2, gain_inv=lambda x: np.ones(x.shape[:-1] + (1, 1)), lipschitz_gain_inv=np.array([1.0, 0.0]))
        rc.BezierReachability(md2, rc.box_limits(md2, 1.0, [-1, -1], [1, 1]), 0.5)
    with pytest.raises(ValueError):
        rc.box_limits(md, np.nan, [-1] * 4, [1] * 4)


def test_state_dependent_gain_with_deviation_box_is_sound():
    # q'' = u / (1 + 0.5 sin(q)^2) -> g^-1 = 1 + 0.5 sin^2, Lipschitz 0.5 in q
    md = rc.PlanningModel(
        1,
        2,
        gain_inv=lambda x: (1 + 0.5 * np.sin(x[..., 0]) ** 2)[..., None, None],
        lipschitz_gain_inv=np.array([0.5, 0.0]),
    )
    lim = rc.box_limits(md, 2.0, [-2, -2], [2, 2], deviation=np.array([0.2, np.inf]))
    R = rc.BezierReachability(md, lim, 0.4, refinement=3, reference="start")
    rng = np.random.default_rng(5)
    x0, xT = near_pairs(rng, np.array([-2, -2]), np.array([2, 2]), 0.2, 20000)
    ok = R.test(x0, xT)
    assert ok.sum() > 50
    assert np.all(R.violation(R.curve(x0[ok], xT[ok]), SAMPLES) <= 1e-9)
