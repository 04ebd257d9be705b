"""The packets of ARCHER's flywheel-board firmware (see ``docs/archer_firmware_protocol.md``).

The codec layer of the driver: pure functions, no I/O. One UDP datagram is one
packet, all fields little-endian IEEE-754 float32, no header, no checksum (UDP's
own checksum is the only one):

- computer -> board, 40 bytes: a :class:`Setpoint` (10 floats), or a reset
  command: the same 40 bytes whose first eight are ``01 02 .. 08``;
- board -> computer, 52 bytes: a :class:`BoardState` (13 floats), one per packet
  the board received.

The board lists its wheels in the order 1, 3, 2; :class:`BoardState` holds them in
our joint order (wheel 1, 2, 3 = joints 0, 1, 2), the permutation lives here only.
Decoding is strict: a wrong length, a non-finite float or a quaternion that is not
a unit quaternion raise :class:`CodecError`, whose ``kind`` names the counter.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

SETPOINT = struct.Struct("<10f")
STATE = struct.Struct("<13f")
RESET_MAGIC = bytes(range(1, 9))  # 01 02 03 04 05 06 07 08
RESET_PACKET = RESET_MAGIC + bytes(SETPOINT.size - len(RESET_MAGIC))
WIRE_WHEEL_ORDER = (0, 2, 1)  # wire slot k carries our wheel WIRE_WHEEL_ORDER[k] (firmware: wheels 1, 3, 2)
QUAT_NORM_TOL = 0.01  # a float32 unit quaternion is within 1e-6 of norm 1; farther is not one
CONTACT_THRESHOLD = 0.5  # the contact flag travels as 0.0 / 1.0

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]


class CodecError(ValueError):
    """A packet that must be dropped; ``kind`` names the counter it goes to."""

    def __init__(self, kind: str, detail: str) -> None:
        self.kind = kind
        super().__init__(f"{kind}: {detail}")


@dataclass(frozen=True)
class Setpoint:
    """What the computer commands; the board's PD tracks it."""

    quat_des: Quat  # desired attitude, body -> world [w, x, y, z]
    omega_des: Vec3  # desired body rate [rad/s], body frame
    torque_ff: Vec3  # feed-forward body torque [N m], body frame


@dataclass(frozen=True)
class BoardState:
    """One reply of the board, wheels in our joint order."""

    wheel_vel: Vec3  # wheel speeds [rad/s], wheels 1, 2, 3
    gyro: Vec3  # body rates from the IMU [rad/s], body frame
    quat: Quat  # measured attitude, body -> world [w, x, y, z]
    foot_contact: bool  # the foot board's contact flag
    foot_deflection: float  # spring deflection [m], 0 = fully extended
    foot_deflection_rate: float  # [m/s]


Packet = Setpoint | None  # None: the reset command


def _finite(values: tuple[float, ...], what: str) -> None:
    for v in values:
        if not math.isfinite(v):
            raise CodecError("non_finite", f"{what} carries {v}")


def _unit(q: tuple[float, ...], what: str) -> None:
    norm = math.sqrt(sum(c * c for c in q))
    if abs(norm - 1.0) > QUAT_NORM_TOL:
        raise CodecError("quaternion", f"{what} quaternion has norm {norm:.4g}")


def is_reset(data: bytes) -> bool:
    return len(data) == SETPOINT.size and data[: len(RESET_MAGIC)] == RESET_MAGIC


def pack_setpoint(sp: Setpoint) -> bytes:
    values = (*sp.quat_des, *sp.omega_des, *sp.torque_ff)
    _finite(values, "setpoint")
    _unit(sp.quat_des, "setpoint")
    return SETPOINT.pack(*values)


def unpack_setpoint(data: bytes) -> Packet:
    """A received 40-byte packet -> a setpoint, or None for the reset command."""
    if len(data) != SETPOINT.size:
        raise CodecError("length", f"{len(data)} bytes, a setpoint is {SETPOINT.size}")
    if is_reset(data):
        return None
    v = SETPOINT.unpack(data)
    _finite(v, "setpoint")
    _unit(v[0:4], "setpoint")
    return Setpoint((v[0], v[1], v[2], v[3]), (v[4], v[5], v[6]), (v[7], v[8], v[9]))


def pack_state(s: BoardState) -> bytes:
    wire_wheels = tuple(s.wheel_vel[j] for j in WIRE_WHEEL_ORDER)
    values = (*wire_wheels, *s.gyro, *s.quat, 1.0 if s.foot_contact else 0.0, s.foot_deflection, s.foot_deflection_rate)
    _finite(values, "state")
    return STATE.pack(*values)


def unpack_state(data: bytes) -> BoardState:
    if len(data) != STATE.size:
        raise CodecError("length", f"{len(data)} bytes, a state is {STATE.size}")
    v = STATE.unpack(data)
    _finite(v, "state")
    _unit(v[6:10], "state")
    wheels = [0.0, 0.0, 0.0]
    for slot, joint in enumerate(WIRE_WHEEL_ORDER):
        wheels[joint] = v[slot]
    return BoardState(
        wheel_vel=(wheels[0], wheels[1], wheels[2]),
        gyro=(v[3], v[4], v[5]),
        quat=(v[6], v[7], v[8], v[9]),
        foot_contact=v[10] > CONTACT_THRESHOLD,
        foot_deflection=v[11],
        foot_deflection_rate=v[12],
    )
