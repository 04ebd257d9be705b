"""MPC refinement (eq. 7.2) of graph paths: continuity, feasibility, clearance, fallback."""

from __future__ import annotations

import math

import numpy as np
import pytest

from onboard.geometry import bezier as bz
from onboard.high_level.tracking import collision as col
from onboard.geometry import polygons as pg
from onboard.high_level.planning import bezier_graph as bg
from onboard.high_level.planning import graph_planner as gp
from onboard.high_level.tracking import reachability as reach
from onboard.contracts.params import PlannerParams

PARAMS = PlannerParams(nodes=1500, tube=0.05)
ROBOT_RADIUS = 0.13
BOUNDS = (0.0, 0.0, 6.0, 6.0)
OBSTACLES = [
    np.array([[2.5, 2.0], [3.5, 2.0], [3.5, 3.2], [2.5, 3.2]]),
    np.array([[1.0, 3.5], [1.6, 3.4], [1.4, 4.2]]),
    np.array([[4.0, 0.8], [4.6, 0.8], [4.6, 1.4], [4.0, 1.4]]),
]


@pytest.fixture(scope="module")
def graph() -> bg.BezierGraph:
    return bg.build_graph(bg.spec_from_params(PARAMS, BOUNDS))


def _planner(graph: bg.BezierGraph) -> gp.GraphPlanner:
    planner = gp.GraphPlanner(PARAMS, ROBOT_RADIUS, bounds=BOUNDS)
    planner.set_graph(graph)
    planner.set_obstacles(OBSTACLES)
    planner.set_goal((5.2, 5.0), 0.1)
    assert planner.plan((0.8, 0.8), (0.0, 0.0), stamp_ns=1_000_000_000) is not None
    return planner


def _segments(ref) -> list[tuple[float, float, np.ndarray]]:
    return [(s.t0, s.duration, np.array(s.control_points)) for s in ref.segments]


def _mpc_test() -> reach.BezierReachability:
    return reach.BezierReachability(reach.double_integrator(2), bg.speed_limits(PARAMS.a_max, PARAMS.v_max), PARAMS.mpc_dt)


def test_refined_reference_is_continuous_feasible_and_clear(graph):
    planner = _planner(graph)
    start = planner.path.states[0]
    ref = planner.refine(start[:2], start[2:], stamp_ns=1_000_000_000)
    assert ref is not None and not ref.hold and planner.stats.refine_failures == 0
    segs = _segments(ref)
    assert len(segs) > PARAMS.mpc_horizon
    assert np.all(np.abs(segs[0][2][0] - start[:2]) <= PARAMS.tube + 1e-6)  # within the tube of the state (7.2b)
    t = 0.0
    for k, (t0, dur, C) in enumerate(segs):
        assert t0 == pytest.approx(t, abs=1e-9)
        t += dur
        if k:
            _, pdur, P = segs[k - 1]
            assert np.allclose(P[-1], C[0], atol=1e-9)  # position continuous
            v_end = bz.derivative_points(P, pdur, 1)[-1]
            v_start = bz.derivative_points(C, dur, 1)[0]
            assert np.allclose(v_end, v_start, atol=1e-6)  # velocity continuous
    # The MPC part obeys the speed and acceleration bounds, densely sampled.
    mpc_ctrl = np.stack([C for _, _, C in segs[: PARAMS.mpc_horizon]])
    assert np.all(_mpc_test().violation(mpc_ctrl) <= 1e-6)
    # Every segment keeps the margin from every obstacle, densely sampled.
    pts = np.stack([bz.evaluate(C, dur, np.linspace(0.0, dur, 60)) for _, dur, C in segs])
    clearance = col.samples_clearance(pts, pg.pack_polygons(OBSTACLES), reach=1.0)
    assert clearance.min() > planner.margin
    # The reference ends where the graph path ends: at rest at the goal.
    assert np.allclose(segs[-1][2][-1], [5.2, 5.0], atol=1e-6)
    assert ref.t_ref_ns == 1_000_000_000


def test_refinement_follows_the_robot_along_the_path(graph):
    planner = _planner(graph)
    t0_ns = planner.path_t0_ns
    lengths = []
    for k in range(40):
        now = t0_ns + int(k * 0.05e9)
        x = bg.path_states(planner.path.control_points, planner.path.tau, np.array([(now - t0_ns) * 1e-9]))[0]
        ref = planner.refine(x[:2], x[2:], now)
        assert ref is not None and not ref.hold
        # Knots stay on the path's time grid: t_ref is a whole number of mpc_dt after the path's start.
        steps = (ref.t_ref_ns - t0_ns) / (PARAMS.mpc_dt * 1e9)
        assert steps == pytest.approx(round(steps), abs=1e-6)
        horizon = np.stack([np.array(s.control_points) for s in ref.segments[: PARAMS.mpc_horizon]])
        lengths.append(float(bz.path_length_bound(horizon).sum()))
    st = planner.stats
    assert st.refine_failures == 0 and st.refines + st.refine_reused == 40
    assert st.refines >= 20  # a solve at least at every knot (every 0.1 s; the calls come every 0.05 s)
    # The refinement shortens (or keeps) the graph path over the same horizon.
    graph_pts = bg.path_states(planner.path.control_points, planner.path.tau,
                               np.linspace(1.95, 1.95 + PARAMS.mpc_horizon * PARAMS.mpc_dt, 400))[:, :2]
    graph_len = float(np.linalg.norm(np.diff(graph_pts, axis=0), axis=1).sum())
    assert lengths[-1] <= graph_len * 1.05


def test_state_far_from_the_path_falls_back_to_the_graph_path(graph):
    planner = _planner(graph)
    start = planner.path.states[0]
    ref = planner.refine(start[:2] + [1.5, 0.0], start[2:], stamp_ns=1_000_000_000)
    assert planner.stats.refine_failures == 1
    graph_ref = planner.path_reference(0)
    assert [s.control_points for s in ref.segments] == [s.control_points for s in graph_ref.segments]
    assert planner.needs_replan(start[:2] + [1.5, 0.0], 1_000_000_000, PARAMS.replan_deviation)


def test_refine_in_free_cells_keeps_each_segment_in_a_cell(graph):
    cells = [np.array([[0.2, 0.2], [5.8, 0.2], [5.8, 2.2], [0.2, 2.2]]), np.array([[3.8, 0.2], [5.8, 0.2], [5.8, 5.8], [3.8, 5.8]])]
    planner = gp.GraphPlanner(PARAMS, ROBOT_RADIUS, bounds=BOUNDS)
    planner.set_graph(graph)
    planner.set_free_cells(cells)
    planner.set_goal((4.8, 5.0), 0.1)
    assert planner.plan((0.8, 1.2), (0.0, 0.0), 0) is not None
    start = planner.path.states[0]
    ref = planner.refine(start[:2], start[2:], 0)
    assert planner.stats.refine_failures == 0
    ctrl = np.stack([np.array(s.control_points) for s in ref.segments[: PARAMS.mpc_horizon]])
    assert np.all(col.free_cell_of(col.hull_set(ctrl), pg.pack_polygons(cells), planner.margin) >= 0)


def test_contract_check_grows_the_tube_and_reports(graph):
    from onboard.contracts import messages as msgs

    planner = _planner(graph)
    few = msgs.TrackingTube(hops=2, impact_err_p50=0.3, impact_err_p95=0.4, impact_err_max=0.5, attitude_err_p95=0.1)
    assert planner.check_tube(few) is None  # not judged on two impacts
    ok = msgs.TrackingTube(hops=30, impact_err_p50=0.02, impact_err_p95=0.04, impact_err_max=0.06, attitude_err_p95=0.1)
    assert planner.check_tube(ok) is None and planner.tube == 0.05
    bad = msgs.TrackingTube(hops=30, impact_err_p50=0.05, impact_err_p95=0.08, impact_err_max=0.1, attitude_err_p95=0.1)
    version = planner.world_version
    report = planner.check_tube(bad, stamp_ns=5)
    assert report is not None and report.violated and report.promised == 0.05 and report.achieved == 0.08
    assert planner.tube == pytest.approx(0.08 * PARAMS.tube_growth) and planner.world_version == version + 1
    huge = msgs.TrackingTube(hops=30, impact_err_p50=1.0, impact_err_p95=2.0, impact_err_max=3.0, attitude_err_p95=0.1)
    assert planner.check_tube(huge).violations == 2 and planner.tube == PARAMS.tube_max
    assert [r.violations for r in planner.drain_contract_reports()] == [1, 2] and planner.drain_contract_reports() == []


def test_the_last_solution_is_reused_only_while_nothing_changed(graph):
    planner = _planner(graph)
    start = planner.path.states[0]
    t0 = planner.path_t0_ns
    first = planner.refine(start[:2], start[2:], t0)
    again = planner.refine(start[:2] + 0.01, start[2:], t0 + 20_000_000)  # same knot, state moved 1 cm
    assert planner.stats.refines == 1 and planner.stats.refine_reused == 1
    assert again.segments == first.segments and again.stamp_ns == t0 + 20_000_000
    planner.refine(start[:2] + 0.2, start[2:], t0 + 30_000_000)  # out of the tube: solve again
    assert planner.stats.refines == 2
    planner.set_obstacles(OBSTACLES[:2])  # the world changed: solve again
    planner.refine(start[:2], start[2:], t0 + 40_000_000)
    assert planner.stats.refines == 3
    planner.refine(start[:2], start[2:], t0 + 100_000_000)  # the next knot: solve again
    assert planner.stats.refines == 4


def test_a_linear_algebra_failure_is_a_failed_refinement_not_a_crash(graph, monkeypatch):
    """numpy's "SVD did not converge" once escaped the MPC's polish and killed a lockstep run."""
    planner = _planner(graph)
    start = planner.path.states[0]
    mpc = planner._ensure_mpc(PARAMS.halfspaces)

    def diverged(*_args, **_kwargs):
        raise np.linalg.LinAlgError("SVD did not converge")

    monkeypatch.setattr(mpc, "solve", diverged)
    ref = planner.refine(start[:2], start[2:], stamp_ns=1_000_000_000)
    assert ref is not None and not ref.hold  # the graph path itself: collision free
    assert planner.stats.refine_failures == 1 and planner.stats.refine_numerical_errors == 1
    assert "SVD did not converge" in planner.stats.last_refine_error


def test_at_the_path_end_at_rest_the_path_holds_the_robot_without_a_solve(graph):
    """Past the path's end every knot sits on its end at rest, a problem whose answer is that end:
    no solve while the state rests within the tube there; a push out of it is refined again."""
    planner = _planner(graph)
    end_ns = planner.path_t0_ns + int(round(planner.path.duration * 1e9))
    goal = planner.path.states[-1]
    assert np.allclose(goal[2:], 0.0)
    ref = planner.refine(goal[:2] + 0.01, [0.02, -0.02], end_ns + 50_000_000)
    again = planner.refine(goal[:2] - 0.01, [0.0, 0.05], end_ns + 150_000_000)
    assert planner.stats.refines == 0 and planner.stats.refine_idle == 2
    assert not ref.hold and again.segments is ref.segments and again.stamp_ns == end_ns + 150_000_000
    assert ref.segments == planner.path_reference().segments
    planner.refine(goal[:2] + 0.2, [0.0, 0.0], end_ns + 250_000_000)  # pushed out of the tube
    assert planner.stats.refines == 1
    planner.refine(goal[:2], [0.3, 0.0], end_ns + 350_000_000)  # moving faster than the start tolerance
    assert planner.stats.refines == 2 and planner.stats.refine_idle == 2
    before_end = planner.refine(goal[:2], [0.0, 0.0], end_ns - 2 * int(PARAMS.mpc_dt * 1e9))  # knots not all at the end yet
    assert before_end is not None and planner.stats.refines == 3


@pytest.mark.parametrize("seed", range(5))
def test_the_state_is_the_numpy_formula_to_the_bit(graph, seed):
    """The refinement-rate state in plain floats equals concatenating the position with
    limit_speed of the velocity, near the speed bound included."""
    planner = _planner(graph)
    rng = np.random.default_rng(seed)
    v_max = PARAMS.v_max
    for _ in range(200):
        p = rng.uniform(-5.0, 5.0, 2)
        direction = rng.normal(size=2)
        v = direction / np.linalg.norm(direction) * v_max * rng.choice([0.5, 1.0, 1.0 - 1e-12, 1.0 + 1e-12, 1.1, 2.0])
        expected = np.concatenate([p, bg.limit_speed(v, v_max)])
        got = planner._state(p, v)
        assert got.tobytes() == expected.tobytes()
    with pytest.raises(bg.PlanningError):
        planner._state((0.0,), (0.0, 0.0))
    with pytest.raises(bg.PlanningError):
        planner._state((0.0, math.nan), (0.0, 0.0))
