"""A client written only from docs/archer_firmware_protocol.md talks to ``archer emulate archer-firmware``.

Nothing from ``drivers`` is imported: the layouts below are the page's tables, written
with ``socket`` and ``struct`` only, so a mismatch between the page and the code fails
here. What the client can observe is what a lab's own client could: the replies (and,
once the emulator stops, the counters it prints as documented).
"""

from __future__ import annotations

import json
import math
import socket
import struct
import subprocess
import sys
import time

import pytest

SETPOINT = "<10f"  # quat_des w x y z, omega_des x y z, torque_ff x y z
STATE = "<13f"  # wheel 1, wheel 3, wheel 2, rate x y z, quat w x y z, contact, deflection, rate
RESET = bytes((1, 2, 3, 4, 5, 6, 7, 8)) + bytes(32)
UPRIGHT = (1.0, 0.0, 0.0, 0.0)
REPLY_TIMEOUT_S = 0.5  # generous: the machine is shared; the emulator answers within 1 ms when it runs
FF = 0.02  # [N m] feed-forward: the emulator's stand-in wheels spin up visibly, within float range
WHEEL_1, WHEEL_3, WHEEL_2 = 0, 1, 2  # slots of the state packet


def setpoint(q=UPRIGHT, w=(0.0, 0.0, 0.0), tau=(0.0, 0.0, 0.0)) -> bytes:
    return struct.pack(SETPOINT, *q, *w, *tau)


class Emulator:
    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))  # a free port: the emulator's only accepted peer
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "services.cli.main", "emulate", "archer-firmware", "--peer-port", str(self.sock.getsockname()[1])],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )
        self.info = json.loads(self.proc.stdout.readline())
        self.board = (self.info["host"], self.info["port"])
        self.final: dict[str, float] = {}

    def request(self, payload: bytes) -> tuple[float, ...]:
        """Send one packet and wait for its one reply."""
        self.sock.sendto(payload, self.board)
        self.sock.settimeout(REPLY_TIMEOUT_S)
        data, addr = self.sock.recvfrom(4096)
        assert addr == self.board
        assert len(data) == 52
        return struct.unpack(STATE, data)

    def nothing_arrives(self, wait_s: float) -> bool:
        self.sock.settimeout(wait_s)
        try:
            self.sock.recvfrom(4096)
        except TimeoutError:
            return True
        return False

    def command_for(self, duration_s: float, payload: bytes, min_replies: int = 20) -> list[tuple[float, tuple[float, ...]]]:
        """Send ``payload`` every 2 ms for ``duration_s``, and on until ``min_replies`` came (a
        stalled test process gets only a few in the time): (local time, reply) of each."""
        out = []
        end = time.monotonic() + duration_s
        while time.monotonic() < end or len(out) < min_replies:
            out.append((time.monotonic(), self.request(payload)))
            time.sleep(0.002)
        return out

    def stop(self) -> None:
        self.sock.close()
        self.proc.terminate()
        _, err = self.proc.communicate(timeout=10)
        assert self.proc.returncode == 0, err
        self.final = json.loads(err.strip().splitlines()[-1])["final"]


@pytest.fixture
def emulator():
    emu = Emulator()
    try:
        yield emu
    finally:
        if emu.proc.poll() is None:
            emu.stop()


def slope(samples: list[tuple[float, tuple[float, ...]]], slot: int, max_gap_s: float = 0.02) -> float:
    """d(speed)/dt over the intervals between replies shorter than ``max_gap_s``: a stall
    of this process (a loaded machine) would let the watchdog stop the motor in a longer one."""
    dv = dt = 0.0
    for (t0, r0), (t1, r1) in zip(samples, samples[1:]):
        if t1 - t0 < max_gap_s:
            dv += r1[slot] - r0[slot]
            dt += t1 - t0
    return dv / dt


def test_it_answers_only_a_request_with_13_floats(emulator) -> None:
    info = emulator.info
    assert info["device"] == "archer-firmware" and info["host"] == "127.0.0.1" and info["protocol"].endswith("archer_firmware_protocol.md")
    assert info["watchdog_s"] == pytest.approx(0.1)
    assert emulator.nothing_arrives(0.2)  # it never streams
    state = emulator.request(setpoint())
    assert state[6:10] == UPRIGHT  # the emulator's body stands still, upright
    assert state[10] == 1.0  # in contact
    assert all(math.isfinite(v) for v in state)
    assert emulator.nothing_arrives(0.1)  # one reply per request, no more
    for _ in range(20):
        emulator.request(setpoint())  # each one answered
    emulator.stop()
    assert emulator.final["replies"] == 21 and emulator.final["setpoints"] == 21


def test_wheel_order_is_one_three_two(emulator) -> None:
    about_x = emulator.command_for(0.15, setpoint(tau=(FF, 0.0, 0.0)))
    assert slope(about_x, WHEEL_1) < 0  # a positive body torque about x spins wheel 1 negative
    assert about_x[-1][1][WHEEL_2] == 0.0 and about_x[-1][1][WHEEL_3] == 0.0
    about_y = emulator.command_for(0.15, setpoint(tau=(0.0, FF, 0.0)))
    assert slope(about_y, WHEEL_2) < 0 and about_y[-1][1][WHEEL_3] == 0.0  # wheel 2 is the third float
    about_z = emulator.command_for(0.15, setpoint(tau=(0.0, 0.0, FF)))
    assert slope(about_z, WHEEL_3) < 0  # wheel 3 is the second float


def test_motors_go_off_after_100_ms_of_silence(emulator) -> None:
    spinning = emulator.command_for(0.3, setpoint(tau=(FF, 0.0, 0.0)))
    accel = slope(spinning, WHEEL_1)  # [rad/s^2] while the motor drives
    assert accel < 0
    last_speed = spinning[-1][1][WHEEL_1]
    time.sleep(0.5)
    # the reply goes out as the packet is read, before the board's next PD step: it shows the silence
    probe = emulator.request(setpoint())
    driven_s = (probe[WHEEL_1] - last_speed) / accel  # how long the motor kept driving after the last packet
    assert 0.07 < driven_s < 0.25, driven_s  # 100 ms, not the 500 ms of silence
    emulator.stop()
    assert emulator.final["watchdog_trips"] == 1


def test_reset_stops_the_motors_and_is_answered(emulator) -> None:
    spinning = emulator.command_for(0.1, setpoint(tau=(FF, 0.0, 0.0)))
    accel = slope(spinning, WHEEL_1)
    assert accel < 0
    answered = []
    start = time.monotonic()
    for _ in range(15):  # every 20 ms: the watchdog stays fed, only the reset can stop the motors
        answered.append(emulator.request(RESET)[WHEEL_1])
        time.sleep(0.02)
    elapsed = time.monotonic() - start
    # undriven, the wheel only coasts down (a little friction): never faster, far from what the motor adds
    assert all(abs(b) <= abs(a) for a, b in zip(answered, answered[1:]))
    assert abs(answered[-1] - answered[0]) < 0.05 * abs(accel) * elapsed
    emulator.stop()
    assert emulator.final["resets"] == 15 and emulator.final["watchdog_trips"] == 0


def test_bad_packets_are_dropped_counted_and_never_applied(emulator) -> None:
    spinning = emulator.command_for(0.1, setpoint(tau=(FF, 0.0, 0.0)))
    reverse = setpoint(tau=(-50 * FF, 0.0, 0.0))  # what a bad packet would command if applied
    bad = [
        reverse[:39],  # truncated
        reverse[:8],
        reverse + b"\x00",  # oversized
        reverse + bytes(200),
        struct.pack(SETPOINT, *UPRIGHT, 0.0, 0.0, 0.0, math.nan, 0.0, 0.0),
        struct.pack(SETPOINT, *UPRIGHT, math.inf, 0.0, 0.0, -50 * FF, 0.0, 0.0),
    ]
    stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    stranger.bind(("127.0.0.1", 0))  # right host, wrong port: not the configured peer
    try:
        for packet in bad:
            emulator.sock.sendto(packet, emulator.board)
        for _ in range(5):
            stranger.sendto(reverse, emulator.board)
        assert emulator.nothing_arrives(0.1)  # none of them answered ...
        stranger.settimeout(0.05)
        with pytest.raises(TimeoutError):
            stranger.recvfrom(4096)
    finally:
        stranger.close()
    after = emulator.command_for(0.1, setpoint(tau=(FF, 0.0, 0.0)))
    assert after[0][1][WHEEL_1] < spinning[-1][1][WHEEL_1]  # ... nor applied: the wheel kept its direction
    emulator.stop()
    final = emulator.final
    assert final["length"] == 4 and final["non_finite"] == 2 and final["udp_foreign"] == 5
    assert final["setpoints"] == len(spinning) + len(after)


# real time: loops at their rate, processes and Zenoh over loopback share two loaded cores
pytestmark = pytest.mark.timing_sensitive(reason="real-time loops, processes or Zenoh over loopback on a shared host")
