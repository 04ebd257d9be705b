"""Closed loop through UDP: our driver sends the upright attitude, the emulated board's PD holds the twin.

``archer emulate archer-firmware --twin hop-in-place`` runs in its own process on its
own clock (no lockstep): the PD, the current clamp and the foot board's hop cycle act
on the MuJoCo twin, and all the test sees is the board's replies.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import tempfile
import time

import pytest

from drivers.archer_firmware import codec as c
from drivers.archer_firmware.device import ArcherBoard
from drivers.archer_firmware.transport import UdpLink
from onboard.geometry import quaternion as quat
from onboard.contracts.params import ArcherFirmwareParams

UPRIGHT = c.Setpoint((1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
HOLD_S = 4.0
PERIOD_S = 0.002  # the computer's rate here: 500 Hz, the board runs its PD at 1 kHz regardless
STARTUP_S = 60.0  # MuJoCo import and model compile on a loaded machine


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def fly(config: str | None = None) -> tuple[list[c.BoardState], ArcherBoard, dict[str, float]]:
    """Send the upright setpoint for HOLD_S; the states seen, the device, the emulator's counters."""
    params = ArcherFirmwareParams()
    computer_port = free_port()
    cmd = [sys.executable, "-m", "services.cli.main", "emulate", "archer-firmware", "--twin", "hop-in-place", "--peer-port", str(computer_port)]
    if config is not None:
        cmd += ["--config", config]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    states: list[c.BoardState] = []
    board = None
    try:
        info = json.loads(proc.stdout.readline())
        assert info["twin"] is True
        board = ArcherBoard(UdpLink(("127.0.0.1", computer_port), (info["host"], info["port"]), time.monotonic), params)
        board.open()
        end = time.monotonic() + HOLD_S
        while time.monotonic() < end:
            board.exchange(time.monotonic(), UPRIGHT)
            if board.fresh:
                states.append(board.state)
            time.sleep(PERIOD_S)
    finally:
        if board is not None:
            board.close()
        proc.terminate()
        _, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err
    return states, board, json.loads(err.strip().splitlines()[-1])["final"]


def test_the_board_pd_holds_the_hopping_twin_upright() -> None:
    states, board, final = fly()
    assert not board.faults
    assert len(states) > 0.5 * HOLD_S / PERIOD_S  # most requests answered on a shared machine
    tilts = [quat.tilt(s.quat) for s in states]
    assert max(tilts) < 0.15, max(tilts)  # [rad]; a fall is 45 degrees
    touchdowns = sum(1 for a, b in zip(states, states[1:]) if b.foot_contact and not a.foot_contact)
    assert touchdowns >= 4  # the foot board hops by itself
    assert final["hops"] >= 4
    # (a stall of this process beyond 100 ms on a shared machine trips the board's watchdog:
    # the motors stop and come back with the next setpoint, which this test survives)


@pytest.mark.parametrize("gains", ["kp_tilt = 0.0\nkd_tilt = 0.0\n"])
def test_without_the_pd_the_hopping_twin_falls(gains: str) -> None:
    """The control for the test above: the same run with the board's tilt gains zeroed."""
    fd, path = tempfile.mkstemp(suffix=".toml")
    try:
        with os.fdopen(fd, "w") as f:
            f.write("[archer_firmware]\n" + gains)
        states, _board, _final = fly(path)
    finally:
        os.unlink(path)
    assert max(quat.tilt(s.quat) for s in states) > 0.3


# real time: loops at their rate, processes and Zenoh over loopback share two loaded cores
pytestmark = pytest.mark.timing_sensitive(reason="real-time loops, processes or Zenoh over loopback on a shared host")
