"""Twin sensors: truth without noise, seeded noise statistics, rates, latency, dropouts, depth."""

from __future__ import annotations

import dataclasses
import math

import mujoco
import numpy as np
import pytest

from onboard.contracts import messages as msgs
from onboard.contracts.binary_messages import decode_depth, encode_depth
from onboard.contracts.params import TwinParams
from robot_description import params as rd
from sim_twin import model as tm
from sim_twin.sensors import SensorSuite

MS = 1_000_000


def _standing(noise: bool, **overrides) -> tuple[mujoco.MjModel, mujoco.MjData, SensorSuite]:
    model = tm.load_model()
    data = mujoco.MjData(model)
    p = rd.robot_params()
    q_eq = p.sprung_mass * p.gravity / p.spring_stiffness  # standing at the spring's equilibrium
    data.qpos[2] = p.leg_length - q_eq
    data.qpos[model.joint("foot_slide").qposadr[0]] = q_eq
    params = dataclasses.replace(TwinParams(noise=noise), **overrides)
    return model, data, SensorSuite(model, params, seed=3)


def _run(model, data, suite, ticks: int, gravity: bool = True) -> list[tuple[int, str, object]]:
    if not gravity:  # float at rest far above the floor, spring relaxed
        model.opt.gravity[:] = 0.0
        data.qpos[:] = model.qpos0
        data.qpos[2] = 5.0
    out = []
    substeps = round(0.001 / model.opt.timestep)
    for k in range(1, ticks + 1):
        for _ in range(substeps):
            mujoco.mj_step(model, data)
        now = k * MS
        out.extend((now, topic, msg) for topic, msg in suite.tick(data, now))
    return out


def test_truth_without_noise() -> None:
    model, data, suite = _standing(noise=False)
    out = _run(model, data, suite, 300)
    imu = [msg for _, t, msg in out if t == "imu"][-1]
    joints = [msg for _, t, msg in out if t == "joints"][-1]
    pose = [msg for _, t, msg in out if t == "pose"][-1]
    assert isinstance(imu, msgs.ImuSample) and isinstance(joints, msgs.JointSensors)
    assert np.allclose(imu.quat, data.qpos[3:7]) and np.allclose(imu.gyro, data.qvel[3:6])
    # standing still: specific force is +g along body z
    assert np.allclose(imu.accel, [0.0, 0.0, 9.81], atol=0.05)
    assert joints.foot_contact and joints.foot_pos == pytest.approx(data.qpos[model.joint("foot_slide").qposadr[0]])
    assert joints.foot_pos == pytest.approx(rd.robot_params().sprung_mass * 9.81 / 11700, rel=0.05)
    assert np.allclose(pose.position, data.qpos[:3], atol=1e-4)  # 10 ms old, nearly still
    # messages are valid wire messages
    for msg in (imu, joints, pose):
        assert msgs.decode(msgs.encode(msg), type(msg)) == msg


def test_noise_statistics_and_seed() -> None:
    model, data, suite = _standing(noise=True)
    out = _run(model, data, suite, 2000, gravity=False)  # floating at rest: truth is zero rate
    gyro = np.array([msg.gyro for _, t, msg in out if t == "imu"])
    p = suite.params
    assert np.allclose(gyro.mean(axis=0), suite.gyro_bias, atol=4 * p.gyro_noise_density * math.sqrt(1000) / math.sqrt(2000))
    assert np.allclose(gyro.std(axis=0), p.gyro_noise_density * math.sqrt(1000), rtol=0.1)
    assert np.linalg.norm(suite.gyro_bias) > 0
    accel = np.array([msg.accel for _, t, msg in out if t == "imu"])
    assert np.allclose(accel.mean(axis=0), suite.accel_bias, atol=0.01)
    # same seed: the same messages; another seed: different
    model2, data2, suite2 = _standing(noise=True)
    again = _run(model2, data2, suite2, 50, gravity=False)
    first = [msg for _, t, msg in out[: len(again)] if t != "depth"]
    assert [msg for _, t, msg in again if t != "depth"] == first
    other = SensorSuite(model2, p, seed=4)
    assert other.gyro_bias != suite.gyro_bias


def test_rates_latency_dropouts() -> None:
    model, data, suite = _standing(noise=True, pose_rate_hz=100.0, pose_latency_s=0.012, pose_dropout=0.3,
                                   depth_rate_hz=10.0, depth_latency_s=0.03)
    out = _run(model, data, suite, 1000)
    imu = [(now, msg) for now, t, msg in out if t == "imu"]
    poses = [(now, msg) for now, t, msg in out if t == "pose"]
    depths = [(now, msg) for now, t, msg in out if t == "depth"]
    assert len(imu) == 1000 and all(now == msg.stamp_ns for now, msg in imu)
    # 99 captures delivered within the run (the last 12 ms are still in flight), 30 % lost
    assert 50 <= len(poses) <= 85
    assert all(now - msg.stamp_ns == 12 * MS for now, msg in poses)
    seqs = [msg.seq for _, msg in poses]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    assert len(depths) == 10 and all(now - msg.stamp_ns == 30 * MS for now, msg in depths)
    with pytest.raises(ValueError):
        SensorSuite(model, TwinParams(pose_dropout=1.0))
    with pytest.raises(ValueError):
        SensorSuite(model, TwinParams(pose_rate_hz=0.0))


def test_depth_camera_sees_floor_and_wall_but_not_robot() -> None:
    spec = tm.load_spec()
    wall_x = 2.0
    spec.worldbody.add_geom(name="wall", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.05, 2.0, 1.0],
                            pos=[wall_x + 0.05, 0.0, 1.0], contype=1, conaffinity=2, group=0)
    model = spec.compile()
    data = mujoco.MjData(model)
    data.qpos[2] = 0.6
    mujoco.mj_forward(model, data)
    suite = SensorSuite(model, TwinParams(noise=False), seed=0)
    img = suite.depth_image(data, 5)
    h, w = img.depth.shape
    assert (h, w) == (48, 48 * 4 // 3)
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, img.cam_quat)
    rot = rot.reshape(3, 3)
    assert np.allclose(rot[:, 2], [math.cos(math.radians(30)), 0, -math.sin(math.radians(30))], atol=1e-6)  # looks forward, down
    hits_floor = hits_wall = 0
    for v in range(0, h, 5):
        for u in range(0, w, 5):
            ray = rot @ np.array([(u + 0.5 - img.cx) / img.fx, (v + 0.5 - img.cy) / img.fy, 1.0])  # z-depth 1
            t_floor = -img.cam_pos[2] / ray[2] if ray[2] < 0 else math.inf
            t_wall = (wall_x - img.cam_pos[0]) / ray[0] if ray[0] > 0 else math.inf
            t = min(t_floor, t_wall)
            expect = t if t <= 6.0 else 0.0
            assert img.depth[v, u] == pytest.approx(expect, abs=1e-4), (u, v)
            hits_floor += t_floor < t_wall and t <= 6.0
            hits_wall += t_wall < t_floor
    assert hits_floor > 10 and hits_wall > 10  # the bottom rows look through the robot's own foot
    back = decode_depth(encode_depth(img))
    assert np.array_equal(back.depth, img.depth) and back.stamp_ns == 5
