"""The Teensy frame layer: COBS, CRC, header, payloads, and the resynchronising decoder."""

from __future__ import annotations

import math
import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.teensy import protocol as p

finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False, width=32)


def test_crc_check_value() -> None:
    assert p.crc16(b"123456789") == 0x29B1


@pytest.mark.parametrize(
    "data, encoded",
    [
        (b"", "01"),
        (b"\x00", "01 01"),
        (bytes.fromhex("11220033"), "03 11 22 02 33"),
        (bytes.fromhex("110000"), "02 11 01 01"),
        (bytes(range(1, 255)), "ff " + bytes(range(1, 255)).hex(" ") + " 01"),
    ],
)
def test_cobs_examples(data: bytes, encoded: str) -> None:
    assert p.cobs_encode(data).hex(" ") == encoded
    assert p.cobs_decode(bytes.fromhex(encoded)) == data


@given(st.binary(max_size=700))
def test_cobs_round_trip_without_zeros(data: bytes) -> None:
    enc = p.cobs_encode(data)
    assert 0 not in enc
    assert len(enc) <= len(data) + len(data) // 254 + 1
    assert p.cobs_decode(enc) == data


def test_cobs_rejects_malformed_blocks() -> None:
    with pytest.raises(p.FrameError) as err:
        p.cobs_decode(b"\x05\x01\x02")
    assert err.value.kind == "cobs"


@given(st.integers(0, 0xFFFF), st.binary(max_size=p.MAX_PAYLOAD), st.sampled_from(list(p.FrameType)))
def test_frame_round_trip(seq: int, payload: bytes, ftype: p.FrameType) -> None:
    wire = p.encode_frame(ftype, seq, payload)
    assert wire.endswith(b"\x00") and wire.count(0) == 1
    frame = p.decode_frame(wire[:-1])
    assert (frame.frame_type, frame.seq, frame.payload) == (ftype, seq, payload)


@given(st.tuples(finite, finite, finite), finite, st.booleans())
def test_torque_payload_round_trip(wheels, foot, armed) -> None:
    cmd = p.TorqueCmd(wheels, foot, armed)
    got = p.parse_torque(p.decode_frame(p.make_torque(1, cmd)[:-1]).payload)
    assert got.armed == armed
    assert got.wheel_torque == pytest.approx(wheels, rel=1e-6, abs=1e-6)
    assert got.foot_torque == pytest.approx(foot, rel=1e-6, abs=1e-6)


def test_sensor_payload_round_trip_and_size() -> None:
    s = p.Sensors(123, p.SENSOR_CONTACT | p.SENSOR_ARMED, (1.0, 0.0, 0.0, 0.0), (0.1, 0.2, 0.3), (0.0, 0.0, 9.81),
                  (1.0, 2.0, 3.0), (4.0, 5.0, 6.0), (0.5, 0.25, 0.125), 0.01, -0.2, 1.5, 77, 3)
    payload = p.decode_frame(p.make_sensors(9, s)[:-1]).payload
    assert len(payload) == 97  # as docs/teensy_protocol.md says
    got = p.parse_sensors(payload)
    assert got.t_us == 123 and got.flags == s.flags and got.last_cmd_seq == 77 and got.crc_errors == 3
    assert got.accel == pytest.approx(s.accel) and got.wheel_torque == pytest.approx(s.wheel_torque)


def test_payload_sizes_match_the_docs() -> None:
    assert (p.TORQUE.size, p.ATTITUDE.size, p.HEARTBEAT.size, p.GAINS.size, p.SENSORS.size, p.STATUS.size) == (17, 45, 4, 24, 97, 4)


def test_non_finite_and_wrong_size_payloads_are_rejected() -> None:
    nan_torque = struct.pack("<B3ff", 1, 0.1, math.nan, 0.0, 0.0)
    with pytest.raises(p.FrameError) as err:
        p.parse_torque(nan_torque)
    assert err.value.kind == "payload"
    with pytest.raises(p.FrameError):
        p.parse_torque(nan_torque[:-1])
    with pytest.raises(p.FrameError):
        p.parse_sensors(bytes(96))


def test_decoder_resynchronises_after_garbage_and_counts() -> None:
    dec = p.FrameDecoder()
    good = p.make_torque(1, p.TorqueCmd((0.1, 0.2, 0.3), 0.4, True))
    assert dec.feed(b"\x13\x37 noise \x00" + good[:5]) == []
    frames = dec.feed(good[5:] + p.make_torque(2, p.TorqueCmd((0.0, 0.0, 0.0), 0.0, False)))
    assert [f.seq for f in frames] == [1, 2]
    assert dec.counts["cobs"] + dec.counts["short"] + dec.counts["crc"] == 1
    bad = bytearray(good)
    bad[6] ^= 0x01 if bad[6] != 0x01 else 0x02  # a bit error: still no zero inside
    assert dec.feed(bytes(bad)) == []
    assert dec.counts["crc"] >= 1
    assert dec.feed(b"\x00\x00\x00") == []  # idle delimiters
    assert dec.feed(p.make_torque(5, p.TorqueCmd((0.0, 0.0, 0.0), 0.0, False)))[0].seq == 5
    assert dec.counts["gaps"] == 1 and dec.counts["missing"] == 2


def test_decoder_drops_oversize_runs() -> None:
    dec = p.FrameDecoder()
    assert dec.feed(b"\x01" * (p.MAX_ENCODED + 10)) == []
    assert dec.counts["oversize"] == 1
    assert dec.feed(b"\x01" * 20 + b"\x00") == []  # the rest of the oversize run
    good = p.make_heartbeat(1, 5)
    assert len(dec.feed(good)) == 1


def test_version_and_length_checks() -> None:
    dec = p.FrameDecoder()
    dec.feed(p.encode_frame(p.FrameType.HEARTBEAT, 1, bytes(4), version=2))
    assert dec.counts["version"] == 1
    body = p.HEADER.pack(1, p.FrameType.HEARTBEAT, 1, 9) + bytes(4)  # says 9, carries 4
    dec.feed(p.cobs_encode(body + p.CRC.pack(p.crc16(body))) + b"\x00")
    assert dec.counts["length"] == 1
    assert dec.rejected == 2
