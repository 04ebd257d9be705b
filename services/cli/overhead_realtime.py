"""``archer sim --mode realtime --obstacles-from overhead`` (issue 28): the indoor lab end to end on the
real-time twin. The twin renders its overhead view at ``camera_overhead.rate_hz`` and serves it as an
IP camera does, MJPEG over HTTP on 127.0.0.1 at a free port (:class:`OverheadRig`); the
``camera_overhead`` service reads that stream through ``cv2.VideoCapture``, calibrates the floor on the
twin's markers, tracks the obstacles and publishes them; the twin publishes no ground-truth obstacles,
so the planner sees only what the camera service makes of the frames.

:class:`ObstacleProbe` listens to ``world/polytopes`` beside the run for its report: the camera's
achieved rate, and the latency from a frame's capture (when the twin sampled the scene) to its
obstacles arriving on the bus.
"""

from __future__ import annotations

import multiprocessing
import os
import tempfile
import threading
import time
import tomllib
from pathlib import Path
from types import SimpleNamespace
from typing import Any

from drivers.camera_overhead.emulator import MjpegServer
from onboard.contracts import messages as m
from onboard.contracts.topics import TOPICS
from services.runtime.config import load_params
from sim_twin import overhead_camera as oc

LOOPBACK = "127.0.0.1"


def twin_camera_overrides(source: str) -> dict[str, Any]:
    """``camera_overhead`` settings for the twin's camera: its stream, its lens, its markers' poses
    (the lab's survey, for the twin's floor), whatever a lab profile says of its own camera."""
    cam, markers = oc.default_camera(), oc.default_markers()
    lens = cam.lens
    return {"source": source, "crop_left": False, "fx": lens.fx, "fy": lens.fy, "cx": lens.cx, "cy": lens.cy,
            "dist": [float(d) for d in lens.dist],
            "marker_ids": [mk.id for mk in markers], "marker_x": [mk.x for mk in markers],
            "marker_y": [mk.y for mk in markers], "marker_yaw": [mk.yaw for mk in markers],
            "marker_size": markers[0].size, "names_file": ""}


# the drawing process stands for the camera's own hardware, which takes nothing from the robot's computer:
# the default priority (not the twin's real time, nor niced below the stack), so that it streams near its rate
RENDER_NICE = 0
RENDER_START_TIMEOUT_S = 120.0  # [s] for the drawing process to import OpenCV and bind its port, loaded machine


def _render_main(conn: Any, obstacles: Any, seed: int, host: str) -> None:
    """The drawing process: scenes from the twin in, frames out on the MJPEG server; gone when the
    twin's end of the pipe is (the parent's death included)."""
    import dataclasses

    import cv2
    import numpy as np

    if os.sched_getscheduler(0) != os.SCHED_OTHER:  # spawned by the twin's real-time process
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    os.setpriority(os.PRIO_PROCESS, 0, max(RENDER_NICE, os.getpriority(os.PRIO_PROCESS, 0)))  # never above the caller's
    # the pixel noise drawn by OpenCV (the same sigma), ~6x cheaper than the lockstep renderer's numpy
    # draw, which leaves a loaded machine's camera at a frame a second
    camera = oc.default_camera()
    renderer = oc.OverheadRenderer(dataclasses.replace(camera, noise_sigma=0.0), oc.default_markers(), seed=seed)
    noise = np.empty((camera.height, camera.width, 3), np.int16)
    cv2.setRNGSeed(seed)
    server = MjpegServer(host).start()
    stamps: list[int] = []
    render_ms: list[float] = []
    skipped = 0
    try:
        conn.send(server.url)
        while True:
            try:
                item = conn.recv()
                while item is not None and conn.poll():  # behind: the newest scene only
                    item = conn.recv()
                    skipped += 1
            except EOFError:
                return
            if item is None:
                break
            stamp, offsets, robot_xy = item
            tic = time.perf_counter()
            frame = renderer.render(SimpleNamespace(obstacles=obstacles, offsets=offsets), robot_xy)  # type: ignore[arg-type]
            if camera.noise_sigma > 0:
                cv2.randn(noise, 0.0, camera.noise_sigma)
                frame = cv2.add(frame, noise, dtype=cv2.CV_8U)  # saturated to 0..255
            server.publish(frame)
            render_ms.append((time.perf_counter() - tic) * 1e3)
            stamps.append(stamp)
        r = sorted(render_ms)
        conn.send({"stamps_ns": stamps, "summary": {
            **dict(server.counts), "scenes_skipped": skipped,
            "render_ms_p50": round(r[len(r) // 2], 2) if r else None,
            "render_ms_p99": round(r[min(len(r) - 1, int(0.99 * len(r)))], 2) if r else None}})
    finally:
        server.stop()


class SceneStream:
    """The twin's overhead camera as an IP camera: a process of its own draws each scene the twin
    sends (:meth:`send`) and serves it on ``url``. ``finish`` stops it and returns the capture stamps
    of the frames it served and its counters."""

    def __init__(self, scenario: Any, seed: int, host: str = LOOPBACK) -> None:
        ctx = multiprocessing.get_context("spawn")  # no fork of a process with Zenoh's and MuJoCo's threads
        self._conn, child = ctx.Pipe()
        self._send_lock = threading.Lock()
        self._proc = ctx.Process(target=_render_main, args=(child, list(scenario.obstacles), seed, host),
                                 name="archer-overhead-camera", daemon=True)
        self._proc.start()
        child.close()
        if not self._conn.poll(RENDER_START_TIMEOUT_S):
            self._proc.kill()
            raise RuntimeError("the twin's overhead camera process did not start")
        self.url: str = self._conn.recv()
        self._result: dict[str, Any] | None = None

    def send(self, stamp_ns: int, offsets: Any, robot_xy: tuple[float, float]) -> None:
        with self._send_lock:
            self._conn.send((stamp_ns, offsets, robot_xy))

    def finish(self, timeout_s: float = 10.0) -> dict[str, Any]:
        if self._result is None:
            self._result = {"stamps_ns": [], "summary": {}}
            try:
                with self._send_lock:
                    self._conn.send(None)
                if self._conn.poll(timeout_s):
                    self._result = self._conn.recv()
            except (OSError, EOFError):
                pass
            self._conn.close()
            self._proc.join(timeout=timeout_s)
            if self._proc.is_alive():
                self._proc.kill()
                self._proc.join()
        return self._result


class OverheadRig:
    """The twin's camera process and its MJPEG server, started before the stack, and the config file that
    points the ``camera_overhead`` service at it (and the planner at a world with nothing unseen, as
    the lab profile does: the camera sees the whole floor)."""

    def __init__(self, config: str | None, toml: Any, scenario: Any, seed: int) -> None:
        self.params = load_params(config, ("camera_overhead",))["camera_overhead"]
        self.stream = SceneStream(scenario, seed)
        user = tomllib.loads(Path(config).read_text()) if config else {}
        user["camera_overhead"] = {**user.get("camera_overhead", {}), **twin_camera_overrides(self.stream.url)}
        user["planner"] = {**user.get("planner", {}), "require_seen": False}
        fd, self.config_path = tempfile.mkstemp(prefix="archer-overhead-", suffix=".toml")
        with os.fdopen(fd, "w") as f:
            f.write(toml(user))
        try:
            load_params(self.config_path)  # what the services will read is valid before they start
        except BaseException:
            self.close()
            raise

    @property
    def rate_hz(self) -> float:
        return self.params.rate_hz

    def close(self) -> None:
        self.stream.finish()
        if os.path.exists(self.config_path):
            os.unlink(self.config_path)


class ObstacleProbe:
    """``world/polytopes`` as they arrive on a session beside the run: (arrival, stamp, count, source)."""

    def __init__(self, session: Any, ns: str, clock_ns: Any = time.monotonic_ns) -> None:
        self.arrivals: list[tuple[int, int, int, str]] = []
        self.rejected = 0
        self._lock = threading.Lock()
        self._clock_ns = clock_ns
        topic = TOPICS["polytopes"]
        self._sub = session.declare_subscriber(topic.key(ns), self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        now = self._clock_ns()
        try:
            msg = m.decode(sample.payload.to_bytes(), m.PolytopeSet)
        except Exception:  # noqa: BLE001 (a bad payload is counted, the probe keeps listening)
            self.rejected += 1
            return
        with self._lock:
            self.arrivals.append((now, msg.stamp_ns, len(msg.polytopes), msg.source))

    def close(self) -> None:
        self._sub.undeclare()

    def report(self, frame_stamps_ns: list[int]) -> dict[str, Any]:
        """The camera's messages: how many, their rate (first to last), obstacles per message, the
        latency from the capture of the frame each came from (the twin's scene sampled, then drawn,
        encoded, streamed) to its arrival here, and the camera service's part of it (frame received
        to arrival here).

        A message's stamp is when the camera service received its frame; that frame is the newest one
        captured before it (the stream carries each frame as soon as it is encoded, never a backlog:
        tests/test_overhead_realtime.py reads it frame for frame)."""
        import bisect

        with self._lock:
            got = [a for a in self.arrivals if a[3] == "camera_overhead"]
            others = sorted({a[3] for a in self.arrivals} - {"camera_overhead"})
        latencies = []
        for arrived, stamp, _, _ in got:
            k = bisect.bisect_right(frame_stamps_ns, stamp) - 1
            if k >= 0:
                latencies.append((arrived - frame_stamps_ns[k]) / 1e6)
        latencies.sort()
        in_service = sorted((arrived - stamp) / 1e6 for arrived, stamp, _, _ in got)  # frame received -> here
        counts = sorted(a[2] for a in got)

        def pct(xs: list[float], q: float) -> float | None:
            return round(xs[min(len(xs) - 1, int(q * len(xs)))], 1) if xs else None

        span_s = (got[-1][0] - got[0][0]) / 1e9 if len(got) > 1 else 0.0
        return {"messages": len(got), "rate_hz": round((len(got) - 1) / span_s, 3) if span_s > 0 else 0.0,
                "obstacles_p50": counts[len(counts) // 2] if counts else 0, "obstacles_max": counts[-1] if counts else 0,
                "latency_ms_p50": pct(latencies, 0.5), "latency_ms_p99": pct(latencies, 0.99),
                "latency_ms_max": round(latencies[-1], 1) if latencies else None,
                "service_latency_ms_p50": pct(in_service, 0.5), "service_latency_ms_p99": pct(in_service, 0.99),
                "other_sources": others, "rejected": self.rejected}
