"""A client written only from docs/teensy_protocol.md talks to ``archer emulate teensy``.

Nothing from ``drivers`` is imported: COBS, the CRC and the layouts below follow the
page's words, so a mismatch between the page and the code fails here.
"""

from __future__ import annotations

import json
import struct
import subprocess
import sys
import time

import pytest
import serial

DELIM = 0x00


def crc16_ccitt_false(data: bytes) -> int:
    """Polynomial 0x1021, initial value 0xFFFF, no reflection, no final XOR (bit by bit)."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc


def cobs_encode(data: bytes) -> bytes:
    """Split at each zero; pieces of up to 254 non-zero bytes become [length + 1, bytes]."""
    out = bytearray()
    block = bytearray()
    for byte in data:
        if byte == 0:
            out += bytes((len(block) + 1,)) + block
            block = bytearray()
        else:
            block.append(byte)
            if len(block) == 254:
                out += b"\xff" + block
                block = bytearray()
    out += bytes((len(block) + 1,)) + block
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    out = bytearray()
    i = 0
    while i < len(data):
        k = data[i]
        out += data[i + 1 : i + k]
        i += k
        if k < 0xFF and i < len(data):
            out.append(0)
    return bytes(out)


def frame(ftype: int, seq: int, payload: bytes) -> bytes:
    body = struct.pack("<BBHB", 1, ftype, seq, len(payload)) + payload
    return cobs_encode(body + struct.pack("<H", crc16_ccitt_false(body))) + bytes((DELIM,))


def parse(encoded: bytes) -> tuple[int, int, bytes] | None:
    body = cobs_decode(encoded)
    if len(body) < 7 or struct.unpack("<H", body[-2:])[0] != crc16_ccitt_false(body[:-2]):
        return None
    version, ftype, seq, length = struct.unpack("<BBHB", body[:5])
    if version != 1 or length != len(body) - 7:
        return None
    return ftype, seq, body[5:-2]


def test_crc_and_cobs_as_the_docs_state() -> None:
    assert crc16_ccitt_false(b"123456789") == 0x29B1
    assert cobs_encode(b"\x00") == bytes.fromhex("0101")
    assert cobs_encode(bytes.fromhex("11220033")) == bytes.fromhex("0311220233")
    assert cobs_encode(bytes.fromhex("110000")) == bytes.fromhex("02110101")


@pytest.fixture
def emulated_teensy():
    proc = subprocess.Popen([sys.executable, "-m", "services.cli.main", "emulate", "teensy"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        info = json.loads(proc.stdout.readline())
        yield info
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=10)
        assert proc.returncode == 0, err


def read_frames(port: serial.Serial, buffer: bytearray) -> list[tuple[int, int, bytes]]:
    buffer += port.read(65536)
    out = []
    while DELIM in buffer:
        cut = buffer.index(DELIM)
        chunk = bytes(buffer[:cut])
        del buffer[: cut + 1]
        if chunk:
            parsed = parse(chunk)
            if parsed is not None:
                out.append(parsed)
    return out


def test_a_docs_only_client_commands_torque_and_reads_sensors(emulated_teensy) -> None:
    info = emulated_teensy
    assert info["device"] == "teensy" and info["version"] == 1 and info["protocol"].endswith("teensy_protocol.md")
    port = serial.Serial(info["port"], timeout=0)
    buffer = bytearray()
    seq = 0
    sensors = []
    try:
        end = time.monotonic() + 0.4
        while time.monotonic() < end:
            seq += 1
            port.write(frame(0x01, seq, struct.pack("<B3ff", 1, 0.5, -0.25, 0.0, 1.5)))  # TORQUE, armed
            sensors += [f for f in read_frames(port, buffer) if f[0] == 0x10]
            time.sleep(0.001)
        assert len(sensors) > 100  # one per millisecond from the Teensy's own clock
        ftype, _seq, payload = sensors[-1]
        assert len(payload) == 97
        flags = payload[4]
        quat = struct.unpack_from("<4f", payload, 5)
        accel = struct.unpack_from("<3f", payload, 33)
        wheel_torque = struct.unpack_from("<3f", payload, 69)
        last_cmd_seq = struct.unpack_from("<H", payload, 93)[0]
        assert flags & 0x02 and flags & 0x01  # armed, foot contact
        assert quat == (1.0, 0.0, 0.0, 0.0) and accel[2] == pytest.approx(9.81)
        assert wheel_torque == pytest.approx((0.5, -0.25, 0.0))
        assert seq - last_cmd_seq <= 20
        # stop commanding: within 100 ms the Teensy zeroes the motors and says so
        stopped = time.monotonic()
        status = []
        while time.monotonic() - stopped < 0.4:
            frames = read_frames(port, buffer)
            status += [f for f in frames if f[0] == 0x11]
            sensors = [f for f in frames if f[0] == 0x10] or sensors
            time.sleep(0.005)
        payload = sensors[-1][2]
        assert payload[4] & 0x04 and not payload[4] & 0x02  # watchdog tripped, disarmed
        assert struct.unpack_from("<3f", payload, 69) == (0.0, 0.0, 0.0)
        assert any(struct.unpack("<HH", f[2])[0] == 1 for f in status)  # STATUS 1
    finally:
        port.close()


# real time: loops at their rate, processes and Zenoh over loopback share two loaded cores
pytestmark = pytest.mark.timing_sensitive(reason="real-time loops, processes or Zenoh over loopback on a shared host")
