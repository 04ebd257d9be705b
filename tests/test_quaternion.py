"""Quaternion and rotation-group identities, property-based (hypothesis)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from onboard.geometry import quaternion as qt

finite = st.floats(min_value=-1.0, max_value=1.0, allow_nan=False)


@st.composite
def unit_quats(draw) -> qt.Quat:
    q = (draw(finite), draw(finite), draw(finite), draw(finite))
    if qt.norm(q) < 1e-3:
        q = (1.0, q[1], q[2], q[3])
    return qt.normalize(q)


@st.composite
def rotvecs(draw, max_angle: float = math.pi - 1e-3) -> qt.Vec3:
    axis = (draw(finite), draw(finite), draw(finite))
    n = math.sqrt(sum(a * a for a in axis))
    if n < 1e-3:
        axis, n = (0.0, 0.0, 1.0), 1.0
    ang = draw(st.floats(min_value=0.0, max_value=max_angle))
    return tuple(a / n * ang for a in axis)


vec3 = st.tuples(finite, finite, finite)


def close(a, b, tol=1e-9) -> bool:
    return all(abs(x - y) <= tol for x, y in zip(a, b, strict=True))


def same_rotation(a, b, tol=1e-9) -> bool:
    return close(a, b, tol) or close(a, tuple(-c for c in b), tol)


@settings(max_examples=200)
@given(unit_quats(), unit_quats(), unit_quats())
def test_product_is_associative_and_keeps_unit_norm(a, b, c):
    assert close(qt.mul(qt.mul(a, b), c), qt.mul(a, qt.mul(b, c)), 1e-12)
    assert abs(qt.norm(qt.mul(a, b)) - 1.0) < 1e-12


@settings(max_examples=200)
@given(unit_quats())
def test_inverse_gives_identity(q):
    assert close(qt.mul(q, qt.inv(q)), qt.IDENTITY, 1e-12)
    assert close(qt.mul(qt.inv(q), q), qt.IDENTITY, 1e-12)
    assert close(qt.inv(q), qt.conj(q), 1e-12)


@settings(max_examples=200)
@given(unit_quats())
def test_exp_log_roundtrip_up_to_double_cover(q):
    assert same_rotation(qt.exp(qt.log(q)), q, 1e-9)


@settings(max_examples=200)
@given(rotvecs())
def test_log_exp_roundtrip_below_half_turn(v):
    assert close(qt.log(qt.exp(v)), v, 1e-9)
    assert abs(qt.angle(qt.exp(v)) - math.sqrt(sum(c * c for c in v))) < 1e-9


@settings(max_examples=200)
@given(unit_quats())
def test_double_cover_log_and_im_agree_for_q_and_minus_q(q):
    minus = tuple(-c for c in q)
    if abs(q[0]) > 1e-9:  # a half turn (w = 0) is about either direction
        assert close(qt.log(q), qt.log(minus), 1e-12)
        assert close(qt.im(q), qt.im(minus), 1e-12)
    # the chosen representative is the shortest rotation
    assert math.sqrt(sum(c * c for c in qt.log(q))) <= math.pi + 1e-12


@settings(max_examples=200)
@given(rotvecs(max_angle=0.2))
def test_im_agrees_with_log_to_first_order(v):
    a = math.sqrt(sum(c * c for c in v))
    err = max(abs(x - y) for x, y in zip(qt.im(qt.exp(v)), qt.log(qt.exp(v)), strict=True))
    assert err <= a**3 / 24.0 + 1e-12  # 2 sin(a/2) = a - a^3/24 + ...


@settings(max_examples=200)
@given(unit_quats(), vec3)
def test_rotation_matches_matrix_and_preserves_length(q, v):
    r = np.array(qt.to_matrix(q))
    assert np.allclose(r @ np.array(v), qt.rotate(q, v), atol=1e-12)
    assert np.allclose(r.T @ r, np.eye(3), atol=1e-12)
    assert abs(np.linalg.det(r) - 1.0) < 1e-12
    assert close(qt.rotate_inv(q, qt.rotate(q, v)), v, 1e-12)


@settings(max_examples=200)
@given(unit_quats(), unit_quats(), vec3)
def test_product_composes_rotations(a, b, v):
    assert close(qt.rotate(qt.mul(a, b), v), qt.rotate(a, qt.rotate(b, v)), 1e-12)


@settings(max_examples=200)
@given(unit_quats())
def test_matrix_roundtrip(q):
    assert same_rotation(qt.from_matrix(qt.to_matrix(q)), q, 1e-9)


@settings(max_examples=200)
@given(
    st.floats(-3.1, 3.1), st.floats(-1.5, 1.5), st.floats(-3.1, 3.1),
)
def test_euler_roundtrip_away_from_gimbal_lock(roll, pitch, yaw):
    q = qt.from_euler(roll, pitch, yaw)
    assert abs(qt.norm(q) - 1.0) < 1e-12
    assert close(qt.to_euler(q), (roll, pitch, yaw), 1e-9)
    assert abs(qt.yaw_of(q) - yaw) < 1e-9


def test_euler_order_is_yaw_then_pitch_then_roll():
    roll, pitch, yaw = 0.3, -0.2, 1.1
    expected = qt.mul(
        qt.exp((0.0, 0.0, yaw)), qt.mul(qt.exp((0.0, pitch, 0.0)), qt.exp((roll, 0.0, 0.0)))
    )
    assert same_rotation(qt.from_euler(roll, pitch, yaw), expected, 1e-12)


@pytest.mark.parametrize("pitch", [0.5 * math.pi, -0.5 * math.pi])
def test_euler_at_gimbal_lock_still_reproduces_the_rotation(pitch):
    q = qt.from_euler(0.0, pitch, 0.7)
    assert same_rotation(qt.from_euler(*qt.to_euler(q)), q, 1e-9)


@settings(max_examples=200)
@given(st.floats(-0.9, 0.9), st.floats(-0.9, 0.9), st.floats(-3.1, 3.1))
def test_from_axis_yaw_points_body_z_along_axis(ax, ay, yaw):
    az = math.sqrt(max(1e-6, 1.0 - ax * ax - ay * ay))
    q = qt.from_axis_yaw((ax, ay, az), yaw)
    n = math.sqrt(ax * ax + ay * ay + az * az)
    assert close(qt.body_z(q), (ax / n, ay / n, az / n), 1e-9)
    assert abs(qt.tilt(q) - math.atan2(math.hypot(ax, ay), az)) < 1e-9  # (acos(az / n) is ill-conditioned near 0)
    if abs(ax) < 1e-9 and abs(ay) < 1e-9:
        assert abs(qt.yaw_of(q) - yaw) < 1e-9


def test_exp_integrates_a_constant_body_rate():
    omega = (0.4, -1.0, 2.0)
    q = qt.IDENTITY
    h = 1e-3
    for _ in range(1000):
        q = qt.mul(q, qt.exp(tuple(w * h for w in omega)))
    assert close(qt.log(q), qt.log(qt.exp(omega)), 1e-9)


def test_bad_inputs_raise():
    with pytest.raises(ValueError):
        qt.normalize((0.0, 0.0, 0.0, 0.0))
    with pytest.raises(ValueError):
        qt.normalize((math.nan, 0.0, 0.0, 1.0))
    with pytest.raises(ZeroDivisionError):
        qt.inv((0.0, 0.0, 0.0, 0.0))
    with pytest.raises(ValueError):
        qt.from_axis_yaw((1.0, 0.0, -0.1), 0.0)
    assert not qt.is_finite((1.0, math.inf, 0.0, 0.0))
