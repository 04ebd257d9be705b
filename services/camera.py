"""The ``camera`` service: the D435's depth and colour, one frame a hop, for perception.

Subscribes: ``state`` (the pose that places each frame in the world), ``phase`` (apex events).
Reads: a D435 over USB, or a recording of one, through librealsense (:mod:`drivers.realsense`,
``pip install '.[realsense]'``); a reader thread waits on the SDK. Every frame's sensor
timestamp is mapped onto the stack's clock (:class:`ClockMap`: librealsense's global time where
it is plausible, else the least-delayed frame's offset, from the first frame that came as it was
captured rather than from a queue); with ``capture = "apex"``
the frame captured nearest each apex is kept (:class:`ApexPicker`), and only that one is
filtered (decimation, spatial) and aligned (colour to depth).
Computes: the camera's pose at the frame's capture time, the estimate nearest it (moved by
its velocity over the gap) composed with the camera's mount (the MJCF site ``depth_camera``).
The camera is opened once a valid estimate has arrived; a frame no recent valid estimate
can place is refused (``rejected.no_state``).
Publishes: ``depth`` (binary DepthImage, metres) and ``color`` (binary ColorImage, RGB
aligned to the depth pixels), both stamped with the capture time; with
``[estimator] visual_odometry`` and ``position_source = "odometry"`` also ``visual_odometry``: each published frame against the
previous one (:mod:`onboard.perception.visual_odometry`, placed by the same estimate), the CoM's
displacement between their capture times (refusals counted as ``vo_rejected.<reason>``).
"""

from __future__ import annotations

import asyncio
import math
import threading
import time
from collections import deque
from typing import Any, ClassVar

import numpy as np

from drivers.realsense import load
from drivers.realsense.device import D435, WAIT_SLICE_MS, FrameSource, PipelineSource, RawFrame, StreamConfig
from drivers.realsense.frames import ApexPicker, ClockMap
from onboard.contracts import messages as m
from onboard.contracts.binary_messages import ColorImage, DepthImage, encode_color, encode_depth
from onboard.contracts.params import CameraParams, EstimatorParams
from onboard.perception.visual_odometry import VisualOdometry, VoFrame
from onboard.geometry import quaternion as qt
from robot_description.params import CameraMount, camera_mount
from services.runtime.service import Service

STATE_HISTORY = 3000  # estimates kept to place a frame (3 s at 1 kHz: a frame delivered late on a loaded host)
PICK_WINDOW_S = 0.2  # frames kept for the apex picker


def stream_config(p: CameraParams) -> StreamConfig:
    return StreamConfig(width=p.width, height=p.height, fps=p.fps, color=p.color, color_width=p.color_width,
                        color_height=p.color_height, color_fps=p.color_fps, decimation=p.decimation, spatial=p.spatial)


def _stamp(state: m.StateEstimate) -> int:
    return state.stamp_ns


def camera_pose(state: m.StateEstimate, at_ns: int, mount: CameraMount) -> tuple[list[float], list[float]]:
    """Optical centre [m] and optical->world quaternion at ``at_ns`` from an estimate near it."""
    dt = (at_ns - state.stamp_ns) * 1e-9
    com = [p + v * dt for p, v in zip(state.position, state.velocity)]
    offset = qt.rotate(state.quat, mount.pos_from_com)
    return [c + o for c, o in zip(com, offset)], qt.normalize(qt.mul(state.quat, mount.quat))


class CameraService(Service):
    name: ClassVar[str] = "camera"
    params_sections: ClassVar[tuple[str, ...]] = ("camera", "estimator")  # estimator: its visual odometry
    subscribes: ClassVar[tuple[str, ...]] = ("state", "phase")

    async def setup(self) -> None:
        p: CameraParams = self.params["camera"]
        self.stream = stream_config(p)
        self.stream.check()
        if p.source == "file" and not p.file:
            raise ValueError("camera.source = 'file' needs camera.file")
        self.rs = load()  # an optional extra: only this service needs it
        self.mount = camera_mount(p.robot_variant)
        self._depth_pub = self.publisher("depth")
        self._color_pub = self.publisher("color") if p.color else None
        est: EstimatorParams = self.params["estimator"]
        # only where the estimator fuses it (no motion capture), and it needs the colour
        fused = est.visual_odometry and est.position_source == "odometry"
        self.vo = VisualOdometry(est) if fused and p.color else None
        self._vo_pub = self.publisher("visual_odometry") if self.vo is not None else None
        self._vo_seq = 0
        self._published = self.rate("depth")
        self._received = self.rate("frames")
        # decoded only where a frame is placed: a few a second of the estimator's 1 kHz
        self._states = self.sampled_history("state", STATE_HISTORY)
        self._apexes: deque[int] = deque()
        self.on_message("phase", self._on_phase)
        self.clock_map = ClockMap(p.clock_window, round(p.min_latency_s * 1e9), round(p.global_time_max_age_s * 1e9),
                                  live=p.source != "file")
        keep = max(2, math.ceil(p.fps * PICK_WINDOW_S))
        self.picker: ApexPicker[RawFrame] = ApexPicker(round(p.apex_tolerance_s * 1e9), keep)
        self.camera: D435 | None = None
        self._stop = threading.Event()
        self.reader_error: BaseException | None = None
        self._seq = 0
        self.frames = 0  # new frames read
        self.apexes = 0  # apex events received
        self.last_offset_ms = 0.0
        self._reader = threading.Thread(target=self._read, name="camera-reader", daemon=True)

    def _on_phase(self, event: m.PhaseEvent) -> None:
        if event.event == "apex":
            self.apexes += 1
            self._apexes.append(event.stamp_ns)

    def open_source(self, p: CameraParams) -> FrameSource:
        """The frames: a camera or a recording through ``rs.pipeline`` (an emulation hands its own)."""
        return PipelineSource(self.rs, self.stream, serial=p.serial, file=p.file if p.source == "file" else "",
                              real_time=p.file_real_time)

    def _open(self, p: CameraParams) -> D435 | None:
        try:
            source = self.open_source(p)
        except RuntimeError as exc:  # no camera, busy, or an unreadable file
            self.count("open_failed")
            self.log.warning("camera: cannot open %s: %s", p.file or p.serial or "the first D435", exc)
            return None
        self.log.info("camera: %s open, depth scale %.6f m", getattr(source, "name", "?"), source.depth_scale)
        return D435(self.rs, self.stream, source)

    def _read(self) -> None:
        try:
            # A frame no estimate can place is of no use: the stream starts with the estimates.
            while not self._stop.is_set() and not self._estimates_ready():
                self._stop.wait(WAIT_SLICE_MS / 1000.0)
            while not self._stop.is_set():
                p: CameraParams = self.params["camera"]
                cam = self._open(p)
                if cam is None:
                    self._stop.wait(p.reopen_s)
                    continue
                self.camera = cam
                try:
                    self._stream(cam, p)
                finally:
                    cam.stop()
        except BaseException as exc:  # reported by main(); the service goes to error
            self.reader_error = exc

    def _stream(self, cam: D435, p: CameraParams) -> None:
        while not self._stop.is_set():
            raw = cam.wait(WAIT_SLICE_MS)
            if raw is None:
                continue
            self._received.tick()
            self.frames += 1
            now_ns = self.clock.now_ns()
            stale_before = self.clock_map.stale
            stamp_ns = self.clock_map.stamp(raw.sensor_ns, now_ns, raw.domain, time.time_ns() - now_ns)
            if stamp_ns is None:  # too late, or read from a queue before the map settled: counted
                if stale_before == 0 and self.clock_map.stale == 1:  # the first late frame is said; the count says how many followed
                    self.log.warning("camera: a frame came more than %.1f s after its capture: dropped",
                                     p.global_time_max_age_s)
                continue
            if p.capture == "every":
                self._publish(cam, raw, stamp_ns)
                continue
            picked = None
            while self._apexes:
                picked = self.picker.add_apex(self._apexes.popleft()) or picked
            picked = self.picker.add_frame(stamp_ns, raw) or picked
            if picked is not None:
                self.last_offset_ms = picked.offset_ns / 1e6
                self._publish(cam, picked.frame, picked.stamp_ns)

    def _estimates_ready(self) -> bool:
        newest = self._states.newest()
        return newest is not None and newest.valid

    def _state_near(self, at_ns: int, max_age_ns: int) -> m.StateEstimate | None:
        best = self._states.nearest(at_ns, _stamp)
        if best is None or abs(best.stamp_ns - at_ns) > max_age_ns or not best.valid:
            return None
        return best

    def _publish(self, cam: D435, raw: RawFrame, stamp_ns: int) -> None:
        p: CameraParams = self.params["camera"]
        state = self._state_near(stamp_ns, round(p.state_max_age_s * 1e9))
        if state is None:
            self.count("rejected.no_state")
            return
        pos, quat = camera_pose(state, stamp_ns, self.mount)
        frame = cam.process(raw)
        self._seq += 1
        cam_pos, cam_quat = np.array(pos), np.array(quat)
        self._depth_pub.put_bytes(encode_depth(DepthImage(frame.depth, frame.fx, frame.fy, frame.cx, frame.cy,
                                                          cam_pos, cam_quat, stamp_ns, self._seq)))
        if self._color_pub is not None and frame.color is not None:
            self._color_pub.put_bytes(encode_color(ColorImage(frame.color, frame.fx, frame.fy, frame.cx, frame.cy,
                                                              cam_pos, cam_quat, stamp_ns, self._seq)))
        self._published.tick()
        if self.vo is not None and frame.color is not None:
            self._visual_odometry(frame.depth, frame.color, (frame.fx, frame.fy, frame.cx, frame.cy), state, quat, stamp_ns)

    def _visual_odometry(self, depth: np.ndarray, color: np.ndarray, intrinsics: tuple[float, float, float, float],
                         state: m.StateEstimate, cam_quat: list[float], stamp_ns: int) -> None:
        """This frame against the previous published one; the displacement published, or the refusal counted."""
        assert self.vo is not None and self._vo_pub is not None
        lever = qt.rotate(state.quat, [-v for v in self.mount.pos_from_com])  # CoM - optical centre, world
        fx, fy, cx, cy = intrinsics
        delta = self.vo.step(VoFrame(stamp_ns, color, depth, fx, fy, cx, cy,
                                     (cam_quat[0], cam_quat[1], cam_quat[2], cam_quat[3]), (lever[0], lever[1], lever[2])))
        if delta is None:
            if self.vo.last_reason:
                self.count(f"vo_rejected.{self.vo.last_reason}")
            return
        self._vo_seq += 1
        delta.seq = self._vo_seq
        self._vo_pub.put(delta)
        self.count("vo_published")

    async def main(self) -> None:
        self._reader.start()
        self.state = "degraded"  # until frames flow
        while not self.stopping.is_set():
            try:
                await asyncio.wait_for(self.stopping.wait(), 0.5)
            except asyncio.TimeoutError:
                pass
            if self.reader_error is not None:
                self.state = "error"
                self.fail(f"camera reader crashed: {self.reader_error!r}")
                return
            self.state = "running" if self.rates_hz().get("frames", 0.0) > 0 else "degraded"

    async def teardown(self) -> None:
        self._stop.set()
        await asyncio.to_thread(self._reader.join, 5.0)

    def status_extra(self) -> dict[str, float]:
        cam: Any = self.camera
        return {"published": float(self._seq), "apex_missed": float(self.picker.missed), "frames": float(self.frames),
                "apexes": float(self.apexes), "global_stamps": float(self.clock_map.global_stamps),
                "stale_frames": float(self.clock_map.stale), "queued_frames": float(self.clock_map.queued),
                "apex_offset_ms": self.last_offset_ms,
                "repeats": float(cam.repeats if cam else 0), "unpaired": float(cam.unpaired if cam else 0)}
