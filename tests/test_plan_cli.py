"""``archer plan`` on scene files and ``archer goal`` over a real Zenoh router."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time

import numpy as np
import pytest

from onboard.geometry import bezier as bz
from onboard.high_level.tracking import collision as col
from onboard.geometry import polygons as pg
from onboard.contracts import messages as m
from onboard.contracts.topics import TOPICS
from services.cli.plan import SceneError, parse_scene

WALL_WITH_GAP = [
    [[2.9, 0.0], [3.1, 0.0], [3.1, 3.9], [2.9, 3.9]],
    [[2.9, 5.1], [3.1, 5.1], [3.1, 6.0], [2.9, 6.0]],
]


def _scene(**kw) -> dict:
    scene = {"bounds": [[0, 0], [6, 6]], "obstacles": WALL_WITH_GAP, "start": [1, 1], "goal": [5, 1],
             "nodes": 1500, "seed": 2, "robot_radius": 0.13, "tube": 0.05}
    scene.update(kw)
    return scene


def _archer(args: list[str], tmp_path, stdin: str | None = None) -> subprocess.CompletedProcess:
    env = dict(os.environ, ARCHER_CACHE_DIR=str(tmp_path / "cache"))
    return subprocess.run([sys.executable, "-m", "services.cli.main", *args], input=stdin, capture_output=True, text=True,
                          env=env, timeout=120, cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def test_plan_through_the_gap_and_cache_hit(tmp_path):
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(_scene()))
    run = _archer(["plan", "--input", str(path), "--json"], tmp_path)
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    assert out["found"] and out["nodes"] == 1500 + 41 * 41 and out["lattice_nodes"] == 41 * 41  # 0.15 m rest lattice
    assert out["edges"] > 5000 and not out["graph_cached"]
    assert out["clearance"] == pytest.approx(0.18)
    assert set(out["limits"]) == {"v_max", "a_max", "segment_s"} and out["plan_ms"] > 0
    segs = out["segments"]
    assert segs[0]["control_points"][0] == [1, 1] and segs[-1]["control_points"][-1] == [5, 1]
    t = 0.0
    pts = []
    for s in segs:
        assert s["t0"] == pytest.approx(t)
        t += s["duration"]
        pts.append(bz.evaluate(np.array(s["control_points"]), s["duration"], np.linspace(0, s["duration"], 100)))
    pts = np.concatenate(pts)
    # Densely sampled, the path keeps the clearance and passes the gap (y in [3.9, 5.1] at x = 3).
    clearance = col.samples_clearance(pts[None], pg.pack_polygons(WALL_WITH_GAP), reach=1.0)[0]
    assert clearance > out["clearance"]
    assert 3.9 < pts[np.argmin(np.abs(pts[:, 0] - 3.0)), 1] < 5.1
    again = json.loads(_archer(["plan", "--input", str(path), "--json"], tmp_path).stdout)
    assert again["graph_cached"] and again["segments"] == segs


def test_no_path_exits_1(tmp_path):
    closed = [[[2.9, 0.0], [3.1, 0.0], [3.1, 6.0], [2.9, 6.0]]]
    run = _archer(["plan", "--input", "-", "--json"], tmp_path, stdin=json.dumps(_scene(obstacles=closed)))
    assert run.returncode == 1
    out = json.loads(run.stdout)
    assert out["found"] is False and out["segments"] == []


@pytest.mark.parametrize(
    "change, message",
    [
        ({"obstacles": [[[0, 0], [2, 0], [1, 0.2], [2, 2], [0, 2]]]}, "obstacle 0: polygon is not convex"),
        ({"obstacles": [[[0, 0], [1, 1], [2, 2]]]}, "zero area"),
        ({"obstacles": [[[0, 0], [1, 0], [1, 0], [0, 1]]]}, "repeated vertex"),
        ({"start": [3.0, 1.0]}, "start [3.0, 1.0] is inside obstacle 0"),
        ({"goal": [3.0, 5.5]}, "goal [3.0, 5.5] is inside obstacle 1"),
        ({"start": [7.0, 1.0]}, "outside the bounds"),
        ({"bounds": [[0, 0], [0, 6]]}, "bounds"),
        ({"limits": {"v_max": -1}}, "limits.v_max"),
        ({"limits": {"jerk": 1}}, "limits must be"),
        ({"nodes": 1}, "nodes"),
        ({"tube": "big"}, "tube"),
        ({"colour": "red"}, "unknown scene keys: colour"),
    ],
)
def test_bad_scenes_are_rejected(change, message):
    with pytest.raises(SceneError, match=message.replace("[", r"\[").replace("]", r"\]")):
        parse_scene(json.dumps(_scene(**change)))


def test_bad_scene_exit_code_2(tmp_path):
    nan_scene = json.dumps(_scene()).replace('"start": [1, 1]', '"start": [NaN, 1]')
    run = _archer(["plan", "--input", "-", "--json"], tmp_path, stdin=nan_scene)
    assert run.returncode == 2 and "non-finite" in run.stderr and run.stdout == ""
    run = _archer(["plan", "--input", "-"], tmp_path, stdin='{"bounds": ')
    assert run.returncode == 2 and "not valid JSON" in run.stderr
    run = _archer(["plan", "--input", str(tmp_path / "missing.json")], tmp_path)
    assert run.returncode == 2 and "cannot read" in run.stderr
    missing = {k: v for k, v in _scene().items() if k != "goal"}
    run = _archer(["plan", "--input", "-"], tmp_path, stdin=json.dumps(missing))
    assert run.returncode == 2 and "lacks: goal" in run.stderr


def test_goal_command_reaches_a_subscriber(zenoh_router, zenoh_session, tmp_path):
    ns = "archer/goal-test"
    got: list[m.Goal] = []
    sub = zenoh_session.declare_subscriber(TOPICS["goal"].key(ns), lambda s: got.append(m.decode(s.payload.to_bytes(), m.Goal)))
    try:
        run = _archer(["goal", "2.5", "-1.0", "--tolerance", "0.2", "--endpoint", zenoh_router, "--namespace", ns], tmp_path)
        assert run.returncode == 0, run.stderr
        deadline = time.monotonic() + 5
        while not got and time.monotonic() < deadline:
            time.sleep(0.02)
        assert got and got[0].position == [2.5, -1.0] and got[0].tolerance == 0.2
    finally:
        sub.undeclare()
    run = _archer(["goal", "nan", "1", "--endpoint", zenoh_router], tmp_path)
    assert run.returncode == 2
    lonely = _archer(["goal", "1", "1", "--endpoint", zenoh_router, "--namespace", "archer/nobody", "--wait", "0.3"], tmp_path)
    assert lonely.returncode == 1 and "nothing subscribes" in lonely.stderr
    assert not math.isnan(got[0].position[0])


# real time: loops at their rate, processes and Zenoh over loopback share two loaded cores
pytestmark = pytest.mark.timing_sensitive(reason="real-time loops, processes or Zenoh over loopback on a shared host")
