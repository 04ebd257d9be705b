"""Our ARCHER firmware driver against the emulated board on UDP loopback, ticked by hand.

Both ends run in this process on real sockets; time is a hand-moved clock, so late,
missing and watchdog figures are exact. Bad input at either end (wrong size, NaN,
a stranger's datagram) is dropped, counted and never applied.
"""

from __future__ import annotations

import dataclasses
import math
import socket
import struct
import time

import pytest

from drivers.archer_firmware import codec as c
from drivers.archer_firmware.device import ArcherBoard
from drivers.udp import free_udp_port
from drivers.archer_firmware.emulator import BoardEmulator, FootBoard, FootPhase
from drivers.archer_firmware.transport import UdpLink
from onboard.geometry import quaternion as quat
from onboard.low_level.tracking.foot_control import FootPhysics
from onboard.contracts.params import ArcherFirmwareParams

PARAMS = ArcherFirmwareParams()
FOOT = FootPhysics(total_mass=3.0, gravity=9.81, spring_k=3000.0, spool_radius=0.01, travel=0.06)
UPRIGHT = c.Setpoint((1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
LOCAL = ("127.0.0.1", 0)


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def free_port() -> int:
    return free_udp_port(LOCAL[0])


@pytest.fixture
def pair():
    """(clock, board emulator, our device), each accepting only the other."""
    clock = Clock()
    computer_port = free_port()
    emu = BoardEmulator(PARAMS, FOOT, LOCAL, ("127.0.0.1", computer_port), clock)
    board = ArcherBoard(UdpLink(("127.0.0.1", computer_port), emu.link.local, clock), PARAMS)
    try:
        yield clock, emu, board
    finally:
        emu.close()
        board.close()


def settle() -> None:
    """Loopback delivery is asynchronous: give the kernel a moment."""
    time.sleep(0.005)


def test_a_setpoint_is_answered_and_the_state_kept_with_its_time(pair) -> None:
    clock, emu, board = pair
    emu.motors[0].velocity, emu.motors[1].velocity, emu.motors[2].velocity = 1.0, 2.0, 3.0
    board.exchange(clock.t, UPRIGHT)
    settle()
    emu.tick(clock.t)
    settle()
    clock.t += 0.001
    board.exchange(clock.t, UPRIGHT)
    assert board.fresh and board.state_rx_s == clock.t
    assert board.state is not None and board.state.wheel_vel == (1.0, 2.0, 3.0)  # back in joint order
    assert board.state.quat == (1.0, 0.0, 0.0, 0.0) and board.state.foot_contact
    assert (board.stats.replies, board.stats.late, board.stats.missing) == (1, 0, 0)
    assert emu.counts["setpoints"] == 1 and emu.motors_on


def test_late_missing_and_unsolicited_replies_are_counted(pair) -> None:
    clock, emu, board = pair
    board.exchange(clock.t, UPRIGHT)
    settle()
    emu.tick(clock.t)
    settle()
    clock.t += 0.005  # read 5 ms after the request: late
    board.exchange(clock.t, None)
    assert board.stats.late == 1 and board.stats.replies == 1
    board.exchange(clock.t, UPRIGHT)  # the board never reads this one
    clock.t += PARAMS.reply_missing_s + 0.001
    board.exchange(clock.t, None)
    assert board.stats.missing == 1
    settle()
    emu.tick(clock.t)  # the board answers it after all: no request waits any more
    settle()
    board.exchange(clock.t, None)
    assert board.stats.unsolicited == 1


def test_the_computer_watchdog_latches_and_goes_silent(pair) -> None:
    clock, emu, board = pair
    for _ in range(5):  # commanding, the board never answers
        board.exchange(clock.t, UPRIGHT)
        clock.t += 0.03
    assert board.faulted and "no reply" in board.faults[0]
    sent = board.link.tx
    board.exchange(clock.t, UPRIGHT)
    assert board.link.tx == sent  # silence: the board's own watchdog stops the motors
    assert board.recover(clock.t) and not board.faulted
    board.exchange(clock.t, UPRIGHT)
    assert board.link.tx == sent + 1


def test_the_device_refuses_to_send_a_non_finite_setpoint(pair) -> None:
    clock, emu, board = pair
    board.exchange(clock.t, c.Setpoint((1.0, 0.0, 0.0, 0.0), (math.nan, 0.0, 0.0), (0.0, 0.0, 0.0)))
    assert board.stats.refused_setpoints == 1 and board.link.tx == 0


def test_bad_states_and_strangers_are_dropped_at_the_computer() -> None:
    clock = Clock()
    fake_board = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    fake_board.bind(LOCAL)
    stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    stranger.bind(LOCAL)
    board = ArcherBoard(UdpLink(LOCAL, fake_board.getsockname(), clock), PARAMS)
    try:
        good = struct.pack("<13f", 1, 3, 2, 0, 0, 0, 1, 0, 0, 0, 1, 0.01, 0)
        me = board.link.local
        fake_board.sendto(good[:51], me)  # truncated
        fake_board.sendto(good + b"\0", me)  # oversized
        fake_board.sendto(struct.pack("<13f", math.nan, 3, 2, 0, 0, 0, 1, 0, 0, 0, 1, 0.01, 0), me)
        fake_board.sendto(struct.pack("<13f", 1, 3, 2, 0, 0, 0, 0, 0, 0, 0, 1, 0.01, 0), me)  # zero quaternion
        stranger.sendto(good, me)
        settle()
        board.exchange(clock.t, None)
        assert board.state is None and not board.fresh  # nothing applied
        s = board.stats
        assert (s.rejected_length, s.rejected_non_finite, s.rejected_quaternion) == (2, 1, 1)
        assert board.link.foreign == 1 and board.link.rx == 4
        fake_board.sendto(good, me)
        settle()
        board.exchange(clock.t, None)
        assert board.state is not None and board.state.wheel_vel == (1.0, 2.0, 3.0)
    finally:
        board.close()
        fake_board.close()
        stranger.close()


def test_the_board_drops_bad_packets_and_strangers_without_answering() -> None:
    clock = Clock()
    computer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    computer.bind(LOCAL)
    stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    stranger.bind(LOCAL)
    emu = BoardEmulator(PARAMS, FOOT, LOCAL, computer.getsockname(), clock)
    try:
        push = struct.pack("<10f", 1, 0, 0, 0, 0, 0, 0, 0.5, 0, 0)
        board = emu.link.local
        for packet in (push[:39], push + b"\0", struct.pack("<10f", 1, 0, 0, 0, 0, 0, 0, math.inf, 0, 0),
                       struct.pack("<10f", 0, 0, 0, 0, 0, 0, 0, 0.5, 0, 0)):
            computer.sendto(packet, board)
        stranger.sendto(push, board)
        settle()
        emu.tick(clock.t)
        assert emu.setpoint is None and not emu.motors_on and emu.applied == [0.0, 0.0, 0.0, 0.0]
        assert (emu.counts["length"], emu.counts["non_finite"], emu.counts["quaternion"]) == (2, 1, 1)
        assert emu.link.foreign == 1 and emu.counts["replies"] == 0
        computer.setblocking(False)
        stranger.setblocking(False)
        for sock in (computer, stranger):
            with pytest.raises(BlockingIOError):
                sock.recv(4096)
    finally:
        emu.close()
        computer.close()
        stranger.close()


def test_board_pd_torque_current_clamp_and_watchdog() -> None:
    clock = Clock()
    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    peer.bind(LOCAL)
    emu = BoardEmulator(PARAMS, FOOT, LOCAL, peer.getsockname(), clock)
    try:
        tilt = 0.02  # [rad] about body x
        emu.body.quat = quat.exp((tilt, 0.0, 0.0))
        emu.body.gyro = (0.0, 0.1, 0.0)
        peer.sendto(c.pack_setpoint(UPRIGHT), emu.link.local)
        settle()
        emu.tick(clock.t)
        tau = emu.body_torque()
        assert tau[0] == pytest.approx(-PARAMS.kp_tilt * math.sin(tilt / 2), rel=1e-6)  # vector part of the error
        assert tau[1] == pytest.approx(-PARAMS.kd_tilt * 0.1)
        # identity wheel axes: a motor torque t puts -t on the body
        assert emu.applied[0] == pytest.approx(-tau[0]) and emu.applied[1] == pytest.approx(-tau[1])
        emu.body.quat = quat.exp((0.5, 0.0, 0.0))  # far off: the current clamp decides
        clock.t += 0.001
        emu.tick(clock.t)
        assert emu.currents[0] == PARAMS.current_max
        assert emu.applied[0] == pytest.approx(PARAMS.current_max * PARAMS.torque_constant)
        clock.t += PARAMS.watchdog_s - 0.002  # still fed
        emu.tick(clock.t)
        assert emu.motors_on and emu.counts["watchdog_trips"] == 0
        clock.t += 0.003  # 101 ms after the last packet
        emu.tick(clock.t)
        assert not emu.motors_on and emu.applied == [0.0, 0.0, 0.0, 0.0] and emu.counts["watchdog_trips"] == 1
        peer.sendto(c.RESET_PACKET, emu.link.local)
        settle()
        emu.tick(clock.t)
        assert emu.counts["resets"] == 1 and not emu.motors_on
        assert len(peer.recv(4096)) == 52 and len(peer.recv(4096)) == 52  # both packets answered
    finally:
        emu.close()
        peer.close()


def test_foot_board_cycle_flight_compression_thrust() -> None:
    foot = FootBoard(PARAMS, FOOT)
    r = FOOT.spool_radius
    wind = foot.step(True, False, 0.0, 0.0, 0.0, 0.0)
    assert foot.phase == FootPhase.FLIGHT and wind > 0  # winds the preload in
    hold = foot.step(True, False, PARAMS.foot_preload_m, 0.0, PARAMS.foot_preload_m / r, 0.0)
    assert hold == pytest.approx(r * FOOT.spring_k * PARAMS.foot_preload_m)  # holds the spring force
    release = foot.step(True, True, PARAMS.foot_preload_m, 0.3, PARAMS.foot_preload_m / r, 0.0)
    assert foot.phase == FootPhase.COMPRESSION and release < 0  # touchdown: unwind
    foot.step(True, True, 0.05, -0.1, 0.0, 0.0)
    assert foot.phase == FootPhase.THRUST
    foot.step(True, True, 0.04, 0.05, 0.0, 0.0)
    assert foot.phase == FootPhase.THRUST  # a bounce in the stance does not restart it
    foot.step(True, False, 0.0, 0.0, 0.0, 0.0)
    assert foot.phase == FootPhase.FLIGHT and foot.hops == 1
    assert foot.step(False, False, 0.0, 0.0, 1.0, 1.0) == 0.0 and foot.phase == FootPhase.IDLE


def test_the_reader_thread_stamps_replies_as_they_arrive() -> None:
    """A reply read 50 ms after it came is stamped with its arrival: it is not late."""
    params = dataclasses.replace(PARAMS, reply_late_s=0.03)
    computer_port = free_port()
    emu = BoardEmulator(params, FOOT, LOCAL, ("127.0.0.1", computer_port), time.monotonic)
    board = ArcherBoard(UdpLink(("127.0.0.1", computer_port), emu.link.local, time.monotonic), params)
    try:
        board.open()
        board.exchange(time.monotonic(), UPRIGHT)
        settle()
        emu.tick(time.monotonic())
        time.sleep(0.05)
        now = time.monotonic()
        board.exchange(now, None)
        assert board.fresh and now - board.state_rx_s > 0.04
        assert board.stats.late == 0 and board.stats.replies == 1
    finally:
        emu.close()
        board.close()
