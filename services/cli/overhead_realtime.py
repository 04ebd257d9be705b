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

import os
import tempfile
import threading
import time
import tomllib
from pathlib import Path
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


class OverheadRig:
    """The MJPEG server the twin streams to, bound before the stack starts, and the config file that
    points the ``camera_overhead`` service at it (and the planner at a world with nothing unseen, as
    the lab profile does: the camera sees the whole floor)."""

    def __init__(self, config: str | None, toml: Any) -> None:
        self.params = load_params(config, ("camera_overhead",))["camera_overhead"]
        self.server = MjpegServer(LOOPBACK).start()
        user = tomllib.loads(Path(config).read_text()) if config else {}
        user["camera_overhead"] = {**user.get("camera_overhead", {}), **twin_camera_overrides(self.server.url)}
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
        self.server.stop()
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
        """The camera's messages: how many, their rate (first to last), obstacles per message, and the
        latency from the capture of the frame each came from to its arrival here.

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
        counts = sorted(a[2] for a in got)

        def pct(xs: list[float], q: float) -> float | None:
            return round(xs[min(len(xs) - 1, int(q * len(xs)))], 1) if xs else None

        span_s = (got[-1][0] - got[0][0]) / 1e9 if len(got) > 1 else 0.0
        return {"messages": len(got), "rate_hz": round((len(got) - 1) / span_s, 3) if span_s > 0 else 0.0,
                "obstacles_p50": counts[len(counts) // 2] if counts else 0, "obstacles_max": counts[-1] if counts else 0,
                "latency_ms_p50": pct(latencies, 0.5), "latency_ms_p99": pct(latencies, 0.99),
                "latency_ms_max": round(latencies[-1], 1) if latencies else None,
                "other_sources": others, "rejected": self.rejected}
