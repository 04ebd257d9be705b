"""The socketcand server the drive emulator serves, with python-can's stock client and ours."""

from __future__ import annotations

import socket
import time

import can
import pytest

from drivers.elmo import codec as c
from drivers.elmo.transport import CAN_ERR_BUSOFF, CanTransport
from drivers.socketcand import ERROR_FLAG, SocketcandBus, SocketcandServer, format_frame, parse_send

SETTLE_S = 0.15  # the server holds frames back until a new client's raw mode settled


def echo_plus_one(frame: c.Frame, now: float) -> list[c.Frame]:
    """A device that answers every frame with the identifier + 1 and the same data."""
    return [c.Frame(frame.can_id + 1, frame.data)]


@pytest.fixture
def server():
    srv = SocketcandServer(echo_plus_one).start()
    try:
        yield srv
    finally:
        srv.stop()


def recv_all(bus: can.BusABC, n: int, timeout_s: float = 2.0) -> list[can.Message]:
    got: list[can.Message] = []
    end = time.monotonic() + timeout_s
    while len(got) < n and time.monotonic() < end:
        msg = bus.recv(0.05)
        if msg is not None:
            got.append(msg)
    return got


def test_text_formats() -> None:
    assert format_frame(c.Frame(0x181, bytes.fromhex("0102")), 1.5) == "< frame 181 1.500000 0102 >"
    assert format_frame(c.Frame(0x080, b""), 2.0) == "< frame 080 2.000000  >"
    assert format_frame(c.Frame(ERROR_FLAG | CAN_ERR_BUSOFF, bytes(8)), 1.0) == "< error 00000040 1.000000 >"
    assert parse_send("< send 601 8 40 0 10 0 0 0 0 0 >") == c.Frame(0x601, bytes.fromhex("4000100000000000"))
    for bad in ("< send 601 2 40 >", "< send 800 0 >", "< frame 1 2 >", "< send 601 9 0 0 0 0 0 0 0 0 0 >"):
        with pytest.raises(ValueError):
            parse_send(bad)


def test_stock_client_and_ours_share_the_bus(server: SocketcandServer) -> None:
    stock = can.Bus(**server.bus_kwargs())
    ours = SocketcandBus(server.channel, "127.0.0.1", server.port)
    try:
        time.sleep(SETTLE_S)
        ours.send_many([can.Message(arbitration_id=0x200 + i, data=[i, i], is_extended_id=False) for i in range(3)])
        seen = recv_all(stock, 6)  # the frames themselves and the device's answers
        ids = sorted(m.arbitration_id for m in seen)
        assert ids == [0x200, 0x201, 0x201, 0x202, 0x202, 0x203]
        assert [bytes(m.data) for m in seen if m.arbitration_id == 0x200] == [b"\x00\x00"]
        stock.send(can.Message(arbitration_id=0x300, data=b"\x07", is_extended_id=False))
        seen = recv_all(ours, 5)  # the device answers every client, the sender too
        assert sorted(m.arbitration_id for m in seen) == [0x201, 0x202, 0x203, 0x300, 0x301]
        assert server.frames_from_clients == 4
    finally:
        stock.shutdown()
        ours.shutdown()


def test_error_frames_reach_the_transport_as_latched_faults(server: SocketcandServer) -> None:
    transport = CanTransport(SocketcandBus(server.channel, "127.0.0.1", server.port))
    try:
        time.sleep(SETTLE_S)
        server.broadcast([c.Frame(ERROR_FLAG | CAN_ERR_BUSOFF, bytes(8))])
        end = time.monotonic() + 2.0
        while not transport.fault and time.monotonic() < end:
            transport.poll()
            time.sleep(0.005)
        assert transport.fault == "CAN error frame: bus-off" and transport.bus_off == 1
    finally:
        transport.shutdown()


def test_a_vanished_server_breaks_the_transport(server: SocketcandServer) -> None:
    transport = CanTransport(SocketcandBus(server.channel, "127.0.0.1", server.port))
    try:
        time.sleep(SETTLE_S)
        server.disconnect_clients()
        end = time.monotonic() + 2.0
        while not transport.broken and time.monotonic() < end:
            transport.poll()
            time.sleep(0.005)
        assert transport.broken and "receive failed" in transport.fault
        assert transport.recv(0.01) is None
    finally:
        transport.shutdown()


def test_bad_commands_get_an_error_reply(server: SocketcandServer) -> None:
    with socket.create_connection(("127.0.0.1", server.port), timeout=2.0) as s:
        assert s.recv(64) == b"< hi >"
        s.sendall(b"< open nosuchbus >")
        assert b"error" in s.recv(64)
        s.sendall(b"< open can0 >")
        assert s.recv(64) == b"< ok >"
        s.sendall(b"< rawmode >")
        assert s.recv(64) == b"< ok >"
        s.sendall(b"< send 601 3 1 >")
        assert b"error" in s.recv(64)
        s.sendall(b"< dance >")
        assert b"error" in s.recv(64)
