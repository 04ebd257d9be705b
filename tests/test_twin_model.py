"""The MJCF model: variants, MuJoCo/Pinocchio agreement, and physics against hand predictions."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pinocchio as pin
import pytest

from robot_description import params as rd
from sim_twin import model as tm


def _pinocchio(variant: str, tmp_path) -> pin.Model:
    if variant == "indoor":
        return pin.buildModelFromMJCF(str(rd.model_path("indoor")))  # the very same file
    path = tmp_path / f"archer_{variant}.xml"
    path.write_text(tm.pinocchio_xml(variant))
    return pin.buildModelFromMJCF(str(path))


def _q_mj_to_pin(q: np.ndarray) -> np.ndarray:
    # MuJoCo free joint: [p, w x y z]; Pinocchio: [p, x y z w]
    return np.concatenate([q[:3], q[4:7], q[3:4], q[7:]])


def test_variant_masses_and_params() -> None:
    indoor, outdoor, fast = (rd.robot_params(v) for v in ("indoor", "outdoor", "sim15nm"))
    assert indoor.total_mass == pytest.approx(5.92)
    assert outdoor.total_mass == pytest.approx(8.25)
    # Loaded raw (payload held by welds rather than fused), the outdoor file weighs the same.
    raw = mujoco.MjModel.from_xml_path(str(rd.model_path("outdoor")))
    assert raw.body_subtreemass[0] == pytest.approx(8.25)
    assert indoor.spring_stiffness == 11700.0 and indoor.foot_travel == pytest.approx(0.1)
    assert indoor.foot_mass == pytest.approx(0.4)
    assert indoor.leg_length == pytest.approx(0.40)
    assert outdoor.leg_length > indoor.leg_length  # tennis ball under the tip
    assert indoor.footprint_radius == pytest.approx(0.13) and outdoor.footprint_radius == pytest.approx(0.17)
    assert indoor.wheel_torque_peak == pytest.approx(1.6) and fast.wheel_torque_peak == pytest.approx(15.0)
    assert np.allclose(indoor.wheel_axes, np.eye(3))
    m = tm.load_model("sim15nm")
    assert m.actuator_ctrlrange[m.actuator("wheel_x").id][1] == pytest.approx(15.0)
    with pytest.raises(ValueError):
        tm.load_model("moon")


def test_wheel_speed_torque_curve() -> None:
    p = rd.robot_params()
    assert p.wheel_torque_available(0.0, 5.0) == pytest.approx(p.wheel_torque_peak)
    assert p.wheel_torque_available(500.0, 1.0) == pytest.approx(1.0)
    half = 0.5 * (p.wheel_speed_knee + p.wheel_no_load_speed)
    assert p.wheel_torque_available(half, 2.0) == pytest.approx(0.5 * p.wheel_torque_peak)
    assert p.wheel_torque_available(-half, -2.0) == pytest.approx(-0.5 * p.wheel_torque_peak)
    assert p.wheel_torque_available(700.0, 1.0) == 0.0
    # braking keeps the full peak even at high speed
    assert p.wheel_torque_available(600.0, -5.0) == pytest.approx(-p.wheel_torque_peak)
    # KV115 on 50.8 V
    assert p.wheel_no_load_speed == pytest.approx(115 * 50.8 * 2 * math.pi / 60, rel=1e-3)


@pytest.mark.parametrize("variant", ["indoor", "outdoor"])
def test_pinocchio_agrees_with_mujoco(variant: str, tmp_path) -> None:
    m = tm.load_model(variant)
    d = mujoco.MjData(m)
    pm = _pinocchio(variant, tmp_path)
    pd = pm.createData()
    assert (pm.nq, pm.nv) == (m.nq, m.nv)
    assert [pm.names[i] for i in range(1, pm.njoints)] == [m.joint(j).name for j in range(m.njnt)]
    assert sum(inertia.mass for inertia in pm.inertias) == pytest.approx(m.body_subtreemass[0], rel=1e-12)

    params = rd.robot_params(variant)
    rng = np.random.default_rng(7)
    for k in range(4):
        q = m.qpos0.copy()
        if k > 0:  # the first sample is the reference pose RobotParams is read at
            q[:3] = rng.normal(size=3)
            quat = rng.normal(size=4)
            q[3:7] = quat / np.linalg.norm(quat)
            q[7:] = rng.uniform(-0.5, 0.5, size=m.nq - 7)
            q[m.joint("foot_slide").qposadr[0]] = rng.uniform(0.0, 0.1)
        d.qpos[:] = q
        mujoco.mj_forward(m, d)
        qp = _q_mj_to_pin(q)

        com_pin = pin.centerOfMass(pm, pd, qp)
        assert np.allclose(com_pin, d.subtree_com[1], atol=1e-12)

        # Mass matrix. Pinocchio's free-flyer velocity is [v_body, w_body]; MuJoCo's is [v_world, w_body].
        m_mj = np.zeros((m.nv, m.nv))
        mujoco.mj_fullM(m, d, m_mj)
        m_pin = pin.crba(pm, pd, qp)
        m_pin = np.triu(m_pin) + np.triu(m_pin, 1).T
        t = np.eye(m.nv)
        t[:3, :3] = d.xmat[1].reshape(3, 3).T
        assert np.allclose(t.T @ m_pin @ t, m_mj, atol=1e-12)

        # Composite (centroidal) inertia in world axes.
        pin.ccrba(pm, pd, qp, np.zeros(pm.nv))
        rot = d.xmat[1].reshape(3, 3)
        if k == 0:
            assert np.allclose(pd.Ig.inertia, np.array(params.inertia_com), atol=1e-12)
            assert np.allclose(com_pin - d.xpos[1], params.com_offset_body, atol=1e-12)
        else:
            assert pd.Ig.mass == pytest.approx(params.total_mass)
            assert np.all(np.linalg.eigvalsh(rot.T @ pd.Ig.inertia @ rot) > 0)


def _upright(m: mujoco.MjModel, d: mujoco.MjData, tip_height: float) -> None:
    p = rd.robot_params()
    d.qpos[:] = m.qpos0
    d.qpos[2] = p.leg_length + tip_height
    d.qvel[:] = 0.0
    mujoco.mj_forward(m, d)


def test_passive_drop_matches_spring_and_impact_model() -> None:
    """Drop with the foot extended: compression, stance time and rebound height from hand models.

    Prediction: the foot (unsprung mass m_f) stops at touchdown and loses its kinetic energy; the
    sprung mass m_s compresses the linear spring (gravity included) and returns at the same speed;
    at full extension the stop jerks the foot along, a perfectly inelastic m_s-m_f collision, so
    the rebound apex is h (m_s / M)^2.
    """
    p = rd.robot_params()
    m = tm.load_model()
    d = mujoco.MjData(m)
    h = 0.30
    _upright(m, d, h)
    slide = m.joint("foot_slide").qposadr[0]
    g, k, ms, mf = p.gravity, p.spring_stiffness, p.sprung_mass, p.foot_mass
    v = math.sqrt(2 * g * h)

    touchdown = liftoff = None
    qmax = 0.0
    apex = None
    z_prev = d.qpos[2]
    while d.time < 1.0:
        mujoco.mj_step(m, d)
        qmax = max(qmax, d.qpos[slide])
        in_contact = d.ncon > 0
        if touchdown is None and in_contact:
            touchdown = d.time
        if touchdown is not None and liftoff is None and not in_contact and d.time - touchdown > 0.01:
            liftoff = d.time
        if liftoff is not None and d.qpos[2] < z_prev:
            apex = z_prev - p.leg_length
            break
        z_prev = d.qpos[2]
    assert touchdown is not None and liftoff is not None and apex is not None

    # Max compression: 1/2 k q^2 = 1/2 m_s v^2 + m_s g q
    q_pred = (ms * g + math.sqrt((ms * g) ** 2 + k * ms * v * v)) / k
    assert qmax == pytest.approx(q_pred, rel=0.03)
    # Stance time of the spring-mass with gravity: (pi + 2 asin(q_eq / A)) / w
    w = math.sqrt(k / ms)
    q_eq = ms * g / k
    amp = math.hypot(q_eq, v / w)
    t_pred = (math.pi + 2 * math.asin(q_eq / amp)) / w
    assert liftoff - touchdown == pytest.approx(t_pred, rel=0.03)
    # Rebound: the soft contact gives back a little of the foot's energy, never more than it had.
    apex_pred = h * (ms / (ms + mf)) ** 2
    assert apex == pytest.approx(apex_pred, rel=0.04)
    assert apex < h * ms / (ms + mf)  # upper bound: only the touchdown loss


def test_wheel_torque_spins_body_by_momentum_conservation() -> None:
    """In free fall (no gravity torque about the CoM), torque tau on wheel i for T seconds gives the
    body -tau T / (I_ii - J) and the wheel tau T / J + tau T / (I_ii - J), where I is the whole
    robot's inertia about its CoM (wheels locked) and J the wheel's spin inertia."""
    p = rd.robot_params()
    m = tm.load_model()
    d = mujoco.MjData(m)
    inertia = np.array(p.inertia_com)
    big_j = p.wheel_spin_inertia
    tau, duration = 0.8, 0.1
    for axis, name in enumerate(("wheel_x", "wheel_y", "wheel_z")):
        mujoco.mj_resetData(m, d)
        d.qpos[2] = 5.0  # high above the floor
        act = m.actuator(name).id
        dof = m.joint(name).dofadr[0]
        while d.time < duration - 1e-9:
            d.ctrl[:] = 0.0
            d.ctrl[act] = tau
            mujoco.mj_step(m, d)
        body_rate = d.qvel[3:6]  # body frame
        expect = -tau * duration / (inertia[axis][axis] - big_j)
        assert body_rate[axis] == pytest.approx(expect, rel=0.01)
        others = [i for i in range(3) if i != axis]
        assert np.all(np.abs(body_rate[others]) < 1e-3 * abs(expect))
        wheel_expect = tau * duration / big_j - expect
        assert d.qvel[dof] == pytest.approx(wheel_expect, rel=0.01)
        # and the total angular momentum about the CoM stays zero
        mujoco.mj_subtreeVel(m, d)
        assert np.linalg.norm(d.subtree_angmom[1]) < 1e-6


def test_cable_pulls_but_never_pushes() -> None:
    """Hanging in zero gravity, spool torque T compresses the spring to T / (r k); a negative torque
    only unwinds the spool and leaves the foot extended."""
    p = rd.robot_params()
    m = tm.load_model()
    m.opt.gravity[:] = 0.0
    d = mujoco.MjData(m)
    d.qpos[2] = 5.0
    slide = m.joint("foot_slide").qposadr[0]
    spool = m.joint("foot_motor").qposadr[0]
    act = m.actuator("foot_motor").id
    torque = 4.0
    samples, slack = [], []
    for _ in range(2000):  # 1 s; the undamped spring-spool mode oscillates about its equilibrium
        d.ctrl[act] = torque
        mujoco.mj_step(m, d)
        samples.append(d.qpos[slide])
        slack.append(d.qpos[slide] - p.spool_radius * d.qpos[spool])
    assert np.mean(samples) == pytest.approx(torque / (p.spool_radius * p.spring_stiffness), rel=0.03)
    assert max(samples) > 0.01
    assert np.max(np.abs(slack)) < 2e-3  # taut throughout (the soft cable stretches about 1 mm)
    for _ in range(2000):
        d.ctrl[act] = -1.0
        mujoco.mj_step(m, d)
    assert d.qpos[slide] == pytest.approx(0.0, abs=1e-3)
    assert d.qpos[slide] - p.spool_radius * d.qpos[spool] > 0.01  # slack: the cable did not push


@pytest.mark.parametrize("variant", rd.VARIANTS)
def test_the_foot_touch_sensor_feels_whatever_part_of_the_foot_meets_the_ground(variant: str) -> None:
    """Dropped upright on the floor, the foot's touch sensor carries the robot's weight on
    average (it bounces on its spring; the outdoor robot lands on its tennis ball, below the
    bare tip's site, where the sensor read nothing)."""
    m = tm.load_model(variant)
    d = mujoco.MjData(m)
    params = rd.robot_params(variant)
    root = m.joint(rd.ROOT_JOINT).qposadr[0]
    d.qpos[root + 2] = params.leg_length + 0.005  # the foot 5 mm above the floor
    touch = m.sensor(rd.FOOT_TOUCH_SENSOR).adr[0]
    readings = []
    for _ in range(int(0.5 / m.opt.timestep)):
        d.qpos[root + 3:root + 7] = [1.0, 0.0, 0.0, 0.0]  # held upright
        d.qvel[3:6] = 0.0
        mujoco.mj_step(m, d)
        readings.append(d.sensordata[touch])
    assert np.mean(readings) > 0.5 * params.total_mass * params.gravity
