"""Our CiA 402 driver against the emulated ELMO drives on python-can's virtual bus.

Configuration over SDO, enabling, torque in and out, and the faults: EMCY, bus-off,
error frames, a dead host, a dead drive, corrupted feedback; recovery only on command.
"""

from __future__ import annotations

import struct
import time
import uuid
from dataclasses import dataclass

import can
import pytest

from drivers.elmo import codec as c
from drivers.elmo.device import DriveGroup, ElmoDrive, joint_drives
from drivers.elmo.emulator import DriveBusEmulator, VirtualBusRunner, make_emulator
from drivers.elmo.od import DriveConfig
from drivers.elmo.sdo import SdoClient, SdoError
from drivers.elmo.transport import CAN_ERR_PROT, CanTransport
from onboard.contracts.params import HardwareParams, SafetyLimits

PARAMS = HardwareParams()
GEARS = (1.0, 1.0, 1.0, 3.0)
HEARTBEAT_TIMEOUT_S = SafetyLimits().heartbeat_timeout_s
TICK_S = 0.001
REACTION_SLACK_S = 0.15  # scheduling on a loaded 2-core machine, on top of each bound


@dataclass
class Rig:
    emulator: DriveBusEmulator
    group: DriveGroup
    transport: CanTransport


@pytest.fixture
def rig():
    channel = f"elmo-{uuid.uuid4().hex}"
    emu_bus = can.Bus(interface="virtual", channel=channel)
    host_bus = can.Bus(interface="virtual", channel=channel)
    emulator = make_emulator(PARAMS)
    runner = VirtualBusRunner(emulator, emu_bus).start()
    transport = CanTransport(host_bus)
    group = DriveGroup(transport, [ElmoDrive(j) for j in joint_drives(PARAMS, GEARS)], PARAMS, HEARTBEAT_TIMEOUT_S)
    try:
        yield Rig(emulator, group, transport)
    finally:
        runner.stop()
        assert runner.error is None, runner.error
        emu_bus.shutdown()
        host_bus.shutdown()


def run(group: DriveGroup, ticks: int, torques=(0.0, 0.0, 0.0, 0.0), armed: bool = True) -> None:
    next_t = time.monotonic()
    for _ in range(ticks):
        group.exchange(torques, armed)
        next_t += TICK_S
        time.sleep(max(0.0, next_t - time.monotonic()))


def applied(emulator: DriveBusEmulator) -> list[float]:
    return [d.applied_torque for d in emulator.drives]


def wait_until(predicate, timeout_s: float, poll_s: float = 0.001) -> float:
    """Seconds until ``predicate()`` held; raises when it did not within ``timeout_s``."""
    t0 = time.monotonic()
    while not predicate():
        if time.monotonic() - t0 > timeout_s:
            raise AssertionError(f"condition not met within {timeout_s} s")
        time.sleep(poll_s)
    return time.monotonic() - t0


def started(rig: Rig, torques=(0.5, -0.5, 0.25, 2.0)) -> None:
    rig.group.start()
    rig.group.enable()
    run(rig.group, 30, torques)
    assert all(abs(t) > 0 for t in applied(rig.emulator))


def test_configures_enables_and_commands_torque_in_cst_mode(rig: Rig) -> None:
    group, emu = rig.group, rig.emulator
    group.start()
    wait_until(lambda: all(d.nmt == c.NmtState.OPERATIONAL for d in emu.drives), 0.5)
    for d in emu.drives:  # the mapping the driver wrote over SDO
        assert d.value(c.RPDO_MAP, 0) == 2
        assert (d.value(c.RPDO_MAP, 1), d.value(c.RPDO_MAP, 2)) == c.RPDO1_MAPPING
        assert tuple(d.value(c.TPDO_MAP, i) for i in (1, 2, 3)) == c.TPDO1_MAPPING
        assert d.value(c.TPDO_COMM + 1, 2) == PARAMS.position_every
        assert d.value(c.MODES_DISPLAY) == c.MODE_CST
        assert d.value(c.PRODUCER_HEARTBEAT) == round(PARAMS.drive_heartbeat_period_s * 1000)
        assert d.value(c.CONSUMER_HEARTBEAT, 1) == (PARAMS.host_node_id << 16) | round(HEARTBEAT_TIMEOUT_S * 1000)
    assert all(d.name == DriveConfig().device_name for d in group.drives)  # a segmented upload
    group.enable()
    assert all(d.state == c.DriveState.OPERATION_ENABLED for d in emu.drives)
    torques = (0.5, -0.5, 0.25, 2.0)
    run(group, 40, torques)
    motor_torques = [t / g for t, g in zip(torques, GEARS)]
    assert applied(emu) == pytest.approx(motor_torques, abs=0.001)  # per mille of 0.996 N m
    assert [d.feedback.torque for d in group.drives] == pytest.approx(torques, abs=0.004)
    assert [d.feedback.velocity > 0 for d in group.drives] == [True, False, True, True]
    assert all(d.feedback.position != 0.0 for d in group.drives)  # TPDO2 every 10th SYNC
    assert emu.drives[0].motor.velocity == pytest.approx(group.drives[0].feedback.velocity, rel=0.3)  # one SYNC of lag
    s = group.summary()
    assert s["faults_latched"] == 0 and s["malformed"] == 0 and s["feedback_ok"] > 0, (s, group.faults)


def test_torque_is_clamped_at_the_current_limit(rig: Rig) -> None:
    rig.group.start()
    rig.group.enable()
    run(rig.group, 20, (5.0, -5.0, 0.0, 30.0))
    clamp = PARAMS.current_max[0] * PARAMS.torque_constant[0]  # 12 A x 0.083 N m/A
    assert applied(rig.emulator)[:2] == pytest.approx([clamp, -clamp], abs=0.002)
    assert applied(rig.emulator)[3] == pytest.approx(clamp, abs=0.002)  # motor side of the gearbox
    assert rig.group.drives[3].torque_limit == pytest.approx(3 * clamp, abs=0.01)


def test_no_torque_while_disarmed_or_not_yet_enabled(rig: Rig) -> None:
    rig.group.start()
    rig.group.exchange((1.0, 1.0, 1.0, 1.0), armed=True)  # first tick: drives still SWITCH ON DISABLED
    run(rig.group, 1, (1.0, 1.0, 1.0, 1.0))
    assert applied(rig.emulator) == [0.0] * 4
    run(rig.group, 10, (0.5, 0.5, 0.5, 0.5))
    assert all(t > 0 for t in applied(rig.emulator))
    run(rig.group, 5, (0.5, 0.5, 0.5, 0.5), armed=False)
    assert applied(rig.emulator) == [0.0] * 4
    assert all(d.state == c.DriveState.READY_TO_SWITCH_ON for d in rig.emulator.drives)


def test_sdo_client_segmented_upload_and_abort_codes(rig: Rig) -> None:
    rig.group.start()
    sdo = SdoClient(rig.transport, 1, 0.5)
    assert sdo.read_string(c.DEVICE_NAME) == DriveConfig().device_name
    assert sdo.segments >= 4  # 34 characters in 7-byte segments
    assert sdo.read_u32(c.IDENTITY, 1) == c.ELMO_VENDOR_ID
    with pytest.raises(SdoError) as err:
        sdo.read_u32(0x5FFF)
    assert err.value.code == c.SdoAbort.NO_OBJECT
    with pytest.raises(SdoError) as err:
        sdo.read_u32(c.IDENTITY, 9)
    assert err.value.code == c.SdoAbort.NO_SUBINDEX
    with pytest.raises(SdoError) as err:
        sdo.write(c.STATUSWORD, 0, "<H", 0)
    assert err.value.code == c.SdoAbort.READ_ONLY
    with pytest.raises(SdoError) as err:  # six bytes into a 16-bit object: a segmented download, refused at the end
        sdo.download(c.TARGET_TORQUE, 0, b"\x01\x02\x03\x04\x05\x06")
    assert err.value.code == c.SdoAbort.LENGTH_MISMATCH
    with pytest.raises(SdoError) as err:  # the mapping of a live PDO is frozen
        sdo.write(c.TPDO_MAP, 0, "<B", 0)
    assert err.value.code == c.SdoAbort.DEVICE_STATE
    sdo.write(c.TPDO_COMM + 2, 1, "<I", c.PDO_COB_INVALID | 0x381)
    with pytest.raises(SdoError) as err:  # strings are not mappable
        sdo.write(c.TPDO_MAP + 2, 1, "<I", c.pdo_mapping_entry(c.DEVICE_NAME, 0, 8))
    assert err.value.code == c.SdoAbort.NOT_MAPPABLE
    for i in (1, 2, 3):
        sdo.write(c.TPDO_MAP + 2, i, "<I", c.pdo_mapping_entry(c.POSITION_ACTUAL, 0, 32))
    with pytest.raises(SdoError) as err:  # 96 bits do not fit in a frame
        sdo.write(c.TPDO_MAP + 2, 0, "<B", 3)
    assert err.value.code == c.SdoAbort.PDO_TOO_LONG
    with pytest.raises(SdoError) as err:
        sdo.write(c.MODES_OF_OPERATION, 0, "<b", 1)  # the emulated drive does cyclic torque only
    assert err.value.code == c.SdoAbort.VALUE_RANGE


def test_sdo_timeout_when_the_node_is_silent(rig: Rig) -> None:
    rig.group.start()
    rig.emulator.kill(2)
    time.sleep(0.01)
    sdo = SdoClient(rig.transport, 2, 0.05)
    with pytest.raises(SdoError) as err:
        sdo.read_u32(c.DEVICE_TYPE)
    assert err.value.code == c.SdoAbort.TIMEOUT


def test_emcy_latches_a_fault_and_every_motor_stops(rig: Rig) -> None:
    started(rig)
    rig.emulator.emcy_fault(2, 0x2340, c.ErrorRegister.CURRENT)
    for _ in range(200):
        run(rig.group, 1, (0.5, -0.5, 0.25, 2.0))
        if rig.group.faulted and applied(rig.emulator) == [0.0] * 4:
            break
    assert any("node 2 EMCY 0x2340" in f and "short circuit" in f for f in rig.group.faults)
    run(rig.group, 20, (0.5, -0.5, 0.25, 2.0))
    assert applied(rig.emulator) == [0.0] * 4  # the others are disabled by the host, not just node 2
    assert rig.emulator.drive(2).state == c.DriveState.FAULT
    assert all(d.state == c.DriveState.SWITCH_ON_DISABLED for d in rig.emulator.drives if d.node_id != 2)


def test_recovery_only_on_command(rig: Rig) -> None:
    started(rig)
    rig.emulator.emcy_fault(1, 0x4310, c.ErrorRegister.TEMPERATURE)
    run(rig.group, 100, (0.3, 0.3, 0.3, 0.3))
    assert rig.group.faulted and applied(rig.emulator) == [0.0] * 4
    run(rig.group, 100, (0.3, 0.3, 0.3, 0.3))  # time alone changes nothing
    assert rig.group.faulted and applied(rig.emulator) == [0.0] * 4
    rig.group.recover()
    assert not rig.group.faulted
    rig.group.enable()
    run(rig.group, 20, (0.3, 0.3, 0.3, 0.3))
    assert all(t > 0 for t in applied(rig.emulator))
    assert rig.group.stats.recoveries == 1
    assert rig.emulator.drive(1).value(c.ERROR_CODE) == 0  # fault reset cleared it


def test_bus_off_latches_and_the_drives_stop_on_their_own(rig: Rig) -> None:
    started(rig)
    t0 = time.monotonic()
    rig.emulator.bus_off(1.0)  # the host's frames stop reaching the drives
    run(rig.group, 5, (0.5, -0.5, 0.25, 2.0))  # the same torques: a zero sent before the bus-off bites would stop them
    wait_until(lambda: applied(rig.emulator) == [0.0] * 4, HEARTBEAT_TIMEOUT_S + REACTION_SLACK_S)
    stopped_after = time.monotonic() - t0
    # by their own heartbeat consumer (the host's frames no longer arrive), nothing else:
    # its counter goes up before the torque goes to zero
    assert [d.counters.get("heartbeat_lost") for d in rig.emulator.drives] == [1] * 4
    assert stopped_after <= HEARTBEAT_TIMEOUT_S + REACTION_SLACK_S
    run(rig.group, 5)
    assert any("bus-off" in f for f in rig.group.faults)
    assert rig.transport.bus_off == 1
    wait_until(lambda: all(d.state == c.DriveState.FAULT for d in rig.emulator.drives), 0.1)  # heartbeat consumer reaction


def test_error_frame_latches(rig: Rig) -> None:
    started(rig)
    rig.emulator.error_frame(CAN_ERR_PROT)
    run(rig.group, 50, (0.5, -0.5, 0.25, 2.0))
    assert any("protocol-violation" in f for f in rig.group.faults)
    assert applied(rig.emulator) == [0.0] * 4


def test_dead_host_the_drives_stop_within_the_heartbeat_timeout(rig: Rig) -> None:
    started(rig)
    last_exchange = time.monotonic()  # the host "dies" here: no SYNC, no heartbeat, nothing
    wait_until(lambda: applied(rig.emulator) == [0.0] * 4, HEARTBEAT_TIMEOUT_S + REACTION_SLACK_S)
    assert time.monotonic() - last_exchange <= HEARTBEAT_TIMEOUT_S + REACTION_SLACK_S
    wait_until(lambda: all(d.state == c.DriveState.FAULT for d in rig.emulator.drives), 0.1)
    assert all(d.value(c.ERROR_CODE) == 0x8130 for d in rig.emulator.drives)


def test_dead_drive_is_detected_and_the_others_stop(rig: Rig) -> None:
    started(rig)
    rig.emulator.kill(3)
    for _ in range(400):
        run(rig.group, 1, (0.5, -0.5, 0.25, 2.0))
        if rig.group.faulted:
            break
    assert any(f in rig.group.faults for f in ("node 3 heartbeat lost", "node 3 feedback lost"))
    run(rig.group, 5, (0.5, -0.5, 0.25, 2.0))
    assert [applied(rig.emulator)[i] for i in (0, 1, 3)] == [0.0, 0.0, 0.0]


def test_corrupted_feedback_is_rejected_and_a_long_burst_faults(rig: Rig) -> None:
    started(rig)
    rig.emulator.corrupt_feedback(1, 5)
    run(rig.group, 30, (0.5, -0.5, 0.25, 2.0))
    assert rig.group.stats.malformed == 5
    assert not rig.group.faulted  # a few bad frames stay below the feedback timeout
    assert all(t != 0.0 for t in applied(rig.emulator))
    rig.emulator.corrupt_feedback(1, 1000)
    for _ in range(400):
        run(rig.group, 1, (0.5, -0.5, 0.25, 2.0))
        if rig.group.faulted:
            break
    assert "node 1 feedback lost" in rig.group.faults
    run(rig.group, 5)
    assert applied(rig.emulator) == [0.0] * 4


def test_dropped_feedback_is_counted_as_missed(rig: Rig) -> None:
    started(rig)
    before = rig.group.stats.feedback_missed
    rig.emulator.drop_feedback(4, 3)
    run(rig.group, 20, (0.5, -0.5, 0.25, 2.0))
    assert rig.group.stats.per_node_missed[4] >= 3
    assert rig.group.stats.feedback_missed - before >= 3
    assert not rig.group.faulted


def test_a_rebooting_drive_latches(rig: Rig) -> None:
    started(rig)
    rig.transport.send(c.make_nmt(c.NmtCommand.RESET_NODE, 4))  # as if its power blinked
    run(rig.group, 20)
    assert "node 4 rebooted" in rig.group.faults


def test_rpdo_of_wrong_length_gets_an_emcy(rig: Rig) -> None:
    started(rig)
    rig.transport.send(c.Frame(0x201, struct.pack("<H", 0x0F)))
    run(rig.group, 10)
    assert rig.emulator.drive(1).counters.get("rpdo_length_errors") == 1
    assert any("0x8210" in f for f in rig.group.faults)


def test_quick_stop_zeroes_torque_and_the_drive_enables_again(rig: Rig) -> None:
    started(rig)
    for _ in range(50):
        rig.group.exchange((0.5, -0.5, 0.25, 2.0), armed=True, quick_stop=True)
        time.sleep(TICK_S)
        if all(d.state == c.DriveState.QUICK_STOP_ACTIVE for d in rig.emulator.drives):
            break
    assert all(d.state == c.DriveState.QUICK_STOP_ACTIVE for d in rig.emulator.drives)  # 0x605A = 6: stay
    assert applied(rig.emulator) == [0.0] * 4
    run(rig.group, 3, (0.5, -0.5, 0.25, 2.0))
    assert not rig.group.faulted
    run(rig.group, 20, (0.5, -0.5, 0.25, 2.0))
    assert all(t != 0.0 for t in applied(rig.emulator))
