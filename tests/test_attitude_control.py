"""Quaternion PD sign and convergence, spin-down, wheel torque allocation."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from onboard.low_level.tracking import attitude_control as ac
from onboard.geometry import quaternion as qt

INERTIA = np.diag([0.045, 0.045, 0.025])  # about a hopper's torso + wheels [kg m^2]
KP = (6.0, 6.0, 3.0)
KD = (0.6, 0.6, 0.35)


def simulate_rigid_body(q0, w0, q_des, use_log, seconds=2.0, h=1e-3, torque_max=None):
    """Euler equations + Lie-group attitude update under the PD law."""
    q, w = q0, np.array(w0, dtype=float)
    inv_i = np.linalg.inv(INERTIA)
    for _ in range(int(seconds / h)):
        u = np.array(ac.pd_torque(q, tuple(w), q_des, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), KP, KD, use_log))
        if torque_max is not None:
            u = np.clip(u, -torque_max, torque_max)
        w = w + h * inv_i @ (u - np.cross(w, INERTIA @ w))
        q = qt.normalize(qt.mul(q, qt.exp(tuple(w * h))))
    return q, w


@pytest.mark.parametrize("use_log", [False, True])
def test_pd_torque_opposes_a_small_error(use_log):
    for axis in range(3):
        v = [0.0, 0.0, 0.0]
        v[axis] = 0.05
        u = ac.pd_torque(qt.exp(v), (0, 0, 0), qt.IDENTITY, (0, 0, 0), (0, 0, 0), KP, KD, use_log)
        assert u[axis] == pytest.approx(-KP[axis] * 0.05, rel=1e-3)
        assert all(abs(u[i]) < 1e-12 for i in range(3) if i != axis)
        # rate damping and feed-forward
        w = [0.0, 0.0, 0.0]
        w[axis] = 1.0
        u = ac.pd_torque(qt.IDENTITY, w, qt.IDENTITY, (0, 0, 0), (0.1, 0.2, 0.3), KP, KD, use_log)
        assert u[axis] == pytest.approx(-KD[axis] + (0.1, 0.2, 0.3)[axis])


@pytest.mark.parametrize("use_log", [False, True])
@settings(max_examples=12, deadline=None)
@given(
    st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1)),
    st.floats(0.05, 2.0),
    st.tuples(st.floats(-2, 2), st.floats(-2, 2), st.floats(-2, 2)),
)
def test_pd_converges_from_large_errors(use_log, axis, ang, w0):
    n = math.sqrt(sum(a * a for a in axis)) or 1.0
    q_des = qt.from_euler(0.1, -0.2, 0.5)
    q0 = qt.mul(q_des, qt.exp(tuple(a / n * ang for a in axis)))
    q, w = simulate_rigid_body(q0, w0, q_des, use_log, seconds=4.0, torque_max=1.5)
    assert qt.angle_between(q, q_des) < 1e-3
    assert np.linalg.norm(w) < 1e-2


def test_error_is_the_same_for_both_covers_of_the_desired_attitude():
    q = qt.from_euler(0.2, 0.1, -0.3)
    q_des = qt.from_euler(0.0, 0.3, 0.1)
    minus = tuple(-c for c in q_des)
    for use_log in (False, True):
        assert ac.attitude_error(q, q_des, use_log) == pytest.approx(ac.attitude_error(q, minus, use_log))


def test_spin_down_decays_wheel_speed_exponentially():
    i_w, gamma, h = 0.00111, 0.01, 1e-4
    speed = np.array([300.0, -150.0, 40.0])
    for _ in range(int(0.2 / h)):
        speed = speed + h * np.array(ac.spin_down(tuple(speed), gamma)) / i_w
    expected = np.array([300.0, -150.0, 40.0]) * math.exp(-gamma / i_w * 0.2)
    assert np.allclose(speed, expected, rtol=1e-2)
    assert ac.spin_down((1.0, -2.0, 0.0), 0.5) == (-0.5, 1.0, -0.0)


@st.composite
def wheel_axes(draw):
    """A rotated, skewed (but well-conditioned) set of three unit axes, as rows."""
    q = qt.normalize((1.0, draw(st.floats(-1, 1)), draw(st.floats(-1, 1)), draw(st.floats(-1, 1))))
    skew = np.array([[draw(st.floats(-0.4, 0.4)) for _ in range(3)] for _ in range(3)])
    m = (np.array(qt.to_matrix(q)) @ (np.eye(3) + skew)).T
    return m / np.linalg.norm(m, axis=1)[:, None]


@settings(max_examples=100)
@given(wheel_axes(), st.tuples(st.floats(-2, 2), st.floats(-2, 2), st.floats(-2, 2)))
def test_allocation_applies_the_requested_body_torque(axes, u):
    alloc = ac.WheelAllocation.from_axes(axes)
    tau = alloc.wheel_torques(u)
    assert np.allclose(alloc.body_torque(tau), u, atol=1e-9)
    # by reaction: the body feels minus the sum of the motor torques about their axes
    assert np.allclose(-(axes.T @ np.array(tau)), u, atol=1e-9)


def test_orthogonal_wheels_map_body_torque_to_minus_motor_torque():
    alloc = ac.WheelAllocation.from_axes(np.eye(3))
    assert alloc.wheel_torques((0.1, -0.2, 0.3)) == pytest.approx((-0.1, 0.2, -0.3))


def test_degenerate_wheel_axes_are_refused():
    with pytest.raises(ValueError):
        ac.WheelAllocation.from_axes([(1, 0, 0), (0, 1, 0), (1, 1, 0)])
