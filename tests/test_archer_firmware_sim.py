"""``archer sim --mode realtime --hardware archer-firmware``: the whole stack on the emulated ARCHER
boards (UDP) and the OptiTrack stream (NatNet), one twin behind both, for a few seconds."""

from __future__ import annotations

import pytest

import json
import os
import signal
import subprocess
import sys
import uuid

from services.runtime.zenoh_session import free_endpoint
from helpers import check_service_failures, judge_realtime_outcome
from test_twin_cli import REQUIRED

DURATION_S = 6.0
TIMEOUT_S = 40.0  # service start-up (controller build, planner-free) + the run + the stop, on a loaded machine


def test_the_stack_hops_in_place_on_the_emulated_boards_and_mocap() -> None:
    argv = [sys.executable, "-m", "services.cli.main", "sim", "--mode", "realtime", "--hardware", "archer-firmware",
            "--scenario", "hop-in-place", "--duration", str(DURATION_S), "--json", "--quiet",
            "--endpoint", free_endpoint(), "--namespace", f"archer/fw{uuid.uuid4().hex[:8]}"]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=TIMEOUT_S)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 0, err[-3000:]
    m = json.loads(out.strip().splitlines()[-1])
    for key in REQUIRED:  # the same physics metrics as any realtime run
        assert key in m, key
    assert m["hardware"] == "archer-firmware"
    # the stack is up and stayed up: hardware and mocap in place of the twin's topics
    assert m["services_started"] == ["control", "estimator", "hardware", "mocap", "router", "scenario_reference"]
    check_service_failures(m)
    board = m["board"]
    assert board["setpoints"] > 0 and board["replies"] >= board["setpoints"]  # the control loop commanded it
    assert board["length"] == board["non_finite"] == board["quaternion"] == board["udp_foreign"] == 0
    assert m["natnet"]["frames"] > 0
    # a fresh-clone CI run here simulated 4.0 s of the 6
    judge_realtime_outcome(m, {k: m[k] for k in ("sim_time_s", "falls", "hops")} | {"setpoints": board["setpoints"]})
    # it hops, driven through the board's PD and the foot board's cycle, and does not fall
    assert m["falls"] == 0
    assert m["hops"] >= 5, m["hops"]
    assert board["setpoints"] > 1000  # the control loop at its rate
    assert m["natnet"]["frames"] > 50 * DURATION_S  # the pose went out at the mocap rate


# real time: loops at their rate, processes and Zenoh over loopback share two loaded cores
pytestmark = pytest.mark.timing_sensitive(reason="real-time loops, processes or Zenoh over loopback on a shared host")
