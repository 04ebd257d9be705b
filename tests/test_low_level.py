"""Low-level pieces: phase detection, tube, hop regulator, MLP inference, reference
sampling, and the composed controller's behaviour on synthetic estimates."""

from __future__ import annotations

import dataclasses
import math

import msgspec
import numpy as np
import pytest

from onboard.geometry import quaternion as qt
from onboard.low_level.tracking.foot_control import FootPhysics, HopRegulator
from onboard.contracts.reference import sample_reference
from onboard.contracts.messages import BezierSegment, ComReference, JointSensors, StateEstimate
from onboard.low_level.planning.mlp import Mlp
from onboard.contracts.params import ControlParams, SafetyLimits
from onboard.estimation.phase import PhaseDetector
from onboard.contracts.tube import TubeMonitor
from robot_description.controller import build_controller

MS = 1_000_000


def estimate(t_ns: int, z: float = 0.45, vz: float = 0.0, contact: bool = False, foot_vel: float = 0.0,
             quat=(1.0, 0.0, 0.0, 0.0), omega=(0.0, 0.0, 0.0), xy=(0.0, 0.0), vxy=(0.0, 0.0),
             wheel_vel=(0.0, 0.0, 0.0), foot_pos: float = 0.0) -> StateEstimate:
    return StateEstimate(
        stamp_ns=t_ns, position=[xy[0], xy[1], z], velocity=[vxy[0], vxy[1], vz], quat=list(quat),
        omega=list(omega), wheel_vel=list(wheel_vel), foot_pos=foot_pos, foot_vel=foot_vel, contact=contact,
        phase="stance" if contact else "flight", pos_vel_cov=[0.0] * 36, att_cov=[0.0] * 3,
    )


# --- phase detection -------------------------------------------------------------------------


def synthetic_hops(n_hops: int, chatter: bool = False):
    """A bouncing CoM: ballistic flights, spring-like stances; optional contact chatter."""
    g, t_ns, z_td, vz0 = 9.81, 0, 0.40, 1.4
    flight = 2 * vz0 / g
    stance = 0.07
    out = []
    for _ in range(n_hops):
        for k in range(int(flight * 1000)):
            t = k / 1000
            c = chatter and k == 3  # a bounce of the contact switch just after lift-off
            out.append(estimate(t_ns, z_td + vz0 * t - 0.5 * g * t * t, vz0 - g * t, contact=c))
            t_ns += MS
        for k in range(int(stance * 1000)):
            phase = k / (stance * 1000)
            out.append(estimate(t_ns, z_td - 0.03 * math.sin(math.pi * phase), 0.0, contact=True,
                                foot_vel=math.cos(math.pi * phase)))
            t_ns += MS
    return out


@pytest.mark.parametrize("chatter", [False, True])
def test_phase_detector_sees_each_event_once_per_hop(chatter):
    det = PhaseDetector(min_flight_s=0.05, min_stance_s=0.02, touchdown_height=0.4)
    events = [e.event for s in synthetic_hops(5, chatter) if (e := det.update(s.stamp_ns, s)) is not None]
    assert events == ["apex", "touchdown", "bottom", "liftoff"] * 4 + ["apex", "touchdown", "bottom"]
    assert det.hop == 5
    assert det.last_apex_height == pytest.approx(0.40 + 1.4**2 / (2 * 9.81), abs=2e-3)


# --- tube ------------------------------------------------------------------------------------


def test_tube_reports_percentiles_over_its_window():
    tube = TubeMonitor(window=10)
    assert tube.tube(5).hops == 0
    for k in range(25):
        tube.record_impact(0.01 * k, 0.001 * k)
    t = tube.tube(7)
    assert t.hops == 10 and t.stamp_ns == 7
    vals = np.array([0.01 * k for k in range(15, 25)])
    assert t.impact_err_p50 == pytest.approx(np.percentile(vals, 50))
    assert t.impact_err_p95 == pytest.approx(np.percentile(vals, 95))
    assert t.impact_err_max == pytest.approx(0.24)
    assert t.attitude_err_p95 == pytest.approx(np.percentile(vals / 10, 95))
    assert tube.impacts == 25


# --- hop regulator ----------------------------------------------------------------------------


def test_hop_regulator_reaches_the_hop_height_and_learns_the_loss():
    params = dataclasses.replace(ControlParams(), hop_height=0.10)
    phys = FootPhysics(total_mass=6.0, gravity=9.81, spring_k=11700.0, spool_radius=0.015, travel=0.1)
    reg = HopRegulator(params, phys, loss_nominal=0.3)
    true_loss = 1.0  # [J] per hop, unknown to the regulator
    mg = 6.0 * 9.81
    h = 0.04
    for _ in range(40):
        reg.in_flight(h)
        d = reg.preload_cmd
        reg.on_touchdown(d)
        h = h + (0.5 * phys.spring_k * d * d - true_loss) / mg
        reg.on_apex(h)
    assert h == pytest.approx(0.10, abs=2e-3)
    assert reg.loss == pytest.approx(true_loss, rel=0.05)
    # the spool winds towards the preload in flight and unwinds past the foot in stance
    assert reg.spool_torque(False, 0.0, 0.0, 0.0) > 0.0
    assert reg.spool_torque(True, 0.03, 1.0, 0.0) < 0.0


def test_hop_regulator_never_asks_for_more_than_the_travel_allows():
    params = dataclasses.replace(ControlParams(), hop_height=0.5, preload_max=0.04)
    phys = FootPhysics(6.0, 9.81, 11700.0, 0.015, 0.1)
    reg = HopRegulator(params, phys, loss_nominal=1.0)
    reg.in_flight(0.0)
    assert reg.preload_cmd == pytest.approx(0.04)


# --- MLP ---------------------------------------------------------------------------------------


def test_mlp_inference_matches_a_hand_computation():
    w = {
        "W0": np.array([[1.0, -1.0], [0.5, 2.0]]), "b0": np.array([0.0, -1.0]),
        "W1": np.array([[2.0, 1.0]]), "b1": np.array([0.5]),
        "x_scale": np.array([2.0, 1.0]), "y_scale": np.array([10.0]),
    }
    net = Mlp(w)
    x = (4.0, 1.0)  # scaled: (2, 1) -> hidden relu((1, 2)) = (1, 2) -> 2 + 2 + 0.5 = 4.5 -> 45
    assert net(x) == pytest.approx((45.0,))
    assert net.forward(np.array([x, (-4.0, 1.0)]))[:, 0] == pytest.approx([45.0, 10.0 * (0.0 + 0.0 + 0.5)])


def test_mlp_refuses_malformed_weights():
    with pytest.raises(ValueError):
        Mlp({})
    with pytest.raises(ValueError):
        Mlp({"W0": np.ones((3, 2)), "b0": np.ones(2)})
    with pytest.raises(ValueError):
        Mlp({"W0": np.ones((3, 2)), "b0": np.ones(3), "W1": np.ones((1, 4)), "b1": np.ones(1)})
    with pytest.raises(ValueError):
        Mlp({"W0": np.full((1, 1), np.nan), "b0": np.ones(1)})


# --- reference sampling -------------------------------------------------------------------------


def test_reference_sample_gives_bezier_position_and_velocity():
    ref = ComReference(t_ref_ns=0, segments=[
        BezierSegment(t0=1.0, duration=4.0, control_points=[[0.0, 0.0], [0.0, 0.0], [2.0, 0.0], [2.0, 0.0]]),
    ])
    assert sample_reference(ref, 0.0) == (0.0, 0.0, 0.0, 0.0)
    x, y, vx, vy = sample_reference(ref, 3.0)  # half way: x = 1, speed = 1.5 * 2 / 4
    assert (x, y) == pytest.approx((1.0, 0.0))
    assert (vx, vy) == pytest.approx((0.75, 0.0))
    assert sample_reference(ref, 9.0) == (2.0, 0.0, 0.0, 0.0)


@pytest.mark.parametrize("degree", range(6))
def test_scalar_reference_sampling_agrees_with_onboard_bezier(degree):
    from onboard.geometry import bezier

    rng = np.random.default_rng(degree)
    pts = rng.standard_normal((degree + 1, 2))
    ref = ComReference(t_ref_ns=0, segments=[BezierSegment(t0=1.0, duration=2.5, control_points=pts.tolist())])
    for t in (1.0, 1.3, 2.0, 3.4):
        x, y, vx, vy = sample_reference(ref, t)
        assert (x, y) == pytest.approx(tuple(bezier.evaluate(pts, 2.5, t - 1.0)))
        v = bezier.evaluate(bezier.hodograph(pts, 2.5), 2.5, t - 1.0) if degree else np.zeros(2)
        assert (vx, vy) == pytest.approx(tuple(v))


@pytest.mark.parametrize("degree", [1, 3])
def test_unrolled_reference_sampling_is_bit_identical_to_the_loop(degree):
    # the lockstep run's determinism across versions rests on the same bits, not approx
    from onboard.contracts.reference import _bernstein_point

    rng = np.random.default_rng(10 + degree)
    for _ in range(200):
        pts = rng.uniform(-5.0, 5.0, (degree + 1, 2)).tolist()
        tau = float(rng.uniform(0.1, 10.0))
        ref = ComReference(t_ref_ns=0, segments=[BezierSegment(t0=0.0, duration=tau, control_points=pts)])
        t = float(rng.uniform(0.0, tau))
        s = t / tau
        k = degree / tau
        hod = [[k * (b[0] - a[0]), k * (b[1] - a[1])] for a, b in zip(pts[:-1], pts[1:])]
        assert sample_reference(ref, t) == (*_bernstein_point(pts, s), *_bernstein_point(hod, s))


# --- the composed controller on synthetic estimates ---------------------------------------------


@pytest.fixture(scope="module")
def ctrl_factory():
    def make(**over):
        c = build_controller("indoor", dataclasses.replace(ControlParams(), **over))
        c.request_arm()
        return c
    return make


def joints(t_ns: int, spool: float = 0.0) -> JointSensors:
    return JointSensors(stamp_ns=t_ns, wheel_pos=[0.0] * 3, wheel_vel=[0.0] * 3, wheel_torque=[0.0] * 3,
                        foot_pos=0.0, foot_vel=0.0, foot_contact=False, foot_motor_pos=spool)


def test_flight_pd_rights_a_tilted_robot_and_stance_spins_wheels_down(ctrl_factory):
    c = ctrl_factory()
    q = qt.from_euler(0.1, 0.0, 0.0)  # rolled about body x, CoM at the hold point, at rest
    cmd = c.step(0, estimate(0, quat=q), None, joints(0))
    assert cmd.armed
    body = c.alloc.body_torque(cmd.wheel_torque)
    assert body[0] < 0.0  # torque against the roll
    assert abs(body[1]) < 0.05 * abs(body[0])
    # stance: wheel torque opposes the wheel speed
    c2 = ctrl_factory()
    c2.step(0, estimate(0), None, joints(0))
    t = 0
    for k in range(60):  # enough flight for the detector's dwell time
        t = (k + 1) * MS
        c2.step(t, estimate(t, vz=-1.0), None, joints(t))
    t += MS
    cmd = c2.step(t, estimate(t, contact=True, wheel_vel=(100.0, -50.0, 0.0)), None, joints(t))
    assert c2.phase.phase == "stance"
    assert cmd.wheel_torque[0] < 0 < cmd.wheel_torque[1] and cmd.wheel_torque[2] == 0.0


def test_policy_places_the_foot_towards_the_reference(ctrl_factory):
    for policy in ("zdp", "raibert", "lqr"):
        c = ctrl_factory(policy=policy)
        ref = ComReference(stamp_ns=0, t_ref_ns=0, hold=True,
                           segments=[BezierSegment(t0=0.0, duration=1.0, control_points=[[1.0, 0.5]])])
        c.step(0, estimate(0, vz=0.5), ref, joints(0))
        ax, ay = c.eta
        # the body z axis leans towards the goal (the foot lands behind, pushing the CoM forward)
        assert ax > 0.0 and ay > 0.0, policy
        assert ax > ay
    # clipped policies never ask for more than the tilt limit
    c = ctrl_factory(policy="zdp", tilt_cmd_max=0.05)
    far = ComReference(stamp_ns=0, t_ref_ns=0, hold=True,
                       segments=[BezierSegment(t0=0.0, duration=1.0, control_points=[[50.0, 0.0]])])
    c.step(0, estimate(0, vz=0.5), far, joints(0))
    assert math.hypot(*c.eta) <= math.sin(0.05) + 1e-12


def test_attitude_only_estimate_keeps_the_body_upright_without_position_feedback(ctrl_factory):
    c = ctrl_factory()
    ref = ComReference(stamp_ns=0, t_ref_ns=0, hold=True,
                       segments=[BezierSegment(t0=0.0, duration=1.0, control_points=[[1.0, 0.5]])])
    c.step(0, estimate(0, vz=0.5), ref, joints(0))
    assert math.hypot(*c.eta) > 0.0  # the policy leans towards the reference
    tilted = qt.from_euler(0.1, 0.0, 0.0)
    com_lost = msgspec.structs.replace(estimate(MS, vz=0.5, quat=tilted), valid=False, attitude_valid=True)
    cmd = c.step(MS, com_lost, ref, joints(MS))
    assert cmd.armed and c.supervisor.attitude_only
    assert c.eta == (0.0, 0.0) and qt.tilt(c.q_des) < 1e-9
    # the PD rights the tilted body: roll torque against the roll
    upright = c.step(2 * MS, msgspec.structs.replace(com_lost, stamp_ns=2 * MS, quat=[1.0, 0.0, 0.0, 0.0]), ref, joints(2 * MS))
    assert cmd.wheel_torque != upright.wheel_torque
    assert "estimate_attitude_only" in [e.trip for e in c.drain_safety_events()]


def test_nan_estimate_gives_zero_torque_and_a_safety_event(ctrl_factory):
    c = ctrl_factory()
    c.step(0, estimate(0), None, joints(0))
    c.drain_safety_events()
    cmd = c.step(MS, estimate(MS, z=math.nan), None, joints(MS))
    assert not cmd.armed and cmd.wheel_torque == [0.0, 0.0, 0.0] and cmd.foot_torque == 0.0
    assert [e.trip for e in c.drain_safety_events()] == ["estimate_nonfinite"]


def test_retune_takes_new_gains_and_limits_between_ticks_and_keeps_the_state(ctrl_factory):
    q = qt.from_euler(0.01, -0.005, 0.0)  # a small tilt: the PD output stays inside the torque limit
    states = [estimate(k * MS, vz=0.5 - 0.00981 * k, quat=q) for k in range(40)]
    live = ctrl_factory()
    before = [live.step(s.stamp_ns, s, None, joints(s.stamp_ns)) for s in states[:20]]
    assert all(c.armed for c in before)
    hops, arm_trips = live.phase.hop, live.supervisor.counts.get("arm")

    faster = dataclasses.replace(ControlParams(), kp_tilt=80.0, kd_tilt=5.0)
    live.retune(faster, SafetyLimits(wheel_torque_max=1.2))
    fresh = build_controller("indoor", faster, SafetyLimits(wheel_torque_max=1.2))
    fresh.request_arm()
    for s in states[:20]:  # the same history: gains do not enter the controller's state
        fresh.step(s.stamp_ns, s, None, joints(s.stamp_ns))
    for s in states[20:]:
        got = live.step(s.stamp_ns, s, None, joints(s.stamp_ns))
        want = fresh.step(s.stamp_ns, s, None, joints(s.stamp_ns))
        assert got.armed and got.wheel_torque == want.wheel_torque
    assert live.phase.hop == hops and live.supervisor.counts.get("arm") == arm_trips  # no re-arm, no reset
    assert max(map(abs, got.wheel_torque)) > 1.5 * max(map(abs, before[-1].wheel_torque))  # kp doubled

    # a tighter safety limit clamps the very next command
    live.retune(faster, SafetyLimits(wheel_torque_max=0.01))
    t = 40 * MS
    cmd = live.step(t, estimate(t, vz=0.5 - 0.00981 * 40, quat=q), None, joints(t))
    assert cmd.armed and max(map(abs, cmd.wheel_torque)) <= 0.01

    # what the constructor derived cannot be retuned: refused, nothing changed
    with pytest.raises(ValueError, match=r"control\.hop_height, control\.rate_hz"):
        live.retune(dataclasses.replace(faster, rate_hz=500.0, hop_height=0.1, kp_tilt=1.0), SafetyLimits())
    assert live.p.kp_tilt == 80.0 and live.safety.wheel_torque_max == 0.01


def test_unknown_policy_and_missing_weights_are_refused():
    with pytest.raises(ValueError):
        build_controller("indoor", dataclasses.replace(ControlParams(), policy="magic"))
    with pytest.raises(FileNotFoundError):
        build_controller("indoor", dataclasses.replace(ControlParams(), policy="mlp", mlp_weights="/nonexistent.npz"))


# --- the neural policy --------------------------------------------------------------------------


def test_training_script_runs_and_its_network_drives_the_controller(tmp_path):
    from services.cli import train_zdp

    out = tmp_path / "tiny.npz"
    assert train_zdp.main(["--samples", "20", "--steps", "30", "--out", str(out)]) == 0
    c = build_controller("indoor", dataclasses.replace(ControlParams(), policy="mlp", mlp_weights=str(out)))
    c.request_arm()
    cmd = c.step(0, estimate(0, vz=0.5, xy=(0.2, 0.0)), None, joints(0))
    assert cmd.armed and all(math.isfinite(v) for v in cmd.wheel_torque)
    assert math.hypot(*c.eta) <= math.sin(ControlParams().tilt_cmd_max) + 1e-12


def test_committed_network_reproduces_the_optimal_impact_attitude():
    from robot_description.controller import load_policy_weights

    w = load_policy_weights(ControlParams().mlp_weights)
    assert float(w["meta_validation_rms"]) < 0.005  # [rad-ish] against held-out targets
    net = Mlp(w)
    lim = math.sin(ControlParams().tilt_cmd_max)
    # the foot goes towards the error: +x position or velocity error -> lean back (a_x < 0)
    for err in ((0.2, 0.0, 0.0, 0.0), (0.0, 0.0, 0.4, 0.0)):
        ax, ay = net(err)
        assert ax < -0.2 * lim and abs(ay) < 0.3 * abs(ax)
    # symmetric hopper: a point reflection of the error reflects the command
    z = np.array([0.1, -0.05, 0.2, 0.1])
    assert np.allclose(net(tuple(z)), -np.array(net(tuple(-z))), atol=0.15 * lim)
