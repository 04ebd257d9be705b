"""The ``camera_overhead`` service: obstacles from a camera looking down at the floor (issue 28;
thesis 7.2, Fig. 7.7: the lab's overhead ZED 2, 20 obstacles tracked at 4 Hz).

Subscribes: nothing. Reads: frames from ``camera_overhead.source`` through ``cv2.VideoCapture`` (any
UVC camera by index, a network stream such as an IP camera's ``http://`` MJPEG, or a video file, read
at the service's rate) on a reader thread
(:mod:`drivers.camera_overhead`). Computes: the floor homography from the ArUco markers at their
known poses (on the first frame that shows ``min_markers`` of them; frames before that are counted
``rejected.not_calibrated``), then per frame the obstacles' blobs as convex floor polygons, tracked
(constant-velocity Kalman filters) for velocity and covariance; tracks seeded from ``names_file``
(``archer obstacles init``) carry the operator's names. Publishes: ``polytopes`` (PolytopeSet,
``mode = "obstacles"``, ``source = "camera_overhead"``) at ``rate_hz``, stamped with the frame's
receive time.
"""

from __future__ import annotations

import asyncio
import json
import threading
import time
from typing import ClassVar

import numpy as np

from drivers.camera_overhead import tracking as tk
from drivers.camera_overhead.calibration import CalibrationError, FloorCalibration, Lens, Marker
from drivers.camera_overhead.device import CameraError, LatestFrame, VideoSource
from onboard.contracts import messages as m
from onboard.geometry.polygons import validate_polygon
from onboard.contracts.params import CameraOverheadParams
from services.runtime.service import Service


def lens_of(p: CameraOverheadParams) -> Lens:
    return Lens(p.fx, p.fy, p.cx, p.cy, tuple(p.dist))  # type: ignore[arg-type]


def markers_of(p: CameraOverheadParams) -> list[Marker]:
    return [Marker(int(i), x, y, p.marker_size, yaw) for i, x, y, yaw in zip(p.marker_ids, p.marker_x, p.marker_y, p.marker_yaw)]


def source_of(p: CameraOverheadParams) -> int | str:
    return int(p.source) if p.source.isdigit() else p.source


# a live frame this early (in periods) still counts as the due one: a stream at the service's own rate
# (an IP camera set to it, the twin's) arrives with jitter around the due times, never all late
LIVE_TOLERANCE = 0.5


STREAM_RETRY_S = 1.0  # [s] between tries to open a network stream that gives nothing
STREAM_STALL_S = 1.0  # [s] a live source's wait for a new frame before the loop looks again


def is_stream(source: int | str) -> bool:
    """A network stream (an IP camera's ``http://`` MJPEG, ``rtsp://``): it may not be up yet, or drop."""
    return isinstance(source, str) and "://" in source


def is_live(source: int | str) -> bool:
    """A camera (an index, or a network stream) rather than a file."""
    return isinstance(source, int) or is_stream(source)


def tracker_of(p: CameraOverheadParams) -> tk.Tracker:
    return tk.Tracker(accel_sigma=p.accel_sigma, measure_sigma=p.measure_sigma, gate_m=p.gate_m, max_missed=p.max_missed)


class ObstacleCamera:
    """Frame -> published obstacles, everything but the I/O (the service and `archer obstacles` share it)."""

    def __init__(self, p: CameraOverheadParams) -> None:
        self.p = p
        self.lens = lens_of(p)
        self.markers = markers_of(p)
        self.colour = tk.ColourRange(tuple(p.hsv_low), tuple(p.hsv_high))  # type: ignore[arg-type]
        self.tracker = tracker_of(p)
        self.calibration: FloorCalibration | None = None
        self.names: dict[int, str] = {}

    def calibrate(self, frame: np.ndarray) -> FloorCalibration:
        self.calibration = FloorCalibration.from_frame(frame, self.markers, self.lens, min_markers=self.p.min_markers)
        return self.calibration

    def blobs(self, frame: np.ndarray) -> list[np.ndarray]:
        """Convex floor polygons of the obstacles in ``frame`` (calibrating on it first if need be)."""
        if self.calibration is None:
            self.calibrate(frame)
        assert self.calibration is not None
        return [tk.floor_polygon(b, self.calibration, height=self.p.obstacle_height_m)
                for b in tk.segment(frame, self.colour, self.p.min_area_px)]

    def seed(self, named: list[dict]) -> None:
        """Start tracks at the operator's named obstacles (``archer obstacles init``'s file)."""
        polys = [np.array(o["polygon"], dtype=float) for o in named]
        t0 = self.tracker.tracks[-1].t if self.tracker.tracks else 0.0
        for o, tr in zip(named, self.tracker.update(t0, polys)):
            tr.name = str(o["name"])

    def step(self, frame: np.ndarray, t_s: float, stamp_ns: int) -> m.PolytopeSet:
        tracks = self.tracker.update(t_s, self.blobs(frame))
        polys = []
        for tr in tracks:
            poly = tr.polygon
            A, b = _halfspaces(poly)
            polys.append(m.Polytope(A=A, b=b, vertices=poly.tolist(), velocity=tr.velocity, covariance=tr.position_cov,
                                    name=tr.name))
        return m.PolytopeSet(stamp_ns=stamp_ns, mode="obstacles", polytopes=polys, source="camera_overhead")


def _halfspaces(poly: np.ndarray) -> tuple[list[list[float]], list[float]]:
    e = np.roll(poly, -1, axis=0) - poly
    n = np.stack([e[:, 1], -e[:, 0]], axis=1)
    n /= np.hypot(n[:, 0], n[:, 1])[:, None]
    return n.tolist(), np.einsum("ij,ij->i", n, poly).tolist()


class CameraOverheadService(Service):
    name: ClassVar[str] = "camera_overhead"
    params_sections: ClassVar[tuple[str, ...]] = ("camera_overhead",)

    async def setup(self) -> None:
        p: CameraOverheadParams = self.params["camera_overhead"]
        self.camera = ObstacleCamera(p)
        if p.names_file:
            with open(p.names_file, encoding="utf-8") as f:
                self.camera.seed(json.load(f)["obstacles"])
        # the polygon kernels (numba) loaded before READY, not on the first frame: ~0.6 s, seconds under load
        await asyncio.to_thread(validate_polygon, [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
        self._pub = self.publisher("polytopes")
        self._published = self.rate("polytopes")
        self._stop = threading.Event()
        self.reader_error: BaseException | None = None
        self.source_ended = False
        self._frames = 0
        self._latency_ms = 0.0
        self._reader = threading.Thread(target=self._read, name="camera-reader", daemon=True)

    def _read(self) -> None:
        p: CameraOverheadParams = self.params["camera_overhead"]
        source = source_of(p)
        t0 = self.clock.now_ns()  # the tracks' time: each frame's receipt (not when it was processed)
        try:
            while not self._stop.is_set():
                try:
                    with VideoSource(source, p.crop_left) as src:
                        self._frames_from(src, p, t0)
                except CameraError:
                    if not is_stream(source):
                        raise
                    # a network camera not streaming (yet, or any more): tried again, as it comes back
                    self.count("source.unavailable")
                    self._stop.wait(STREAM_RETRY_S)
                    continue
                if not is_stream(source):
                    self.source_ended = True
                    return
                self.count("source.stream_ended")  # read again from a new connection
        except BaseException as exc:  # reported by main(); the service goes to error
            self.reader_error = exc

    def _frames_from(self, src: VideoSource, p: CameraOverheadParams, t0: int) -> None:
        """Frames at the service's rate until the source gives none (or the service stops): a file's
        frames one after the other, a camera's newest frame when one is due."""
        if is_live(source_of(p)):
            self._live_frames(src, p, t0)
            return
        period = 1.0 / p.rate_hz
        next_t = time.monotonic()
        while not self._stop.wait(max(0.0, next_t - time.monotonic())):
            frame = src.read()
            if frame is None:
                return
            next_t = max(next_t + period, time.monotonic())
            self._process(frame, self.clock.now_ns(), t0)

    def _live_frames(self, src: VideoSource, p: CameraOverheadParams, t0: int) -> None:
        period = 1.0 / p.rate_hz
        grabber = LatestFrame(src, self.clock.now_ns)
        dropped = 0
        try:
            next_t = time.monotonic()
            # woken a little early, it takes the first new frame: a camera at the service's own rate
            # (its frames jittering around the due times) is processed frame by frame, as each arrives
            while not self._stop.wait(max(0.0, next_t - LIVE_TOLERANCE * period - time.monotonic())):
                got = grabber.take(STREAM_STALL_S)
                if grabber.dropped > dropped:  # frames the camera sent that were not due
                    self.count("source.frames_skipped", grabber.dropped - dropped)
                    dropped = grabber.dropped
                if got is None:
                    if grabber.error is not None:
                        raise grabber.error
                    if grabber.ended:
                        return
                    continue  # nothing new yet: a stalled camera
                next_t = max(next_t + period, time.monotonic() - LIVE_TOLERANCE * period)
                self._process(got[0], got[1], t0)
        finally:
            grabber.close()

    def _process(self, frame: np.ndarray, stamp: int, t0: int) -> None:
        """One frame's obstacles published, stamped with its receive time; the tracks advance to it (a
        frame that waited for a busy CPU still moves them by its own interval, not the wait's)."""
        self._frames += 1
        tic = time.perf_counter()
        try:
            msg = self.camera.step(frame, (stamp - t0) / 1e9, stamp)
        except CalibrationError:
            self.count("rejected.not_calibrated")
            return
        self._latency_ms = (time.perf_counter() - tic) * 1e3
        self._pub.put(msg)
        self._published.tick()

    async def main(self) -> None:
        self._reader.start()
        self.state = "degraded"  # until obstacles flow
        while not self.stopping.is_set():
            try:
                await asyncio.wait_for(self.stopping.wait(), 0.25)
            except asyncio.TimeoutError:
                pass
            if self.reader_error is not None:
                self.state = "error"
                self.fail(f"camera reader: {self.reader_error!r}")
                return
            self.state = "running" if self.rates_hz().get("polytopes", 0.0) > 0 and not self.source_ended else "degraded"

    async def teardown(self) -> None:
        self._stop.set()
        self._reader.join(timeout=2.0)

    def status_extra(self) -> dict[str, float]:
        cal = self.camera.calibration
        return {"frames": float(self._frames), "tracks": float(len(self.camera.tracker.tracks)),
                "calibration_rms_px": cal.rms_px if cal is not None else -1.0, "frame_ms": self._latency_ms,
                "source_ended": float(self.source_ended)}
