"""The ARCHER firmware's packets: layout, wheel order, reset, and strict refusal of bad bytes."""

from __future__ import annotations

import math
import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.archer_firmware import codec as c

finite = st.floats(min_value=-1e4, max_value=1e4, allow_nan=False, width=32)
vec3 = st.tuples(finite, finite, finite)
UPRIGHT = (1.0, 0.0, 0.0, 0.0)


@st.composite
def unit_quats(draw):
    q = draw(st.tuples(*[st.floats(-1, 1, width=32)] * 4))
    n = math.sqrt(sum(x * x for x in q))
    if n < 0.1:
        return UPRIGHT
    return tuple(float(struct.unpack("<f", struct.pack("<f", x / n))[0]) for x in q)


def test_sizes_as_the_firmware_sends_them() -> None:
    assert c.SETPOINT.size == 40 and c.STATE.size == 52
    assert c.RESET_PACKET[:8] == bytes.fromhex("0102030405060708") and len(c.RESET_PACKET) == 40


@given(unit_quats(), vec3, vec3)
def test_setpoint_round_trip(q, w, tau) -> None:
    sp = c.Setpoint(q, w, tau)
    data = c.pack_setpoint(sp)
    assert struct.unpack("<10f", data) == (*q, *w, *tau)  # plain little-endian float32, in this order
    assert c.unpack_setpoint(data) == sp


def test_state_wheel_order_is_one_three_two_on_the_wire() -> None:
    s = c.BoardState((1.0, 2.0, 3.0), (0.1, 0.2, 0.3), UPRIGHT, True, 0.02, -0.5)
    wire = struct.unpack("<13f", c.pack_state(s))
    assert wire[:3] == (1.0, 3.0, 2.0)
    assert wire[3:] == pytest.approx((0.1, 0.2, 0.3, 1.0, 0.0, 0.0, 0.0, 1.0, 0.02, -0.5))
    back = c.unpack_state(c.pack_state(s))
    assert back.wheel_vel == (1.0, 2.0, 3.0) and back.foot_contact and back.quat == UPRIGHT
    assert not c.unpack_state(struct.pack("<13f", 0, 0, 0, 0, 0, 0, *UPRIGHT, 0.0, 0, 0)).foot_contact


def test_reset_is_recognised_before_the_floats() -> None:
    assert c.unpack_setpoint(c.RESET_PACKET) is None
    assert c.unpack_setpoint(c.RESET_MAGIC + struct.pack("<8f", *[math.nan] * 8)) is None  # only the prefix counts
    assert not c.is_reset(bytes.fromhex("0102030405060709") + bytes(32))  # one byte off: not a reset ...
    with pytest.raises(c.CodecError) as err:  # ... but floats, and no unit quaternion among them
        c.unpack_setpoint(bytes.fromhex("0102030405060709") + bytes(32))
    assert err.value.kind == "quaternion"
    with pytest.raises(c.CodecError) as err:
        c.unpack_setpoint(c.RESET_MAGIC)  # the magic alone is a truncated packet
    assert err.value.kind == "length"


@pytest.mark.parametrize("size", [0, 8, 39, 41, 52, 2048])
def test_setpoint_of_the_wrong_length_is_refused(size: int) -> None:
    with pytest.raises(c.CodecError) as err:
        c.unpack_setpoint(c.pack_setpoint(c.Setpoint(UPRIGHT, (0, 0, 0), (0, 0, 0))).ljust(size, b"\0")[:size])
    assert err.value.kind == "length"


@pytest.mark.parametrize("size", [0, 40, 51, 53])
def test_state_of_the_wrong_length_is_refused(size: int) -> None:
    with pytest.raises(c.CodecError) as err:
        c.unpack_state(bytes(size))
    assert err.value.kind == "length"


@pytest.mark.parametrize("index", range(10))
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_setpoint_fields_are_refused(index: int, bad: float) -> None:
    values = [*UPRIGHT, 0.0, 0.0, 0.0, 0.1, 0.2, 0.3]
    values[index] = bad
    with pytest.raises(c.CodecError) as err:
        c.unpack_setpoint(struct.pack("<10f", *values))
    assert err.value.kind == "non_finite"
    with pytest.raises(c.CodecError):
        c.pack_setpoint(c.Setpoint(tuple(values[0:4]), tuple(values[4:7]), tuple(values[7:10])))


@pytest.mark.parametrize("index", range(13))
def test_non_finite_state_fields_are_refused(index: int) -> None:
    values = [0.0] * 13
    values[6] = 1.0
    values[index] = math.nan
    with pytest.raises(c.CodecError) as err:
        c.unpack_state(struct.pack("<13f", *values))
    assert err.value.kind == "non_finite"


@pytest.mark.parametrize("q", [(0.0, 0.0, 0.0, 0.0), (2.0, 0.0, 0.0, 0.0), (0.9, 0.0, 0.0, 0.0)])
def test_a_setpoint_quaternion_that_is_not_a_rotation_is_refused(q) -> None:
    with pytest.raises(c.CodecError) as err:
        c.unpack_setpoint(struct.pack("<10f", *q, 0, 0, 0, 0, 0, 0))
    assert err.value.kind == "quaternion"
    with pytest.raises(c.CodecError):
        c.pack_setpoint(c.Setpoint(q, (0, 0, 0), (0, 0, 0)))
