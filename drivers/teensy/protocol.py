"""The computer <-> Teensy framed serial protocol (see ``docs/teensy_protocol.md``).

The frame layer of the Teensy driver: pure functions, no I/O. A frame is

    COBS( version u8 | type u8 | seq u16 | length u8 | payload[length] | crc16 u16 ) 0x00

little-endian, CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final
xor) over header and payload. COBS removes every zero byte, so 0x00 only ever
delimits frames and a receiver resynchronises at the next zero after garbage.
:class:`FrameDecoder` turns a byte stream into frames and counts what it rejects.
"""

from __future__ import annotations

import binascii
import math
import struct
from dataclasses import dataclass
from enum import IntEnum

VERSION = 1
DELIMITER = 0
HEADER = struct.Struct("<BBHB")  # version, type, seq, payload length
CRC = struct.Struct("<H")
CRC_INIT = 0xFFFF
MAX_PAYLOAD = 255
MAX_FRAME = HEADER.size + MAX_PAYLOAD + CRC.size
MAX_ENCODED = MAX_FRAME + MAX_FRAME // 254 + 1  # COBS adds one byte per 254
SEQ_MODULO = 1 << 16


class FrameType(IntEnum):
    TORQUE = 0x01  # host -> Teensy: wheel and foot torques
    ATTITUDE = 0x02  # host -> Teensy: attitude setpoint, the Teensy runs the PD
    HEARTBEAT = 0x03  # both ways: link supervision, never arms anything
    GAINS = 0x04  # host -> Teensy: attitude PD gains
    SENSORS = 0x10  # Teensy -> host: IMU, wheels, foot, status flags
    STATUS = 0x11  # Teensy -> host: an event (watchdog trip, rejected command, fault)


class FrameError(ValueError):
    """A frame that must be dropped; ``kind`` names the counter it goes to."""

    def __init__(self, kind: str, detail: str) -> None:
        self.kind = kind
        super().__init__(f"{kind}: {detail}")


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE; ``crc16(b"123456789") == 0x29B1``."""
    return binascii.crc_hqx(data, CRC_INIT)


def cobs_encode(data: bytes) -> bytes:
    """Consistent Overhead Byte Stuffing (Cheshire & Baker 1999), without the delimiter.

    Each block is a code byte ``k`` followed by ``k - 1`` non-zero bytes; a code below
    0xFF stands for a zero after its block (the last one's zero is implied).
    """
    out = bytearray()
    n = len(data)
    start = 0
    while True:
        limit = min(n, start + 254)
        zero = data.find(b"\x00", start, limit)
        if zero >= 0:
            out.append(zero - start + 1)
            out += data[start:zero]
            start = zero + 1
            continue
        length = limit - start
        out.append(length + 1)
        out += data[start:limit]
        start = limit
        if length < 254:
            return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    """Inverse of :func:`cobs_encode`; raises FrameError on a malformed block."""
    out = bytearray()
    i = 0
    n = len(data)
    while i < n:
        code = data[i]
        if code == 0:
            raise FrameError("cobs", "zero byte inside a frame")
        end = i + code
        if end > n:
            raise FrameError("cobs", "block runs past the frame end")
        out += data[i + 1 : end]
        i = end
        if code < 0xFF and i < n:
            out.append(0)
    return bytes(out)


def encode_frame(frame_type: int, seq: int, payload: bytes, version: int = VERSION) -> bytes:
    """A complete frame on the wire, delimiter included."""
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}")
    body = HEADER.pack(version, frame_type, seq % SEQ_MODULO, len(payload)) + payload
    return cobs_encode(body + CRC.pack(crc16(body))) + b"\x00"


@dataclass(frozen=True)
class RawFrame:
    frame_type: int
    seq: int
    payload: bytes


def decode_frame(encoded: bytes) -> RawFrame:
    """One frame without its delimiter -> header fields and payload, or FrameError."""
    if len(encoded) > MAX_ENCODED:
        raise FrameError("oversize", f"{len(encoded)} bytes")
    body = cobs_decode(encoded)
    if len(body) < HEADER.size + CRC.size:
        raise FrameError("short", f"{len(body)} bytes")
    (crc,) = CRC.unpack_from(body, len(body) - CRC.size)
    if crc16(body[: -CRC.size]) != crc:
        raise FrameError("crc", "checksum mismatch")
    version, frame_type, seq, length = HEADER.unpack_from(body)
    if version != VERSION:
        raise FrameError("version", f"version {version}")
    if length != len(body) - HEADER.size - CRC.size:
        raise FrameError("length", f"header says {length}, frame holds {len(body) - HEADER.size - CRC.size}")
    return RawFrame(frame_type, seq, body[HEADER.size : -CRC.size])


class FrameDecoder:
    """Byte stream -> frames. Garbage is dropped up to the next delimiter and counted."""

    COUNTERS = ("frames", "cobs", "short", "crc", "version", "length", "oversize", "gaps", "missing")

    def __init__(self) -> None:
        self._buffer = bytearray()
        self._discarding = False  # inside an oversize run: skip to the next delimiter
        self.counts = dict.fromkeys(self.COUNTERS, 0)
        self._last_seq: dict[int, int] = {}

    @property
    def rejected(self) -> int:
        c = self.counts
        return c["cobs"] + c["short"] + c["crc"] + c["version"] + c["length"] + c["oversize"]

    def feed(self, data: bytes) -> list[RawFrame]:
        out: list[RawFrame] = []
        buf = self._buffer
        buf += data
        start = 0
        while True:
            zero = buf.find(b"\x00", start)
            if zero < 0:
                break
            chunk = bytes(buf[start:zero])
            start = zero + 1
            if self._discarding:
                self._discarding = False
                continue
            if not chunk:
                continue  # back-to-back delimiters: an idle line
            try:
                frame = decode_frame(chunk)
            except FrameError as exc:
                self.counts[exc.kind] += 1
                continue
            self.counts["frames"] += 1
            last = self._last_seq.get(frame.frame_type)
            if last is not None and frame.seq != (last + 1) % SEQ_MODULO:
                self.counts["gaps"] += 1  # one discontinuity ...
                self.counts["missing"] += (frame.seq - last - 1) % SEQ_MODULO  # ... of this many frames
            self._last_seq[frame.frame_type] = frame.seq
            out.append(frame)
        del buf[:start]
        if len(buf) > MAX_ENCODED:
            self.counts["oversize"] += 1
            buf.clear()
            self._discarding = True
        return out


# --- payloads -----------------------------------------------------------------------------

FLAG_ARMED = 0x01
SENSOR_CONTACT = 0x01
SENSOR_ARMED = 0x02
SENSOR_WATCHDOG = 0x04  # no command frame for 100 ms: motors off
SENSOR_FAULT = 0x08  # a drive fault the Teensy saw

TORQUE = struct.Struct("<B3ff")  # flags, wheel torques [N m], foot torque [N m]
ATTITUDE = struct.Struct("<B4f3f3ff")  # flags, quat_des, omega_des [rad/s], torque_ff [N m], foot [N m]
HEARTBEAT = struct.Struct("<I")  # sender's clock [ms]
GAINS = struct.Struct("<3f3f")  # kp [N m/rad], kd [N m s/rad] per body axis
SENSORS = struct.Struct("<IB4f3f3f3f3f3ffffHH")
STATUS = struct.Struct("<HH")  # status code, running count


class StatusCode(IntEnum):
    OK = 0
    COMMAND_TIMEOUT = 1  # no command frame for 100 ms: torque zeroed
    DRIVE_FAULT = 2  # a drive reported a fault
    COMMAND_REJECTED = 3  # non-finite or unknown command payload
    IMU_FAULT = 4


def _finite(values: tuple[float, ...]) -> bool:
    return all(math.isfinite(v) for v in values)


@dataclass(frozen=True)
class TorqueCmd:
    wheel_torque: tuple[float, float, float]  # [N m]
    foot_torque: float  # [N m]
    armed: bool


@dataclass(frozen=True)
class AttitudeCmd:
    quat_des: tuple[float, float, float, float]  # body->world [w, x, y, z]
    omega_des: tuple[float, float, float]  # [rad/s] body
    torque_ff: tuple[float, float, float]  # [N m]
    foot_torque: float  # [N m]
    armed: bool


@dataclass(frozen=True)
class Gains:
    kp: tuple[float, float, float]  # [N m/rad]
    kd: tuple[float, float, float]  # [N m s/rad]


@dataclass(frozen=True)
class Sensors:
    """One SENSORS frame, in SI units (see the message comments in onboard.contracts.messages)."""

    t_us: int  # Teensy clock [us], wraps at 2^32
    flags: int
    quat: tuple[float, float, float, float]
    gyro: tuple[float, float, float]
    accel: tuple[float, float, float]
    wheel_pos: tuple[float, float, float]
    wheel_vel: tuple[float, float, float]
    wheel_torque: tuple[float, float, float]
    foot_pos: float
    foot_vel: float
    foot_motor_pos: float
    last_cmd_seq: int  # sequence number of the last command frame applied
    crc_errors: int  # frames the Teensy rejected (wraps at 2^16)


def make_torque(seq: int, cmd: TorqueCmd) -> bytes:
    return encode_frame(FrameType.TORQUE, seq, TORQUE.pack(FLAG_ARMED if cmd.armed else 0, *cmd.wheel_torque, cmd.foot_torque))


def make_attitude(seq: int, cmd: AttitudeCmd) -> bytes:
    flags = FLAG_ARMED if cmd.armed else 0
    return encode_frame(FrameType.ATTITUDE, seq, ATTITUDE.pack(flags, *cmd.quat_des, *cmd.omega_des, *cmd.torque_ff, cmd.foot_torque))


def make_heartbeat(seq: int, clock_ms: int) -> bytes:
    return encode_frame(FrameType.HEARTBEAT, seq, HEARTBEAT.pack(clock_ms & 0xFFFFFFFF))


def make_gains(seq: int, gains: Gains) -> bytes:
    return encode_frame(FrameType.GAINS, seq, GAINS.pack(*gains.kp, *gains.kd))


def make_sensors(seq: int, s: Sensors) -> bytes:
    return encode_frame(
        FrameType.SENSORS,
        seq,
        SENSORS.pack(
            s.t_us & 0xFFFFFFFF, s.flags, *s.quat, *s.gyro, *s.accel, *s.wheel_pos, *s.wheel_vel, *s.wheel_torque,
            s.foot_pos, s.foot_vel, s.foot_motor_pos, s.last_cmd_seq % SEQ_MODULO, s.crc_errors % SEQ_MODULO,
        ),
    )


def make_status(seq: int, code: StatusCode, count: int) -> bytes:
    return encode_frame(FrameType.STATUS, seq, STATUS.pack(int(code), count % SEQ_MODULO))


def _unpack(fmt: struct.Struct, payload: bytes, name: str) -> tuple:
    if len(payload) != fmt.size:
        raise FrameError("payload", f"{name} payload of {len(payload)} bytes, expected {fmt.size}")
    values = fmt.unpack(payload)
    if not _finite(tuple(v for v in values if isinstance(v, float))):
        raise FrameError("payload", f"{name} carries a non-finite value")
    return values


def parse_torque(payload: bytes) -> TorqueCmd:
    v = _unpack(TORQUE, payload, "TORQUE")
    return TorqueCmd((v[1], v[2], v[3]), v[4], bool(v[0] & FLAG_ARMED))


def parse_attitude(payload: bytes) -> AttitudeCmd:
    v = _unpack(ATTITUDE, payload, "ATTITUDE")
    return AttitudeCmd((v[1], v[2], v[3], v[4]), (v[5], v[6], v[7]), (v[8], v[9], v[10]), v[11], bool(v[0] & FLAG_ARMED))


def parse_gains(payload: bytes) -> Gains:
    v = _unpack(GAINS, payload, "GAINS")
    return Gains((v[0], v[1], v[2]), (v[3], v[4], v[5]))


def parse_heartbeat(payload: bytes) -> int:
    return _unpack(HEARTBEAT, payload, "HEARTBEAT")[0]


def parse_sensors(payload: bytes) -> Sensors:
    v = _unpack(SENSORS, payload, "SENSORS")
    return Sensors(
        t_us=v[0], flags=v[1], quat=(v[2], v[3], v[4], v[5]), gyro=(v[6], v[7], v[8]), accel=(v[9], v[10], v[11]),
        wheel_pos=(v[12], v[13], v[14]), wheel_vel=(v[15], v[16], v[17]), wheel_torque=(v[18], v[19], v[20]),
        foot_pos=v[21], foot_vel=v[22], foot_motor_pos=v[23], last_cmd_seq=v[24], crc_errors=v[25],
    )


def parse_status(payload: bytes) -> tuple[StatusCode | int, int]:
    code, count = _unpack(STATUS, payload, "STATUS")
    try:
        return StatusCode(code), count
    except ValueError:
        return code, count
