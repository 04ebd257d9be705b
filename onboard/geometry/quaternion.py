"""Unit quaternions and the rotation group, on plain float tuples.

Conventions (as :mod:`onboard.contracts.messages`): ``q = (w, x, y, z)``, unit norm, rotating
body vectors into the world frame (``v_world = q * v_body * q^-1``); world z is up.
Rotation vectors (the Lie algebra, thesis lines 560-612) are in radians: ``exp(v)``
rotates by ``|v|`` about ``v / |v|``, so ``q_{k+1} = q_k exp(omega h)`` integrates a
body rate ``omega`` over ``h`` seconds (thesis eq. 2.10).

Double cover: ``q`` and ``-q`` are the same rotation. :func:`log` and :func:`im`
return the representative with ``w >= 0`` (the shortest rotation), so an attitude
error never asks for a turn of more than pi.

Everything here works on tuples of Python floats because per-tick work on 4-vectors
is cheaper as scalar arithmetic than as numpy calls (ARCHITECTURE.md, timing table).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

Quat = tuple[float, float, float, float]
Vec3 = tuple[float, float, float]

IDENTITY: Quat = (1.0, 0.0, 0.0, 0.0)

# Below this rotation angle [rad] exp/log use their Taylor series: sin(a)/a loses
# all precision near zero in double arithmetic.
_SMALL_ANGLE = 1e-6


def mul(a: Sequence[float], b: Sequence[float]) -> Quat:
    """Hamilton product ``a * b`` (apply ``b`` first, then ``a``)."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def conj(q: Sequence[float]) -> Quat:
    w, x, y, z = q
    return (w, -x, -y, -z)


def norm(q: Sequence[float]) -> float:
    w, x, y, z = q
    return math.sqrt(w * w + x * x + y * y + z * z)


def inv(q: Sequence[float]) -> Quat:
    """Multiplicative inverse; equals :func:`conj` for a unit quaternion."""
    w, x, y, z = q
    n2 = w * w + x * x + y * y + z * z
    if n2 == 0.0:
        raise ZeroDivisionError("zero quaternion has no inverse")
    return (w / n2, -x / n2, -y / n2, -z / n2)


def normalize(q: Sequence[float]) -> Quat:
    n = norm(q)
    if not n > 0.0 or not math.isfinite(n):
        raise ValueError(f"cannot normalize quaternion {tuple(q)}")
    w, x, y, z = q
    return (w / n, x / n, y / n, z / n)


def canonical(q: Sequence[float]) -> Quat:
    """The representative of ``{q, -q}`` with ``w >= 0``."""
    w, x, y, z = q
    if w < 0.0:
        return (-w, -x, -y, -z)
    return (w, x, y, z)


def exp(v: Sequence[float]) -> Quat:
    """Rotation vector [rad] -> unit quaternion (rotation by ``|v|`` about ``v``)."""
    vx, vy, vz = v
    angle = math.sqrt(vx * vx + vy * vy + vz * vz)
    half = 0.5 * angle
    if angle < _SMALL_ANGLE:
        s = 0.5 - angle * angle / 48.0  # sin(a/2)/a
        c = 1.0 - angle * angle / 8.0
    else:
        s = math.sin(half) / angle
        c = math.cos(half)
    return (c, s * vx, s * vy, s * vz)


def log(q: Sequence[float]) -> Vec3:
    """Unit quaternion -> rotation vector [rad], angle in ``[0, pi]`` (shortest)."""
    w, x, y, z = canonical(q)
    sn = math.sqrt(x * x + y * y + z * z)
    if sn < _SMALL_ANGLE:
        # angle = 2 asin(sn) ~ 2 sn (1 + sn^2/6); w ~ 1 here
        k = 2.0 / w * (1.0 - sn * sn / (3.0 * w * w)) if w > 0.0 else 0.0
    else:
        k = 2.0 * math.atan2(sn, w) / sn
    return (k * x, k * y, k * z)


def im(q: Sequence[float]) -> Vec3:
    """The imaginary-part map ``Im`` (thesis lines 2201-2216), scaled by two.

    ``2 Im(q)`` of the ``w >= 0`` representative equals :func:`log` to first order
    (``2 sin(a/2) ~ a``), so the same gains mean the same thing with either map;
    its magnitude saturates (at 2 for a half turn) instead of growing with the angle.
    """
    w, x, y, z = q
    s = 2.0 if w >= 0.0 else -2.0
    return (s * x, s * y, s * z)


def rotate(q: Sequence[float], v: Sequence[float]) -> Vec3:
    """``q * v * q^-1``: a body vector expressed in the world frame."""
    w, x, y, z = q
    vx, vy, vz = v
    # t = 2 (q_vec x v); v' = v + w t + q_vec x t
    tx = 2.0 * (y * vz - z * vy)
    ty = 2.0 * (z * vx - x * vz)
    tz = 2.0 * (x * vy - y * vx)
    return (
        vx + w * tx + (y * tz - z * ty),
        vy + w * ty + (z * tx - x * tz),
        vz + w * tz + (x * ty - y * tx),
    )


def rotate_inv(q: Sequence[float], v: Sequence[float]) -> Vec3:
    """``q^-1 * v * q``: a world vector expressed in the body frame."""
    return rotate(conj(q), v)


def to_matrix(q: Sequence[float]) -> tuple[Vec3, Vec3, Vec3]:
    """Rotation matrix (rows) of a unit quaternion: body -> world."""
    w, x, y, z = q
    return (
        (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
        (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
        (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)),
    )


def from_matrix(r: Sequence[Sequence[float]]) -> Quat:
    """Unit quaternion (``w >= 0``) of a rotation matrix (Shepperd's method)."""
    m00, m01, m02 = r[0]
    m10, m11, m12 = r[1]
    m20, m21, m22 = r[2]
    tr = m00 + m11 + m22
    if tr > 0.0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = (0.25 * s, (m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s)
    elif m00 > m11 and m00 > m22:
        s = 2.0 * math.sqrt(1.0 + m00 - m11 - m22)
        q = ((m21 - m12) / s, 0.25 * s, (m01 + m10) / s, (m02 + m20) / s)
    elif m11 > m22:
        s = 2.0 * math.sqrt(1.0 + m11 - m00 - m22)
        q = ((m02 - m20) / s, (m01 + m10) / s, 0.25 * s, (m12 + m21) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + m22 - m00 - m11)
        q = ((m10 - m01) / s, (m02 + m20) / s, (m12 + m21) / s, 0.25 * s)
    return canonical(normalize(q))


def from_euler(roll: float, pitch: float, yaw: float) -> Quat:
    """Z-Y-X (yaw, then pitch, then roll, intrinsic) Euler angles [rad] -> quaternion."""
    cr, sr = math.cos(0.5 * roll), math.sin(0.5 * roll)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    return (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )


def to_euler(q: Sequence[float]) -> Vec3:
    """Quaternion -> Z-Y-X Euler angles ``(roll, pitch, yaw)`` [rad].

    Pitch is in ``[-pi/2, pi/2]``; at pitch = +-pi/2 (gimbal lock) roll is set to 0.
    """
    w, x, y, z = q
    sp = 2.0 * (w * y - z * x)
    if sp >= 1.0 - 1e-12 or sp <= -1.0 + 1e-12:
        pitch = math.copysign(0.5 * math.pi, sp)
        yaw = -2.0 * math.atan2(x, w) if sp > 0 else 2.0 * math.atan2(x, w)
        return (0.0, pitch, math.atan2(math.sin(yaw), math.cos(yaw)))
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(sp)
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return (roll, pitch, yaw)


def yaw_of(q: Sequence[float]) -> float:
    """Heading [rad]: the angle of the body x axis projected on the world plane."""
    w, x, y, z = q
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def from_axis_yaw(axis: Sequence[float], yaw: float) -> Quat:
    """The attitude whose body z axis points along ``axis`` (world) with heading ``yaw``.

    Built as a tilt (the shortest rotation taking world z to ``axis``) applied after
    a rotation by ``yaw`` about world z. ``axis`` must have a positive z component
    (an upright robot); it is normalized here.
    """
    ax, ay, az = axis
    n = math.sqrt(ax * ax + ay * ay + az * az)
    if not n > 0.0 or az <= 0.0:
        raise ValueError(f"axis {tuple(axis)} is not an upright direction")
    ax, ay, az = ax / n, ay / n, az / n
    # shortest rotation z -> a: half-way quaternion (1 + z.a, z x a) normalized
    w = 1.0 + az
    tilt = normalize((w, -ay, ax, 0.0))
    return mul(tilt, (math.cos(0.5 * yaw), 0.0, 0.0, math.sin(0.5 * yaw)))


def angle(q: Sequence[float]) -> float:
    """Rotation angle [rad] of ``q`` in ``[0, pi]``."""
    w, x, y, z = q
    return 2.0 * math.atan2(math.sqrt(x * x + y * y + z * z), abs(w))


def angle_between(a: Sequence[float], b: Sequence[float]) -> float:
    """Angle [rad] of the rotation taking ``a`` to ``b`` (the geodesic distance)."""
    return angle(mul(conj(a), b))


def tilt(q: Sequence[float]) -> float:
    """Angle [rad] between the body z axis and world z (0 upright, pi upside down)."""
    w, x, y, z = q
    # the half angle from its sine and cosine parts: exact near upright, where acos of the
    # body z axis's world z component (1 - 2 (x^2 + y^2)) loses half the digits
    return 2.0 * math.atan2(math.sqrt(x * x + y * y), math.sqrt(w * w + z * z))


def body_z(q: Sequence[float]) -> Vec3:
    """The body z axis in world coordinates."""
    w, x, y, z = q
    return (2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y))


def is_finite(q: Sequence[float]) -> bool:
    return all(math.isfinite(c) for c in q)
