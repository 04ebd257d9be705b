"""The flip (thesis Fig. 5.13): the planned turn, when it is refused, and the twin flipping and hopping on."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import pytest

from onboard.geometry import quaternion as qt
from onboard.low_level.tracking.flip import NS, TURN
from onboard.contracts.params import ControlParams, SafetyLimits
from robot_description import params as rd
from robot_description.controller import build_controller
from services.runtime.zenoh_session import free_endpoint
from sim_twin import lockstep as ls
from sim_twin.metrics import PhysicsMetrics
from helpers import judge_realtime_outcome


def controller(variant: str):
    robot = rd.robot_params(variant)
    return build_controller(variant, ControlParams(robot=variant), rd.safety_limits_for(SafetyLimits(), robot))


def started_turn(flight_s: float = 0.5):
    flip = controller("sim15nm").flip
    assert flip.request() and flip.state == "pumping" and flip.raising_hop
    flip.on_liftoff(NS, flight_s, 0.3)
    assert flip.state == "turning"
    return flip


def test_the_turn_is_one_full_turn_from_rest_to_rest_about_a_horizontal_axis():
    flip = started_turn()
    plan = flip.plan
    assert plan.duration_s == pytest.approx(0.5 - flip.settle_s)
    end_ns = plan.t0_ns + int(plan.duration_s * NS)
    q0, w0, ff0 = plan.at(plan.t0_ns)
    q_end, w_end, ff_end = plan.at(end_ns)
    q_half, w_half, _ = plan.at(plan.t0_ns + int(plan.duration_s * NS / 2))
    assert qt.angle_between(q0, plan.q0) < 1e-9 and qt.angle_between(q_end, plan.q0) < 1e-6  # upright at both ends
    assert qt.tilt(q_half) == pytest.approx(math.pi, abs=1e-3)  # upside down halfway
    assert max(map(abs, w0)) < 1e-12 and max(map(abs, w_end)) < 1e-3
    assert math.hypot(*w_half) == pytest.approx(plan.alpha * plan.duration_s / 2, rel=1e-3)  # the rate peaks halfway
    assert plan.alpha * plan.duration_s ** 2 == pytest.approx(4 * TURN)
    # the feed-forward accelerates, then brakes, about the same body axis, which stays horizontal
    assert sum(a * b for a, b in zip(ff0, plan.axis)) > 0 and sum(a * b for a, b in zip(plan.at(end_ns - 1000)[2], plan.axis)) < 0
    assert plan.axis[2] == 0.0
    # the rate is the attitude's derivative (body frame): q(t + h) = q(t) exp(omega h)
    for frac in (0.1, 0.4, 0.6, 0.9):
        t_ns = plan.t0_ns + int(frac * plan.duration_s * NS)
        q, w, _ = plan.at(t_ns)
        h_ns = 10_000
        q_next = plan.at(t_ns + h_ns)[0]
        step = qt.log(qt.mul(qt.conj(q), q_next))
        assert step == pytest.approx(tuple(c * h_ns / NS for c in w), abs=2e-5)


def test_the_turn_ends_before_touchdown_and_lifts_the_tilt_bound_only_over_it():
    flip = started_turn()
    t0, dur_ns = flip.plan.t0_ns, int(flip.plan.duration_s * NS)
    assert flip.tilt_exempt(t0 + dur_ns // 2) and flip.target(t0 + dur_ns // 2) is not None
    assert flip.target(t0 + dur_ns + 1_000_000) is None and flip.state == "landing"
    assert not flip.tilt_exempt(t0 + dur_ns + 1_000_000) and not flip.raising_hop
    flip.on_touchdown()
    assert flip.state == "idle" and flip.counters() == {"flips": 1, "flips_dropped": 0, "flips_refused": 0}


def test_a_flight_too_short_for_the_turn_pumps_and_the_request_is_dropped_after_its_hops():
    flip = controller("sim15nm").flip
    short = flip.turn_time_min() + flip.settle_s - 0.02
    assert flip.request()
    for _ in range(flip.pump_hops - 1):
        flip.on_liftoff(NS, short, 0.0)
        assert flip.state == "pumping"
    flip.on_liftoff(NS, short, 0.0)
    assert flip.state == "idle" and flip.dropped == 1 and flip.plan is None


def test_the_indoor_robot_refuses_the_flip_with_its_reason():
    """1.5 N m: a full turn within 70 % of the wheels' torque needs more than a second of flight."""
    ctrl = controller("indoor")
    assert not ctrl.request_flip()
    assert ctrl.flip.state == "idle" and ctrl.flip.refused == 1
    assert "s of flight" in ctrl.flip.last_refusal and ctrl.flip.turn_time_min() > 1.0


def test_a_disarm_cancels_a_flip_under_way():
    ctrl = controller("sim15nm")
    assert ctrl.request_flip() and ctrl.flip.state == "pumping"
    ctrl.disarm(0)
    assert ctrl.flip.state == "idle"


def test_the_tilt_bound_returns_with_the_turns_end_however_it_ends():
    """A touchdown mid-turn (a flight shorter than predicted) ends the exemption: upside down is then a fall."""
    from onboard.contracts.messages import StateEstimate

    def estimate(t_ns: int, quat) -> StateEstimate:
        return StateEstimate(stamp_ns=t_ns, position=[0.0, 0.0, 0.6], velocity=[0.0, 0.0, 0.0], quat=list(quat),
                             omega=[0.0, 0.0, 0.0], wheel_vel=[0.0, 0.0, 0.0], foot_pos=0.0, foot_vel=0.0, contact=False,
                             phase="flight", pos_vel_cov=[0.0] * 36, att_cov=[0.0] * 3)

    ctrl = controller("sim15nm")
    assert ctrl.step(0, estimate(0, qt.IDENTITY), None).armed
    assert ctrl.request_flip()
    ctrl.flip.on_liftoff(NS // 1000, 0.5, 0.0)
    upside_down = qt.from_euler(math.pi, 0.0, 0.0)
    t = NS // 1000 + 200_000_000  # within the turn
    assert ctrl.step(t, estimate(t, upside_down), None).armed
    ctrl.flip.on_touchdown()  # as the phase detector's touchdown calls it
    t += 1_000_000
    assert not ctrl.step(t, estimate(t, upside_down), None).armed
    assert ctrl.supervisor.disarm_reason == "tilt"


@pytest.mark.parametrize("seed", [0, 3])
def test_the_twin_flips_twice_lands_upright_and_hops_on(seed):
    result = ls.run(ls.RunConfig("flip", seed=seed, variant="sim15nm", estimator="kalman"))
    out = result.metrics
    assert out["falls"] == 0 and out["goal_reached"], out
    assert out["flip"] == {"flips": 2, "flips_dropped": 0, "flips_refused": 0}
    assert out["full_turns"] == 2 and out["flight_turn_max_deg"] > 340.0  # measured on the true body rate
    turns = out["flight_turns_deg"]  # every flight that turned the body past 45 deg, one by one: the two flips
    assert len(turns) == 2 and all(340.0 < a < 380.0 for a in turns), turns
    assert out["hops"] >= 25  # hopping before, between and after
    assert 1000.0 < out["max_wheel_speed_rad_s"] < rd.robot_params("sim15nm").wheel_speed_knee


def test_on_the_indoor_robot_the_flip_scenario_hops_on_unflipped():
    out = ls.run(ls.RunConfig("flip", seed=1, variant="indoor", estimator="kalman")).metrics
    assert out["falls"] == 0 and out["full_turns"] == 0
    assert out["flip"] == {"flips": 0, "flips_dropped": 0, "flips_refused": 2}
    assert "s of flight" in out["flip_refusal"]


# the turn is timed on the stack's clock: below this real-time factor the twin turns the body short of it
FLIP_JUDGED_MIN = 0.95


@pytest.mark.timing_sensitive(reason="a real-time run of processes on a shared 2-core host: a twin running behind wall time leaves the flip less time")
def test_in_real_time_the_flip_request_reaches_the_control_loop_as_a_parameter():
    """``archer sim --mode realtime --scenario flip``: the request goes as ``control.flip_request``."""
    proc = subprocess.run([sys.executable, "-m", "services.cli.main", "sim", "--mode", "realtime", "--scenario", "flip",
                           "--variant", "sim15nm", "--duration", "6.5", "--endpoint", free_endpoint(), "--namespace",
                           "test/flip", "--json", "--quiet"], capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["flip"]["requests_sent"] == 1 and out["flip"]["request_errors"] == []
    assert out["flip"]["flips_refused"] == 0 and out["flip"]["flips_dropped"] == 0, out["flip"]
    # a twin that lags wall time turns the body short (287-308 deg measured at RTF 0.74 on a slowed
    # 2-core host), or not yet: a fresh-clone CI run's twin lagged so far that the request was still
    # pending, neither refused nor dropped, at 6.5 s (0.9 deg turned), so neither the turn nor the
    # landing is a test of the flip there
    judge_realtime_outcome(out, {"flight_turn_max_deg": out["flight_turn_max_deg"], "falls": out["falls"]}, FLIP_JUDGED_MIN)
    assert out["flight_turn_max_deg"] > 180.0, out  # the loop took the request: a flight turned the body over
    assert out["falls"] == 0, out
    assert out["flip"]["flips"] == 1 and out["full_turns"] == 1


def _posed(runner: ls.LockstepRunner, z: float, quat: tuple[float, float, float, float]):
    """The twin's data with the robot's root at height ``z`` [m] and attitude ``quat``, its contacts found."""
    import mujoco

    data = mujoco.MjData(runner.model)
    root = runner.metrics.qp_root
    data.qpos[:] = runner.data.qpos
    data.qpos[root + 2] = z
    data.qpos[root + 3:root + 7] = quat
    data.qvel[:] = 0.0
    mujoco.mj_forward(runner.model, data)
    return data


def test_in_a_flip_scenario_only_a_flight_with_a_request_pending_may_turn_over():
    """The tilt bound is lifted in flight only while a requested flip is pending: a tumble in any
    other flight is a fall, and an upside-down landing is a fall whatever was requested."""
    runner = ls.LockstepRunner(ls.RunConfig("flip", seed=0, variant="sim15nm", duration_s=1.0))
    request = runner.scenario.flip_requests_s[0]
    zs = [z / 200 for z in range(120, -40, -1)]  # [m] root heights tried, lowering it to the first contact
    standing = next(d for d in (_posed(runner, z, (1.0, 0.0, 0.0, 0.0)) for z in zs) if any(runner.metrics.contacts.classify(d)))
    assert runner.metrics.contacts.classify(standing)[:2] == (True, False)  # on its foot alone
    sideways = (math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0)  # 90 deg about x
    in_the_air = _posed(runner, 2.0, sideways)
    upside_down = next(d for d in (_posed(runner, z, (0.0, 1.0, 0.0, 0.0)) for z in zs) if any(runner.metrics.contacts.classify(d)))
    assert runner.metrics.contacts.classify(upside_down)[:2] == (False, True)  # on its head
    assert not any(runner.metrics.contacts.classify(in_the_air))

    def fly(metrics, t0: float, tumble) -> None:
        """Lift off from the foot at ``t0`` and spend a flight tilted 90 deg."""
        metrics.update(t0, 0, standing, None, None, (0.0, 0.0, 0.0, 0.0))
        metrics.update(t0 + 0.01, 0, tumble, None, None, (0.0, 0.0, 0.0, 0.0))

    before = PhysicsMetrics(runner.model, runner.scenario, runner.truth, runner.safety)
    fly(before, request - 1.0, in_the_air)  # no request yet: a tumble
    assert before.falls == 1 and before.fall_reason == "tilt"

    pending = PhysicsMetrics(runner.model, runner.scenario, runner.truth, runner.safety)
    fly(pending, request + 0.5, in_the_air)  # the requested turn, under way
    assert pending.falls == 0
    pending.update(request + 0.6, 0, upside_down, None, None, (0.0, 0.0, 0.0, 0.0))  # ...landing on its head
    assert pending.falls == 1 and pending.fall_reason == "body on the ground"
