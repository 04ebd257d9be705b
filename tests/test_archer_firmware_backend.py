"""The hardware-service backend for ARCHER's firmware against the emulated board (UDP loopback)."""

from __future__ import annotations

import dataclasses
import socket
import time

import pytest

from drivers.archer_firmware.emulator import BoardEmulator
from onboard.contracts import messages as msgs
from onboard.low_level.tracking.foot_control import FootPhysics
from onboard.contracts.params import ArcherFirmwareParams
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
    imu = backend.imu()  # the board's attitude and rates; no accelerometer in this firmware's state
    assert imu is not None and imu.quat == [1.0, 0.0, 0.0, 0.0] and imu.stamp_ns == joints.stamp_ns
    assert imu.accel_sensed is False and imu.accel == [0.0, 0.0, 0.0]
    assert backend.board_attitude()[1] == (1.0, 0.0, 0.0, 0.0)


def test_disarmed_or_torque_mode_polls_with_the_reset_command(rig) -> None:
    """No setpoint: the reset command (motors off at once), which the board answers with its
    state: the estimator gets the board's IMU before anything is armed."""
    clock, emu, backend = rig
    sp = msgs.AttitudeSetpoint(quat_des=[1.0, 0.0, 0.0, 0.0], omega_des=[0.0, 0.0, 0.0], torque_ff=[0.1, 0.0, 0.0], foot_torque=0.0, armed=True)
    round_trip(clock, emu, backend, torques=(0.0, 0.0, 0.0, 0.0), armed=True, attitude=sp)
    assert emu.motors_on
    round_trip(clock, emu, backend, torques=(0.2, 0.0, 0.0, 1.0), armed=True, attitude=None)
    assert not emu.motors_on and emu.applied == [0.0, 0.0, 0.0, 0.0]  # torque mode: not applied, motors off
    round_trip(clock, emu, backend, torques=(0.0, 0.0, 0.0, 0.0), armed=False, attitude=None)
    assert emu.counts["resets"] == 2 and emu.counts["setpoints"] == 1 and not emu.motors_on
    backend.exchange(clock[0], (0.0, 0.0, 0.0, 0.0), False, None)
    assert backend.joints() is not None and backend.imu() is not None  # the reset's answer
    assert backend.summary()["torques_ignored"] == 1.0 and not backend.faults


def test_without_polling_disarmed_sends_nothing() -> None:
    computer_port = free_port()
    emu = BoardEmulator(ArcherFirmwareParams(), FOOT, ("127.0.0.1", 0), ("127.0.0.1", computer_port), lambda: 1.0, wheel_axes=AXES)
    params = dataclasses.replace(ArcherFirmwareParams(), computer_port=computer_port, board_port=emu.link.local[1], poll_disarmed=False)
    backend = ArcherFirmwareBackend(params, AXES, lambda: 1.0)
    try:
        backend.exchange(1.0, (0.2, 0.0, 0.0, 1.0), True, None)
        backend.exchange(1.0, (0.0, 0.0, 0.0, 0.0), False, None)
        time.sleep(0.01)
        emu.tick(1.0)
        assert emu.link.rx == 0 and backend.board.link.tx == 0
    finally:
        emu.close()
        backend.close()


def test_the_hardware_service_drives_the_board_through_this_backend(zenoh_router) -> None:
    """The ``hardware`` service, unchanged, with this backend: attitude setpoints reach the
    board's PD, joints and the board's IMU come back on the topics, and when the setpoints
    stop the service stops the board's motors with the reset command."""
    import asyncio
    import threading

    from onboard.contracts.params import HardwareParams, SafetyLimits
    from onboard.contracts.topics import TOPICS
    from services.hardware import HardwareService
    from services.runtime.realtime import DeadlineLoop
    from services.runtime.service import StandInCommander
    from services.runtime.zenoh_session import open_session

    ns = "archer/fwtest"
    computer_port = free_port()
    emu = BoardEmulator(ArcherFirmwareParams(), FOOT, ("127.0.0.1", 0), ("127.0.0.1", computer_port), time.perf_counter, wheel_axes=AXES)
    board_loop = DeadlineLoop(0.001, emu.tick, name="board")
    params = dataclasses.replace(ArcherFirmwareParams(), computer_port=computer_port, board_port=emu.link.local[1])
    backend = ArcherFirmwareBackend(params, AXES)
    # the service takes attitude_cmd when its hardware runs the PD
    hw = HardwareParams(backend="archer-firmware", rt_priority=0)
    service = HardwareService(ns=ns, endpoint=zenoh_router, params={"hardware": hw, "safety": SafetyLimits(), "archer_firmware": params},
                              backend=backend)
    client = open_session(zenoh_router, "peer")
    commander = StandInCommander(client, ns)
    pub = client.declare_publisher(TOPICS["attitude_cmd"].key(ns))
    joints: list[msgs.JointSensors] = []
    sub = client.declare_subscriber(TOPICS["joints"].key(ns), lambda s: joints.append(msgs.decode(s.payload.to_bytes(), msgs.JointSensors)))
    imus: list[msgs.ImuSample] = []
    imu_sub = client.declare_subscriber(TOPICS["imu"].key(ns), lambda s: imus.append(msgs.decode(s.payload.to_bytes(), msgs.ImuSample)))
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
            await until(lambda: len(imus) > 50 and emu.counts["resets"] > 50)  # disarmed: polled, motors off
            assert not emu.motors_on and not imus[-1].accel_sensed
            sending.set()
            await until(lambda: emu.counts["setpoints"] > 200 and emu.motors_on)
            assert emu.applied[:3] == pytest.approx(wheel_ff, abs=1e-6)  # the board's PD, upright at rest: just the feed-forward
            await until(lambda: len(joints) > 100 and joints[-1].wheel_vel[0] > 1.0)  # wheel 1 spins up
            sending.clear()
            resets = emu.counts["resets"]
            await until(lambda: not emu.motors_on, 1.0)  # stale setpoints: the reset command, well before the board's watchdog
            assert emu.counts["resets"] > resets and emu.counts["watchdog_trips"] == 0 and not backend.faults
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
        imu_sub.undeclare()
        pub.undeclare()
        commander.close()
        client.close()
        emu.close()
    assert board_loop.error is None


# real time: loops at their rate, processes and Zenoh over loopback share two loaded cores
pytestmark = pytest.mark.timing_sensitive(reason="real-time loops, processes or Zenoh over loopback on a shared host")
