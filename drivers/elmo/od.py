"""Object dictionary of the emulated ELMO drive, and its EDS export.

The emulator serves these objects over SDO and maps them into PDOs; :func:`to_eds`
writes the same dictionary as an Electronic Data Sheet (CiA 306), the file any
CANopen master (the ``canopen`` package included) loads to talk to the drive.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from enum import IntEnum

from drivers.elmo import codec as c


class DataType(IntEnum):
    BOOLEAN = 0x01
    INTEGER8 = 0x02
    INTEGER16 = 0x03
    INTEGER32 = 0x04
    UNSIGNED8 = 0x05
    UNSIGNED16 = 0x06
    UNSIGNED32 = 0x07
    VISIBLE_STRING = 0x09


_FORMATS = {
    DataType.BOOLEAN: struct.Struct("<?"),
    DataType.INTEGER8: struct.Struct("<b"),
    DataType.INTEGER16: struct.Struct("<h"),
    DataType.INTEGER32: struct.Struct("<i"),
    DataType.UNSIGNED8: struct.Struct("<B"),
    DataType.UNSIGNED16: struct.Struct("<H"),
    DataType.UNSIGNED32: struct.Struct("<I"),
}


def bit_length(dtype: DataType) -> int:
    return 8 * _FORMATS[dtype].size


def encode_value(dtype: DataType, value: int | str) -> bytes:
    if dtype == DataType.VISIBLE_STRING:
        return str(value).encode("ascii")
    return _FORMATS[dtype].pack(value)


def decode_value(dtype: DataType, data: bytes) -> int | str:
    """Decode ``data``; raises ValueError when its length does not fit the type."""
    if dtype == DataType.VISIBLE_STRING:
        return bytes(data).decode("ascii", errors="replace")
    fmt = _FORMATS[dtype]
    if len(data) != fmt.size:
        raise ValueError(f"{len(data)} bytes for a {dtype.name}")
    return fmt.unpack(data)[0]


@dataclass
class Entry:
    """One sub-index: its type, access (``ro``, ``rw``, ``wo``, ``const``) and value."""

    name: str
    dtype: DataType
    access: str
    value: int | str
    pdo_mappable: bool = False

    @property
    def readable(self) -> bool:
        return self.access != "wo"

    @property
    def writable(self) -> bool:
        return self.access in ("rw", "wo")


@dataclass
class Obj:
    """An object: a VAR (one entry at sub-index 0) or a RECORD (sub 0 = count)."""

    index: int
    name: str
    subs: dict[int, Entry] = field(default_factory=dict)
    record: bool = False


@dataclass(frozen=True)
class DriveConfig:
    """What the drive is set up with (the real robot's settings by default)."""

    rated_current_ma: int = 12000  # 0x6075
    rated_torque_mnm: int = 996  # 0x6076 = rated current x 0.083 N m/A
    max_current_permille: int = 1000  # 0x6073: the 12 A clamp
    max_torque_permille: int = 1000  # 0x6072
    counts_per_rev: int = 16384  # 0x608F: encoder increments per motor revolution
    device_name: str = "ELMO Gold Solo Twitter (emulated)"
    sw_version: str = "archer-emulator 1.0"
    serial_number: int = 1


def _var(index: int, name: str, dtype: DataType, access: str, value: int | str, pdo: bool = False) -> Obj:
    return Obj(index, name, {0: Entry(name, dtype, access, value, pdo)})


def _record(index: int, name: str, entries: list[Entry]) -> Obj:
    subs = {0: Entry("Highest sub-index supported", DataType.UNSIGNED8, "ro", len(entries))}
    for i, e in enumerate(entries, start=1):
        subs[i] = e
    return Obj(index, name, subs, record=True)


def _pdo_comm(index: int, name: str, cob_id: int) -> Obj:
    return _record(
        index,
        name,
        [
            Entry("COB-ID", DataType.UNSIGNED32, "rw", cob_id),
            Entry("Transmission type", DataType.UNSIGNED8, "rw", c.TRANSMISSION_SYNC),
            Entry("Inhibit time", DataType.UNSIGNED16, "rw", 0),
            Entry("Reserved", DataType.UNSIGNED8, "rw", 0),
            Entry("Event timer", DataType.UNSIGNED16, "rw", 0),
        ],
    )


def _pdo_map(index: int, name: str, entries: tuple[int, ...]) -> Obj:
    subs = {0: Entry("Number of mapped objects", DataType.UNSIGNED8, "rw", len(entries))}
    for i in range(1, 9):
        subs[i] = Entry(f"Mapped object {i}", DataType.UNSIGNED32, "rw", entries[i - 1] if i <= len(entries) else 0)
    return Obj(index, name, subs, record=True)


N_PDOS = 4
N_HEARTBEAT_CONSUMERS = 1


def drive_dictionary(node_id: int, cfg: DriveConfig) -> dict[int, Obj]:
    """The object dictionary of one drive, with its power-on defaults.

    The default PDO mappings are deliberately *not* the driver's: the driver must
    configure them over SDO (RPDO1 = controlword only, TPDO1 = statusword only,
    others disabled), as with a drive fresh from the factory.
    """
    objs = [
        _var(c.DEVICE_TYPE, "Device type", DataType.UNSIGNED32, "ro", c.DEVICE_TYPE_SERVO),
        _var(c.ERROR_REGISTER, "Error register", DataType.UNSIGNED8, "ro", 0, pdo=True),
        _var(c.COB_ID_SYNC, "COB-ID SYNC", DataType.UNSIGNED32, "rw", c.SYNC_ID),
        _var(c.CYCLE_PERIOD, "Communication cycle period", DataType.UNSIGNED32, "rw", 0),
        _var(c.DEVICE_NAME, "Manufacturer device name", DataType.VISIBLE_STRING, "const", cfg.device_name),
        _var(c.HW_VERSION, "Manufacturer hardware version", DataType.VISIBLE_STRING, "const", "emulated"),
        _var(c.SW_VERSION, "Manufacturer software version", DataType.VISIBLE_STRING, "const", cfg.sw_version),
        _var(c.COB_ID_EMCY, "COB-ID EMCY", DataType.UNSIGNED32, "rw", c.EMCY_BASE + node_id),
        _record(
            c.CONSUMER_HEARTBEAT,
            "Consumer heartbeat time",
            [Entry(f"Consumer heartbeat time {i + 1}", DataType.UNSIGNED32, "rw", 0) for i in range(N_HEARTBEAT_CONSUMERS)],
        ),
        _var(c.PRODUCER_HEARTBEAT, "Producer heartbeat time", DataType.UNSIGNED16, "rw", 0),
        _record(
            c.IDENTITY,
            "Identity object",
            [
                Entry("Vendor-ID", DataType.UNSIGNED32, "ro", c.ELMO_VENDOR_ID),
                Entry("Product code", DataType.UNSIGNED32, "ro", 0x00030924),
                Entry("Revision number", DataType.UNSIGNED32, "ro", 0x00010000),
                Entry("Serial number", DataType.UNSIGNED32, "ro", cfg.serial_number),
            ],
        ),
    ]
    for n in range(N_PDOS):
        objs.append(_pdo_comm(c.RPDO_COMM + n, f"RPDO{n + 1} communication parameter", c.RPDO_BASE[n] + node_id | (c.PDO_COB_INVALID if n else 0)))
    objs.append(_pdo_map(c.RPDO_MAP, "RPDO1 mapping parameter", (c.pdo_mapping_entry(c.CONTROLWORD, 0, 16),)))
    for n in range(1, N_PDOS):
        objs.append(_pdo_map(c.RPDO_MAP + n, f"RPDO{n + 1} mapping parameter", ()))
    for n in range(N_PDOS):
        objs.append(_pdo_comm(c.TPDO_COMM + n, f"TPDO{n + 1} communication parameter", c.TPDO_BASE[n] + node_id | (c.PDO_COB_INVALID if n else 0)))
    objs.append(_pdo_map(c.TPDO_MAP, "TPDO1 mapping parameter", (c.pdo_mapping_entry(c.STATUSWORD, 0, 16),)))
    for n in range(1, N_PDOS):
        objs.append(_pdo_map(c.TPDO_MAP + n, f"TPDO{n + 1} mapping parameter", ()))
    objs += [
        _var(c.ERROR_CODE, "Error code", DataType.UNSIGNED16, "ro", 0, pdo=True),
        _var(c.ABORT_CONNECTION_OPTION, "Abort connection option code", DataType.INTEGER16, "rw", 1),
        _var(c.CONTROLWORD, "Controlword", DataType.UNSIGNED16, "rw", 0, pdo=True),
        _var(c.STATUSWORD, "Statusword", DataType.UNSIGNED16, "ro", 0, pdo=True),
        _var(c.QUICK_STOP_OPTION, "Quick stop option code", DataType.INTEGER16, "rw", 6),
        _var(c.MODES_OF_OPERATION, "Modes of operation", DataType.INTEGER8, "rw", 0, pdo=True),
        _var(c.MODES_DISPLAY, "Modes of operation display", DataType.INTEGER8, "ro", 0, pdo=True),
        _var(c.POSITION_ACTUAL, "Position actual value", DataType.INTEGER32, "ro", 0, pdo=True),
        _var(c.VELOCITY_ACTUAL, "Velocity actual value", DataType.INTEGER32, "ro", 0, pdo=True),
        _var(c.TARGET_TORQUE, "Target torque", DataType.INTEGER16, "rw", 0, pdo=True),
        _var(c.MAX_TORQUE, "Max torque", DataType.UNSIGNED16, "rw", cfg.max_torque_permille),
        _var(c.MAX_CURRENT, "Max current", DataType.UNSIGNED16, "rw", cfg.max_current_permille),
        _var(c.RATED_CURRENT, "Motor rated current", DataType.UNSIGNED32, "rw", cfg.rated_current_ma),
        _var(c.RATED_TORQUE, "Motor rated torque", DataType.UNSIGNED32, "rw", cfg.rated_torque_mnm),
        _var(c.TORQUE_ACTUAL, "Torque actual value", DataType.INTEGER16, "ro", 0, pdo=True),
        _var(c.CURRENT_ACTUAL, "Current actual value", DataType.INTEGER16, "ro", 0, pdo=True),
        _record(
            c.ENCODER_RESOLUTION,
            "Position encoder resolution",
            [
                Entry("Encoder increments", DataType.UNSIGNED32, "rw", cfg.counts_per_rev),
                Entry("Motor revolutions", DataType.UNSIGNED32, "rw", 1),
            ],
        ),
        _record(
            c.INTERPOLATION_PERIOD,
            "Interpolation time period",
            [
                Entry("Interpolation time period value", DataType.UNSIGNED8, "rw", 1),
                Entry("Interpolation time index", DataType.INTEGER8, "rw", -3),
            ],
        ),
        _var(c.SUPPORTED_MODES, "Supported drive modes", DataType.UNSIGNED32, "ro", c.SUPPORTED_CST_BIT | 0x1FF),
    ]
    return {o.index: o for o in objs}


_ACCESS_EDS = {"ro": "ro", "rw": "rw", "wo": "wo", "const": "const"}


def _eds_value(entry: Entry) -> str:
    if entry.dtype == DataType.VISIBLE_STRING:
        return str(entry.value)
    value = int(entry.value)
    if value < 0:
        return str(value)
    return f"0x{value:X}"


def to_eds(objs: dict[int, Obj], node_id: int, product: str = "ARCHER emulated ELMO drive") -> str:
    """The dictionary as an EDS file (CiA 306 text)."""
    lines = [
        "[FileInfo]",
        "FileName=archer_elmo.eds",
        "FileVersion=1",
        "Description=Object dictionary of the ARCHER ELMO drive emulator",
        "",
        "[DeviceInfo]",
        "VendorName=Elmo Motion Control (emulated)",
        f"VendorNumber=0x{c.ELMO_VENDOR_ID:08X}",
        f"ProductName={product}",
        "BaudRate_1000=1",
        "SimpleBootUpSlave=1",
        f"NrOfRXPDO={N_PDOS}",
        f"NrOfTXPDO={N_PDOS}",
        "",
        "[DeviceComissioning]",
        f"NodeID=0x{node_id:02X}",
        "Baudrate=1000",
        "",
    ]
    mandatory = [i for i in sorted(objs) if i in (c.DEVICE_TYPE, c.ERROR_REGISTER, c.IDENTITY)]
    optional = [i for i in sorted(objs) if i not in mandatory]
    for title, group in (("MandatoryObjects", mandatory), ("OptionalObjects", optional)):
        lines.append(f"[{title}]")
        lines.append(f"SupportedObjects={len(group)}")
        lines += [f"{n}=0x{i:04X}" for n, i in enumerate(group, start=1)]
        lines.append("")
    for index in sorted(objs):
        obj = objs[index]
        if not obj.record:
            e = obj.subs[0]
            lines += [
                f"[{index:04X}]",
                f"ParameterName={obj.name}",
                "ObjectType=0x7",
                f"DataType=0x{int(e.dtype):04X}",
                f"AccessType={_ACCESS_EDS[e.access]}",
                f"DefaultValue={_eds_value(e)}",
                f"PDOMapping={int(e.pdo_mappable)}",
                "",
            ]
            continue
        lines += [f"[{index:04X}]", f"ParameterName={obj.name}", "ObjectType=0x9", f"SubNumber={len(obj.subs)}", ""]
        for sub, e in sorted(obj.subs.items()):
            lines += [
                f"[{index:04X}sub{sub:X}]",
                f"ParameterName={e.name}",
                "ObjectType=0x7",
                f"DataType=0x{int(e.dtype):04X}",
                f"AccessType={_ACCESS_EDS[e.access]}",
                f"DefaultValue={_eds_value(e)}",
                f"PDOMapping={int(e.pdo_mappable)}",
                "",
            ]
    return "\n".join(lines)
