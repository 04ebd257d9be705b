"""`archer plot` on a recording written by the recorder's own file writer."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from onboard.contracts import messages as m
from onboard.contracts.params import RecorderParams
from onboard.contracts.topics import TOPICS, status_key
from services.cli.plot import topic_name
from services.recorder import RotatingMcap, _json_schema, schema_for

NS = "archer/plottest"
MS = 1_000_000
OFFSET_M = 0.05  # the CoM runs this far beside the reference
SPEED = 0.2  # [m/s]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _state(t_ns: int, seq: int) -> m.StateEstimate:
    x = SPEED * t_ns / 1e9
    return m.StateEstimate(
        stamp_ns=t_ns, seq=seq, position=[x, OFFSET_M, 0.4], velocity=[SPEED, 0.0, 0.0], quat=[1.0, 0.0, 0.0, 0.0],
        omega=[0.0, 0.0, 0.0], wheel_vel=[10.0, -5.0, 1.0], foot_pos=0.0, foot_vel=0.0, contact=False, phase="flight",
        pos_vel_cov=[0.0] * 36, att_cov=[0.0, 0.0, 0.0],
    )


def write_recording(directory: Path) -> None:
    """Three seconds of a robot tracking a straight reference 5 cm off, at 100 Hz."""
    files = RotatingMcap(directory, RecorderParams(chunk_bytes=100_000))  # rotates by size
    ref = m.ComReference(stamp_ns=1, t_ref_ns=0, segments=[m.BezierSegment(t0=0.0, duration=10.0, control_points=[[0.0, 0.0], [SPEED * 10, 0.0]])])

    def put(topic: str, msg: m.Message) -> None:
        t = max(msg.stamp_ns, 0)  # MCAP times are unsigned (the recorder substitutes the arrival time)
        files.write(TOPICS[topic].key(NS), schema_for(TOPICS[topic]), t, t, msg.seq, m.encode(msg))

    put("reference", ref)
    put("state", _state(-1, 0))  # an estimate before any sensor data: no time of its own
    put("goal", m.Goal(stamp_ns=1, seq=1, position=[2.0, 0.0]))
    square = m.Polytope(A=[[1, 0], [-1, 0], [0, 1], [0, -1]], b=[1.2, -1.0, 0.5, -0.3], vertices=[[1.0, 0.3], [1.2, 0.3], [1.2, 0.5], [1.0, 0.5]])
    put("polytopes", m.PolytopeSet(stamp_ns=1, seq=1, mode="obstacles", polytopes=[square]))
    for i in range(300):
        t = (i + 1) * 10 * MS
        put("state", _state(t, i + 1))
        put("torque_cmd", m.TorqueCommand(stamp_ns=t, seq=i + 1, wheel_torque=[0.1, 0.0, -0.1], foot_torque=1.0, armed=i >= 10))
        if i % 50 == 0:
            status = m.ServiceStatus(stamp_ns=t, service="control", state="running", uptime_s=t / 1e9, rates_hz={}, counters={},
                                     extra={"loop_period_jitter_us_p99": 40.0, "loop_tick_us_p99": 120.0, "loop_overruns": 0.0})
            files.write(status_key(NS, "control"), _json_schema(m.ServiceStatus), t, t, 0, m.encode(status))
        files.tick(dict)
    files.finish({})


def test_channel_keys_map_to_topics_in_any_namespace():
    assert topic_name("archer/robot7/state/estimate") == "state"
    assert topic_name("archer/robot7/svc/control/status") == "status:control"
    assert topic_name("elsewhere/x") is None


def test_archer_plot_writes_pngs_and_figures(tmp_path):
    rec = tmp_path / "rec"
    write_recording(rec)
    assert len(list(rec.glob("*.mcap"))) >= 2  # rotated: the plot reads the directory
    out = tmp_path / "plots"
    result = subprocess.run([sys.executable, "-m", "services.cli.main", "plot", str(rec), "--out", str(out)], capture_output=True, text=True, check=True)
    summary = json.loads(result.stdout.strip().splitlines()[-1])
    names = {"path.png", "tracking.png", "attitude.png", "wheels.png", "torques.png", "timing.png"}
    assert {Path(p).name for p in summary["plots"]} == names
    for name in names:
        data = (out / name).read_bytes()
        assert data.startswith(PNG_MAGIC) and len(data) > 10_000
    assert summary["skipped"] == {"unstamped state": 1}
    assert summary["messages"]["state"] == 300 and summary["messages"]["status:control"] == 6
    assert summary["tracking_error_m"]["p50"] == pytest.approx(OFFSET_M, abs=1e-9)
    assert summary["tracking_error_m"]["max"] == pytest.approx(OFFSET_M, abs=1e-9)
    assert summary["timing"]["state"]["period_ms_p50"] == pytest.approx(10.0)
    assert summary["timing"]["control_loop"]["period_jitter_us_p99"] == 40.0
    assert summary["torque_cmd_disarmed_fraction"] == pytest.approx(10 / 300, abs=1e-4)
    assert summary["polytopes"] == {"mode": "obstacles", "count": 1}
    assert json.loads((out / "summary.json").read_text())["duration_s"] == pytest.approx(2.99)


def test_a_recording_without_state_is_a_clear_error(tmp_path):
    files = RotatingMcap(tmp_path, RecorderParams())
    files.write(TOPICS["goal"].key(NS), schema_for(TOPICS["goal"]), 1, 1, 1, m.encode(m.Goal(stamp_ns=1, position=[1.0, 0.0])))
    files.finish({})
    result = subprocess.run([sys.executable, "-m", "services.cli.main", "plot", str(tmp_path)], capture_output=True, text=True)
    assert result.returncode == 2 and "no state estimates" in result.stderr
