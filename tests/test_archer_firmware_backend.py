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


def test_the_hardware_service_drives_the_board_through_this_backend(zenoh_router) -> None:
    """The ``hardware`` service, unchanged, with this backend: attitude setpoints reach the
    board's PD, joints come back on the topic, and silence stops the board's motors."""
    import asyncio
    import threading

    from onboard.params import HardwareParams, SafetyLimits
    from onboard.topics import TOPICS
    from services.hardware import HardwareService
    from services.realtime import DeadlineLoop
    from services.runtime import StandInCommander
    from services.zenoh_session import open_session

    ns = "archer/fwtest"
    computer_port = free_port()
    emu = BoardEmulator(ArcherFirmwareParams(), FOOT, ("127.0.0.1", 0), ("127.0.0.1", computer_port), time.perf_counter, wheel_axes=AXES)
    board_loop = DeadlineLoop(0.001, emu.tick, name="board")
    params = dataclasses.replace(ArcherFirmwareParams(), computer_port=computer_port, board_port=emu.link.local[1])
    backend = ArcherFirmwareBackend(params, AXES)
    # the service takes attitude_cmd when its hardware runs the PD (hardware.py's attitude mode)
    hw = HardwareParams(backend="teensy", teensy_mode="attitude", rt_priority=0)
    service = HardwareService(ns=ns, endpoint=zenoh_router, params={"hardware": hw, "safety": SafetyLimits()}, backend=backend)
    client = open_session(zenoh_router, "peer")
    commander = StandInCommander(client, ns)
    pub = client.declare_publisher(TOPICS["attitude_cmd"].key(ns))
    joints: list[msgs.JointSensors] = []
    sub = client.declare_subscriber(TOPICS["joints"].key(ns), lambda s: joints.append(msgs.decode(s.payload.to_bytes(), msgs.JointSensors)))
    wheel_ff = [0.05, -0.02, 0.0]
    sending = threading.Event()
    done = threading.Event()

    def publish() -> None:
        seq = 0
        while not done.is_set():
            if sending.is_set():
                seq += 1
                pub.put(msgs.encode(msgs.AttitudeSetpoint(
                    seq=seq, stamp_ns=time.monotonic_ns(), quat_des=[1.0, 0.0, 0.0, 0.0], omega_des=[0.0, 0.0, 0.0],
                    torque_ff=wheel_ff, foot_torque=0.0, armed=True, commander=commander.instance)))
            time.sleep(0.001)

    publisher = threading.Thread(target=publish, daemon=True)

    async def until(predicate, timeout_s: float = 10.0) -> None:
        end = time.monotonic() + timeout_s
        while not predicate():
            assert time.monotonic() < end, "condition not met in time"
            await asyncio.sleep(0.005)

    async def scenario() -> None:
        task = asyncio.create_task(service.run())
        try:
            await until(lambda: service.state == "running")
            sending.set()
            await until(lambda: emu.counts["setpoints"] > 200 and emu.motors_on)
            assert emu.applied[:3] == pytest.approx(wheel_ff, abs=1e-6)  # the board's PD, upright at rest: just the feed-forward
            await until(lambda: len(joints) > 100 and joints[-1].wheel_vel[0] > 1.0)  # wheel 1 spins up
            sending.clear()
            await until(lambda: not emu.motors_on, 1.0)  # silence: the board's own watchdog
            assert emu.counts["watchdog_trips"] == 1 and not backend.faults
        finally:
            sending.clear()
            service.request_stop()
            await asyncio.wait_for(task, 10)

    board_loop.start()
    publisher.start()
    try:
        asyncio.run(scenario())
    finally:
        done.set()
        publisher.join(1.0)
        board_loop.stop()
        sub.undeclare()
        pub.undeclare()
        commander.close()
        client.close()
        emu.close()
    assert board_loop.error is None
