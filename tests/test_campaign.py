"""``archer campaign``: sweep expansion, records, resume, failures, the local pool, Ray."""

from __future__ import annotations

import functools
import importlib.util
import json
import operator
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from services.cli import campaign as cp
from services.cli.campaign_pool import LocalPool
from services.cli.campaign_report import PLOT_PNG, SUMMARY_JSON, SUMMARY_TXT, summarize, table, wilson_interval
from services.cli.main import main

WALL_CLOCK_FIELDS = {"wall_time_s", "realtime_factor", "tick_us_mean"}  # the only report fields a rerun may change
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
TINY = ["--scenario", "hop-in-place", "--seeds", "0-1", "--option", "duration=0.4", "--workers", "2", "--quiet"]
DIE_WITH_PARENT_S = 20.0  # [s] for the workers to start a run; for the kernel to take them down after their parent


def _runs(folder: Path) -> list[dict]:
    return [json.loads(line) for line in (folder / cp.RUNS_FILE).read_text().splitlines()]


def _deterministic(report: dict) -> dict:
    return {k: v for k, v in report.items() if k not in WALL_CLOCK_FIELDS}


def test_seeds_options_and_expansion() -> None:
    assert cp.parse_seeds("0-3,7,2") == [0, 1, 2, 3, 7]
    with pytest.raises(ValueError):
        cp.parse_seeds("5-2")
    axes = cp.parse_options(["perception=truth,depth", "duration=2.5", "no-noise=true"])
    assert axes == {"perception": ["truth", "depth"], "duration": [2.5], "no-noise": [True]}
    with pytest.raises(ValueError, match="campaign sets only"):
        cp.parse_options(["mode=realtime"])
    specs = cp.expand(["forest", "maze"], [0, 1, 2], ["indoor"], axes)
    assert len(specs) == 2 * 3 * 2
    assert len({cp.spec_key(s) for s in specs}) == len(specs)
    assert cp.spec_key({"seed": 1, "scenario": "a", "options": {"b": 1, "a": 2}, "variant": "v"}) == \
        cp.spec_key({"scenario": "a", "variant": "v", "options": {"a": 2, "b": 1}, "seed": 1})
    assert cp.sim_argv(specs[-1]) == ["--scenario", "maze", "--seed", "2", "--variant", "indoor", "--quiet", "--json",
                                      "--duration", "2.5", "--no-noise", "--perception", "depth"]
    assert "--keep-going" not in cp.sim_argv({**specs[0], "options": {"keep-going": False}})


def test_wilson_interval() -> None:
    low, high = wilson_interval(0, 10)
    assert low == 0.0 and high == pytest.approx(0.2775, abs=1e-4)  # z^2 / (n + z^2)
    assert wilson_interval(5, 10) == pytest.approx((0.2366, 0.7634), abs=1e-4)
    assert wilson_interval(10, 10)[1] == pytest.approx(1.0) and wilson_interval(0, 0) == (0.0, 1.0)


def test_campaign_records_resumes_and_keeps_failures(tmp_path, capsys) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[estimator]\nno_such_parameter = 1\n")
    out = tmp_path / "c"
    (tmp_path / "ok.toml").write_text("")
    rc = main(["campaign", *TINY, "--out", str(out), "--option", f"config={tmp_path / 'ok.toml'},{bad}", "--json"])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    runs = _runs(out)
    assert len(runs) == 4 and summary["runs"] == 4 and summary["errors"] == 2
    failed = [r for r in runs if "error" in r]
    assert {r["spec"]["options"]["config"] for r in failed} == {str(bad)}
    assert all("no_such_parameter" in r["error"] and "Traceback" in r["traceback"] for r in failed)
    good = [r for r in runs if "report" in r]
    assert {r["spec"]["seed"] for r in good} == {0, 1}
    ok_group, bad_group = summary["groups"]  # in the order of the sweep
    assert f"config={bad} " in bad_group["group"] and bad_group["successes"] == 0 and bad_group["errors"] == 2
    assert ok_group["runs"] == 2 and ok_group["errors"] == 0
    assert (out / PLOT_PNG).read_bytes()[:8] == PNG_MAGIC
    assert json.loads((out / SUMMARY_JSON).read_text())["runs"] == 4 and "95% CI" in (out / SUMMARY_TXT).read_text()

    # the same function as archer sim: its report, wall-clock figures aside
    spec = good[0]["spec"]
    assert main(["sim", *cp.sim_argv(spec)]) == 0
    assert _deterministic(json.loads(capsys.readouterr().out.strip().splitlines()[-1])) == _deterministic(good[0]["report"])

    # resumed: nothing finished runs again; with --retry-errors only the failures do
    assert main(["campaign", *TINY, "--out", str(out), "--option", f"config={tmp_path / 'ok.toml'},{bad}"]) == 0
    assert len(_runs(out)) == 4
    assert main(["campaign", *TINY, "--out", str(out), "--option", f"config={tmp_path / 'ok.toml'},{bad}", "--retry-errors"]) == 0
    rerun = _runs(out)[4:]
    assert len(rerun) == 2 and all(r["spec"]["options"]["config"] == str(bad) for r in rerun)


def test_pool_records_a_dead_worker_and_goes_on() -> None:
    jobs = [functools.partial(abs, -1), functools.partial(os._exit, 7), functools.partial(abs, -3), functools.partial(abs, -4)]
    with LocalPool(2) as pool:
        results = list(pool.map_unordered(operator.call, jobs, lambda job, reason: ("crashed", job.args[0], reason)))
        workers = [w.process for w in pool._live]
    crashed = [r for r in results if isinstance(r, tuple)]
    assert sorted(r for r in results if not isinstance(r, tuple)) == [1, 3, 4]
    assert len(crashed) == 1 and crashed[0][1] == 7 and "exit code 7" in crashed[0][2]
    assert len(workers) == 2 and not any(p.is_alive() for p in workers)


def _children(pid: int) -> list[int]:
    path = Path(f"/proc/{pid}/task/{pid}/children")
    return [int(c) for c in path.read_text().split()] if path.exists() else []


def test_workers_die_with_the_campaign(tmp_path) -> None:
    proc = subprocess.Popen([sys.executable, "-m", "services.cli.main", "campaign", "--scenario", "hop-in-place", "--seeds", "0-9",
                             "--option", "duration=30", "--workers", "2", "--quiet", "--out", str(tmp_path)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    workers: list[int] = []
    try:
        deadline = time.monotonic() + DIE_WITH_PARENT_S
        while time.monotonic() < deadline:  # both workers inside a run (MuJoCo loaded): only the kernel can stop them now
            workers = [c for c in _children(proc.pid) if "spawn_main" in _cmdline(c)]
            if len(workers) == 2 and all(_maps_mujoco(w) for w in workers):
                break
            time.sleep(0.1)
        assert len(workers) == 2 and all(_maps_mujoco(w) for w in workers)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        deadline = time.monotonic() + DIE_WITH_PARENT_S
        while time.monotonic() < deadline and any(_alive(w) for w in workers):
            time.sleep(0.1)
        assert not any(_alive(w) for w in workers)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for w in workers:
            if _alive(w):
                os.kill(w, signal.SIGKILL)


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


def _maps_mujoco(pid: int) -> bool:
    try:
        return "mujoco" in Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return False


def _alive(pid: int) -> bool:
    """Running (a zombie whose parent is gone is reaped by init, but may linger a moment: it counts as gone)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0] != "Z"
    except (OSError, IndexError):
        return False


@pytest.mark.skipif(importlib.util.find_spec("ray") is None, reason="Ray is the optional extra .[cluster]")
def test_ray_gives_the_local_pool_results(tmp_path) -> None:
    """Not importorskip: imported before the campaign, Ray would fix its node address off loopback."""
    local, ray = tmp_path / "local", tmp_path / "ray"
    assert main(["campaign", *TINY, "--out", str(local)]) == 0
    assert main(["campaign", *TINY, "--out", str(ray), "--ray", "local"]) == 0
    by_key = {r["key"]: r for r in _runs(local)}
    ray_runs = _runs(ray)
    assert len(ray_runs) == len(by_key) == 2
    for r in ray_runs:
        assert _deterministic(r["report"]) == _deterministic(by_key[r["key"]]["report"])


# real time: loops at their rate, processes and Zenoh over loopback share two loaded cores
pytestmark = pytest.mark.timing_sensitive(reason="real-time loops, processes or Zenoh over loopback on a shared host")


def test_onboard_sensing_campaigns_report_the_drift(tmp_path, capsys) -> None:
    """Without motion capture the summary holds the estimate's drift (final, and per metre once a run has
    gone somewhere); with motion capture it holds none."""
    out = tmp_path / "c"
    rc = main(["campaign", "--scenario", "hop-in-place", "--seeds", "0", "--variant", "outdoor", "--option", "duration=1.5",
               "--option", "estimator=kalman", "--option", "sensing=mocap,onboard", "--workers", "1", "--quiet",
               "--out", str(out), "--json"])
    assert rc == 0
    mocap, onboard = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["groups"]
    assert "drift_per_m" not in mocap and "sensing=onboard" in onboard["group"]
    assert onboard["final_drift_m"]["p50"] is not None and "drift_per_m" in onboard
    assert "drift per metre" in (out / SUMMARY_TXT).read_text()


def test_the_summary_counts_the_robots_collisions_soon_after_it_was_hit() -> None:
    """Robot-caused contacts within the reported window after an obstacle came at it are counted apart
    (knocked, then falling into one), and still counted among the robot's."""
    def record(seed: int, events: list[dict]) -> dict:
        report = {"goal_reached": not events, "collisions": len(events), "falls": 0, "final_goal_error_m": 0.01,
                  "rms_tracking_error_m": 0.02, "realtime_factor": 5.0, "sim_time_s": 10.0,
                  "collisions_by_robot": sum(e["by"] == "robot" for e in events),
                  "collisions_by_obstacle": sum(e["by"] == "obstacle" for e in events), "collision_events": events}
        return {"spec": {"scenario": "sliding", "seed": seed, "variant": "indoor", "options": {}}, "report": report}

    knocked = [{"t_s": 4.0, "by": "obstacle", "tilt_deg": 2.0, "since_hit_s": None},
               {"t_s": 4.6, "by": "robot", "tilt_deg": 31.0, "since_hit_s": 0.6}]
    walked = [{"t_s": 9.0, "by": "robot", "tilt_deg": 3.0, "since_hit_s": None}]
    summary = summarize([record(0, knocked), record(1, walked), record(2, [])])
    (group,) = summary["groups"]
    assert "collisions by the robot 2 (1 soon after it was hit), by an obstacle 1" in table(summary)
    assert group["collisions"] == 3 and group["collisions_by_robot"] == 2 and group["collisions_by_obstacle"] == 1
    assert group["collisions_by_robot_after_hit"] == 1 and group["successes"] == 1


def test_the_summary_pools_the_segmenters_iou_over_every_apex_view() -> None:
    """The group's IoU is the pixels' (intersections over unions, summed over runs), not the runs' mean:
    a run with many views weighs more; a run that saw no view adds nothing to the per-run spread."""
    def record(seed: int, intersection: int, union: int, views: int) -> dict:
        report = {"goal_reached": True, "collisions": 0, "falls": 0, "final_goal_error_m": 0.01,
                  "rms_tracking_error_m": 0.02, "realtime_factor": 5.0, "sim_time_s": 10.0,
                  "segmentation": {"segmenter": "color", "iou": intersection / union if union else 0.0, "views": views,
                                   "intersection": intersection, "union": union}}
        return {"spec": {"scenario": "sidewalk", "seed": seed, "variant": "outdoor", "options": {"sensing": "onboard"}},
                "report": report}

    summary = summarize([record(0, 900, 1000, 30), record(1, 50, 100, 3), record(2, 0, 0, 0)])
    (group,) = summary["groups"]
    assert group["segmentation_iou"] == round(950 / 1100, 4) and group["segmentation_views"] == 33
    assert group["segmentation_iou_per_run"]["max"] == 0.9 and group["segmentation_iou_per_run"]["p50"] == 0.7
    assert "segmentation IoU 0.864 over 33 apex views" in table(summary)
    mocap = record(3, 0, 0, 0)
    del mocap["report"]["segmentation"]  # with motion capture no segmenter runs
    assert "segmentation_iou" not in summarize([mocap])["groups"][0]


def test_the_summary_spreads_the_time_to_goal_of_the_runs_that_got_there() -> None:
    """A scenario with a goal reports when the robot first came within its tolerance; a run that never
    did reports None and is left out of the spread, not counted as zero."""
    def record(seed: int, time_to_goal: float | None) -> dict:
        report = {"goal_reached": time_to_goal is not None, "collisions": 0, "falls": 0, "final_goal_error_m": 0.01,
                  "rms_tracking_error_m": 0.02, "realtime_factor": 5.0, "sim_time_s": 100.0, "time_to_goal_s": time_to_goal}
        return {"spec": {"scenario": "sidewalk", "seed": seed, "variant": "outdoor", "options": {}}, "report": report}

    summary = summarize([record(0, 40.0), record(1, 60.0), record(2, None)])
    (group,) = summary["groups"]
    assert group["time_to_goal_s"]["p50"] == 50.0 and group["time_to_goal_s"]["max"] == 60.0
    assert "time to goal p50/p90/max 50.0/58.0/60.0 s" in table(summary)
    hop = record(3, None)
    del hop["report"]["time_to_goal_s"]  # hopping in place has no goal to go to
    assert "time_to_goal_s" not in summarize([hop])["groups"][0]


def test_a_run_that_hopped_on_the_grass_is_no_success() -> None:
    """The grass beside a sidewalk has no geom to collide with: a run that reached its goal with a
    touchdown on it is counted among the runs on kept-off ground, and not as a success."""
    def record(seed: int, on_grass: int) -> dict:
        report = {"goal_reached": True, "collisions": 0, "falls": 0, "final_goal_error_m": 0.01,
                  "rms_tracking_error_m": 0.02, "realtime_factor": 5.0, "sim_time_s": 60.0,
                  "keep_out_touchdowns": on_grass}
        return {"spec": {"scenario": "sidewalk", "seed": seed, "variant": "outdoor", "options": {}}, "report": report}

    summary = summarize([record(0, 0), record(1, 3), record(2, 0)])
    (group,) = summary["groups"]
    assert group["successes"] == 2 and group["runs_on_keep_out"] == 1 and group["keep_out_touchdowns"] == 3
    assert "1 runs touched down on ground kept off (3 touchdowns)" in table(summary)
    forest = record(3, 0)
    del forest["report"]["keep_out_touchdowns"]  # nothing kept off in the forest
    assert "runs_on_keep_out" not in summarize([forest])["groups"][0]
