"""Wheel control laws: quaternion PD in flight, flywheel spin-down on the ground.

Flight (thesis lines 2201-2216, 2719-2734): the body torque

    u = -Kp e - Kd (omega - omega_d) + u_ff,   e = Log(q_d^-1 q)  or  2 Im(q_d^-1 q)

with ``q`` the measured attitude (body -> world), ``omega`` the body rate [rad/s]
(body frame) and ``e`` the attitude error as a rotation vector in the body frame
(``q = q_d exp(e)``). ``Im`` is the thesis's cheap projection onto the Lie algebra
(it was found to work more reliably on hardware), ``Log`` the exact geodesic error;
both are scaled to agree to first order (see :func:`onboard.geometry.quaternion.im`).

Ground (thesis 2723-2731): ``tau_wheel = -gamma * wheel_speed``. In stance the
torque acts about the contact point, where the effective inertia is larger, so
the wheels slow down without upsetting the attitude much and keep their torque
headroom (a motor has no torque left near its top speed).

The wheels act on the body by reaction: a motor torque ``tau_i`` about wheel axis
``a_i`` (body frame) accelerates wheel ``i`` and applies ``-tau_i a_i`` to the body,
so a desired body torque ``u`` needs ``tau = -A^-1 u`` with ``A = [a_1 a_2 a_3]``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from onboard.geometry import quaternion as qt

Vec3 = tuple[float, float, float]
Mat3 = tuple[Vec3, Vec3, Vec3]


def attitude_error(q: Sequence[float], q_des: Sequence[float], use_log: bool) -> Vec3:
    """Body-frame rotation vector [rad] from ``q_des`` to ``q`` (shortest way)."""
    err = qt.mul(qt.conj(q_des), q)
    return qt.log(err) if use_log else qt.im(err)


def pd_torque(
    q: Sequence[float],
    omega: Sequence[float],
    q_des: Sequence[float],
    omega_des: Sequence[float],
    torque_ff: Sequence[float],
    kp: Sequence[float],
    kd: Sequence[float],
    use_log: bool = False,
) -> Vec3:
    """Quaternion PD: desired body torque [N m], body frame.

    ``kp`` [N m/rad] and ``kd`` [N m s/rad] are per body axis (diagonal gains).
    """
    ex, ey, ez = attitude_error(q, q_des, use_log)
    wx, wy, wz = omega
    dx, dy, dz = omega_des
    return (
        -kp[0] * ex - kd[0] * (wx - dx) + torque_ff[0],
        -kp[1] * ey - kd[1] * (wy - dy) + torque_ff[1],
        -kp[2] * ez - kd[2] * (wz - dz) + torque_ff[2],
    )


def spin_down(wheel_vel: Sequence[float], gamma: float) -> Vec3:
    """Ground-phase wheel torques [N m]: ``-gamma * wheel_speed`` (gamma in N m s/rad)."""
    return (-gamma * wheel_vel[0], -gamma * wheel_vel[1], -gamma * wheel_vel[2])


def _inverse3(m: Sequence[Sequence[float]]) -> Mat3:
    (a, b, c), (d, e, f), (g, h, i) = m
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    if abs(det) < 1e-9:
        raise ValueError("wheel axes do not span three dimensions")
    s = 1.0 / det
    return (
        ((e * i - f * h) * s, (c * h - b * i) * s, (b * f - c * e) * s),
        ((f * g - d * i) * s, (a * i - c * g) * s, (c * d - a * f) * s),
        ((d * h - e * g) * s, (b * g - a * h) * s, (a * e - b * d) * s),
    )


@dataclass(frozen=True)
class WheelAllocation:
    """Maps a desired body torque to wheel motor torques for given wheel axes."""

    axes: tuple[Vec3, Vec3, Vec3]  # unit spin axes of wheels 0, 1, 2, body frame
    _neg_inv: Mat3  # -A^-1

    @classmethod
    def from_axes(cls, axes: Sequence[Sequence[float]]) -> WheelAllocation:
        if len(axes) != 3:
            raise ValueError("need exactly three wheel axes")
        clean = tuple(tuple(float(c) for c in a) for a in axes)
        # A has the axes as columns
        a_mat = tuple(tuple(clean[j][i] for j in range(3)) for i in range(3))
        inv = _inverse3(a_mat)
        neg = tuple(tuple(-v for v in row) for row in inv)
        return cls(clean, neg)  # type: ignore[arg-type]

    def wheel_torques(self, body_torque: Sequence[float]) -> Vec3:
        """Motor torques [N m] that apply ``body_torque`` [N m] (body frame) by reaction."""
        ux, uy, uz = body_torque
        r0, r1, r2 = self._neg_inv
        return (
            r0[0] * ux + r0[1] * uy + r0[2] * uz,
            r1[0] * ux + r1[1] * uy + r1[2] * uz,
            r2[0] * ux + r2[1] * uy + r2[2] * uz,
        )

    def body_torque(self, wheel_torque: Sequence[float]) -> Vec3:
        """The reaction torque [N m] on the body of the given motor torques."""
        a0, a1, a2 = self.axes
        t0, t1, t2 = wheel_torque
        return (
            -(a0[0] * t0 + a1[0] * t1 + a2[0] * t2),
            -(a0[1] * t0 + a1[1] * t1 + a2[1] * t2),
            -(a0[2] * t0 + a1[2] * t1 + a2[2] * t2),
        )
