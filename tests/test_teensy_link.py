"""The Teensy driver against the emulated Teensy on a real pseudo-terminal.

Torque and attitude commands, sensor frames, corrupted and garbage bytes, the
Teensy's own 100 ms command watchdog, a vanished port with reconnect and backoff,
and recovery only on command.
"""

from __future__ import annotations

import math
import struct
import time

import pytest

from drivers.teensy import protocol as p
from drivers.teensy.device import Teensy
from drivers.teensy.emulator import WATCHDOG_S, TeensyEmulator
from drivers.teensy.transport import SerialLink
from onboard.contracts.params import HardwareParams

PARAMS = HardwareParams()
GEARS = (1.0, 1.0, 1.0, 3.0)
SLACK_S = 0.15  # scheduling on a loaded 2-core machine
CMD = p.TorqueCmd((0.5, -0.25, 0.125), 2.0, True)


@pytest.fixture
def emulator(tmp_path):
    emu = TeensyEmulator(PARAMS, GEARS, link_dir=str(tmp_path)).start()
    try:
        yield emu
    finally:
        emu.stop()
        assert emu.error is None, emu.error


@pytest.fixture
def teensy(emulator):
    link = SerialLink(emulator.port, PARAMS.reconnect_min_s, PARAMS.reconnect_max_s)
    device = Teensy(link, "torque", PARAMS.link_timeout_s)
    try:
        yield device
    finally:
        link.close()


def run(device: Teensy, seconds: float, torque: p.TorqueCmd | None = CMD, attitude: p.AttitudeCmd | None = None) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        device.exchange(time.monotonic(), torque=torque, attitude=attitude)
        time.sleep(0.001)


def wait_until(predicate, timeout_s: float) -> float:
    t0 = time.monotonic()
    while not predicate():
        assert time.monotonic() - t0 < timeout_s, f"condition not met within {timeout_s} s"
        time.sleep(0.001)
    return time.monotonic() - t0


def test_torques_reach_the_motors_and_sensors_come_back(emulator: TeensyEmulator, teensy: Teensy) -> None:
    run(teensy, 0.3)
    assert emulator.applied == pytest.approx([0.5, -0.25, 0.125, 2.0])
    s = teensy.sensors
    assert s is not None and s.flags & p.SENSOR_ARMED and s.flags & p.SENSOR_CONTACT
    assert s.wheel_torque == pytest.approx((0.5, -0.25, 0.125))
    assert s.wheel_vel[0] > 0 > s.wheel_vel[1]
    assert s.quat == (1.0, 0.0, 0.0, 0.0) and s.accel[2] == pytest.approx(9.81)
    assert 0 <= emulator.last_cmd_seq - s.last_cmd_seq <= 5  # the frame in flight
    summary = teensy.summary()
    assert summary["sensors"] > 50 and summary["rejected_frames"] == 0 and not teensy.faults
    assert emulator.counts["heartbeats"] >= 2 and emulator.counts["rejected"] == 0


def test_torque_is_clamped_at_the_drive_current_limit(emulator: TeensyEmulator, teensy: Teensy) -> None:
    run(teensy, 0.1, p.TorqueCmd((5.0, -5.0, 0.0), 50.0, True))
    clamp = PARAMS.current_max[0] * PARAMS.torque_constant[0]
    assert emulator.applied == pytest.approx([clamp, -clamp, 0.0, 3 * clamp])


def test_disarmed_command_means_zero_torque(emulator: TeensyEmulator, teensy: Teensy) -> None:
    run(teensy, 0.1)
    run(teensy, 0.05, p.TorqueCmd((0.5, 0.5, 0.5), 1.0, False))
    assert emulator.applied == [0.0] * 4 and not emulator.armed


def test_corrupted_frames_and_garbage_are_counted_and_survived(emulator: TeensyEmulator, teensy: Teensy) -> None:
    run(teensy, 0.1)
    emulator.corrupt_next(10)
    emulator.send_garbage(b"\x42" * 40 + b"\x00\x17\x00")
    run(teensy, 0.2)
    counts = teensy.link.decoder.counts
    assert teensy.link.decoder.rejected >= 10
    assert counts["crc"] + counts["cobs"] + counts["short"] + counts["length"] >= 10
    assert counts["gaps"] >= 1
    assert not teensy.faults  # 10 ms of bad frames is below the link timeout
    assert emulator.applied == pytest.approx([0.5, -0.25, 0.125, 2.0])


def test_a_long_burst_of_corrupted_frames_loses_the_link(emulator: TeensyEmulator, teensy: Teensy) -> None:
    run(teensy, 0.1)
    emulator.corrupt_next(10_000)
    run(teensy, PARAMS.link_timeout_s + SLACK_S)
    assert any("no sensor frame" in f for f in teensy.faults)
    assert emulator.applied == [0.0] * 4  # the host sends disarmed frames once faulted
    assert not emulator.armed


def test_host_silence_trips_the_teensy_watchdog(emulator: TeensyEmulator, teensy: Teensy) -> None:
    run(teensy, 0.1)
    assert emulator.applied != [0.0] * 4
    last_command = time.monotonic()  # the host dies: nothing more on the line
    wait_until(lambda: emulator.applied == [0.0] * 4, WATCHDOG_S + SLACK_S)
    assert time.monotonic() - last_command >= WATCHDOG_S * 0.9
    assert emulator.watchdog_tripped and emulator.counts["watchdog_trips"] == 1
    run(teensy, 0.1)  # the host comes back: armed commands do not restart the motors
    assert any("watchdog" in f for f in teensy.faults)
    assert emulator.applied == [0.0] * 4
    assert teensy.recover(time.monotonic())  # the host's disarmed frames cleared the trip
    run(teensy, 0.05)
    assert emulator.applied == pytest.approx([0.5, -0.25, 0.125, 2.0])


def test_vanished_port_faults_reconnects_and_recovers_on_command(emulator: TeensyEmulator, teensy: Teensy) -> None:
    run(teensy, 0.1)
    emulator.unplug(replug_after_s=0.3)
    t0 = time.monotonic()
    run(teensy, 0.05)
    assert any("vanished" in f for f in teensy.faults)
    assert not teensy.link.connected
    wait_until(lambda: emulator.applied == [0.0] * 4, WATCHDOG_S + SLACK_S)  # the Teensy stops by itself
    assert time.monotonic() - t0 < WATCHDOG_S + SLACK_S + 0.05
    run(teensy, 0.6)  # the port is back: the link reopens with backoff
    assert teensy.link.connected and teensy.link.connects == 2
    assert teensy.link.open_failures >= 1  # it tried while the port was gone
    assert teensy.faulted and emulator.applied == [0.0] * 4  # no torque until an operator recovers
    assert teensy.recover(time.monotonic())
    run(teensy, 0.1)
    assert emulator.applied == pytest.approx([0.5, -0.25, 0.125, 2.0])


def test_recovery_is_refused_while_the_link_is_down(emulator: TeensyEmulator, teensy: Teensy) -> None:
    run(teensy, 0.1)
    emulator.unplug()
    run(teensy, 0.05)
    assert not teensy.recover(time.monotonic())
    assert teensy.faulted


def test_backoff_doubles_up_to_the_ceiling(tmp_path) -> None:
    link = SerialLink(str(tmp_path / "no-such-port"), 0.05, 0.2)
    now = 0.0
    attempts = []
    for _ in range(2000):
        before = link.open_failures
        link.ensure_open(now)
        if link.open_failures > before:
            attempts.append(now)
        now += 0.001
    gaps = [b - a for a, b in zip(attempts, attempts[1:])]
    assert gaps[:3] == pytest.approx([0.05, 0.1, 0.2], abs=0.0015)
    assert len(gaps) > 5 and gaps[3:] == pytest.approx([0.2] * (len(gaps) - 3), abs=0.0015)


def test_emulator_rejects_non_finite_commands(emulator: TeensyEmulator, teensy: Teensy) -> None:
    run(teensy, 0.1)
    payload = struct.pack("<B3ff", p.FLAG_ARMED, 1.0, math.inf, 0.0, 0.0)
    teensy.link.send(p.encode_frame(p.FrameType.TORQUE, 60000, payload), time.monotonic())
    wait_until(lambda: emulator.counts["rejected"] == 1, 0.5)
    assert emulator.applied == pytest.approx([0.5, -0.25, 0.125, 2.0])  # the bad frame changed nothing
    run(teensy, 0.02)
    assert teensy.last_status is not None and teensy.last_status[0] == p.StatusCode.COMMAND_REJECTED


def test_attitude_mode_runs_the_pd_on_the_teensy(emulator: TeensyEmulator, teensy: Teensy) -> None:
    teensy.mode = "attitude"
    gains = p.Gains((2.0, 2.0, 2.0), (0.1, 0.1, 0.1))
    teensy.link.send(teensy.make_gains(gains), time.monotonic())
    half = 0.05  # desired attitude: 0.1 rad about body x, so the error drives wheel 0 positive
    att = p.AttitudeCmd((math.cos(half), math.sin(half), 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.01), 0.0, True)
    run(teensy, 0.1, torque=None, attitude=att)
    expected_x = 2.0 * math.sin(half)  # -kp * vec(conj(q_des) * identity).x
    assert emulator.applied[0] == pytest.approx(expected_x, rel=1e-3)
    assert emulator.applied[2] == pytest.approx(0.01)
