"""The estimator without an accelerometer (``ImuSample.accel_sensed`` False, ARCHER's firmware):
the spring's push as the stance specific force, no gravity correction, a wider covariance."""

from __future__ import annotations

import math

import pytest

from onboard.geometry import quaternion as qt
from onboard.estimation.estimator import StateEstimator
from onboard.contracts.messages import ImuSample, JointSensors, PoseMeasurement
from onboard.contracts.params import EstimatorParams
from robot_description.params import robot_params

ROBOT = robot_params("indoor")
MS = 1_000_000
STATIC_S = ROBOT.total_mass * ROBOT.gravity / ROBOT.spring_stiffness  # the spring holds the robot's weight (+ foot's, within mu)


def stand(accel_sensed: bool, quat=qt.IDENTITY, seconds: float = 1.0, compression: float | None = None) -> StateEstimator:
    """The robot standing still on its foot; one pose at the start, then IMU and joints only."""
    est = StateEstimator(EstimatorParams(), ROBOT)
    m_sprung = ROBOT.total_mass - ROBOT.foot_mass
    s = m_sprung * ROBOT.gravity / ROBOT.spring_stiffness if compression is None else compression
    f_body = qt.rotate(qt.conj(quat), (0.0, 0.0, ROBOT.gravity)) if accel_sensed else (0.0, 0.0, 0.0)
    for k in range(int(seconds * 1000)):
        t = (k + 1) * MS
        est.update_imu(ImuSample(stamp_ns=t, quat=list(quat), gyro=[0.0, 0.0, 0.0], accel=list(f_body), accel_sensed=accel_sensed), t)
        est.update_joints(JointSensors(stamp_ns=t, wheel_pos=[0.0] * 3, wheel_vel=[0.0] * 3, wheel_torque=[0.0] * 3,
                                       foot_pos=s, foot_vel=0.0, foot_contact=True), t)
        if k == 10:
            est.update_pose(PoseMeasurement(stamp_ns=t, position=[0.0, 0.0, 0.4], quat=list(quat)), t)
    return est


def test_the_spring_holding_the_weight_keeps_the_modelled_com_at_rest():
    est = stand(accel_sensed=False)
    v = est.estimate(1000 * MS).velocity
    assert max(abs(x) for x in v) < 1e-6  # k s / m_sprung = g: no net acceleration


def test_a_spring_pushing_harder_than_the_weight_accelerates_the_modelled_com_up():
    m_sprung = ROBOT.total_mass - ROBOT.foot_mass
    s = 2.0 * m_sprung * ROBOT.gravity / ROBOT.spring_stiffness  # twice the weight: (1 - mu) g upwards
    est = stand(accel_sensed=False, seconds=0.1, compression=s)
    # past the newest sample the estimate is predicted with the CoM acceleration held
    dvz = est.estimate(110 * MS).velocity[2] - est.estimate(100 * MS).velocity[2]
    mu_sprung = m_sprung / ROBOT.total_mass
    assert dvz / 0.010 == pytest.approx(mu_sprung * ROBOT.gravity, rel=1e-3)


def test_modelled_force_never_corrects_the_attitude_with_gravity():
    tilted = qt.from_euler(0.15, 0.0, 0.0)
    modelled = stand(accel_sensed=False, quat=tilted, seconds=1.5)
    # it starts from the IMU's tilted attitude and fuses a pose saying the same; the gyro reads
    # zero, so nothing may move it (a force modelled along the leg would pull it upright if
    # gravity correction took it for the accelerometer's)
    assert qt.angle_between(tuple(modelled.estimate(1500 * MS).quat), tilted) < 1e-6


def test_without_an_accelerometer_the_stance_covariance_grows_faster():
    sensed, modelled = stand(accel_sensed=True), stand(accel_sensed=False)
    var = [e.estimate(1000 * MS).pos_vel_cov for e in (sensed, modelled)]
    vv_sensed, vv_modelled = var[0][21], var[1][21]  # x velocity variance
    ratio = EstimatorParams().accel_psd_stance_modelled / EstimatorParams().accel_psd_stance
    assert ratio > 1.0 and vv_sensed * 1.2 < vv_modelled < vv_sensed * ratio * 1.5, (vv_sensed, vv_modelled)
    assert math.isfinite(vv_modelled)
