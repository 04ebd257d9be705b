"""Every schema round-trips; malformed payloads raise MessageError."""

from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest

from onboard.contracts import binary_messages as bm
from onboard.contracts import messages as m
from onboard.contracts.topics import TOPICS

V3 = [0.1, -0.2, 0.3]
Q = [1.0, 0.0, 0.0, 0.0]
POLY = m.Polytope(A=[[1.0, 0.0], [-1.0, 0.0]], b=[1.0, 1.0], vertices=[[1.0, 0.0], [-1.0, 0.0]])

SAMPLES: list[msgspec.Struct] = [
    m.ImuSample(stamp_ns=5, seq=2, quat=Q, gyro=V3, accel=V3),
    m.JointSensors(wheel_pos=V3, wheel_vel=V3, wheel_torque=V3, foot_pos=0.01, foot_vel=-0.1, foot_contact=True),
    m.PoseMeasurement(position=V3, quat=Q),
    m.VisualOdometryDelta(from_stamp_ns=1, displacement=V3, cov=[1e-6, 0.0, 0.0, 0.0, 1e-6, 0.0, 0.0, 0.0, 1e-6], inliers=40),
    m.StateEstimate(
        position=V3, velocity=V3, quat=Q, omega=V3, wheel_vel=V3, foot_pos=0.0, foot_vel=0.0,
        contact=False, phase="flight", pos_vel_cov=[0.0] * 36, att_cov=[1e-4] * 3,
    ),
    m.PhaseEvent(event="apex", hop=3, position=V3, velocity=V3),
    m.TorqueCommand(wheel_torque=V3, foot_torque=1.0, armed=True),
    m.AttitudeSetpoint(quat_des=Q, omega_des=V3, torque_ff=V3, foot_torque=0.0, armed=False),
    m.MidLevelSetpoint(quat_des=Q, omega_des=V3, torque_ff=V3, qp_iterations=[7, 8], solve_ms=6.1),
    m.PolytopeSet(mode="free", polytopes=[POLY]),
    m.ComReference(t_ref_ns=10, segments=[m.BezierSegment(t0=0.0, duration=1.0, control_points=[[0, 0], [1, 1]])]),
    m.Waypoints(points=[[0.0, 0.0]], sets=[POLY]),
    m.Goal(position=[2.0, 0.0]),
    m.TrackingTube(hops=3, impact_err_p50=0.01, impact_err_p95=0.02, impact_err_max=0.03, attitude_err_p95=0.01),
    m.ContractReport(layer="planner", promised=0.1, achieved=0.05, violated=False, violations=0),
    m.SafetyEvent(trip="tilt", value=1.0, limit=0.78, armed=False, count=1),
    m.ServiceStatus(service="x", state="running", uptime_s=1.0, rates_hz={"a": 1.0}, counters={"b": 2}),
]


@pytest.mark.parametrize("msg", SAMPLES, ids=lambda s: type(s).__name__)
def test_round_trip(msg):
    assert m.decode(m.encode(msg), type(msg)) == msg


def test_every_json_topic_has_a_sample():
    covered = {type(s) for s in SAMPLES}
    assert {t.msg_type for t in TOPICS.values() if t.msg_type} <= covered


@pytest.mark.parametrize(
    "payload",
    [
        b"",
        b"not json",
        b'{"quat":[1,0,0],"gyro":[0,0,0],"accel":[0,0,0]}',  # wrong length
        b'{"quat":[1,0,0,0],"gyro":[0,0,"x"],"accel":[0,0,0]}',  # wrong type
        b'{"quat":[1,0,0,0],"gyro":[0,0,0],"accel":[0,0,0],"extra":1}',  # unknown field
        b'{"quat":[1,0,0,0],"gyro":[0,0,0]}',  # missing field
        b'{"quat":[1,0,0,0],"gyro":[0,0,0],"accel":[0,0,0],"version":99}',  # future schema
    ],
)
def test_malformed_imu_rejected(payload):
    with pytest.raises(m.MessageError):
        m.decode(payload, m.ImuSample)


def test_non_finite_rejected():
    msg = m.ImuSample(quat=Q, gyro=[math.nan, 0.0, 0.0], accel=V3)
    with pytest.raises(m.MessageError):
        m.decode(m.encode(msg), m.ImuSample)
    # 1e999 parses as inf in JSON
    with pytest.raises(m.MessageError):
        m.decode(b'{"quat":[1,0,0,0],"gyro":[1e999,0,0],"accel":[0,0,0]}', m.ImuSample)


def test_depth_round_trip_and_truncation():
    img = bm.DepthImage(
        depth=np.arange(12, dtype=np.float32).reshape(3, 4), fx=100.0, fy=101.0, cx=2.0, cy=1.5,
        cam_pos=np.array([0.0, 1.0, 2.0]), cam_quat=np.array([1.0, 0.0, 0.0, 0.0]), stamp_ns=7, seq=3,
    )
    raw = bm.encode_depth(img)
    back = bm.decode_depth(raw)
    assert np.array_equal(back.depth, img.depth) and back.fx == 100.0 and back.stamp_ns == 7
    with pytest.raises(m.MessageError):
        bm.decode_depth(raw[:-1])
    with pytest.raises(m.MessageError):
        bm.decode_grid(raw)  # wrong kind


def test_grid_round_trip_and_bad_header():
    grid = bm.OccupancyGrid(cells=np.eye(5, 7, dtype=np.uint8) * 100, resolution=0.05, origin=(-1.0, 2.0), seq=4)
    back = bm.decode_grid(bm.encode_grid(grid))
    assert np.array_equal(back.cells, grid.cells) and back.origin == (-1.0, 2.0)
    with pytest.raises(m.MessageError):
        bm.decode_grid(b"XXXX" + bm.encode_grid(grid)[4:])
