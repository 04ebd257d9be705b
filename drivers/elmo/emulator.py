"""Emulated ELMO drives on a python-can bus, strict enough to catch driver bugs.

Each :class:`EmulatedDrive` is a CANopen slave with the object dictionary of
:mod:`drivers.elmo.od`: NMT (boot-up, start/stop/pre-operational, resets), an SDO
server (expedited and segmented, with the CiA 301 abort codes), PDO mapping that
obeys the CiA 301 rules (a mapping changes only while its PDO is disabled, entries
must exist, be mappable and fit in 8 bytes), synchronous RPDOs applied and TPDOs
sampled at SYNC (transmission type n: every n-th SYNC), a heartbeat producer
(0x1017) and consumer (0x1016, reaction per 0x6007), EMCY, and the CiA 402 state
machine with cyclic synchronous torque mode driving a motor model.

:class:`DriveBusEmulator` holds several drives behind one bus and
injects faults: EMCY, dead drives, dropped or corrupted PDOs, error frames and
bus-off (the host's frames stop reaching the drives).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import can

from drivers.elmo import codec as c
from drivers.elmo.od import DataType, DriveConfig, Obj, bit_length, decode_value, drive_dictionary, encode_value
from drivers.elmo.transport import CAN_ERR_BUSOFF, make_error_frame
from onboard.contracts.params import HardwareParams

log = logging.getLogger("archer.drivers.elmo.emulator")

MAX_SYNC_DT_S = 0.01  # a motor step never integrates over a longer gap than this
MAX_PDO_BITS = 64
SDO_SERVER_TIMEOUT_S = 1.0  # an unfinished segmented transfer is dropped after this
QUICK_STOP_STAY = range(5, 9)  # 0x605A codes that stay in QUICK STOP ACTIVE
SERVICE_PERIOD_S = 0.002  # timer resolution of heartbeats and consumer timeouts
ERROR_FLAG = 0x20000000  # SocketCAN's CAN_ERR_FLAG: marks an error frame among output frames


class MotorModel(Protocol):
    """What the drive's current loop drives: motor-shaft angle and speed."""

    position: float  # [rad] motor shaft
    velocity: float  # [rad/s] motor shaft

    def step(self, torque: float, dt_s: float) -> None: ...


class InertiaLoad:
    """Stand-in load when no twin is behind the emulator: J dw/dt = tau - b w.

    These numbers describe the emulator's load, not the robot (whose parameters
    live in the MJCF model); they only need a plausible time constant.
    """

    def __init__(self, inertia: float = 2.0e-4, damping: float = 1.0e-5) -> None:
        self.inertia = inertia  # [kg m^2]
        self.damping = damping  # [N m s/rad]
        self.position = 0.0
        self.velocity = 0.0

    def step(self, torque: float, dt_s: float) -> None:
        accel = (torque - self.damping * self.velocity) / self.inertia
        self.velocity += accel * dt_s
        self.position += self.velocity * dt_s


def drive_config(params: HardwareParams, joint: int, serial_number: int = 1) -> DriveConfig:
    """The drive set-up of joint ``joint``: rated current = the clamp, rated torque = kt x clamp."""
    current = params.current_max[joint]
    return DriveConfig(
        rated_current_ma=round(current * 1000),
        rated_torque_mnm=round(current * params.torque_constant[joint] * 1000),
        serial_number=serial_number,
    )


@dataclass
class _SdoTransfer:
    upload: bool
    index: int
    subindex: int
    toggle: int = 0
    data: bytearray | bytes = b""
    offset: int = 0
    size: int | None = None
    started_s: float = 0.0


class EmulatedDrive:
    """One CiA 402 drive. :meth:`receive` and :meth:`poll` return the frames it sends."""

    def __init__(self, node_id: int, cfg: DriveConfig | None = None, motor: MotorModel | None = None) -> None:
        self.node_id = c.check_node_id(node_id)
        self.cfg = cfg or DriveConfig()
        self.motor: MotorModel = motor or InertiaLoad()
        self.od: dict[int, Obj] = {}
        self.nmt = c.NmtState.BOOTUP
        self.state = c.DriveState.NOT_READY_TO_SWITCH_ON
        self.applied_torque_permille = 0  # what the current loop applies now
        self.last_controlword = 0
        self.muted = False  # a dead drive: sends nothing, hears nothing
        self.drop_tpdo = 0  # fault injection: TPDO1s still to drop
        self.corrupt_tpdo = 0  # fault injection: TPDO1s still to send truncated
        self.counters: dict[str, int] = {}
        self._sdo: _SdoTransfer | None = None
        self._pending_rpdo: dict[int, bytes] = {}
        self._tpdo_counter = [0] * 4
        self._last_sync_s: float | None = None
        self._next_heartbeat_s = 0.0
        self._consumer_last_s: float | None = None  # monitoring starts on the first heartbeat
        self._queued: list[c.Frame] = []  # frames caused by an SDO or PDO write, sent at the next poll
        self._reset_node()

    # --- object dictionary ----------------------------------------------------------

    def value(self, index: int, subindex: int = 0) -> int | str:
        return self.od[index].subs[subindex].value

    def _set(self, index: int, value: int | str, subindex: int = 0) -> None:
        self.od[index].subs[subindex].value = value

    def _count(self, name: str) -> None:
        self.counters[name] = self.counters.get(name, 0) + 1

    def _reset_node(self) -> None:
        self.od = drive_dictionary(self.node_id, self.cfg)
        self.state = c.DriveState.SWITCH_ON_DISABLED  # NOT READY passes on by itself
        self.applied_torque_permille = 0
        self._reset_communication()

    def _reset_communication(self) -> None:
        fresh = drive_dictionary(self.node_id, self.cfg)
        for index, obj in fresh.items():
            if 0x1000 <= index < 0x2000:
                self.od[index] = obj
        self._sdo = None
        self._pending_rpdo.clear()
        self._tpdo_counter = [0] * 4
        self._consumer_last_s = None
        self.nmt = c.NmtState.PRE_OPERATIONAL

    def boot(self, now: float) -> list[c.Frame]:
        """Power-on: the boot-up message."""
        self._next_heartbeat_s = now
        return [c.make_heartbeat(self.node_id, c.NmtState.BOOTUP)]

    # --- frames in ---------------------------------------------------------------------

    def receive(self, frame: c.Frame, now: float) -> list[c.Frame]:
        if self.muted:
            return []
        can_id = frame.can_id
        if can_id == c.NMT_ID:
            return self._on_nmt(frame.data, now)
        if self.nmt == c.NmtState.STOPPED:
            if can_id == c.HEARTBEAT_BASE + self._consumer_node():
                self._consumer_last_s = now
            return []
        if can_id == c.SYNC_ID:
            return self._on_sync(now)
        if can_id == c.SDO_RX_BASE + self.node_id:
            return self._on_sdo(frame.data, now)
        if can_id == c.HEARTBEAT_BASE + self._consumer_node() and self._consumer_time_ms():
            self._consumer_last_s = now
            return []
        if self.nmt == c.NmtState.OPERATIONAL:
            for n in range(4):
                cob = int(self.value(c.RPDO_COMM + n, 1))
                if not cob & c.PDO_COB_INVALID and cob & 0x7FF == can_id:
                    return self._on_rpdo(n, frame.data)
        return []

    def _on_nmt(self, data: bytes, now: float) -> list[c.Frame]:
        try:
            command, node = c.parse_nmt(data)
        except ValueError:
            self._count("bad_nmt")
            return []
        if node not in (0, self.node_id):
            return []
        if command == c.NmtCommand.START:
            self.nmt = c.NmtState.OPERATIONAL
        elif command in (c.NmtCommand.STOP, c.NmtCommand.ENTER_PRE_OPERATIONAL):
            if self.nmt == c.NmtState.OPERATIONAL and self.state == c.DriveState.OPERATION_ENABLED:
                self.state = c.DriveState.SWITCH_ON_DISABLED  # no PDOs any more: power off
                self.applied_torque_permille = 0
            self.nmt = c.NmtState.STOPPED if command == c.NmtCommand.STOP else c.NmtState.PRE_OPERATIONAL
        elif command == c.NmtCommand.RESET_NODE:
            self._reset_node()
            return self.boot(now)
        elif command == c.NmtCommand.RESET_COMMUNICATION:
            self._reset_communication()
            return self.boot(now)
        return []

    # --- SDO server ------------------------------------------------------------------------

    def _abort(self, index: int, subindex: int, code: int) -> list[c.Frame]:
        self._sdo = None
        self._count("sdo_aborts")
        return [c.make_sdo_abort(c.SDO_TX_BASE + self.node_id, index, subindex, code)]

    def _on_sdo(self, data: bytes, now: float) -> list[c.Frame]:
        try:
            msg = c.parse_sdo(data, client_to_server=True)
        except ValueError:
            self._count("bad_sdo")
            return []
        if msg.cs == c.CS_ABORT:
            self._sdo = None
            return []
        tr = self._sdo
        if tr is not None and now - tr.started_s > SDO_SERVER_TIMEOUT_S:
            tr = self._sdo = None
        if msg.cs == c.CCS_INITIATE_UPLOAD:
            return self._initiate_upload(msg.index, msg.subindex, now)
        if msg.cs == c.CCS_INITIATE_DOWNLOAD:
            return self._initiate_download(msg, now)
        if msg.cs == c.CCS_UPLOAD_SEGMENT:
            if tr is None or not tr.upload:
                return self._abort(0, 0, c.SdoAbort.INVALID_COMMAND)
            if msg.toggle != tr.toggle:
                return self._abort(tr.index, tr.subindex, c.SdoAbort.TOGGLE_BIT)
            chunk = bytes(tr.data[tr.offset : tr.offset + c.SEGMENT_BYTES])
            tr.offset += len(chunk)
            last = tr.offset >= len(tr.data)
            out = [c.make_sdo_upload_segment(self.node_id, tr.toggle, chunk, last)]
            tr.toggle ^= 1
            if last:
                self._sdo = None
            return out
        if msg.cs == c.CCS_DOWNLOAD_SEGMENT:
            if tr is None or tr.upload:
                return self._abort(0, 0, c.SdoAbort.INVALID_COMMAND)
            if msg.toggle != tr.toggle:
                return self._abort(tr.index, tr.subindex, c.SdoAbort.TOGGLE_BIT)
            assert isinstance(tr.data, bytearray)
            tr.data += msg.payload
            out = [c.make_sdo_download_segment_response(self.node_id, tr.toggle)]
            tr.toggle ^= 1
            if msg.last:
                self._sdo = None
                if tr.size is not None and tr.size != len(tr.data):
                    return self._abort(tr.index, tr.subindex, c.SdoAbort.LENGTH_MISMATCH)
                code = self._write(tr.index, tr.subindex, bytes(tr.data))
                if code:
                    return self._abort(tr.index, tr.subindex, code)
            return out
        return self._abort(msg.index, msg.subindex, c.SdoAbort.INVALID_COMMAND)

    def _initiate_upload(self, index: int, subindex: int, now: float) -> list[c.Frame]:
        obj = self.od.get(index)
        if obj is None:
            return self._abort(index, subindex, c.SdoAbort.NO_OBJECT)
        entry = obj.subs.get(subindex)
        if entry is None:
            return self._abort(index, subindex, c.SdoAbort.NO_SUBINDEX)
        if not entry.readable:
            return self._abort(index, subindex, c.SdoAbort.WRITE_ONLY)
        data = encode_value(entry.dtype, entry.value)
        self._count("sdo_uploads")
        if len(data) <= c.EXPEDITED_MAX:
            self._sdo = None
            return [c.make_sdo_upload_response(self.node_id, index, subindex, data)]
        self._sdo = _SdoTransfer(True, index, subindex, data=data, started_s=now)
        return [c.make_sdo_upload_response(self.node_id, index, subindex, data)]

    def _initiate_download(self, msg: c.SdoMessage, now: float) -> list[c.Frame]:
        self._count("sdo_downloads")
        if msg.expedited:
            code = self._write(msg.index, msg.subindex, msg.payload)
            if code:
                return self._abort(msg.index, msg.subindex, code)
            return [c.make_sdo_initiate_download_response(self.node_id, msg.index, msg.subindex)]
        obj = self.od.get(msg.index)
        if obj is None:
            return self._abort(msg.index, msg.subindex, c.SdoAbort.NO_OBJECT)
        if msg.subindex not in obj.subs:
            return self._abort(msg.index, msg.subindex, c.SdoAbort.NO_SUBINDEX)
        self._sdo = _SdoTransfer(False, msg.index, msg.subindex, data=bytearray(), size=msg.size, started_s=now)
        return [c.make_sdo_initiate_download_response(self.node_id, msg.index, msg.subindex)]

    def _write(self, index: int, subindex: int, data: bytes) -> int:
        """Write one entry as the SDO server would; returns an abort code or 0."""
        obj = self.od.get(index)
        if obj is None:
            return c.SdoAbort.NO_OBJECT
        entry = obj.subs.get(subindex)
        if entry is None:
            return c.SdoAbort.NO_SUBINDEX
        if not entry.writable:
            return c.SdoAbort.READ_ONLY
        try:
            value = decode_value(entry.dtype, data)
        except ValueError:
            return c.SdoAbort.LENGTH_MISMATCH
        code = self._check_write(index, subindex, value)
        if code:
            return code
        entry.value = value
        self._after_write(index, subindex, value)
        return 0

    def _pdo_of_mapping(self, index: int) -> int | None:
        if c.RPDO_MAP <= index < c.RPDO_MAP + 4:
            return c.RPDO_COMM + index - c.RPDO_MAP
        if c.TPDO_MAP <= index < c.TPDO_MAP + 4:
            return c.TPDO_COMM + index - c.TPDO_MAP
        return None

    def _mapping_bits(self, entry_value: int, receive: bool) -> int | None:
        """Bit length of a valid mapping entry, or None."""
        index, subindex, bits = c.split_mapping_entry(entry_value)
        obj = self.od.get(index)
        target = obj.subs.get(subindex) if obj else None
        if target is None or not target.pdo_mappable or target.dtype == DataType.VISIBLE_STRING:
            return None
        if bit_length(target.dtype) != bits:
            return None
        if receive and not target.writable:
            return None
        return bits

    def _check_write(self, index: int, subindex: int, value: int | str) -> int:
        assert isinstance(value, (int, str))
        comm = self._pdo_of_mapping(index)
        if comm is not None:
            valid = not int(self.value(comm, 1)) & c.PDO_COB_INVALID
            if valid:
                return c.SdoAbort.DEVICE_STATE  # mapping is frozen while the PDO exists
            receive = index < c.TPDO_MAP
            if subindex == 0:
                if int(value) > 8:
                    return c.SdoAbort.VALUE_RANGE
                total = 0
                for i in range(1, int(value) + 1):
                    bits = self._mapping_bits(int(self.value(index, i)), receive)
                    if bits is None:
                        return c.SdoAbort.NOT_MAPPABLE
                    total += bits
                if total > MAX_PDO_BITS:
                    return c.SdoAbort.PDO_TOO_LONG
            else:
                if int(self.value(index, 0)) != 0:
                    return c.SdoAbort.DEVICE_STATE  # clear sub 0 before changing entries
                if int(value) != 0 and self._mapping_bits(int(value), receive) is None:
                    return c.SdoAbort.NOT_MAPPABLE
            return 0
        if (c.RPDO_COMM <= index < c.RPDO_COMM + 4) or (c.TPDO_COMM <= index < c.TPDO_COMM + 4):
            if subindex == 1:
                current = int(self.value(index, 1))
                if not current & c.PDO_COB_INVALID and not int(value) & c.PDO_COB_INVALID and (int(value) & 0x7FF) != (current & 0x7FF):
                    return c.SdoAbort.VALUE_RANGE  # the identifier changes only while disabled
            if subindex == 2 and not 0 <= int(value) <= 240:
                return c.SdoAbort.VALUE_RANGE  # only synchronous PDOs are emulated
            return 0
        if index == c.MODES_OF_OPERATION and value not in (0, c.MODE_CST):
            return c.SdoAbort.VALUE_RANGE
        if index in (c.MAX_CURRENT, c.MAX_TORQUE) and int(value) > c.I16_MAX:
            return c.SdoAbort.VALUE_TOO_HIGH
        return 0

    def _after_write(self, index: int, subindex: int, value: int | str) -> None:
        if index == c.MODES_OF_OPERATION:
            self._set(c.MODES_DISPLAY, value)
        elif index == c.CONTROLWORD:
            self._on_controlword(int(value))
        elif index == c.CONSUMER_HEARTBEAT:
            self._consumer_last_s = None  # re-armed by the next heartbeat
        elif index == c.PRODUCER_HEARTBEAT:
            self._next_heartbeat_s = 0.0

    # --- PDOs and SYNC -----------------------------------------------------------------

    def _mapped(self, mapping_index: int) -> list[tuple[int, int, DataType]]:
        out = []
        for i in range(1, int(self.value(mapping_index, 0)) + 1):
            index, subindex, _bits = c.split_mapping_entry(int(self.value(mapping_index, i)))
            out.append((index, subindex, self.od[index].subs[subindex].dtype))
        return out

    def _on_rpdo(self, n: int, data: bytes) -> list[c.Frame]:
        size = sum(bit_length(d) for _i, _s, d in self._mapped(c.RPDO_MAP + n)) // 8
        if len(data) != size:
            self._count("rpdo_length_errors")
            return [c.make_emcy(self.node_id, 0x8210, c.ErrorRegister.GENERIC | c.ErrorRegister.COMMUNICATION)]
        self._count("rpdos")
        self._pending_rpdo[n] = data  # synchronous: applied at the next SYNC
        return []

    def _apply_rpdo(self, n: int, data: bytes) -> None:
        offset = 0
        for index, subindex, dtype in self._mapped(c.RPDO_MAP + n):
            width = bit_length(dtype) // 8
            value = decode_value(dtype, data[offset : offset + width])
            offset += width
            self.od[index].subs[subindex].value = value
            self._after_write(index, subindex, value)

    def _on_sync(self, now: float) -> list[c.Frame]:
        if self.nmt != c.NmtState.OPERATIONAL:
            self._last_sync_s = now
            return []
        self._count("syncs")
        if not self._pending_rpdo and int(self.value(c.RPDO_COMM, 1)) & c.PDO_COB_INVALID == 0:
            self._count("sync_without_rpdo")  # the host's command for this cycle is late or lost
        for n in sorted(self._pending_rpdo):
            self._apply_rpdo(n, self._pending_rpdo[n])
        self._pending_rpdo.clear()
        if self.state == c.DriveState.FAULT_REACTION_ACTIVE:
            self.state = c.DriveState.FAULT
        dt = 0.0 if self._last_sync_s is None else min(MAX_SYNC_DT_S, max(0.0, now - self._last_sync_s))
        self._last_sync_s = now
        self._run_motor(dt)
        out: list[c.Frame] = []
        for n in range(4):
            cob = int(self.value(c.TPDO_COMM + n, 1))
            if cob & c.PDO_COB_INVALID:
                continue
            every = max(1, int(self.value(c.TPDO_COMM + n, 2)))
            self._tpdo_counter[n] += 1
            if self._tpdo_counter[n] < every:
                continue
            self._tpdo_counter[n] = 0
            frame = self._make_tpdo(n, cob & 0x7FF)
            if n == 0 and self.drop_tpdo > 0:
                self.drop_tpdo -= 1
                continue
            if n == 0 and self.corrupt_tpdo > 0:
                self.corrupt_tpdo -= 1
                frame = c.Frame(frame.can_id, frame.data[:-1])
            out.append(frame)
        return out

    def _make_tpdo(self, n: int, cob: int) -> c.Frame:
        data = b"".join(encode_value(d, self.od[i].subs[s].value) for i, s, d in self._mapped(c.TPDO_MAP + n))
        return c.Frame(cob, data)

    def _torque_limit_permille(self) -> int:
        return min(int(self.value(c.MAX_TORQUE)), int(self.value(c.MAX_CURRENT)))

    def _run_motor(self, dt: float) -> None:
        if self.state == c.DriveState.OPERATION_ENABLED and self.value(c.MODES_DISPLAY) == c.MODE_CST:
            limit = self._torque_limit_permille()
            self.applied_torque_permille = max(-limit, min(limit, int(self.value(c.TARGET_TORQUE))))
        else:
            self.applied_torque_permille = 0
        if self.state == c.DriveState.QUICK_STOP_ACTIVE and int(self.value(c.QUICK_STOP_OPTION)) not in QUICK_STOP_STAY:
            self.state = c.DriveState.SWITCH_ON_DISABLED
        rated_nm = int(self.value(c.RATED_TORQUE)) / 1000.0
        torque_nm = self.applied_torque_permille / c.PERMILLE * rated_nm
        self.motor.step(torque_nm, dt)
        counts_per_rad = int(self.value(c.ENCODER_RESOLUTION, 1)) / int(self.value(c.ENCODER_RESOLUTION, 2)) / (2.0 * 3.141592653589793)
        self._set(c.POSITION_ACTUAL, _wrap_i32(round(self.motor.position * counts_per_rad)))
        self._set(c.VELOCITY_ACTUAL, _wrap_i32(round(self.motor.velocity * counts_per_rad)))
        self._set(c.TORQUE_ACTUAL, self.applied_torque_permille)
        # rated torque = kt x rated current, so current and torque share the per mille value
        self._set(c.CURRENT_ACTUAL, self.applied_torque_permille)
        self._publish_statusword()

    # --- CiA 402 ----------------------------------------------------------------------------

    def _publish_statusword(self) -> None:
        sw = c.STATUSWORD_OF_STATE[self.state] | c.SW_REMOTE
        if self.state in (c.DriveState.SWITCHED_ON, c.DriveState.OPERATION_ENABLED, c.DriveState.QUICK_STOP_ACTIVE):
            sw |= c.SW_VOLTAGE_ENABLED
        if self.state not in (c.DriveState.QUICK_STOP_ACTIVE,) and self.state not in (
            c.DriveState.NOT_READY_TO_SWITCH_ON,
            c.DriveState.SWITCH_ON_DISABLED,
            c.DriveState.FAULT,
            c.DriveState.FAULT_REACTION_ACTIVE,
        ):
            sw |= c.SW_QUICK_STOP_N
        if self.state == c.DriveState.OPERATION_ENABLED and self.value(c.MODES_DISPLAY) == c.MODE_CST:
            sw |= c.SW_FOLLOWS_COMMAND
        self._set(c.STATUSWORD, sw)

    def _on_controlword(self, cw: int) -> None:
        previous = self.last_controlword
        self.last_controlword = cw
        s = self.state
        D = c.DriveState
        if s in (D.FAULT, D.FAULT_REACTION_ACTIVE):
            if s == D.FAULT and cw & c.CW_FAULT_RESET and not previous & c.CW_FAULT_RESET:
                self.state = D.SWITCH_ON_DISABLED
                self._set(c.ERROR_CODE, 0)
                self._set(c.ERROR_REGISTER, 0)
                self._queued.append(c.make_emcy(self.node_id, c.EMCY_NO_ERROR, 0))
            self._publish_statusword()
            return
        if cw & c.CW_FAULT_RESET:
            self._publish_statusword()
            return
        disable_voltage = not cw & c.CW_ENABLE_VOLTAGE
        quick_stop = (cw & (c.CW_ENABLE_VOLTAGE | c.CW_QUICK_STOP_N)) == c.CW_ENABLE_VOLTAGE
        shutdown = (cw & 0x07) == 0x06
        switch_on = (cw & 0x0F) == 0x07
        enable = (cw & 0x0F) == 0x0F
        if s == D.SWITCH_ON_DISABLED:
            if shutdown:
                self.state = D.READY_TO_SWITCH_ON
        elif s == D.READY_TO_SWITCH_ON:
            if disable_voltage or quick_stop:
                self.state = D.SWITCH_ON_DISABLED
            elif switch_on or enable:
                self.state = D.SWITCHED_ON
        elif s == D.SWITCHED_ON:
            if disable_voltage or quick_stop:
                self.state = D.SWITCH_ON_DISABLED
            elif shutdown:
                self.state = D.READY_TO_SWITCH_ON
            elif enable:
                self.state = D.OPERATION_ENABLED
        elif s == D.OPERATION_ENABLED:
            if disable_voltage:
                self.state = D.SWITCH_ON_DISABLED
            elif quick_stop:
                self.state = D.QUICK_STOP_ACTIVE
            elif shutdown:
                self.state = D.READY_TO_SWITCH_ON
            elif switch_on:
                self.state = D.SWITCHED_ON
        elif s == D.QUICK_STOP_ACTIVE:
            if disable_voltage:
                self.state = D.SWITCH_ON_DISABLED
            elif enable and int(self.value(c.QUICK_STOP_OPTION)) in QUICK_STOP_STAY:
                self.state = D.OPERATION_ENABLED
        if self.state != D.OPERATION_ENABLED:
            self.applied_torque_permille = 0
        self._publish_statusword()

    def fault(self, code: int, register: int = c.ErrorRegister.GENERIC, elmo_code: int = 0) -> list[c.Frame]:
        """Enter FAULT REACTION ACTIVE (torque off at once) and send the EMCY."""
        self.state = c.DriveState.FAULT_REACTION_ACTIVE
        self.applied_torque_permille = 0
        self._set(c.ERROR_CODE, code)
        self._set(c.ERROR_REGISTER, int(register) | c.ErrorRegister.GENERIC)
        self._publish_statusword()
        self._count("faults")
        return [c.make_emcy(self.node_id, code, int(register) | c.ErrorRegister.GENERIC, elmo_code)]

    # --- timers ---------------------------------------------------------------------------------

    def poll(self, now: float) -> list[c.Frame]:
        """Heartbeat producer and consumer; frames queued by SDO-triggered events."""
        out = self._queued
        self._queued = []
        if self.muted:
            return []
        if self.state == c.DriveState.FAULT_REACTION_ACTIVE:
            self.state = c.DriveState.FAULT  # the reaction (torque off) is done
            self._publish_statusword()
        producer_ms = int(self.value(c.PRODUCER_HEARTBEAT))
        if producer_ms and now >= self._next_heartbeat_s:
            out.append(c.make_heartbeat(self.node_id, self.nmt))
            self._next_heartbeat_s = now + producer_ms / 1000.0
        timeout_ms = self._consumer_time_ms()
        if timeout_ms and self._consumer_last_s is not None and now - self._consumer_last_s > timeout_ms / 1000.0:
            self._consumer_last_s = None  # one reaction per loss
            self._count("heartbeat_lost")
            out += self._on_connection_lost()
        return out

    def _on_connection_lost(self) -> list[c.Frame]:
        option = int(self.value(c.ABORT_CONNECTION_OPTION))
        register = c.ErrorRegister.COMMUNICATION
        if option == 1 or self.state == c.DriveState.OPERATION_ENABLED and option not in (2, 3):
            return self.fault(0x8130, register)
        if option == 2:
            self.state = c.DriveState.SWITCH_ON_DISABLED
        elif option == 3 and self.state == c.DriveState.OPERATION_ENABLED:
            self.state = c.DriveState.QUICK_STOP_ACTIVE
        self.applied_torque_permille = 0
        self._publish_statusword()
        return [c.make_emcy(self.node_id, 0x8130, int(register) | c.ErrorRegister.GENERIC)]

    def _consumer_node(self) -> int:
        return (int(self.value(c.CONSUMER_HEARTBEAT, 1)) >> 16) & 0x7F

    def _consumer_time_ms(self) -> int:
        return int(self.value(c.CONSUMER_HEARTBEAT, 1)) & 0xFFFF

    def next_timer(self) -> float:
        producer_ms = int(self.value(c.PRODUCER_HEARTBEAT))
        return self._next_heartbeat_s if producer_ms else float("inf")

    @property
    def applied_torque(self) -> float:
        """Torque the motor gets now [N m at the motor shaft]."""
        return self.applied_torque_permille / c.PERMILLE * int(self.value(c.RATED_TORQUE)) / 1000.0


def _wrap_i32(value: int) -> int:
    return (value + 0x80000000) % 0x100000000 - 0x80000000


class DriveBusEmulator:
    """Several drives behind one bus: the bus-side logic, independent of how frames travel.

    :meth:`handle` takes one frame from the bus and returns what the drives answer;
    :meth:`service` runs the timers (heartbeats, consumer timeouts) and queued fault
    injections. Both are thread-safe. Error frames in the output carry
    :data:`ERROR_FLAG` in their identifier (with the SocketCAN error class below it).
    Runners move the frames: :class:`VirtualBusRunner` on a python-can bus (tests), the
    socketcand server of ``archer emulate drives`` over TCP.
    """

    def __init__(self, drives: Sequence[EmulatedDrive], host_node_id: int = 127) -> None:
        self.drives = list(drives)
        self._by_id = {d.node_id: d for d in self.drives}
        self.host_node_id = host_node_id
        self._lock = threading.Lock()
        self._actions: queue.SimpleQueue[Callable[[float], list[c.Frame]]] = queue.SimpleQueue()
        self._ignore_host_until = 0.0
        self.frames_in = 0
        self.frames_out = 0
        self.frames_ignored = 0
        self.syncs = 0
        self.on_sync: Callable[[float], None] | None = None  # the twin hook: exchange with the plant

    def drive(self, node_id: int) -> EmulatedDrive:
        return self._by_id[node_id]

    def boot(self, now: float) -> list[c.Frame]:
        with self._lock:
            out: list[c.Frame] = []
            for d in self.drives:
                out += d.boot(now)
            self.frames_out += len(out)
            return out

    def handle(self, frame: c.Frame, now: float) -> list[c.Frame]:
        """The drives' answer to one frame seen on the bus."""
        with self._lock:
            self.frames_in += 1
            if now < self._ignore_host_until:
                self.frames_ignored += 1
                return []
            if frame.can_id == c.SYNC_ID:
                self.syncs += 1
                if self.on_sync is not None:
                    self.on_sync(now)
            base, node = c.split_id(frame.can_id)
            out: list[c.Frame] = []
            if frame.can_id in (c.NMT_ID, c.SYNC_ID) or base == c.HEARTBEAT_BASE:
                for d in self.drives:
                    out += d.receive(frame, now)
            else:
                drive = self._by_id.get(node)
                if drive is not None:
                    out = drive.receive(frame, now)
            self.frames_out += len(out)
            return out

    def service(self, now: float) -> list[c.Frame]:
        """Timers and queued fault injections."""
        with self._lock:
            out: list[c.Frame] = []
            while True:
                try:
                    action = self._actions.get_nowait()
                except queue.Empty:
                    break
                out += action(now)
            for d in self.drives:
                out += d.poll(now)
            self.frames_out += len(out)
            return out

    def summary(self) -> dict[str, object]:
        """Counters of the bus and of every drive."""
        with self._lock:
            return {
                "frames_in": self.frames_in,
                "frames_out": self.frames_out,
                "frames_ignored": self.frames_ignored,
                "syncs": self.syncs,
                "drives": {str(d.node_id): dict(d.counters) for d in self.drives},
            }

    def next_wake(self, now: float) -> float:
        return min((d.next_timer() for d in self.drives), default=now + SERVICE_PERIOD_S)

    # --- fault injection (any thread; runs at the next service()) ---------------------------

    def inject(self, action: Callable[[float], list[c.Frame]]) -> None:
        self._actions.put(action)

    def emcy_fault(self, node_id: int, code: int, register: int = c.ErrorRegister.GENERIC, elmo_code: int = 0) -> None:
        self.inject(lambda now: self._by_id[node_id].fault(code, register, elmo_code))

    def _set_drive(self, node_id: int, **changes: object) -> None:
        def act(now: float) -> list[c.Frame]:
            drive = self._by_id[node_id]
            for name, value in changes.items():
                setattr(drive, name, value)
            return []

        self.inject(act)

    def kill(self, node_id: int) -> None:
        """The drive dies: no heartbeat, no PDO, no answer."""
        self._set_drive(node_id, muted=True)

    def drop_feedback(self, node_id: int, count: int) -> None:
        """The next ``count`` TPDO1 frames of the drive are lost."""
        self._set_drive(node_id, drop_tpdo=count)

    def corrupt_feedback(self, node_id: int, count: int) -> None:
        """The next ``count`` TPDO1 frames go out one byte short."""
        self._set_drive(node_id, corrupt_tpdo=count)

    def error_frame(self, error_class: int) -> None:
        self.inject(lambda now: [c.Frame(ERROR_FLAG | error_class, bytes(8))])

    def bus_off(self, duration_s: float) -> None:
        """The host's controller goes bus-off: it is told so, and for ``duration_s`` its frames never arrive."""

        def act(now: float) -> list[c.Frame]:
            self._ignore_host_until = now + duration_s
            return [c.Frame(ERROR_FLAG | CAN_ERR_BUSOFF, bytes(8))]

        self.inject(act)


def to_message(frame: c.Frame) -> can.Message:
    if frame.can_id & ERROR_FLAG:
        return make_error_frame(frame.can_id & ~ERROR_FLAG)
    return can.Message(arbitration_id=frame.can_id, data=frame.data, is_extended_id=False)


class VirtualBusRunner:
    """Runs a :class:`DriveBusEmulator` on a python-can bus, on its own thread."""

    def __init__(self, emulator: DriveBusEmulator, bus: can.BusABC) -> None:
        self.emulator = emulator
        self.bus = bus
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="drive-emulator", daemon=True)

    def start(self) -> VirtualBusRunner:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(2.0)

    def __enter__(self) -> VirtualBusRunner:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _send(self, frames: list[c.Frame]) -> None:
        for f in frames:
            try:
                self.bus.send(to_message(f))
            except can.CanError as exc:
                log.warning("emulator send failed", extra={"fields": {"error": str(exc)}})

    def _run(self) -> None:
        emu = self.emulator
        try:
            self._send(emu.boot(time.monotonic()))
            while not self._stop.is_set():
                now = time.monotonic()
                self._send(emu.service(now))
                timeout = min(SERVICE_PERIOD_S, max(0.0, emu.next_wake(now) - now))
                msg = self.bus.recv(timeout)
                while msg is not None:
                    if not msg.is_error_frame and not msg.is_extended_id and not msg.is_remote_frame:
                        self._send(emu.handle(c.Frame(msg.arbitration_id, bytes(msg.data)), time.monotonic()))
                    msg = self.bus.recv(0.0)
        except BaseException as exc:  # surfaced to the owner through .error
            self.error = exc
            log.exception("drive emulator crashed")


def make_emulator(params: HardwareParams, motors: Sequence[MotorModel] | None = None) -> DriveBusEmulator:
    """Emulated drives for every node of ``params``, set up as the real robot's."""
    drives = []
    for i, node_id in enumerate(params.node_ids):
        motor = motors[i] if motors is not None else None
        drives.append(EmulatedDrive(node_id, drive_config(params, i, serial_number=i + 1), motor))
    return DriveBusEmulator(drives, params.host_node_id)


class SocketcandRunner:
    """Serves a :class:`DriveBusEmulator` as a socketcand bus on 127.0.0.1 (``archer emulate drives``).

    Requests are answered on the connection's own thread; a timer thread runs the
    heartbeats, consumer timeouts and fault injections every ``SERVICE_PERIOD_S``.
    """

    def __init__(self, emulator: DriveBusEmulator, channel: str = "can0", port: int = 0) -> None:
        from drivers.socketcand import SocketcandServer  # the emulator core does not need TCP

        self.emulator = emulator
        self.server = SocketcandServer(emulator.handle, channel, port)
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="drive-emulator-timers", daemon=True)

    def bus_kwargs(self) -> dict[str, object]:
        return self.server.bus_kwargs()

    def start(self) -> SocketcandRunner:
        self.server.start()
        self.server.broadcast(self.emulator.boot(time.monotonic()))
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(2.0)
        self.server.stop()

    def __enter__(self) -> SocketcandRunner:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _run(self) -> None:
        try:
            while not self._stop.wait(SERVICE_PERIOD_S):
                self.server.broadcast(self.emulator.service(time.monotonic()))
        except BaseException as exc:  # surfaced to the owner through .error
            self.error = exc
            log.exception("drive emulator timers crashed")
