"""The geometric MPC as the mid level: the low level tracks its setpoint and falls back to the
ZDP when there is none fresh and finite; the mid level turns estimates into setpoints and
refuses what it cannot use; on the twin it tracks the square without a fall."""

from __future__ import annotations

import math

import msgspec
import pytest

from onboard.low_level.tracking import attitude_control as ac
from onboard.contracts import messages as m
from onboard.geometry import quaternion as qt
from onboard.contracts.params import ControlParams, GeometricMpcParams, SafetyLimits
from robot_description.controller import build_controller, build_gmpc_mid_level
from sim_twin.lockstep import RunConfig, run

MS = 1_000_000


def estimate(t_ns: int, z: float = 0.5, vz: float = -0.5, quat=(1.0, 0.0, 0.0, 0.0), xy=(0.0, 0.0), vxy=(0.0, 0.0),
             valid: bool = True, contact: bool = False) -> m.StateEstimate:
    return m.StateEstimate(stamp_ns=t_ns, position=[xy[0], xy[1], z], velocity=[vxy[0], vxy[1], vz], quat=list(quat),
                           omega=[0.0, 0.0, 0.0], wheel_vel=[0.0, 0.0, 0.0], foot_pos=0.02, foot_vel=0.0, contact=contact,
                           phase="stance" if contact else "flight", pos_vel_cov=[0.0] * 36, att_cov=[0.0] * 3, valid=valid)


def setpoint(t_ns: int, quat=None, omega=(0.3, -0.2, 0.0), ff=(0.1, 0.2, -0.1)) -> m.MidLevelSetpoint:
    quat = quat if quat is not None else qt.from_euler(0.05, -0.08, 0.0)
    return m.MidLevelSetpoint(stamp_ns=t_ns, quat_des=list(quat), omega_des=list(omega), torque_ff=list(ff), qp_iterations=[7, 7])


def controller(mid_level: str = "geometric_mpc"):
    c = build_controller("sim15nm", ControlParams(mid_level=mid_level), SafetyLimits(wheel_torque_max=15.0))
    c.request_arm()
    return c


def test_the_loop_tracks_a_fresh_setpoint_with_the_quaternion_pd():
    c = controller()
    st = estimate(10 * MS, quat=qt.from_euler(-0.02, 0.03, 0.0))
    sp = setpoint(5 * MS)
    cmd = c.step(10 * MS, st, None, None, sp)
    p = c.p
    body = ac.pd_torque(st.quat, st.omega, sp.quat_des, sp.omega_des, c.alloc.body_torque(sp.torque_ff),
                        (p.kp_tilt, p.kp_tilt, p.kp_yaw), (p.kd_tilt, p.kd_tilt, p.kd_yaw), p.attitude_log)
    assert cmd.armed
    assert cmd.wheel_torque == pytest.approx(list(c.alloc.wheel_torques(body)), abs=1e-12)
    assert (c.mid_level_ticks, c.mid_level_fallback_ticks) == (1, 0)
    assert tuple(c.q_des) == tuple(sp.quat_des)


@pytest.mark.parametrize("bad", ["stale", "nan_quat", "inf_ff", "none"])
def test_without_a_fresh_finite_setpoint_the_zdp_flies(bad):
    now = 100 * MS
    sp = {"stale": setpoint(now - int((ControlParams().mid_level_stale_s + 0.001) * 1e9)),
          "nan_quat": setpoint(now, quat=(math.nan, 0.0, 0.0, 1.0)),
          "inf_ff": setpoint(now, ff=(math.inf, 0.0, 0.0)),
          "none": None}[bad]
    gmpc, zdp = controller(), controller("zdp")
    st = estimate(now, quat=qt.from_euler(0.04, 0.0, 0.0), vxy=(0.3, 0.0))
    cmd = gmpc.step(now, st, None, None, sp)
    assert cmd.wheel_torque == zdp.step(now, st, None, None).wheel_torque  # exactly the ZDP's command
    assert all(math.isfinite(v) for v in cmd.wheel_torque)
    assert (gmpc.mid_level_ticks, gmpc.mid_level_fallback_ticks) == (0, 1)


def test_with_the_zdp_mid_level_a_setpoint_is_ignored():
    c, plain = controller("zdp"), controller("zdp")
    st = estimate(10 * MS)
    assert c.step(10 * MS, st, None, None, setpoint(9 * MS)).wheel_torque == plain.step(10 * MS, st, None, None).wheel_torque
    assert (c.mid_level_ticks, c.mid_level_fallback_ticks) == (0, 0)


@pytest.fixture(scope="module")
def mid():
    return build_gmpc_mid_level("sim15nm", GeometricMpcParams(), ControlParams(mid_level="geometric_mpc"),
                                SafetyLimits(wheel_torque_max=15.0))


def test_the_mid_level_answers_a_flight_estimate_with_a_setpoint_toward_the_target(mid):
    """Behind the held place and moving away from it: the plan leans the body so that the
    landing pushes back (foot placed beyond the CoM in the direction of travel)."""
    mid.hold = None
    hold = m.ComReference(stamp_ns=0, t_ref_ns=0, hold=True,
                          segments=[m.BezierSegment(t0=0.0, duration=1.0, control_points=[[0.0, 0.0], [0.0, 0.0]])])
    sp = mid.step(50 * MS, estimate(50 * MS, z=0.55, xy=(0.0, 0.0), vxy=(0.4, 0.0)), hold)
    assert sp is not None and mid.last_solution.ok
    msgspec.json.decode(m.encode(sp), type=m.MidLevelSetpoint)  # it goes out as a message
    knots = mid.last_solution.knots
    touchdown = next(k for k, knot in enumerate(knots) if knot.kind == "touchdown")
    q_td = qt.mul(mid.last_solution.q0, qt.exp(mid.last_solution.z[touchdown][3:6]))
    assert qt.body_z(q_td)[0] < -0.02  # the foot, at -leg * body z from the CoM, lands ahead of it
    assert all(abs(u) <= 15.0 for u in sp.torque_ff)


@pytest.mark.parametrize("bad", ["invalid", "nan"])
def test_the_mid_level_refuses_an_unusable_estimate(mid, bad):
    before = mid.rejected
    st = estimate(60 * MS, valid=bad != "invalid")
    if bad == "nan":
        st = msgspec.structs.replace(st, velocity=[math.nan, 0.0, -0.5])
    assert mid.step(60 * MS, st, None) is None
    assert mid.rejected == before + 1 and mid.last_status == "estimate not usable"


def _run(mid_level: str) -> dict:
    cfg = RunConfig(scenario="square", seed=0, duration_s=8.0, variant="sim15nm", estimator="kalman",
                    control_params=ControlParams(mid_level=mid_level))
    return run(cfg).metrics


def test_on_the_twin_the_mpc_tracks_the_square_closer_than_the_zdp():
    gmpc, zdp = _run("geometric_mpc"), _run("zdp")
    assert gmpc["falls"] == 0 and gmpc["hops"] >= 20
    assert gmpc["mid_level_solves"] >= 790  # 100 Hz
    assert gmpc["mid_level_fallback_ticks"] < 0.01 * gmpc["mid_level_ticks"]  # the first ms only
    assert gmpc["rms_tracking_error_m"] < 0.7 * zdp["rms_tracking_error_m"]


def plan_setpoint(t_ns: int, **change) -> m.MidLevelSetpoint:
    """A plan of two flight knots (0-20 ms, 20-40 ms) turning about body x, then a touchdown."""
    q1, q2 = qt.from_euler(0.04, 0.0, 0.0), qt.from_euler(0.08, 0.0, 0.0)
    fields = dict(plan_t=[0.0, 0.02, 0.04, 0.04], plan_quat=[list(qt.IDENTITY), list(q1), list(q2), list(q2)],
                  plan_omega=[[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.2, 0.0, 0.0]],
                  plan_torque=[[0.5, 0.0, 0.0], [-0.5, 0.0, 0.0], [0.0, 0.0, 0.0]])
    fields.update(change)
    return m.MidLevelSetpoint(stamp_ns=t_ns, quat_des=list(qt.IDENTITY), omega_des=[0.0, 0.0, 0.0], torque_ff=[0.0, 0.0, 0.0],
                              qp_iterations=[7, 7], **fields)


def test_the_loop_follows_the_plan_at_the_time_it_acts():
    c = controller()
    sp = plan_setpoint(0)
    q, w, ff = c._mid_level_target(10 * MS, sp)  # half-way through the first knot
    assert qt.angle_between(q, qt.from_euler(0.02, 0.0, 0.0)) < 1e-9
    assert w == pytest.approx((1.0, 0.0, 0.0)) and list(ff) == [0.5, 0.0, 0.0]
    q, _, ff = c._mid_level_target(25 * MS, sp)  # the second knot: its own torque
    assert qt.angle_between(q, qt.from_euler(0.05, 0.0, 0.0)) < 1e-9 and list(ff) == [-0.5, 0.0, 0.0]
    q, w, ff = c._mid_level_target(45 * MS, sp)  # past the plan: its end, no feed-forward
    assert qt.angle_between(q, qt.from_euler(0.08, 0.0, 0.0)) < 1e-9 and list(w) == [0.2, 0.0, 0.0] and ff == (0.0, 0.0, 0.0)
    assert (c.mid_level_ticks, c.mid_level_fallback_ticks) == (3, 0)


@pytest.mark.parametrize("bad", [
    {"plan_t": [0.0, 0.02, 0.01, 0.04]},  # time goes back
    {"plan_torque": [[0.5, 0.0, 0.0]]},  # a torque short
    {"plan_omega": [[1.0, 0.0, 0.0]] * 3 + [[math.nan, 0.0, 0.0]]},
    {"plan_quat": [list(qt.IDENTITY)] * 3 + [[math.inf, 0.0, 0.0, 0.0]]},
])
def test_a_malformed_plan_never_reaches_a_motor(bad):
    gmpc, zdp = controller(), controller("zdp")
    now = 10 * MS
    st = estimate(now, quat=qt.from_euler(0.04, 0.0, 0.0))
    cmd = gmpc.step(now, st, None, None, plan_setpoint(0, **bad))
    assert cmd.wheel_torque == zdp.step(now, st, None, None).wheel_torque
    assert (gmpc.mid_level_ticks, gmpc.mid_level_fallback_ticks) == (0, 1)


def test_the_mid_levels_plan_is_the_solutions_first_stretch(mid):
    sp = mid.step(70 * MS, estimate(70 * MS, z=0.5, vxy=(0.2, 0.0)), None)
    sol = mid.last_solution
    assert sp is not None and sp.plan_t[0] == 0.0 and sp.plan_t[-1] >= GeometricMpcParams().setpoint_plan_s
    assert len(sp.plan_torque) == len(sp.plan_t) - 1
    for k, t in enumerate(sp.plan_t):
        assert t == pytest.approx(sol.knots[k].t if k < len(sol.knots) else sol.knots[-1].t + sol.knots[-1].h)
        assert qt.angle_between(sp.plan_quat[k], qt.mul(sol.q0, qt.exp(sol.z[k][3:6]))) < 1e-9
    msgspec.json.decode(m.encode(sp), type=m.MidLevelSetpoint)


def test_realtime_mid_level_flag_joins_the_users_config(tmp_path, monkeypatch):
    """The services read their parameters from the config file: the flag goes there, beside
    the user's settings, for the run only."""
    import argparse
    import tomllib
    from pathlib import Path

    from services.cli import sim

    user = tmp_path / "user.toml"
    user.write_text('[control]\nkp_tilt = 30.0\n\n[gmpc]\nhorizon = 16\n')
    seen: dict = {}

    def fake_run(args):
        seen["path"] = args.config
        seen["config"] = tomllib.loads(Path(args.config).read_text())
        return {}

    monkeypatch.setattr(sim, "_run_realtime", fake_run)
    sim.run_realtime(argparse.Namespace(config=str(user), mid_level="geometric_mpc", variant="indoor"))
    robot = {"robot": "indoor"}  # every service reads the twin's robot
    assert seen["config"] == {"control": {"kp_tilt": 30.0, "mid_level": "geometric_mpc", **robot}, "gmpc": {"horizon": 16},
                              "estimator": robot, "planner": robot}
    assert not Path(seen["path"]).exists()  # gone after the run


# real time: loops at their rate, processes and Zenoh over loopback share two loaded cores
pytestmark = pytest.mark.timing_sensitive(reason="real-time loops, processes or Zenoh over loopback on a shared host")
