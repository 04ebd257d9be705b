"""Safety supervisor: trips on NaN, stale and invalid data, tilt, limits; arming."""

from __future__ import annotations

import dataclasses
import math

import msgspec
import pytest

from onboard.geometry import quaternion as qt
from onboard.contracts.messages import BezierSegment, ComReference, StateEstimate
from onboard.contracts.params import ControlParams, SafetyLimits
from onboard.low_level.tracking.supervisor import Supervisor

MS = 1_000_000
LIMITS = SafetyLimits()
PARAMS = ControlParams()


def estimate(stamp_ns: int, **kw) -> StateEstimate:
    fields = dict(
        stamp_ns=stamp_ns, position=[0.0, 0.0, 0.45], velocity=[0.0, 0.0, 0.0], quat=[1.0, 0.0, 0.0, 0.0],
        omega=[0.0, 0.0, 0.0], wheel_vel=[0.0, 0.0, 0.0], foot_pos=0.0, foot_vel=0.0, contact=False,
        phase="flight", pos_vel_cov=[0.0] * 36, att_cov=[0.0, 0.0, 0.0], valid=True,
    )
    fields.update(kw)
    return StateEstimate(**fields)


def armed_supervisor(t_ns: int = 0) -> Supervisor:
    sup = Supervisor(LIMITS, PARAMS)
    assert sup.check_estimate(t_ns, estimate(t_ns))
    assert sup.armed
    assert [e.trip for e in sup.drain_events()] == ["arm"]
    return sup


def test_arms_only_when_requested_valid_and_upright():
    sup = Supervisor(LIMITS, dataclasses.replace(PARAMS, auto_arm=False))
    assert not sup.check_estimate(0, estimate(0))
    assert not sup.armed
    sup.request_arm()
    tilted = qt.from_euler(PARAMS.arm_tilt_max + 0.05, 0.0, 0.0)
    assert not sup.check_estimate(MS, estimate(MS, quat=list(tilted)))
    assert not sup.check_estimate(2 * MS, estimate(2 * MS, valid=False))
    assert not sup.armed
    assert sup.check_estimate(3 * MS, estimate(3 * MS))
    assert sup.armed and sup.counts["arm"] == 1


@pytest.mark.parametrize(
    "bad",
    [
        dict(position=[math.nan, 0.0, 0.4]),
        dict(quat=[1.0, math.inf, 0.0, 0.0]),
        dict(wheel_vel=[0.0, -math.inf, 0.0]),
        dict(foot_vel=math.nan),
    ],
)
def test_non_finite_estimate_gives_the_safe_command_and_is_counted(bad):
    sup = armed_supervisor()
    assert not sup.check_estimate(MS, estimate(MS, **bad))
    ev = sup.drain_events()
    assert [e.trip for e in ev] == ["estimate_nonfinite"]
    assert sup.counts["estimate_nonfinite"] == 1
    # a good estimate again: back in business (a glitch is not a fall)
    assert sup.check_estimate(2 * MS, estimate(2 * MS))


def test_stale_estimate_trips_and_a_lasting_fault_disarms_latched():
    sup = armed_supervisor()
    stale = estimate(0)
    t = int(LIMITS.estimate_stale_s * 1e9) + MS
    assert not sup.check_estimate(t, stale)
    ev = sup.drain_events()
    assert ev[0].trip == "estimate_stale" and ev[0].value > LIMITS.estimate_stale_s
    assert sup.armed  # not yet
    end = t + int(PARAMS.estimate_fault_disarm_s * 1e9) + MS
    while t < end:
        t += MS
        sup.check_estimate(t, stale)
    assert not sup.armed
    assert sup.disarm_reason == "estimate_lost"
    assert [e.trip for e in sup.drain_events()] == ["estimate_lost"]
    # latched: a good estimate does not re-arm without a request
    assert not sup.check_estimate(t + MS, estimate(t + MS))
    sup.request_arm()
    assert sup.check_estimate(t + 2 * MS, estimate(t + 2 * MS))


def test_invalid_estimate_is_refused():
    sup = armed_supervisor()
    assert not sup.check_estimate(MS, estimate(MS, valid=False, attitude_valid=False))
    assert sup.counts["estimate_invalid"] == 1


def test_attitude_only_estimate_holds_attitude_for_its_bound_then_disarms_latched():
    sup = armed_supervisor()
    com_lost = dict(valid=False, attitude_valid=True)
    assert sup.check_estimate(MS, estimate(MS, **com_lost))
    assert sup.attitude_only and sup.armed
    assert [e.trip for e in sup.drain_events()] == ["estimate_attitude_only"]  # once per episode
    # a whole valid tick ends the episode; a stale or invalid one in between does not
    assert sup.check_estimate(2 * MS, estimate(2 * MS))
    assert not sup.attitude_only
    t = 3 * MS
    start = t
    bound = int(PARAMS.attitude_only_max_s * 1e9)
    while t - start < bound - MS:
        stamp = t if (t // MS) % 50 else t - 10 * MS  # a stale estimate now and then
        sup.check_estimate(t, estimate(stamp, **com_lost))
        t += MS
    assert sup.armed
    assert not sup.check_estimate(start + bound, estimate(start + bound, **com_lost))
    assert not sup.armed and sup.disarm_reason == "estimate_lost"
    assert not sup.attitude_only
    assert sup.drain_events()[-1].trip == "estimate_lost"
    # latched; and attitude alone never arms
    sup.request_arm()
    assert not sup.check_estimate(t + MS, estimate(t + MS, **com_lost))
    assert sup.check_estimate(t + 2 * MS, estimate(t + 2 * MS))


def test_tilt_beyond_the_limit_is_a_fall_and_disarms():
    sup = armed_supervisor()
    fallen = qt.from_euler(0.0, LIMITS.tilt_max + 0.01, 0.0)
    assert not sup.check_estimate(MS, estimate(MS, quat=list(fallen)))
    assert not sup.armed
    ev = sup.drain_events()
    assert ev[-1].trip == "tilt" and ev[-1].value == pytest.approx(LIMITS.tilt_max + 0.01) and not ev[-1].armed


def test_a_planned_turn_lifts_the_tilt_bound_and_only_while_it_lasts():
    sup = armed_supervisor()
    upside_down = list(qt.from_euler(math.pi, 0.0, 0.0))
    sup.tilt_exempt = True  # the low level's flip, within its planned turn
    assert sup.check_estimate(MS, estimate(MS, quat=upside_down)) and sup.armed
    sup.tilt_exempt = False  # the turn is over: still over is a fall
    assert not sup.check_estimate(2 * MS, estimate(2 * MS, quat=upside_down))
    assert not sup.armed and sup.drain_events()[-1].trip == "tilt"


def test_torque_clamp_and_overspeed_cutoff_trip_once_per_episode():
    sup = armed_supervisor()
    m = LIMITS.wheel_torque_max
    for k in range(5):
        wheel, foot = sup.limit_command(k * MS, (2 * m, -3 * m, 0.1), 30.0, (0.0, 0.0, 0.0))
        assert wheel == (m, -m, 0.1)
        assert foot == LIMITS.foot_torque_max
    assert sup.counts["wheel_torque"] == 1 and sup.counts["foot_torque"] == 1
    # a wheel at its speed limit may brake but not accelerate
    s = LIMITS.wheel_speed_max
    wheel, _ = sup.limit_command(6 * MS, (0.5, -0.5, 0.5), 0.0, (s, s, -s - 1))
    assert wheel == (0.0, -0.5, 0.5)
    assert sup.counts["wheel_speed"] == 1
    # back inside the limits, then over again: a second episode
    sup.limit_command(7 * MS, (0.0, 0.0, 0.0), 0.0, (0.0, 0.0, 0.0))
    sup.limit_command(8 * MS, (2 * m, 0.0, 0.0), 0.0, (0.0, 0.0, 0.0))
    assert sup.counts["wheel_torque"] == 2
    assert all(e.count >= 1 for e in sup.drain_events())


def test_non_finite_command_never_reaches_a_motor():
    sup = armed_supervisor()
    wheel, foot = sup.limit_command(MS, (math.nan, 0.2, 0.1), 1.0, (0.0, 0.0, 0.0))
    assert wheel == (0.0, 0.0, 0.0) and foot == 0.0
    assert sup.counts["command_nonfinite"] == 1


def reference(stamp_ns: int, points=((0.0, 0.0), (1.0, 0.0))) -> ComReference:
    return ComReference(stamp_ns=stamp_ns, t_ref_ns=0,
                        segments=[BezierSegment(t0=0.0, duration=4.0, control_points=[list(p) for p in points])])


def test_stale_or_malformed_reference_falls_back_to_hopping_in_place():
    sup = armed_supervisor()
    ref = reference(0)
    assert sup.check_reference(MS, ref) is ref
    assert sup.check_reference(MS, None) is None
    late = int(LIMITS.reference_stale_s * 1e9) + MS
    assert sup.check_reference(late, ref) is None
    assert sup.check_reference(late + MS, ref) is None
    assert sup.counts["reference_stale"] == 1  # one trip per episode
    fresh = reference(late)
    assert sup.check_reference(late + MS, fresh) is fresh
    bad = ComReference(stamp_ns=late, t_ref_ns=0, segments=[])
    assert sup.check_reference(late + MS, bad) is None
    nan_ref = reference(late, points=((0.0, 0.0), (math.nan, 0.0)))
    assert sup.check_reference(late + 2 * MS, nan_ref) is None
    assert sup.check_reference(late + 3 * MS, nan_ref) is None  # the verdict holds for the same message
    assert sup.counts["reference_invalid"] == 1
    assert sup.check_reference(late + 4 * MS, fresh) is fresh  # and does not stick to the next one


def test_a_republished_reference_keeps_its_verdict_and_new_segments_are_checked():
    """A planner republishing its kept path wraps the same segments in a new message (checked
    once); a message with other segments is checked again, whatever came before it."""
    sup = armed_supervisor()
    good = reference(0)
    assert sup.check_reference(MS, good) is good
    copy = msgspec.structs.replace(good, stamp_ns=MS)
    assert copy.segments is good.segments
    assert sup.check_reference(2 * MS, copy) is copy
    nan_ref = reference(2 * MS, points=((0.0, 0.0), (math.nan, 0.0)))
    assert sup.check_reference(3 * MS, nan_ref) is None
    assert sup.check_reference(4 * MS, msgspec.structs.replace(nan_ref, stamp_ns=4 * MS)) is None
    assert sup.counts["reference_invalid"] == 1
    in_place = reference(5 * MS)
    assert sup.check_reference(5 * MS, in_place) is in_place
