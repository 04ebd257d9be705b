"""``archer emulate drives|teensy|archer-firmware`` as processes: the one JSON line and stock clients.

A stock python-can client opens the printed bus and talks raw CANopen to the drives;
the ``canopen`` package loads the printed EDS over the same socketcand bus; pyserial
opens the printed Teensy port.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import struct
import subprocess
import time

import can
import canopen
import pytest
import serial

from helpers import EMULATE, start_emulator, stop_emulator

LIVENESS_S = 0.5  # twin tests check physics, not timing: heartbeat/link bounds a loaded machine keeps


def recv_until(bus: can.BusABC, predicate, timeout_s: float) -> list[can.Message]:
    got = []
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and not predicate(got):
        msg = bus.recv(0.05)
        if msg is not None:
            got.append(msg)
    return got


def test_drives_print_one_line_a_stock_python_can_client_can_use() -> None:
    proc, info = start_emulator("drives", "--node-ids", "1,2,3,4")
    try:
        assert info["interface"] == "socketcand" and info["channel"] == "can0"
        assert info["bus"]["host"] == "127.0.0.1" and info["node_ids"] == [1, 2, 3, 4]
        assert os.path.exists(info["eds"])
        bus = can.Bus(**info["bus"])
        try:
            time.sleep(0.15)  # the server's raw mode settles
            bus.send(can.Message(arbitration_id=0x000, data=[0x82, 0], is_extended_id=False))  # NMT reset communication
            got = recv_until(bus, lambda m: sum(x.arbitration_id in (0x701, 0x702, 0x703, 0x704) for x in m) >= 4, 3.0)
            bootups = {m.arbitration_id for m in got if 0x701 <= m.arbitration_id <= 0x704 and bytes(m.data) == b"\x00"}
            assert bootups == {0x701, 0x702, 0x703, 0x704}
            bus.send(can.Message(arbitration_id=0x603, data=[0x40, 0x00, 0x10, 0, 0, 0, 0, 0], is_extended_id=False))  # SDO read 0x1000
            got = recv_until(bus, lambda m: any(x.arbitration_id == 0x583 for x in m), 3.0)
            reply = next(m for m in got if m.arbitration_id == 0x583)
            assert reply.data[0] == 0x43 and struct.unpack_from("<I", reply.data, 4)[0] & 0xFFFF == 0x0192  # CiA 402
        finally:
            bus.shutdown()
    finally:
        final = stop_emulator(proc)
    assert final["frames_in"] >= 2 and set(final["drives"]) == {"1", "2", "3", "4"}


def test_drives_report_their_counters_on_sigusr1_and_keep_serving() -> None:
    """What ``archer bench hardware`` reads at both ends of its window."""
    proc, info = start_emulator("drives", "--node-ids", "1,2")
    try:
        bus = can.Bus(**info["bus"])
        try:
            time.sleep(0.15)
            proc.send_signal(signal.SIGUSR1)
            time.sleep(0.2)  # the report is out before the frame goes
            bus.send(can.Message(arbitration_id=0x000, data=[0x82, 0], is_extended_id=False))  # NMT reset communication
            got = recv_until(bus, lambda m: sum(x.arbitration_id in (0x701, 0x702) for x in m) >= 2, 3.0)
            assert {m.arbitration_id for m in got} >= {0x701, 0x702}  # still serving after the signal
            proc.send_signal(signal.SIGUSR1)
            time.sleep(0.2)
        finally:
            bus.shutdown()
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    reports = [json.loads(line) for line in err.splitlines() if line.startswith('{"counters"')]
    assert len(reports) == 2
    first, second = reports
    assert second["monotonic_s"] > first["monotonic_s"]
    assert second["counters"]["frames_in"] - first["counters"]["frames_in"] == 1  # the one NMT frame
    assert set(second["counters"]["drives"]) == {"1", "2"}


def test_canopen_package_reads_the_drive_over_the_printed_bus() -> None:
    proc, info = start_emulator("drives", "--node-ids", "7")
    network = canopen.Network()
    try:
        network.connect(**info["bus"])
        node = network.add_node(7, info["eds"])
        time.sleep(0.15)
        assert node.sdo["Manufacturer device name"].raw.startswith("ELMO")
        assert node.sdo[0x6502].raw & (1 << 9)  # cyclic synchronous torque supported
        assert node.sdo[0x6076].raw == 996  # rated torque [mN m] = 12 A x 0.083 N m/A
    finally:
        network.disconnect()
        stop_emulator(proc)


def test_bad_node_ids_are_a_clear_error() -> None:
    result = subprocess.run(EMULATE + ["drives", "--node-ids", "1,x"], capture_output=True, text=True, timeout=30)
    assert result.returncode == 2 and "--node-ids" in result.stderr and result.stdout == ""
    result = subprocess.run(EMULATE + ["drives", "--node-ids", "0,200"], capture_output=True, text=True, timeout=30)
    assert result.returncode == 2


def test_archer_firmware_on_a_taken_port_is_a_clear_error() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        port = str(taken.getsockname()[1])
        result = subprocess.run(EMULATE + ["archer-firmware", "--port", port], capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and f"127.0.0.1:{port}" in result.stderr and result.stdout == ""
    result = subprocess.run(EMULATE + ["archer-firmware", "--peer-port", "70000"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and "--peer-port" in result.stderr


def test_teensy_prints_a_port_pyserial_opens() -> None:
    proc, info = start_emulator("teensy")
    try:
        assert info["device"] == "teensy" and info["pty"].startswith("/dev/pts/")
        port = serial.Serial(info["port"], timeout=0.2)
        try:
            data = b""
            end = time.monotonic() + 2.0
            while data.count(b"\x00") < 5 and time.monotonic() < end:
                data += port.read(4096)
            assert data.count(b"\x00") >= 5  # sensor frames, delimited, without being asked
        finally:
            port.close()
    finally:
        final = stop_emulator(proc)
    assert final["sensors"] > 0


@pytest.mark.parametrize("device", ["drives", "teensy", "archer-firmware"])
def test_the_line_is_json_with_a_pid(device: str) -> None:
    proc, info = start_emulator(device)
    try:
        assert info["pid"] == proc.pid and info["device"] == device
    finally:
        stop_emulator(proc)


def test_teensy_with_the_twin_behind_it_reports_the_twins_physics() -> None:
    from drivers.teensy import protocol as p
    from drivers.teensy.device import Teensy
    from drivers.teensy.transport import SerialLink

    proc, info = start_emulator("teensy", "--twin", "hop-in-place")
    teensy = Teensy(SerialLink(info["port"], 0.05, 1.0), "torque", LIVENESS_S)
    try:
        end = time.monotonic() + 0.6
        while time.monotonic() < end:
            teensy.exchange(time.monotonic(), torque=p.TorqueCmd((0.3, 0.0, 0.0), 0.0, True))
            time.sleep(0.001)
        s = teensy.sensors
        assert s is not None and not teensy.faults
        assert s.wheel_vel[0] > 10.0 and abs(s.wheel_vel[1]) < 1.0  # the twin's wheel spins up
        assert s.gyro[0] < -0.1  # and the body turns the other way (reaction)
        assert s.quat != (1.0, 0.0, 0.0, 0.0)  # the static emulator would report identity
    finally:
        teensy.link.close()
        stop_emulator(proc)


def test_drives_with_the_twin_behind_them_step_the_physics_on_sync() -> None:
    from drivers.elmo.device import DriveGroup, ElmoDrive, joint_drives
    from drivers.elmo.transport import CanTransport
    from drivers.socketcand import SocketcandBus
    from onboard.contracts.params import HardwareParams
    from services.hardware import gear_ratios

    proc, info = start_emulator("drives", "--twin", "hop-in-place")
    bus = info["bus"]
    transport = CanTransport(SocketcandBus(bus["channel"], bus["host"], bus["port"]))
    params = HardwareParams()
    group = DriveGroup(transport, [ElmoDrive(j) for j in joint_drives(params, gear_ratios())], params, LIVENESS_S)
    try:
        group.start()
        group.enable(timeout_s=5.0)
        for _ in range(400):
            group.exchange((0.0, 0.0, 0.3, 0.0), armed=True)
            time.sleep(0.001)
        fb = [d.feedback for d in group.drives]
        assert fb[2].velocity > 10.0 and abs(fb[0].velocity) < 1.0
        assert fb[2].torque == pytest.approx(0.3, abs=0.005)
    finally:
        group.stop()
        transport.shutdown()
        final = stop_emulator(proc)
    assert final["syncs"] >= 400
