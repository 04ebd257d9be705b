"""Interoperability with an independent CANopen implementation, the ``canopen`` package.

- canopen's master (``BaseNode402``) drives our emulated drive: PDO mapping over SDO,
  cyclic synchronous torque mode, OPERATION ENABLED, a torque commanded and read back.
- our driver drives canopen's own slave (``LocalNode``), given the CiA 402 reactions
  a drive needs (statusword from controlword, torque actual from target torque at
  SYNC, TPDO at SYNC) on top of canopen's SDO server, NMT slave and PDO maps.
"""

from __future__ import annotations

import struct
import time
import uuid

import can
import canopen
import pytest

from drivers.elmo import codec as c
from drivers.elmo.device import DriveGroup, ElmoDrive, JointDrive
from drivers.elmo.emulator import DriveBusEmulator, EmulatedDrive, VirtualBusRunner
from drivers.elmo.od import DriveConfig, drive_dictionary, to_eds
from drivers.elmo.sdo import SdoClient
from drivers.elmo.transport import CanTransport
from onboard.contracts.params import HardwareParams

NODE = 5
CFG = DriveConfig()
RATED_TORQUE_NM = CFG.rated_torque_mnm / 1000.0


@pytest.fixture
def channel() -> str:
    return f"canopen-{uuid.uuid4().hex}"


@pytest.fixture
def eds(tmp_path) -> str:
    path = tmp_path / "archer_elmo.eds"
    path.write_text(to_eds(drive_dictionary(NODE, CFG), NODE))
    return str(path)


def wait_for(predicate, timeout_s: float) -> None:
    t0 = time.monotonic()
    while not predicate():
        assert time.monotonic() - t0 < timeout_s, "condition not met in time"
        time.sleep(0.002)


def test_canopen_master_enables_our_emulated_drive_in_cst_and_reads_torque_back(channel: str, eds: str) -> None:
    emulator = DriveBusEmulator([EmulatedDrive(NODE, CFG)])
    emu_bus = can.Bus(interface="virtual", channel=channel)
    network = canopen.Network()
    with VirtualBusRunner(emulator, emu_bus) as runner:
        network.connect(interface="virtual", channel=channel)
        try:
            node = canopen.BaseNode402(NODE, eds)
            network.add_node(node)
            node.nmt.send_command(0x82)  # reset communication
            node.nmt.wait_for_bootup(2.0)
            assert node.sdo[0x1008].raw == CFG.device_name  # segmented upload by canopen's SDO client
            node.tpdo.read()
            node.rpdo.read()
            node.rpdo[1].clear()
            node.rpdo[1].add_variable(0x6040)
            node.rpdo[1].add_variable(0x6071)
            node.rpdo[1].trans_type = 1
            node.rpdo[1].enabled = True
            node.tpdo[1].clear()
            node.tpdo[1].add_variable(0x6041)
            node.tpdo[1].add_variable(0x6077)
            node.tpdo[1].add_variable(0x6061)
            node.tpdo[1].trans_type = 1
            node.tpdo[1].enabled = True
            node.rpdo.save()
            node.tpdo.save()
            node.setup_402_state_machine(read_pdos=False)
            assert node.is_op_mode_supported("CYCLIC SYNCHRONOUS TORQUE")  # 0x6502
            node.sdo[0x6060].raw = 10
            assert node.sdo[0x6061].raw == 10
            node.nmt.state = "OPERATIONAL"
            node.rpdo[1]["Controlword"].raw = 0
            node.rpdo[1]["Target torque"].raw = 0
            node.rpdo[1].start(0.005)  # canopen sends the RPDO periodically ...
            network.sync.start(0.005)  # ... and SYNCs, on which the drive applies it and answers
            node.state = "OPERATION ENABLED"
            assert node.state == "OPERATION ENABLED"
            drive = emulator.drive(NODE)
            assert drive.state == c.DriveState.OPERATION_ENABLED
            assert node.op_mode == "CYCLIC SYNCHRONOUS TORQUE"  # now from the TPDO
            node.rpdo[1]["Target torque"].raw = 250  # per mille of the rated torque
            wait_for(lambda: node.tpdo[1]["Torque actual value"].raw == 250, 1.0)
            assert drive.applied_torque == pytest.approx(0.25 * RATED_TORQUE_NM)
            assert node.tpdo[1]["Modes of operation display"].raw == 10
            node.state = "SWITCH ON DISABLED"
            wait_for(lambda: drive.applied_torque == 0.0, 1.0)
        finally:
            network.sync.stop()
            node.rpdo[1].stop()
            network.disconnect()
            emu_bus.shutdown()
    assert runner.error is None


class Cia402OnLocalNode:
    """The drive behaviour canopen's LocalNode lacks, hooked onto it (test scaffolding).

    canopen provides the SDO server, the NMT slave and the object store; this adds what
    a CiA 402 drive does with them: the state machine on controlword writes, and at
    each SYNC applying the received RPDO1 and sending TPDO1 from the mapping our
    driver configured.
    """

    def __init__(self, network: canopen.Network, node: canopen.LocalNode) -> None:
        self.network = network
        self.node = node
        self.state = c.DriveState.SWITCH_ON_DISABLED
        self.rpdo_data: bytes | None = None
        self.syncs = 0
        self.sync_counter = 0
        node.add_write_callback(self._on_write)
        node.add_read_callback(self._on_read)
        self._set(c.STATUSWORD, "<H", c.STATUSWORD_OF_STATE[self.state])
        network.subscribe(c.SYNC_ID, self._on_sync)
        network.subscribe(c.RPDO_BASE[0] + node.id, self._on_rpdo)

    def _set(self, index: int, fmt: str, value: int) -> None:
        self.node.set_data(index, 0, struct.pack(fmt, value))

    def _get(self, index: int, sub: int, fmt: str) -> int:
        return struct.unpack(fmt, self.node.get_data(index, sub))[0]

    def _on_read(self, index: int, subindex: int, od) -> int | None:
        if index == c.MODES_DISPLAY:
            return self._get(c.MODES_OF_OPERATION, 0, "<b")
        return None

    def _on_write(self, index: int, subindex: int, od, data: bytes) -> None:
        if index == c.CONTROLWORD:
            self._controlword(struct.unpack("<H", data)[0])

    def _controlword(self, cw: int) -> None:
        D = c.DriveState
        s = self.state
        if s == D.SWITCH_ON_DISABLED and cw & 0x87 == 0x06:
            s = D.READY_TO_SWITCH_ON
        elif s == D.READY_TO_SWITCH_ON and cw & 0x8F == 0x07:
            s = D.SWITCHED_ON
        elif s == D.SWITCHED_ON and cw & 0x8F == 0x0F:
            s = D.OPERATION_ENABLED
        elif not cw & 0x02:
            s = D.SWITCH_ON_DISABLED
        elif s in (D.SWITCHED_ON, D.OPERATION_ENABLED) and cw & 0x87 == 0x06:
            s = D.READY_TO_SWITCH_ON
        self.state = s
        self.node.data_store.setdefault(c.STATUSWORD, {})[0] = struct.pack("<H", c.STATUSWORD_OF_STATE[s])

    def _on_rpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self.rpdo_data = bytes(data)

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if self.node.nmt.state != "OPERATIONAL":
            return
        self.syncs += 1
        if self.rpdo_data is not None:
            cw, torque = struct.unpack("<Hh", self.rpdo_data)
            self.node.set_data(c.TARGET_TORQUE, 0, struct.pack("<h", torque))
            self._controlword(cw)
        enabled = self.state == c.DriveState.OPERATION_ENABLED
        target = self._get(c.TARGET_TORQUE, 0, "<h") if enabled else 0
        self._set(c.TORQUE_ACTUAL, "<h", target)
        for n in (0, 1):
            cob = self._get(c.TPDO_COMM + n, 1, "<I")
            if cob & c.PDO_COB_INVALID:
                continue
            every = max(1, self._get(c.TPDO_COMM + n, 2, "<B"))
            if self.syncs % every:
                continue
            payload = b""
            for i in range(1, self._get(c.TPDO_MAP + n, 0, "<B") + 1):
                index, sub, bits = c.split_mapping_entry(self._get(c.TPDO_MAP + n, i, "<I"))
                payload += self.node.get_data(index, sub)[: bits // 8]
            self.network.send_message(cob & 0x7FF, payload)


def test_our_driver_drives_canopens_local_node(channel: str, eds: str) -> None:
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel)
    host_bus = can.Bus(interface="virtual", channel=channel)
    try:
        local = canopen.LocalNode(NODE, eds)
        label = canopen.objectdictionary.ODVariable("Host label", 0x2000, 0)
        label.data_type = canopen.objectdictionary.VISIBLE_STRING
        label.access_type = "rw"
        local.object_dictionary.add_object(label)
        network.add_node(local)
        drive_logic = Cia402OnLocalNode(network, local)
        params = HardwareParams(node_ids=(NODE,), torque_constant=(0.083,), current_max=(12.0,), joint_sign=(1,))
        transport = CanTransport(host_bus)
        sdo = SdoClient(transport, NODE, 0.5)
        # canopen's SDO server answers our client, expedited and segmented both ways
        assert sdo.read_string(c.DEVICE_NAME) == CFG.device_name
        sdo.download(c.TPDO_COMM + 3, 1, struct.pack("<I", c.PDO_COB_INVALID | 0x485))
        assert sdo.read_u32(c.TPDO_COMM + 3, 1) == c.PDO_COB_INVALID | 0x485
        sdo.download(0x2000, 0, b"archer hardware service, node 5")  # segmented: 31 bytes in 5 segments
        assert local.sdo[0x2000].raw == "archer hardware service, node 5"
        assert sdo.read_string(0x2000) == "archer hardware service, node 5"
        local.nmt.state = "PRE-OPERATIONAL"  # what a slave is after its boot-up
        group = DriveGroup(transport, [ElmoDrive(JointDrive(NODE, 0.083, 12.0, 1.0, 1))], params, 0.1)
        # canopen's LocalNode announces no boot-up on an NMT reset from the bus: configure
        # it as found (PRE-OPERATIONAL) instead of resetting it first
        group.start(reset_communication=False)
        drive = group.drives[0]
        assert local.sdo[0x1A00][0].raw == 3  # our mapping is in canopen's object store
        assert local.sdo[0x1A00][1].raw == c.TPDO1_MAPPING[0]
        assert local.sdo[0x1600][2].raw == c.RPDO1_MAPPING[1]
        assert local.sdo[0x6060].raw == c.MODE_CST
        assert local.sdo[0x1016][1].raw == (params.host_node_id << 16) | 100
        wait_for(lambda: local.nmt.state == "OPERATIONAL", 1.0)
        t0 = time.monotonic()
        while drive.feedback.state != c.DriveState.OPERATION_ENABLED:
            group.exchange([0.0], armed=True)
            time.sleep(0.002)
            assert time.monotonic() - t0 < 2.0, f"stuck in {drive.feedback.state}"
        assert drive_logic.state == c.DriveState.OPERATION_ENABLED
        for _ in range(10):
            group.exchange([0.4], armed=True)
            time.sleep(0.002)
        assert local.sdo[0x6071].raw == round(0.4 / RATED_TORQUE_NM * 1000)
        assert drive.feedback.torque == pytest.approx(0.4, abs=0.001)
        assert not group.faults
    finally:
        network.disconnect()
        host_bus.shutdown()
