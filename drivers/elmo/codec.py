"""CANopen (CiA 301) and CiA 402 frames: build and parse, nothing else.

The frame layer of the ELMO driver: pure functions that turn requests into
``Frame(can_id, data)`` and received frames into values. No bus, no clock, no
threads; the transport (:mod:`drivers.elmo.transport`) moves the frames and the
device layer (:mod:`drivers.elmo.device`) decides what to send. ``make_*`` builds a
frame without sending it.

Byte order on CANopen is little-endian throughout. The predefined connection set
assigns the identifiers: NMT 0x000, SYNC 0x080, EMCY 0x080+node, TPDO1..4
0x180/0x280/0x380/0x480+node, RPDO1..4 0x200/0x300/0x400/0x500+node, SDO
server->client 0x580+node, client->server 0x600+node, heartbeat 0x700+node.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum
from typing import NamedTuple


class Frame(NamedTuple):
    can_id: int  # 11-bit identifier
    data: bytes


# --- identifiers ---------------------------------------------------------------------

NMT_ID = 0x000
SYNC_ID = 0x080
EMCY_BASE = 0x080
TPDO_BASE = (0x180, 0x280, 0x380, 0x480)
RPDO_BASE = (0x200, 0x300, 0x400, 0x500)
SDO_TX_BASE = 0x580  # server -> client
SDO_RX_BASE = 0x600  # client -> server
HEARTBEAT_BASE = 0x700
NODE_ID_MAX = 127


def check_node_id(node_id: int) -> int:
    if not 1 <= node_id <= NODE_ID_MAX:
        raise ValueError(f"CANopen node id {node_id} outside 1..{NODE_ID_MAX}")
    return node_id


def split_id(can_id: int) -> tuple[int, int]:
    """(function code base, node id) of a predefined-connection-set identifier."""
    return can_id & 0x780, can_id & 0x7F


# --- NMT ---------------------------------------------------------------------------------


class NmtCommand(IntEnum):
    START = 0x01
    STOP = 0x02
    ENTER_PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


class NmtState(IntEnum):
    """The state byte of a heartbeat frame."""

    BOOTUP = 0x00
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


def make_nmt(command: NmtCommand, node_id: int = 0) -> Frame:
    """NMT command to ``node_id`` (0: every node)."""
    return Frame(NMT_ID, bytes((int(command), node_id)))


def parse_nmt(data: bytes) -> tuple[NmtCommand, int]:
    if len(data) != 2:
        raise ValueError(f"NMT frame of {len(data)} bytes")
    return NmtCommand(data[0]), data[1]


def make_sync() -> Frame:
    return Frame(SYNC_ID, b"")


def make_heartbeat(node_id: int, state: NmtState) -> Frame:
    return Frame(HEARTBEAT_BASE + node_id, bytes((int(state),)))


def parse_heartbeat(data: bytes) -> NmtState:
    if len(data) != 1:
        raise ValueError(f"heartbeat of {len(data)} bytes")
    return NmtState(data[0] & 0x7F)  # bit 7 is the node-guarding toggle


# --- SDO -----------------------------------------------------------------------------------
# Command byte layouts (CiA 301 7.2.4.3). ccs = client command specifier, scs = server.

CCS_DOWNLOAD_SEGMENT = 0
CCS_INITIATE_DOWNLOAD = 1
CCS_INITIATE_UPLOAD = 2
CCS_UPLOAD_SEGMENT = 3
SCS_UPLOAD_SEGMENT = 0
SCS_DOWNLOAD_SEGMENT = 1
SCS_INITIATE_UPLOAD = 2
SCS_INITIATE_DOWNLOAD = 3
CS_ABORT = 4
SEGMENT_BYTES = 7
EXPEDITED_MAX = 4


class SdoAbort(IntEnum):
    TOGGLE_BIT = 0x05030000
    TIMEOUT = 0x05040000
    INVALID_COMMAND = 0x05040001
    UNSUPPORTED_ACCESS = 0x06010000
    WRITE_ONLY = 0x06010001
    READ_ONLY = 0x06010002
    NO_OBJECT = 0x06020000
    NOT_MAPPABLE = 0x06040041
    PDO_TOO_LONG = 0x06040042
    LENGTH_MISMATCH = 0x06070010
    TOO_LONG = 0x06070012
    TOO_SHORT = 0x06070013
    NO_SUBINDEX = 0x06090011
    VALUE_RANGE = 0x06090030
    VALUE_TOO_HIGH = 0x06090031
    VALUE_TOO_LOW = 0x06090032
    GENERAL = 0x08000000
    CANNOT_STORE = 0x08000020
    LOCAL_CONTROL = 0x08000021
    DEVICE_STATE = 0x08000022


SDO_ABORT_TEXT = {
    SdoAbort.TOGGLE_BIT: "toggle bit not alternated",
    SdoAbort.TIMEOUT: "SDO protocol timed out",
    SdoAbort.INVALID_COMMAND: "client/server command specifier not valid",
    SdoAbort.UNSUPPORTED_ACCESS: "unsupported access to an object",
    SdoAbort.WRITE_ONLY: "attempt to read a write-only object",
    SdoAbort.READ_ONLY: "attempt to write a read-only object",
    SdoAbort.NO_OBJECT: "object does not exist in the object dictionary",
    SdoAbort.NOT_MAPPABLE: "object cannot be mapped to the PDO",
    SdoAbort.PDO_TOO_LONG: "mapped objects exceed the PDO length",
    SdoAbort.LENGTH_MISMATCH: "data type does not match, length of service parameter does not match",
    SdoAbort.TOO_LONG: "data type does not match, length too high",
    SdoAbort.TOO_SHORT: "data type does not match, length too low",
    SdoAbort.NO_SUBINDEX: "sub-index does not exist",
    SdoAbort.VALUE_RANGE: "value range of parameter exceeded",
    SdoAbort.VALUE_TOO_HIGH: "value of parameter written too high",
    SdoAbort.VALUE_TOO_LOW: "value of parameter written too low",
    SdoAbort.GENERAL: "general error",
    SdoAbort.CANNOT_STORE: "data cannot be transferred or stored",
    SdoAbort.LOCAL_CONTROL: "data cannot be transferred because of local control",
    SdoAbort.DEVICE_STATE: "data cannot be transferred in the present device state",
}


def abort_text(code: int) -> str:
    try:
        return SDO_ABORT_TEXT[SdoAbort(code)]
    except ValueError:
        return "unknown abort code"


def _mux(index: int, subindex: int) -> bytes:
    return struct.pack("<HB", index, subindex)


def make_sdo_upload_request(node_id: int, index: int, subindex: int) -> Frame:
    """Client: initiate upload (read) of ``index:subindex``."""
    return Frame(SDO_RX_BASE + node_id, bytes((CCS_INITIATE_UPLOAD << 5,)) + _mux(index, subindex) + bytes(4))


def make_sdo_upload_segment_request(node_id: int, toggle: int) -> Frame:
    return Frame(SDO_RX_BASE + node_id, bytes(((CCS_UPLOAD_SEGMENT << 5) | (toggle << 4),)) + bytes(7))


def make_sdo_download_request(node_id: int, index: int, subindex: int, data: bytes) -> Frame:
    """Client: initiate download (write). Expedited up to 4 bytes, else segmented with size."""
    if len(data) <= EXPEDITED_MAX:
        n_unused = EXPEDITED_MAX - len(data)
        cmd = (CCS_INITIATE_DOWNLOAD << 5) | (n_unused << 2) | 0b11  # expedited, size indicated
        return Frame(SDO_RX_BASE + node_id, bytes((cmd,)) + _mux(index, subindex) + data + bytes(n_unused))
    cmd = (CCS_INITIATE_DOWNLOAD << 5) | 0b01  # segmented, size indicated
    return Frame(SDO_RX_BASE + node_id, bytes((cmd,)) + _mux(index, subindex) + struct.pack("<I", len(data)))


def make_sdo_download_segment(node_id: int, toggle: int, chunk: bytes, last: bool) -> Frame:
    if len(chunk) > SEGMENT_BYTES:
        raise ValueError("an SDO segment carries at most 7 bytes")
    n_unused = SEGMENT_BYTES - len(chunk)
    cmd = (CCS_DOWNLOAD_SEGMENT << 5) | (toggle << 4) | (n_unused << 1) | int(last)
    return Frame(SDO_RX_BASE + node_id, bytes((cmd,)) + chunk + bytes(n_unused))


def make_sdo_abort(cob_id: int, index: int, subindex: int, code: int) -> Frame:
    """Abort, from either side (``cob_id`` is 0x600+node from a client, 0x580+node from a server)."""
    return Frame(cob_id, bytes((CS_ABORT << 5,)) + _mux(index, subindex) + struct.pack("<I", code))


# server side (used by the emulator)


def make_sdo_initiate_download_response(node_id: int, index: int, subindex: int) -> Frame:
    return Frame(SDO_TX_BASE + node_id, bytes((SCS_INITIATE_DOWNLOAD << 5,)) + _mux(index, subindex) + bytes(4))


def make_sdo_download_segment_response(node_id: int, toggle: int) -> Frame:
    return Frame(SDO_TX_BASE + node_id, bytes(((SCS_DOWNLOAD_SEGMENT << 5) | (toggle << 4),)) + bytes(7))


def make_sdo_upload_response(node_id: int, index: int, subindex: int, data: bytes) -> Frame:
    """Server: initiate upload response; expedited when ``data`` fits in 4 bytes."""
    if len(data) <= EXPEDITED_MAX:
        n_unused = EXPEDITED_MAX - len(data)
        cmd = (SCS_INITIATE_UPLOAD << 5) | (n_unused << 2) | 0b11
        return Frame(SDO_TX_BASE + node_id, bytes((cmd,)) + _mux(index, subindex) + data + bytes(n_unused))
    cmd = (SCS_INITIATE_UPLOAD << 5) | 0b01
    return Frame(SDO_TX_BASE + node_id, bytes((cmd,)) + _mux(index, subindex) + struct.pack("<I", len(data)))


def make_sdo_upload_segment(node_id: int, toggle: int, chunk: bytes, last: bool) -> Frame:
    n_unused = SEGMENT_BYTES - len(chunk)
    cmd = (SCS_UPLOAD_SEGMENT << 5) | (toggle << 4) | (n_unused << 1) | int(last)
    return Frame(SDO_TX_BASE + node_id, bytes((cmd,)) + chunk + bytes(n_unused))


@dataclass(frozen=True)
class SdoMessage:
    """A parsed SDO frame, from either direction.

    ``cs`` is the command specifier (ccs or scs by direction; 4 = abort), ``toggle``
    the segment toggle, ``payload`` the data carried (expedited data, a segment's
    bytes), ``size`` the announced size of a segmented transfer (or None),
    ``last`` the no-more-segments flag, ``abort_code`` set for aborts.
    """

    cs: int
    index: int
    subindex: int
    toggle: int
    payload: bytes
    size: int | None
    expedited: bool
    last: bool
    abort_code: int


def parse_sdo(data: bytes, client_to_server: bool) -> SdoMessage:
    """Parse an SDO frame; segment frames carry no index (returned as -1)."""
    if len(data) != 8:
        raise ValueError(f"SDO frame of {len(data)} bytes, expected 8")
    cmd = data[0]
    cs = cmd >> 5
    if cs == CS_ABORT:
        index, subindex = struct.unpack_from("<HB", data, 1)
        return SdoMessage(cs, index, subindex, 0, b"", None, False, True, struct.unpack_from("<I", data, 4)[0])
    segment_cs = CCS_DOWNLOAD_SEGMENT if client_to_server else SCS_UPLOAD_SEGMENT
    initiate_with_data = CCS_INITIATE_DOWNLOAD if client_to_server else SCS_INITIATE_UPLOAD
    if cs == segment_cs:
        n_unused = (cmd >> 1) & 0x7
        return SdoMessage(cs, -1, -1, (cmd >> 4) & 1, bytes(data[1 : 8 - n_unused]), None, False, bool(cmd & 1), 0)
    index, subindex = struct.unpack_from("<HB", data, 1)
    if cs == initiate_with_data:
        expedited = bool(cmd & 0b10)
        size_indicated = bool(cmd & 0b01)
        if expedited:
            n = EXPEDITED_MAX - ((cmd >> 2) & 0x3) if size_indicated else EXPEDITED_MAX
            return SdoMessage(cs, index, subindex, 0, bytes(data[4 : 4 + n]), n, True, True, 0)
        size = struct.unpack_from("<I", data, 4)[0] if size_indicated else None
        return SdoMessage(cs, index, subindex, 0, b"", size, False, False, 0)
    toggle = (cmd >> 4) & 1
    return SdoMessage(cs, index, subindex, toggle, b"", None, False, False, 0)


# --- EMCY -------------------------------------------------------------------------------------


class ErrorRegister(IntEnum):
    """Bits of object 0x1001, repeated in byte 2 of every EMCY."""

    GENERIC = 0x01
    CURRENT = 0x02
    VOLTAGE = 0x04
    TEMPERATURE = 0x08
    COMMUNICATION = 0x10
    PROFILE = 0x20
    MANUFACTURER = 0x80


EMCY_NO_ERROR = 0x0000
EMCY_MANUFACTURER = 0xFF00  # ELMO: the reason is the ELMO error code in byte 3

# EMCY error codes an ELMO Gold drive sends (CiA 301 / 402 codes as the ELMO
# CANopen implementation guide uses them).
EMCY_CODES: dict[int, str] = {
    0x0000: "error reset or no error",
    0x1000: "generic error",
    0x2340: "short circuit: motor or its wiring may be defective",
    0x3120: "under-voltage: power supply shut down or its impedance too high",
    0x3310: "over-voltage: power supply voltage too high or regeneration not absorbed",
    0x4310: "temperature: drive overheating",
    0x5441: "drive disabled by the inhibit input",
    0x6180: "fatal CPU error: stack overflow",
    0x6200: "user program aborted by an error",
    0x7121: "motor stuck: commanded current but no motion",
    0x7300: "feedback loss: no match between encoder and Hall position",
    0x8110: "CAN message lost (corrupted or overrun)",
    0x8120: "CAN controller in error-passive mode",
    0x8130: "heartbeat or life-guard event: the host stopped",
    0x8140: "recovered from bus off",
    0x8210: "PDO not processed: length error",
    0x8220: "PDO length exceeded",
    0x8311: "peak current exceeded",
    0x8480: "speed tracking error",
    0x8481: "speed limit exceeded",
    0x8611: "position tracking error",
    0x8680: "position limit exceeded",
    0xFF00: "manufacturer-specific (see the ELMO error code)",
}

# Byte 3 of an ELMO EMCY with error code 0xFF00 (motion-queue and CAN events).
ELMO_ERROR_CODES: dict[int, str] = {
    0x07: "cannot initialise motion: bad setup data",
    0x08: "mode terminated, motor stopped automatically",
    0x09: "a CAN message has been lost",
    0x34: "motion queue full",
    0x56: "motion queue low",
    0x5B: "write pointer out of range",
    0x5C: "PDO 0x3xx not mapped",
    0xA6: "position beyond modulo",
}


@dataclass(frozen=True)
class Emergency:
    node_id: int
    code: int  # EMCY error code (0x0000 = error reset)
    register: int  # error register 0x1001
    elmo_code: int  # ELMO error code (byte 3)
    field1: int  # ELMO data field 1 (bytes 4-5)
    field2: int  # ELMO data field 2 (bytes 6-7)

    @property
    def is_reset(self) -> bool:
        return self.code == EMCY_NO_ERROR

    def describe(self) -> str:
        text = EMCY_CODES.get(self.code)
        if text is None:
            text = EMCY_CODES.get(self.code & 0xFF00, "unknown error code")
        if self.code == EMCY_MANUFACTURER:
            text = ELMO_ERROR_CODES.get(self.elmo_code, f"ELMO error 0x{self.elmo_code:02X}")
        return f"node {self.node_id} EMCY 0x{self.code:04X}: {text}"


def make_emcy(node_id: int, code: int, register: int, elmo_code: int = 0, field1: int = 0, field2: int = 0) -> Frame:
    return Frame(EMCY_BASE + node_id, struct.pack("<HBBHH", code, register, elmo_code, field1, field2))


def parse_emcy(node_id: int, data: bytes) -> Emergency:
    if len(data) != 8:
        raise ValueError(f"EMCY of {len(data)} bytes, expected 8")
    code, register, elmo_code, field1, field2 = struct.unpack("<HBBHH", data)
    return Emergency(node_id, code, register, elmo_code, field1, field2)


# --- CiA 402 ------------------------------------------------------------------------------------

# objects
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
QUICK_STOP_OPTION = 0x605A
MODES_OF_OPERATION = 0x6060
MODES_DISPLAY = 0x6061
POSITION_ACTUAL = 0x6064
VELOCITY_ACTUAL = 0x606C
TARGET_TORQUE = 0x6071
MAX_TORQUE = 0x6072
MAX_CURRENT = 0x6073
RATED_CURRENT = 0x6075
RATED_TORQUE = 0x6076
TORQUE_ACTUAL = 0x6077
CURRENT_ACTUAL = 0x6078
ENCODER_RESOLUTION = 0x608F
INTERPOLATION_PERIOD = 0x60C2
SUPPORTED_MODES = 0x6502
ERROR_CODE = 0x603F
ABORT_CONNECTION_OPTION = 0x6007

MODE_CST = 10  # cyclic synchronous torque
SUPPORTED_CST_BIT = 1 << 9

# CiA 301 communication objects
DEVICE_TYPE = 0x1000
ERROR_REGISTER = 0x1001
COB_ID_SYNC = 0x1005
CYCLE_PERIOD = 0x1006
DEVICE_NAME = 0x1008
HW_VERSION = 0x1009
SW_VERSION = 0x100A
COB_ID_EMCY = 0x1014
CONSUMER_HEARTBEAT = 0x1016
PRODUCER_HEARTBEAT = 0x1017
IDENTITY = 0x1018
RPDO_COMM = 0x1400
RPDO_MAP = 0x1600
TPDO_COMM = 0x1800
TPDO_MAP = 0x1A00
PDO_COB_INVALID = 1 << 31  # bit 31 of a PDO COB-ID: PDO does not exist / disabled
TRANSMISSION_SYNC = 1  # PDO transmission type: on every SYNC

ELMO_VENDOR_ID = 0x0000009A
DEVICE_TYPE_SERVO = 0x00020192  # CiA 402, servo drive


class Controlword(IntEnum):
    """Commands of the CiA 402 state machine (bits 0-3 and 7)."""

    DISABLE_VOLTAGE = 0x0000
    QUICK_STOP = 0x0002
    SHUTDOWN = 0x0006
    SWITCH_ON = 0x0007  # also "disable operation" from OPERATION ENABLED
    ENABLE_OPERATION = 0x000F
    FAULT_RESET = 0x0080


CW_SWITCH_ON = 0x01
CW_ENABLE_VOLTAGE = 0x02
CW_QUICK_STOP_N = 0x04  # active low
CW_ENABLE_OPERATION = 0x08
CW_FAULT_RESET = 0x80
CW_HALT = 0x100

SW_READY_TO_SWITCH_ON = 0x0001
SW_SWITCHED_ON = 0x0002
SW_OPERATION_ENABLED = 0x0004
SW_FAULT = 0x0008
SW_VOLTAGE_ENABLED = 0x0010
SW_QUICK_STOP_N = 0x0020  # active low: 0 while a quick stop is active
SW_SWITCH_ON_DISABLED = 0x0040
SW_WARNING = 0x0080
SW_REMOTE = 0x0200
SW_TARGET_REACHED = 0x0400
SW_FOLLOWS_COMMAND = 0x1000  # cyclic modes: the drive follows the command value


class DriveState(IntEnum):
    NOT_READY_TO_SWITCH_ON = 0
    SWITCH_ON_DISABLED = 1
    READY_TO_SWITCH_ON = 2
    SWITCHED_ON = 3
    OPERATION_ENABLED = 4
    QUICK_STOP_ACTIVE = 5
    FAULT_REACTION_ACTIVE = 6
    FAULT = 7


# (mask, value) pairs of CiA 402 table 30
_STATE_PATTERNS = (
    (0x4F, 0x00, DriveState.NOT_READY_TO_SWITCH_ON),
    (0x4F, 0x40, DriveState.SWITCH_ON_DISABLED),
    (0x6F, 0x21, DriveState.READY_TO_SWITCH_ON),
    (0x6F, 0x23, DriveState.SWITCHED_ON),
    (0x6F, 0x27, DriveState.OPERATION_ENABLED),
    (0x6F, 0x07, DriveState.QUICK_STOP_ACTIVE),
    (0x4F, 0x0F, DriveState.FAULT_REACTION_ACTIVE),
    (0x4F, 0x08, DriveState.FAULT),
)

STATUSWORD_OF_STATE = {
    DriveState.NOT_READY_TO_SWITCH_ON: 0x0000,
    DriveState.SWITCH_ON_DISABLED: 0x0040,
    DriveState.READY_TO_SWITCH_ON: 0x0021,
    DriveState.SWITCHED_ON: 0x0023,
    DriveState.OPERATION_ENABLED: 0x0027,
    DriveState.QUICK_STOP_ACTIVE: 0x0007,
    DriveState.FAULT_REACTION_ACTIVE: 0x000F,
    DriveState.FAULT: 0x0008,
}


def state_of(statusword: int) -> DriveState | None:
    """The CiA 402 state a statusword shows, or None for a pattern outside the table."""
    for mask, value, state in _STATE_PATTERNS:
        if statusword & mask == value:
            return state
    return None


def next_command(state: DriveState, target: DriveState) -> Controlword | None:
    """The controlword that moves ``state`` one step towards ``target``.

    ``target`` is OPERATION_ENABLED (enable), QUICK_STOP_ACTIVE (quick stop: from
    OPERATION ENABLED the drive stops in QUICK STOP ACTIVE, from the other states a
    quick stop command leads to SWITCH ON DISABLED), SWITCH_ON_DISABLED (disable),
    READY_TO_SWITCH_ON or SWITCHED_ON. None when already there or when the drive must
    move by itself (NOT READY, FAULT REACTION ACTIVE).
    """
    if state == target:
        return None
    if state == DriveState.FAULT:
        return Controlword.FAULT_RESET
    if state in (DriveState.NOT_READY_TO_SWITCH_ON, DriveState.FAULT_REACTION_ACTIVE):
        return None
    if target == DriveState.QUICK_STOP_ACTIVE:
        return Controlword.QUICK_STOP if state != DriveState.SWITCH_ON_DISABLED else None
    if target == DriveState.SWITCH_ON_DISABLED:
        return Controlword.DISABLE_VOLTAGE
    if state == DriveState.QUICK_STOP_ACTIVE:
        return Controlword.DISABLE_VOLTAGE
    order = (DriveState.SWITCH_ON_DISABLED, DriveState.READY_TO_SWITCH_ON, DriveState.SWITCHED_ON, DriveState.OPERATION_ENABLED)
    step = {
        DriveState.READY_TO_SWITCH_ON: Controlword.SHUTDOWN,
        DriveState.SWITCHED_ON: Controlword.SWITCH_ON,
        DriveState.OPERATION_ENABLED: Controlword.ENABLE_OPERATION,
    }
    here, there = order.index(state), order.index(target)
    if there > here:
        return step[order[here + 1]]
    return step[target] if target != DriveState.SWITCH_ON_DISABLED else Controlword.DISABLE_VOLTAGE


# --- PDO payloads -------------------------------------------------------------------------------


def pdo_mapping_entry(index: int, subindex: int, bits: int) -> int:
    """Value of a PDO mapping sub-entry (0x1600/0x1A00 sub 1..8)."""
    return (index << 16) | (subindex << 8) | bits


def split_mapping_entry(value: int) -> tuple[int, int, int]:
    return value >> 16, (value >> 8) & 0xFF, value & 0xFF


# The driver's fixed mapping (configured over SDO at start-up, see device.py):
# RPDO1 = controlword u16, target torque i16 (per mille of rated torque)
# TPDO1 = statusword u16, torque actual i16 (per mille), velocity actual i32 [counts/s]
# TPDO2 = position actual i32 [counts] (every ``position_every`` SYNCs)
RPDO1_STRUCT = struct.Struct("<Hh")
TPDO1_STRUCT = struct.Struct("<Hhi")
TPDO2_STRUCT = struct.Struct("<i")

RPDO1_MAPPING = (pdo_mapping_entry(CONTROLWORD, 0, 16), pdo_mapping_entry(TARGET_TORQUE, 0, 16))
TPDO1_MAPPING = (
    pdo_mapping_entry(STATUSWORD, 0, 16),
    pdo_mapping_entry(TORQUE_ACTUAL, 0, 16),
    pdo_mapping_entry(VELOCITY_ACTUAL, 0, 32),
)
TPDO2_MAPPING = (pdo_mapping_entry(POSITION_ACTUAL, 0, 32),)

PERMILLE = 1000.0
I16_MAX = 0x7FFF


def make_rpdo1(node_id: int, controlword: int, target_torque_permille: int) -> Frame:
    """RPDO1: controlword and target torque [per mille of rated torque]."""
    tq = max(-I16_MAX, min(I16_MAX, target_torque_permille))
    return Frame(RPDO_BASE[0] + node_id, RPDO1_STRUCT.pack(controlword, tq))


def parse_tpdo1(data: bytes) -> tuple[int, int, int]:
    """TPDO1 -> (statusword, torque actual [per mille], velocity [counts/s])."""
    if len(data) != TPDO1_STRUCT.size:
        raise ValueError(f"TPDO1 of {len(data)} bytes, expected {TPDO1_STRUCT.size}")
    return TPDO1_STRUCT.unpack(data)


def parse_tpdo2(data: bytes) -> int:
    """TPDO2 -> position actual [counts]."""
    if len(data) != TPDO2_STRUCT.size:
        raise ValueError(f"TPDO2 of {len(data)} bytes, expected {TPDO2_STRUCT.size}")
    return TPDO2_STRUCT.unpack(data)[0]
