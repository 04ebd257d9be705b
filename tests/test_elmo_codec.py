"""CANopen / CiA 402 frame layer and the CAN bit budget: pure functions, no bus."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers import can_budget as cb
from drivers.elmo import codec as c
from drivers.elmo.od import DataType, DriveConfig, decode_value, drive_dictionary, encode_value, to_eds

# --- bit budget -------------------------------------------------------------------------


@given(st.integers(0, 0x7FF), st.binary(max_size=8))
def test_exact_frame_bits_lie_between_unstuffed_and_worst_case(can_id: int, data: bytes) -> None:
    bits = cb.frame_bits(can_id, data)
    assert cb.unstuffed_bits(len(data)) <= bits <= cb.worst_case_bits(len(data))


@given(st.integers(0, 0x1FFFFFFF), st.binary(max_size=8))
def test_extended_frames_too(can_id: int, data: bytes) -> None:
    bits = cb.frame_bits(can_id, data, extended=True)
    assert cb.unstuffed_bits(len(data), True) <= bits <= cb.worst_case_bits(len(data), True)


def test_textbook_frame_lengths() -> None:
    # 47 + 8n bits before stuffing; 8 data bytes: 111, at worst 135 (24 stuff bits)
    assert cb.unstuffed_bits(8) == 111
    assert cb.worst_case_bits(8) == 135
    assert cb.worst_case_bits(0) == 55
    # alternating bits never stuff: 0x555 identifier with 0x55 data has few stuff bits
    assert cb.frame_bits(0x555, b"\x55" * 8) < cb.frame_bits(0x000, b"\x00" * 8)
    # an all-zero frame stuffs at least once per five bits of its identifier and data
    assert cb.frame_bits(0x000, b"\x00" * 8) - cb.unstuffed_bits(8) >= (11 + 64) // 5


def _crc15_by_division(bits: list[int]) -> int:
    """CRC-15 as the remainder of M(x) x^15 divided by g(x), by long division over GF(2)."""
    g = (1 << 15) | 0x4599
    m = 0
    for b in bits:
        m = (m << 1) | b
    m <<= 15
    for shift in range(m.bit_length() - 16, -1, -1):
        if m >> (shift + 15) & 1:
            m ^= g << shift
    return m


@given(st.lists(st.integers(0, 1), min_size=19, max_size=83))
def test_crc15_is_the_polynomial_remainder(bits: list[int]) -> None:
    assert cb._crc15(bits) == _crc15_by_division(bits)


def test_four_drives_at_one_kilohertz_fill_a_megabit_bus() -> None:
    items = [
        cb.TrafficItem("SYNC", 0, 1000),
        cb.TrafficItem("RPDO", c.RPDO1_STRUCT.size, 1000, 4),
        cb.TrafficItem("TPDO", c.TPDO1_STRUCT.size, 1000, 4),
    ]
    load = cb.bus_load(items, 1_000_000)
    assert load.nominal == pytest.approx((47 + 4 * (47 + 32) + 4 * (47 + 64)) / 1000)
    assert 0.8 < load.nominal < load.worst < 1.0


def test_load_meter_sampling_matches_the_exact_count() -> None:
    import random

    rng = random.Random(7)
    meter = cb.LoadMeter()
    exact = 0
    for _ in range(5000):
        data = bytes(rng.randrange(256) for _ in range(8))
        meter.add(0x181, data)
        exact += cb.frame_bits(0x181, data)
    assert meter.frames == 5000
    assert meter.bits == pytest.approx(exact, rel=0.01)


def test_load_meter_counts_exact_bits() -> None:
    meter = cb.LoadMeter()
    meter.add(0x080, b"")
    meter.add(0x181, bytes(8))
    assert meter.frames == 2
    assert meter.bits == cb.frame_bits(0x080, b"") + cb.frame_bits(0x181, bytes(8))
    assert meter.load(0.001, 1_000_000) == pytest.approx(meter.bits / 1000)


# --- NMT, heartbeat, SYNC -------------------------------------------------------------------


def test_nmt_and_heartbeat_frames() -> None:
    assert c.make_nmt(c.NmtCommand.START, 3) == c.Frame(0x000, b"\x01\x03")
    assert c.parse_nmt(b"\x82\x00") == (c.NmtCommand.RESET_COMMUNICATION, 0)
    assert c.make_heartbeat(5, c.NmtState.OPERATIONAL) == c.Frame(0x705, b"\x05")
    assert c.parse_heartbeat(b"\x85") == c.NmtState.OPERATIONAL  # toggle bit ignored
    assert c.make_sync() == c.Frame(0x080, b"")
    with pytest.raises(ValueError):
        c.parse_heartbeat(b"")
    with pytest.raises(ValueError):
        c.check_node_id(0)


# --- SDO -------------------------------------------------------------------------------------


def test_expedited_download_layout() -> None:
    f = c.make_sdo_download_request(2, 0x6060, 0, b"\x0a")
    assert f.can_id == 0x602
    assert f.data == bytes((0x2F, 0x60, 0x60, 0x00, 0x0A, 0, 0, 0))  # 0x2F: 1 byte, expedited, sized
    f = c.make_sdo_download_request(2, 0x1017, 0, struct.pack("<H", 50))
    assert f.data[0] == 0x2B
    f = c.make_sdo_download_request(2, 0x1016, 1, struct.pack("<I", 1))
    assert f.data[0] == 0x23


def test_segmented_download_initiate_announces_the_size() -> None:
    f = c.make_sdo_download_request(1, 0x2000, 0, b"hello world")
    assert f.data[0] == 0x21
    assert struct.unpack_from("<I", f.data, 4)[0] == 11
    seg = c.make_sdo_download_segment(1, 1, b"rld", last=True)
    assert seg.data[0] == 0x10 | (4 << 1) | 1
    m = c.parse_sdo(seg.data, client_to_server=True)
    assert (m.cs, m.toggle, m.payload, m.last) == (c.CCS_DOWNLOAD_SEGMENT, 1, b"rld", True)


@given(st.integers(0, 0xFFFF), st.integers(0, 0xFF), st.binary(min_size=0, max_size=4))
def test_expedited_upload_response_round_trip(index: int, sub: int, data: bytes) -> None:
    m = c.parse_sdo(c.make_sdo_upload_response(7, index, sub, data).data, client_to_server=False)
    if data:
        assert m.expedited and m.payload == data and (m.index, m.subindex) == (index, sub)


@given(st.binary(min_size=0, max_size=7), st.integers(0, 1), st.booleans())
def test_upload_segment_round_trip(chunk: bytes, toggle: int, last: bool) -> None:
    m = c.parse_sdo(c.make_sdo_upload_segment(7, toggle, chunk, last).data, client_to_server=False)
    assert (m.payload, m.toggle, m.last) == (chunk, toggle, last)


def test_abort_round_trip_and_text() -> None:
    f = c.make_sdo_abort(0x581, 0x1234, 5, c.SdoAbort.NO_OBJECT)
    m = c.parse_sdo(f.data, client_to_server=False)
    assert m.cs == c.CS_ABORT and m.abort_code == 0x06020000 and (m.index, m.subindex) == (0x1234, 5)
    assert "does not exist" in c.abort_text(m.abort_code)
    assert c.abort_text(0x12345678) == "unknown abort code"


def test_short_sdo_frame_is_rejected() -> None:
    with pytest.raises(ValueError):
        c.parse_sdo(b"\x40\x00", client_to_server=False)


# --- EMCY ---------------------------------------------------------------------------------------


def test_emcy_decoding_with_elmo_codes() -> None:
    e = c.parse_emcy(3, c.make_emcy(3, 0x2340, 0x03).data)
    assert e.code == 0x2340 and not e.is_reset
    assert "short circuit" in e.describe()
    m = c.parse_emcy(3, c.make_emcy(3, 0xFF00, 0x81, elmo_code=0x09, field1=7, field2=9).data)
    assert (m.elmo_code, m.field1, m.field2) == (0x09, 7, 9)
    assert "CAN message has been lost" in m.describe()
    assert c.parse_emcy(3, c.make_emcy(3, 0, 0).data).is_reset
    assert "heartbeat" in c.parse_emcy(1, c.make_emcy(1, 0x8130, 0x11).data).describe()
    with pytest.raises(ValueError):
        c.parse_emcy(3, b"\x00\x10")


# --- CiA 402 ------------------------------------------------------------------------------------


@pytest.mark.parametrize("state, word", list(c.STATUSWORD_OF_STATE.items()))
def test_statusword_patterns(state: c.DriveState, word: int) -> None:
    assert c.state_of(word) == state
    assert c.state_of(word | c.SW_REMOTE | c.SW_WARNING | c.SW_TARGET_REACHED) == state


def _drive_transition(state: c.DriveState, cw: int) -> c.DriveState:
    """The CiA 402 device transitions, written from the standard's table for this test."""
    D = c.DriveState
    table = {
        (D.SWITCH_ON_DISABLED, 0x06): D.READY_TO_SWITCH_ON,
        (D.READY_TO_SWITCH_ON, 0x07): D.SWITCHED_ON,
        (D.READY_TO_SWITCH_ON, 0x00): D.SWITCH_ON_DISABLED,
        (D.SWITCHED_ON, 0x0F): D.OPERATION_ENABLED,
        (D.SWITCHED_ON, 0x06): D.READY_TO_SWITCH_ON,
        (D.SWITCHED_ON, 0x00): D.SWITCH_ON_DISABLED,
        (D.OPERATION_ENABLED, 0x07): D.SWITCHED_ON,
        (D.OPERATION_ENABLED, 0x06): D.READY_TO_SWITCH_ON,
        (D.OPERATION_ENABLED, 0x00): D.SWITCH_ON_DISABLED,
        (D.QUICK_STOP_ACTIVE, 0x00): D.SWITCH_ON_DISABLED,
        (D.OPERATION_ENABLED, 0x02): D.QUICK_STOP_ACTIVE,
        (D.SWITCHED_ON, 0x02): D.SWITCH_ON_DISABLED,
        (D.READY_TO_SWITCH_ON, 0x02): D.SWITCH_ON_DISABLED,
        (D.FAULT, 0x80): D.SWITCH_ON_DISABLED,
    }
    return table[(state, cw)]


@pytest.mark.parametrize("start", [s for s in c.DriveState if s not in (c.DriveState.NOT_READY_TO_SWITCH_ON, c.DriveState.FAULT_REACTION_ACTIVE)])
@pytest.mark.parametrize(
    "target",
    [c.DriveState.OPERATION_ENABLED, c.DriveState.SWITCH_ON_DISABLED, c.DriveState.READY_TO_SWITCH_ON, c.DriveState.SWITCHED_ON,
     c.DriveState.QUICK_STOP_ACTIVE],
)
def test_next_command_reaches_every_target(start: c.DriveState, target: c.DriveState) -> None:
    state = start
    for _ in range(6):
        cw = c.next_command(state, target)
        if cw is None:
            break
        state = _drive_transition(state, int(cw))
    if target == c.DriveState.QUICK_STOP_ACTIVE and start not in (c.DriveState.OPERATION_ENABLED, c.DriveState.QUICK_STOP_ACTIVE):
        assert state == c.DriveState.SWITCH_ON_DISABLED  # a quick stop outside OPERATION ENABLED disables
    else:
        assert state == target


def test_pdo_payloads() -> None:
    f = c.make_rpdo1(4, 0x0F, -123)
    assert f.can_id == 0x204 and struct.unpack("<Hh", f.data) == (0x0F, -123)
    assert struct.unpack("<Hh", c.make_rpdo1(4, 0x0F, 10**6).data)[1] == c.I16_MAX  # saturates, never wraps
    assert c.parse_tpdo1(struct.pack("<Hhi", 0x1237, 500, -4096)) == (0x1237, 500, -4096)
    with pytest.raises(ValueError):
        c.parse_tpdo1(bytes(7))
    assert c.split_mapping_entry(c.pdo_mapping_entry(0x6071, 0, 16)) == (0x6071, 0, 16)


# --- object dictionary ----------------------------------------------------------------------------


def test_value_codecs() -> None:
    assert decode_value(DataType.INTEGER16, encode_value(DataType.INTEGER16, -5)) == -5
    assert decode_value(DataType.VISIBLE_STRING, encode_value(DataType.VISIBLE_STRING, "abc")) == "abc"
    with pytest.raises(ValueError):
        decode_value(DataType.UNSIGNED32, b"\x00\x00")


def test_eds_loads_in_the_canopen_package(tmp_path) -> None:
    import canopen

    od = drive_dictionary(5, DriveConfig())
    path = tmp_path / "drive.eds"
    path.write_text(to_eds(od, 5))
    loaded = canopen.import_od(str(path), node_id=5)
    assert loaded[0x6076].default == DriveConfig().rated_torque_mnm
    assert loaded[0x1A00][1].default == c.pdo_mapping_entry(c.STATUSWORD, 0, 16)
    assert loaded[0x6071].pdo_mappable and loaded[0x6071].data_type == DataType.INTEGER16
    assert loaded[0x1008].default == DriveConfig().device_name
