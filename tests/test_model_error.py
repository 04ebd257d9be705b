"""A twin that is not the model (sim_twin.model_error) and the balance point that copes with it
(onboard.low_level.planning.balance): profiles, draws, what a draw changes in the compiled twin,
the IMU mount, and in lockstep a CoM off the spine found online.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from onboard.contracts.params import ControlParams, TwinParams
from onboard.low_level.planning.balance import BalancePoint
from robot_description import params as rd
from services.cli.campaign import parse_options
from sim_twin import model as tm
from sim_twin import model_error as me
from sim_twin.lockstep import RunConfig, run
from sim_twin.sensors import SensorSuite


def test_shipped_profiles_load_and_draw_per_seed() -> None:
    for name in ("calibrated", "datasheet"):
        prof = me.load_profile(name)
        assert set(prof.factors) <= set(me.FACTORS) and len(prof.factors) >= 20
        a, b, c = me.draw(prof, 3), me.draw(prof, 3), me.draw(prof, 4)
        assert a == b and a != c  # deterministic per seed, different across seeds
        for factor, spread in prof.factors.items():
            vals = a.values[factor][: me.FACTORS[factor].count]
            if spread.dist == "uniform":
                assert all(abs(v - spread.mean) <= spread.spread + 1e-12 for v in vals), factor
    assert me.draw(me.load_profile("nominal"), 0).values == {}
    assert me.draw(me.load_profile(None), 0).report() == {"profile": "nominal"}


def test_inline_profiles_and_refusals() -> None:
    d = me.draw(me.load_profile("com_x=0.01; wheel_coulomb=0.002"), 7)
    assert d.values == {"com_x": (0.01,), "wheel_coulomb": (0.002, 0.002, 0.002)}
    with pytest.raises(ValueError, match="unknown factor"):
        me.load_profile("com_q=0.01")
    with pytest.raises(ValueError, match="not a profile"):
        me.load_profile("no-such-profile")
    assert parse_options(["model-error=nominal,datasheet"]) == {"model-error": ["nominal", "datasheet"]}


def test_a_draw_changes_the_twin_as_it_says() -> None:
    robot = rd.robot_params()
    nominal = tm.load_model()
    model = tm.load_model()
    draw = me.draw(me.load_profile("com_x=0.012;com_y=-0.008;wheel_viscous=0.001;wheel_torque_constant=-0.1;spring_stiffness=-0.15"), 0)
    draw.apply_model(model)
    me.finish_model(model, mujoco.MjData(model))
    c0, c1 = np.array(me.true_com_offset(nominal)), np.array(me.true_com_offset(model))
    assert np.allclose(c0, robot.com_offset_body, atol=1e-6)  # MuJoCo and Pinocchio agree on the nominal CoM
    assert np.allclose(c1 - c0, (0.012, -0.008, 0.0), atol=1e-9)  # the whole robot's CoM moved by the draw
    wheel = int(model.joint(rd.WHEEL_JOINTS[0]).dofadr[0])
    assert model.dof_damping[wheel] == pytest.approx(0.001)
    assert model.actuator_gear[int(model.actuator(rd.WHEEL_ACTUATORS[1]).id), 0] == pytest.approx(0.9)
    foot = int(model.joint(rd.FOOT_JOINT).id)
    assert model.jnt_stiffness[foot] == pytest.approx(0.85 * nominal.jnt_stiffness[foot])
    truth = me.truth_robot(model, robot)
    assert truth.com_offset_body == pytest.approx(tuple(c1))


def test_imu_mount_misalignment_turns_what_the_imu_reads() -> None:
    model = tm.load_model()
    data = mujoco.MjData(model)
    data.qvel[3:6] = (0.3, -0.2, 0.5)  # body rate
    mujoco.mj_forward(model, data)
    twin = TwinParams(noise=False)
    plain = SensorSuite(model, twin, 0)
    turned = SensorSuite(model, twin, 0)
    turned.set_imu_misalignment(0.0, 0.0, math.pi / 2)  # IMU x along body y
    a = next(msg for topic, msg in plain.tick(data, 1_000_000) if topic == "imu")
    b = next(msg for topic, msg in turned.tick(data, 1_000_000) if topic == "imu")
    assert b.gyro == pytest.approx([a.gyro[1], -a.gyro[0], a.gyro[2]])
    assert b.accel == pytest.approx([a.accel[1], -a.accel[0], a.accel[2]])
    assert abs(b.quat[0]) == pytest.approx(math.cos(math.pi / 4))


def test_balance_point_integrates_bounded_in_the_heading_frame_and_resets() -> None:
    bp = BalancePoint(k_pos=-0.2, lever=0.35, ki=0.5, tilt_max=0.05)
    bp.update(0.1, 0.0, math.pi / 2)  # an error along world x is the heading frame's -y
    assert (bp.bx, bp.by) == pytest.approx((0.0, 0.01))
    assert bp.lean(math.pi / 2) == pytest.approx((-0.01, 0.0))  # back in the world: lean against the error
    assert bp.offset(math.pi / 2) == pytest.approx((0.0035, 0.0))
    for _ in range(100):
        bp.update(1.0, 1.0, 0.0)
    assert math.hypot(bp.bx, bp.by) == pytest.approx(0.05)  # anti-windup
    bp.reset()
    assert (bp.bx, bp.by) == (0.0, 0.0)
    off = BalancePoint(-0.2, 0.35, 0.0, 0.05)
    off.update(1.0, 1.0, 0.0)
    assert (off.bx, off.by, off.updates) == (0.0, 0.0, 0)


def test_a_com_off_the_spine_is_found_online() -> None:
    """1.5 cm off the spine, diagonally: hopping in place holds its spot within 1 cm with the
    balance point and stands ~10x the offset away without it (the bug this answers)."""
    error = "com_x=0.0106;com_y=-0.0106"
    on = run(RunConfig(scenario="hop-in-place", estimator="kalman", seed=2, duration_s=20.0, model_error=error))
    off = run(RunConfig(scenario="hop-in-place", estimator="kalman", seed=2, duration_s=20.0, model_error=error,
                        control_params=ControlParams(balance_ki=0.0)))
    assert on.metrics["falls"] == 0 and off.metrics["falls"] == 0
    assert on.metrics["final_goal_error_m"] < 0.01
    assert off.metrics["final_goal_error_m"] > 0.10
    assert on.metrics["model_error"]["com_x"] == pytest.approx(0.0106)


def test_the_real_time_twin_takes_the_same_model_error_and_reports_the_draw(zenoh_router) -> None:
    import asyncio

    from onboard.contracts.params import SafetyLimits
    from services.runtime.peers import query_status
    from services.runtime.zenoh_session import open_session
    from services.twin import TwinService
    from helpers import wait_for

    ns = "archer/twinmodelerror"

    async def scenario() -> None:
        twin = TwinService(ns=ns, endpoint=zenoh_router, params={
            "twin": TwinParams(scenario="hop-in-place", seed=1, model_error="com_x=0.01;wheel_coulomb=0.002"), "safety": SafetyLimits()})
        task = asyncio.create_task(twin.run())
        client = open_session(zenoh_router, "peer")
        try:
            await wait_for(lambda: twin.state == "running")
            status = await asyncio.to_thread(query_status, client, ns, "twin")
            assert status.extra["model_error.com_x"] == pytest.approx(0.01)
            assert status.extra["model_error.wheel_coulomb.2"] == pytest.approx(0.002)
            wheel = int(twin.model.joint(rd.WHEEL_JOINTS[2]).dofadr[0])
            assert twin.model.dof_frictionloss[wheel] == pytest.approx(0.002)
        finally:
            client.close()
            twin.request_stop()
            await asyncio.wait_for(task, 10.0)

    asyncio.run(scenario())
