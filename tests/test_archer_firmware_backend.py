"""The hardware-service backend for ARCHER's firmware against the emulated board (UDP loopback)."""

from __future__ import annotations

import dataclasses
import socket
import time

import pytest

from drivers.archer_firmware.emulator import BoardEmulator
from onboard import messages as msgs
from onboard.foot_control import FootPhysics
from onboard.params import ArcherFirmwareParams
from services.archer_firmware_backend import ArcherFirmwareBackend

FOOT = FootPhysics(total_mass=3.0, gravity=9.81, spring_k=3000.0, spool_radius=0.01, travel=0.06)
AXES = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def rig():
    clock = [50.0]
    now = lambda: clock[0]  # noqa: E731
    computer_port = free_port()
    emu = BoardEmulator(ArcherFirmwareParams(), FOOT, ("127.0.0.1", 0), ("127.0.0.1", computer_port), now, wheel_axes=AXES)
    params = dataclasses.replace(ArcherFirmwareParams(), computer_port=computer_port, board_port=emu.link.local[1])
    backend = ArcherFirmwareBackend(params, AXES, now)
    try:
        yield clock, emu, backend
    finally:
        emu.close()
        backend.close()


def round_trip(clock, emu, backend, **exchange) -> None:
    backend.exchange(clock[0], **exchange)
    time.sleep(0.005)
    emu.tick(clock[0])
    time.sleep(0.005)
    clock[0] += 0.001


def test_an_armed_setpoint_reaches_the_board_and_its_state_comes_back_as_joints(rig) -> None:
    clock, emu, backend = rig
    emu.motors[1].velocity = 7.0
    emu.body.foot_pos, emu.body.foot_vel = 0.01, -0.2
    wheel_ff = [0.1, 0.0, -0.05]  # our message carries wheel torques
    sp = msgs.AttitudeSetpoint(quat_des=[1.0, 0.0, 0.0, 0.0], omega_des=[0.0, 0.0, 0.0], torque_ff=wheel_ff, foot_torque=3.0, armed=True)
    round_trip(clock, emu, backend, torques=(0.0, 0.0, 0.0, 0.0), armed=True, attitude=sp)
    assert emu.setpoint is not None and emu.setpoint.torque_ff == pytest.approx((-0.1, 0.0, 0.05))  # body torque on the wire
    assert emu.applied[:3] == pytest.approx(wheel_ff)  # ... which the board turns back into these wheel torques
    backend.exchange(clock[0], (0.0, 0.0, 0.0, 0.0), False, None)
    joints = backend.joints()
    assert joints is not None and joints.wheel_vel == [0.0, 7.0, 0.0]
    assert (joints.foot_pos, joints.foot_vel, joints.foot_contact) == (pytest.approx(0.01), pytest.approx(-0.2), True)
    assert joints.stamp_ns == int(backend.board.state_rx_s * 1e9)
    assert backend.imu() is None  # no accelerometer in this firmware's state
    assert backend.board_attitude()[1] == (1.0, 0.0, 0.0, 0.0)


def test_disarmed_or_torque_mode_sends_nothing(rig) -> None:
    clock, emu, backend = rig
    round_trip(clock, emu, backend, torques=(0.2, 0.0, 0.0, 1.0), armed=True, attitude=None)
    round_trip(clock, emu, backend, torques=(0.0, 0.0, 0.0, 0.0), armed=False, attitude=None)
    assert emu.link.rx == 0 and backend.board.link.tx == 0
    assert backend.summary()["torques_ignored"] == 1.0 and not backend.faults
