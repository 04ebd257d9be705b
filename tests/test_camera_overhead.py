"""The overhead camera (issue 28): the twin's rendered overhead view calibrated by its ArUco markers,
obstacles segmented into convex floor polygons and tracked with velocity and covariance, on frames
straight from the renderer and through a recorded video file read by ``cv2.VideoCapture``."""

from __future__ import annotations

import math

import cv2
import mujoco
import numpy as np
import pytest

from drivers.camera_overhead import tracking as tk
from drivers.camera_overhead.calibration import CalibrationError, FloorCalibration
from drivers.camera_overhead.device import CameraError, VideoSource
from sim_twin import model as tm
from sim_twin import overhead_camera as oc
from sim_twin import scenarios as sc


LENS = oc.default_camera().lens  # the twin's camera, in the one lens model the driver calibrates with
MARKERS = oc.default_markers()


def _scene(name: str, seed: int):
    scn = sc.make(name, seed=seed)
    spec = tm.load_spec()
    scn.build(spec)
    model = spec.compile()
    return scn, model, mujoco.MjData(model)


@pytest.fixture(scope="module")
def renderer() -> oc.OverheadRenderer:
    return oc.OverheadRenderer(oc.default_camera(), oc.default_markers(), seed=3)


def test_calibration_on_the_twins_frames_has_sub_pixel_error(renderer: oc.OverheadRenderer) -> None:
    for seed in range(3):
        scn, _, _ = _scene("kicked", seed)
        frame = renderer.render(scn, (0.0, 0.0))
        cal = FloorCalibration.from_frame(frame, MARKERS, LENS)
        assert cal.markers_used == tuple(range(len(renderer.markers)))
        assert cal.rms_px < 1.0 and cal.rms_m < 0.01
        # the floor under the camera maps where it is
        probe = np.array([[1.0, 0.5, 0.0], [5.0, -1.5, 0.0]])
        px = renderer.camera.project(probe, distorted=True)
        assert np.allclose(cal.image_to_floor(px), probe[:, :2], atol=0.02)


def test_calibration_refuses_a_frame_without_markers() -> None:
    bare = oc.OverheadRenderer(oc.default_camera(), [], seed=1)
    scn, _, _ = _scene("forest", 0)
    with pytest.raises(CalibrationError):
        FloorCalibration.from_frame(bare.render(scn), MARKERS, LENS)


def _matches(scn: sc.Scenario, polys: list[np.ndarray]) -> None:
    """Every obstacle's footprint lies inside one detected polygon (a silhouette holds its footprint)."""
    assert len(polys) == len(scn.obstacles)
    for k, ob in enumerate(scn.obstacles):
        foot = np.array(ob.vertices) + scn.offsets[k]
        c = foot.mean(axis=0)
        best = min(polys, key=lambda p: math.dist(tk.centroid(p), c))
        assert math.dist(tk.centroid(best), c) < 0.1
        contour = best.astype(np.float32).reshape(-1, 1, 2)
        for v in foot:
            assert cv2.pointPolygonTest(contour, (float(v[0]), float(v[1])), True) > -0.03


def test_obstacles_segment_into_convex_floor_polygons_holding_their_footprints(renderer: oc.OverheadRenderer) -> None:
    for seed in range(3):
        scn, _, _ = _scene("forest", seed)
        frame = renderer.render(scn, (0.0, 0.0))
        cal = FloorCalibration.from_frame(frame, MARKERS, LENS)
        polys = [tk.floor_polygon(b, cal, height=sc.OBSTACLE_HEIGHT) for b in tk.segment(frame, tk.ColourRange())]
        _matches(scn, polys)
        for p in polys:  # convex, counter-clockwise
            e = np.roll(p, -1, axis=0) - p
            assert np.all(e[:, 0] * np.roll(e[:, 1], -1) - e[:, 1] * np.roll(e[:, 0], -1) >= -1e-9)


def test_tracks_give_the_sliding_obstacles_velocity_and_covariance(renderer: oc.OverheadRenderer) -> None:
    scn, model, data = _scene("sliding", 2)
    rate = 4.0
    tracker = tk.Tracker()
    cal = None
    tracks: list[tk.Track] = []
    for i in range(16):  # 4 s at 4 Hz
        t = i / rate
        scn.before_step(t, model, data)
        frame = renderer.render(scn)
        cal = cal or FloorCalibration.from_frame(frame, MARKERS, LENS)
        tracks = tracker.update(t, [tk.floor_polygon(b, cal, height=sc.OBSTACLE_HEIGHT) for b in tk.segment(frame, tk.ColourRange())])
    assert len(tracks) == len(scn.obstacles)
    errors = []
    for k, ob in enumerate(scn.obstacles):
        c = np.array(ob.vertices).mean(axis=0) + scn.offsets[k]
        tr = min(tracks, key=lambda tr: math.dist(tr.x[:2], c))
        errors.append(math.dist(tr.velocity, scn.velocities[k]))
        cov = np.array(tr.position_cov).reshape(2, 2)
        assert np.all(np.linalg.eigvalsh(cov) > 0) and np.trace(cov) < 0.01
    # a slide turns at its ends (the filter lags a turn by a frame or two): most are within 0.08 m/s
    assert np.median(errors) < 0.08, errors


def test_a_recorded_video_goes_through_the_same_capture_path(renderer: oc.OverheadRenderer, tmp_path) -> None:
    scn, model, data = _scene("kicked", 4)
    path = str(tmp_path / "overhead.avi")
    cam = renderer.camera
    writer = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"MJPG"), 4.0, (cam.width, cam.height))
    assert writer.isOpened()
    raw = []
    for i in range(6):
        scn.before_step(i * 0.25, model, data)
        frame = renderer.render(scn)
        raw.append(frame)
        writer.write(frame)
    writer.release()
    with VideoSource(path) as src:
        frames = []
        while (f := src.read()) is not None:
            frames.append(f)
    assert len(frames) == len(raw) and frames[0].shape == raw[0].shape
    cal = FloorCalibration.from_frame(frames[0], MARKERS, LENS)
    assert cal.rms_px < 1.5  # JPEG-compressed frames
    polys = [tk.floor_polygon(b, cal, height=sc.OBSTACLE_HEIGHT) for b in tk.segment(frames[-1], tk.ColourRange())]
    _matches(scn, polys)
    with pytest.raises(CameraError):
        VideoSource(str(tmp_path / "missing.avi"))


def _record(path: str, renderer: oc.OverheadRenderer, name: str, seed: int, frames: int, rate: float) -> sc.Scenario:
    scn, model, data = _scene(name, seed)
    cam = renderer.camera
    writer = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"MJPG"), rate, (cam.width, cam.height))
    for i in range(frames):
        scn.before_step(i / rate, model, data)
        writer.write(renderer.render(scn))
    writer.release()
    return scn


def test_obstacles_init_lists_and_names_what_it_sees(renderer: oc.OverheadRenderer, tmp_path) -> None:
    import json
    import subprocess
    import sys

    video = str(tmp_path / "floor.avi")
    scn = _record(video, renderer, "forest", 1, 2, 4.0)
    archer = [sys.executable, "-m", "services.cli.main", "obstacles"]
    cal = subprocess.run([*archer, "calibrate", "--source", video, "--json"], capture_output=True, text=True, timeout=120)
    assert cal.returncode == 0, cal.stderr
    assert json.loads(cal.stdout)["rms_px"] < 1.5
    names = tmp_path / "names.json"
    got = subprocess.run([*archer, "init", "--source", video, "--name", "0=chair", "--name", "2=box", "--out", str(names), "--json"],
                         capture_output=True, text=True, timeout=120)
    assert got.returncode == 0, got.stderr
    listed = json.loads(got.stdout)
    assert len(listed["obstacles"]) == len(scn.obstacles)
    assert [o["name"] for o in json.loads(names.read_text())["obstacles"]] == ["chair", "box"]
    bad = subprocess.run([*archer, "init", "--source", video, "--name", "99=ghost", "--json"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "no obstacle" in bad.stderr
    missing = subprocess.run([*archer, "calibrate", "--source", str(tmp_path / "none.avi")], capture_output=True, text=True, timeout=120)
    assert missing.returncode == 2 and "cannot open" in missing.stderr


def test_camera_service_publishes_tracked_obstacles_from_a_video_file(renderer: oc.OverheadRenderer, zenoh_router, tmp_path) -> None:
    import asyncio
    import json
    import time

    from onboard.contracts import messages as m
    from onboard.contracts.params import CameraOverheadParams
    from onboard.contracts.topics import TOPICS
    from services.camera_overhead import CameraOverheadService
    from services.runtime.zenoh_session import open_session

    ns = "archer/test-camera"
    video = str(tmp_path / "sliding.avi")
    rate = 8.0
    scn = _record(video, renderer, "sliding", 2, 24, rate)
    first = tk.floor_polygon(tk.segment(cv2.VideoCapture(video).read()[1], tk.ColourRange())[0],
                             FloorCalibration.from_frame(renderer.render(scn), MARKERS, LENS), height=sc.OBSTACLE_HEIGHT)
    names = tmp_path / "names.json"
    names.write_text(json.dumps({"obstacles": [{"name": "crate", "polygon": first.tolist()}]}))
    params = CameraOverheadParams(source=video, rate_hz=rate, names_file=str(names))
    got: list[m.PolytopeSet] = []

    async def scenario() -> dict:
        service = CameraOverheadService(ns=ns, endpoint=zenoh_router, params={"camera_overhead": params})
        task = asyncio.create_task(service.run())
        client = open_session(zenoh_router, "peer")
        sub = client.declare_subscriber(TOPICS["polytopes"].key(ns),
                                        lambda s: got.append(m.decode(s.payload.to_bytes(), m.PolytopeSet)))
        try:
            end = time.monotonic() + 60.0
            while not getattr(service, "source_ended", False) and time.monotonic() < end:
                await asyncio.sleep(0.1)
            await asyncio.sleep(0.5)
            return {"status": service.status_extra(), "counters": service.counters.snapshot()}
        finally:
            sub.undeclare()
            service.stopping.set()
            await asyncio.wait_for(task, 10.0)
            client.close()

    out = asyncio.run(asyncio.wait_for(scenario(), 120))
    assert out["status"]["source_ended"] == 1.0 and 0 < out["status"]["calibration_rms_px"] < 1.5
    assert len(got) >= 20  # every frame of the file, at the rate
    last = got[-1]
    assert last.source == "camera_overhead" and last.mode == "obstacles"
    assert len(last.polytopes) == len(scn.obstacles)
    assert all(len(p.covariance) == 4 for p in last.polytopes)
    assert sum(math.hypot(*p.velocity) > 0.05 for p in last.polytopes) >= len(scn.movers) - 1  # they slide
    assert [p.name for p in last.polytopes].count("crate") == 1


def test_lockstep_planner_on_the_overhead_camera_world() -> None:
    from onboard.contracts.params import CameraOverheadParams
    from services.cli.overhead_world import overhead_world
    from sim_twin.lockstep import RunConfig, run

    res = run(RunConfig(scenario="crossing", seed=3, duration_s=3.0, estimator="truth", planner="graph", record=True,
                        world=overhead_world(CameraOverheadParams())))
    worlds = [msg for topic, _, msg in res.messages if topic == "polytopes" and msg.source == "camera_overhead"]
    assert len(worlds) >= 10  # 4 Hz over 3 s
    assert all(len(w.polytopes) == 1 for w in worlds)  # the walker, seen
    walker = np.array(res.scenario.obstacles[0].vertices).mean(axis=0) + res.scenario.offsets[0]
    assert math.dist(tk.centroid(np.array(worlds[-1].polytopes[0].vertices)), walker) < 0.15
    assert res.metrics["planner_plans"] >= 1 and res.metrics["collisions"] == 0
