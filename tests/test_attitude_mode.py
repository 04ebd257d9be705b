"""Attitude mode of the low level (``control.output = "attitude"``): setpoints for a board that
runs the PD and the foot itself (ARCHER's firmware), and the loop process publishing them."""

from __future__ import annotations

import dataclasses
import math
import time

import pytest

from onboard.contracts import messages as msgs
from onboard.geometry import quaternion as qt
from onboard.contracts.messages import BezierSegment, ComReference
from onboard.contracts.params import ControlParams, SafetyLimits, restart_changes
from onboard.contracts.topics import TOPICS
from robot_description.controller import build_controller
from services.control import ControlLoop, LoopConfig
from test_low_level import MS, estimate, joints

ATTITUDE = dataclasses.replace(ControlParams(), output="attitude")


@pytest.fixture(scope="module")
def make():
    def build(params: ControlParams = ATTITUDE, safety: SafetyLimits | None = None):
        c = build_controller("indoor", params, safety)
        c.request_arm()
        return c
    return build


def fly(c, ref, attitude: bool, n: int = 60):
    """``n`` ms of descending flight towards ``ref``; the last command."""
    out = None
    for k in range(n):
        t = k * MS
        s = estimate(t, vz=-0.5, xy=(0.02, -0.01), vxy=(0.1, 0.0))
        out = c.step_attitude(t, s, ref) if attitude else c.step(t, s, ref, joints(t))
    return out


def test_flight_setpoint_is_the_policy_attitude_the_torque_mode_tracks(make):
    ref = ComReference(stamp_ns=0, t_ref_ns=0, hold=True, segments=[BezierSegment(t0=0.0, duration=1.0, control_points=[[0.6, 0.2]])])
    att, tor = make(), make(ControlParams())
    sp = fly(att, ref, attitude=True)
    fly(tor, ref, attitude=False)
    assert isinstance(sp, msgs.AttitudeSetpoint) and sp.armed
    assert sp.quat_des == pytest.approx(list(tor.q_des), abs=1e-12)  # the same ZDP, the same impact attitude
    assert qt.angle_between(tuple(sp.quat_des), qt.IDENTITY) > 0.01  # leaning towards the reference
    assert sp.omega_des == [0.0, 0.0, 0.0] and sp.torque_ff == [0.0, 0.0, 0.0]
    assert sp.foot_torque == 0.0  # the foot board runs the hop by itself


def test_on_the_ground_upright_then_the_pd_follows_the_estimate_and_wheels_spin_down(make):
    c = make()
    yaw = 0.7
    q = qt.from_euler(0.0, 0.0, yaw)
    sp = c.step_attitude(0, estimate(0, contact=True, quat=q), None)  # arms standing: upright, heading held
    assert sp.armed and qt.angle_between(tuple(sp.quat_des), q) < 1e-9
    c = make()
    c.step_attitude(0, estimate(0, quat=q), None)
    ref = ComReference(stamp_ns=0, t_ref_ns=0, hold=True, segments=[BezierSegment(t0=0.0, duration=1.0, control_points=[[0.5, 0.0]])])
    t = 0
    for k in range(60):
        t = (k + 1) * MS
        flight = c.step_attitude(t, estimate(t, vz=-1.0, quat=q), ref)
    assert c.phase.phase == "flight"
    t += MS
    tilted, rate = qt.from_euler(0.05, -0.03, yaw), (0.2, -0.1, 0.0)
    landed = c.step_attitude(t, estimate(t, contact=True, quat=tilted, omega=rate, wheel_vel=(40.0, -20.0, 0.0)), ref)
    assert c.phase.phase == "stance" and flight.quat_des != landed.quat_des
    # the board's PD adds nothing: it is asked for the attitude and rate the robot has
    assert landed.quat_des == pytest.approx(list(tilted)) and landed.omega_des == pytest.approx(list(rate))
    gamma = ATTITUDE.spin_down_gamma
    assert landed.torque_ff[0] == pytest.approx(-gamma * 40.0) and landed.torque_ff[1] == pytest.approx(gamma * 20.0)
    assert landed.torque_ff[2] == 0.0 and landed.foot_torque == 0.0


def test_feed_forward_is_clamped_to_the_wheel_limit(make):
    c = make(ATTITUDE, SafetyLimits(wheel_torque_max=0.5))
    for k in range(60):
        c.step_attitude(k * MS, estimate(k * MS, vz=-1.0), None)
    sp = c.step_attitude(60 * MS, estimate(60 * MS, contact=True, wheel_vel=(400.0, 0.0, 0.0)), None)
    assert c.phase.phase == "stance" and sp.armed and sp.torque_ff[0] == pytest.approx(-0.5)


def test_bad_estimate_gives_a_disarmed_setpoint_and_a_safety_event(make):
    c = make()
    c.step_attitude(0, estimate(0, contact=True), None)
    c.drain_safety_events()
    sp = c.step_attitude(MS, estimate(MS, z=math.nan), None)
    assert not sp.armed and sp.torque_ff == [0.0, 0.0, 0.0] and sp.foot_torque == 0.0
    assert qt.is_finite(tuple(sp.quat_des)) and abs(qt.norm(tuple(sp.quat_des)) - 1.0) < 1e-9  # still a packable quaternion
    assert [e.trip for e in c.drain_safety_events()] == ["estimate_nonfinite"]


def test_output_needs_a_loop_restart():
    assert restart_changes("control", ControlParams(), ATTITUDE) == ["control.output"]
    with pytest.raises(ValueError):
        build_controller("indoor").retune(ATTITUDE, SafetyLimits())


def test_the_loop_publishes_attitude_setpoints_with_its_commander_and_no_torques(zenoh_router, zenoh_session):
    ns = "archer/attmode"
    got: dict[str, list] = {"attitude_cmd": [], "torque_cmd": []}
    subs = [zenoh_session.declare_subscriber(TOPICS[name].key(ns), lambda s, name=name: got[name].append(s.payload.to_bytes()))
            for name in got]
    loop = ControlLoop(LoopConfig(ns=ns, endpoint=zenoh_router, zenoh_config=None, control=dataclasses.replace(ATTITUDE, rt_priority=0),
                                  safety=SafetyLimits(), commander="c0ffee"))
    try:
        loop.tick(0.0)  # no estimate yet: disarmed
        now = loop.clock.now_ns()
        loop.slots["state"].put(estimate(now, contact=True), now)
        loop.tick(0.0)
        end = time.monotonic() + 5.0
        while len(got["attitude_cmd"]) < 2 and time.monotonic() < end:
            time.sleep(0.01)
    finally:
        loop.close()
        for s in subs:
            s.undeclare()
    first, second = (msgs.decode(raw, msgs.AttitudeSetpoint) for raw in got["attitude_cmd"][:2])
    assert not first.armed and second.armed
    assert first.commander == second.commander == "c0ffee"
    assert got["torque_cmd"] == []


# real time: loops at their rate, processes and Zenoh over loopback share two loaded cores
pytestmark = pytest.mark.timing_sensitive(reason="real-time loops, processes or Zenoh over loopback on a shared host")
