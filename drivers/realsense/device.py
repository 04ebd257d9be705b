"""A D435 (or a recording of one, or its emulation) through librealsense: frames in, depth and colour out.

A *source* hands over framesets: :class:`PipelineSource` runs an ``rs.pipeline`` on a camera
(by serial number) or on a recording (``rs.config.enable_device_from_file``);
:class:`drivers.realsense.emulator.SoftwareD435` is a ``rs.software_device``. :class:`D435`
reads a source cheaply (:meth:`D435.wait`: the frameset kept, its sensor timestamp) and
processes only the frames it is asked to (:meth:`D435.process`), so a 30-90 Hz stream costs
the host little when one frame a hop is used:

1. the SDK's post-processing on depth (``rs-post-processing``'s order): decimation, then in
   disparity space the spatial (edge-preserving) filter. The temporal filter is left out:
   it blends successive frames, and between two apexes the hopping camera moves;
2. colour aligned to the (decimated) depth (``rs.align(rs.stream.depth)``): one pixel, one
   depth and one colour;
3. depth in metres by the device's own depth scale, intrinsics from the processed frame's
   profile (the decimation changes them).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from types import ModuleType
from typing import Any, Protocol

import numpy as np

from drivers.realsense.frames import z16_to_metres
from robot_description.d435 import MAX_DECIMATION, check_mode

WAIT_SLICE_MS = 200  # a reader's wait returns this often, so that it can notice a stop


@dataclass(frozen=True)
class StreamConfig:
    width: int = 848  # depth mode
    height: int = 480
    fps: int = 30
    color: bool = True  # colour stream, aligned to depth
    color_width: int = 848
    color_height: int = 480
    color_fps: int = 30
    decimation: int = 2  # the SDK's decimation filter magnitude (1: off)
    spatial: bool = True  # the SDK's spatial edge-preserving filter

    def check(self) -> None:
        check_mode("depth", self.width, self.height, self.fps)
        if self.color:
            check_mode("color", self.color_width, self.color_height, self.color_fps)
        if not 1 <= self.decimation <= MAX_DECIMATION:
            raise ValueError(f"decimation must be within 1..{MAX_DECIMATION}, got {self.decimation}")


class FrameSource(Protocol):
    depth_scale: float  # [m] per z16 count, from the device

    def wait(self, timeout_ms: int) -> Any | None: ...  # a composite frame, or None on timeout

    def stop(self) -> None: ...


@dataclass
class RawFrame:
    """A frameset as it came (kept: librealsense lets it outlive the wait)."""

    frameset: Any
    sensor_ns: int  # the depth frame's own timestamp [ns] in its domain
    domain: str  # librealsense's timestamp domain: hardware_clock, system_time, global_time
    number: int  # the depth frame number


@dataclass
class CameraFrame:
    depth: np.ndarray  # (h, w) float32 [m]; 0 = no return
    color: np.ndarray | None  # (h, w, 3) uint8 RGB aligned to ``depth``'s pixels; black where depth has no return
    fx: float  # depth intrinsics after processing [px]; principal point as the stack's images have it
    fy: float  # (pixel (i, j) centred at (i + 0.5, j + 0.5); librealsense centres it at (i, j))
    cx: float
    cy: float
    sensor_ns: int
    number: int


class PipelineSource:
    """An ``rs.pipeline`` on a camera (``serial``, or the first one found) or a recording (``file``)."""

    def __init__(self, rs: ModuleType, cfg: StreamConfig, serial: str = "", file: str = "",
                 real_time: bool = True) -> None:
        cfg.check()
        config = rs.config()
        if file:
            # A recording holds its own modes: every recorded stream is enabled as it is.
            config.enable_device_from_file(file, repeat_playback=False)
        else:
            if serial:
                config.enable_device(serial)
            config.enable_stream(rs.stream.depth, cfg.width, cfg.height, rs.format.z16, cfg.fps)
            if cfg.color:
                config.enable_stream(rs.stream.color, cfg.color_width, cfg.color_height, rs.format.rgb8, cfg.color_fps)
        self._pipe = rs.pipeline()
        profile = self._pipe.start(config)
        device = profile.get_device()
        if file:
            device.as_playback().set_real_time(real_time)  # False: every frame, as fast as read
        self.depth_scale = float(device.first_depth_sensor().get_depth_scale())
        self.name = device.get_info(rs.camera_info.name)

    def wait(self, timeout_ms: int) -> Any | None:
        ok, frames = self._pipe.try_wait_for_frames(timeout_ms)
        return frames if ok else None

    def stop(self) -> None:
        self._pipe.stop()


class D435:
    def __init__(self, rs: ModuleType, cfg: StreamConfig, source: FrameSource) -> None:
        cfg.check()
        self.rs = rs
        self.cfg = cfg
        self.source = source
        self.depth_scale = source.depth_scale
        if not self.depth_scale > 0:
            raise ValueError(f"the device reports depth scale {self.depth_scale}")
        self._filters: list[Any] = []
        if cfg.decimation > 1:
            dec = rs.decimation_filter()
            dec.set_option(rs.option.filter_magnitude, cfg.decimation)
            self._filters.append(dec)
        if cfg.spatial:
            self._filters += [rs.disparity_transform(True), rs.spatial_filter(), rs.disparity_transform(False)]
        self._align = rs.align(rs.stream.depth) if cfg.color else None
        self._last_number: int | None = None
        self.repeats = 0  # framesets whose depth frame was already read (a syncer or playback repeats it)
        self.unpaired = 0  # framesets whose colour was not taken with their depth
        self._pair_ms = 500.0 / cfg.fps  # half a depth period

    def wait(self, timeout_ms: int = WAIT_SLICE_MS) -> RawFrame | None:
        """The next frameset with a new depth frame (and its colour), or None after ``timeout_ms``."""
        deadline = time.monotonic() + timeout_ms / 1000.0
        while True:
            left_ms = round(1000.0 * (deadline - time.monotonic()))
            if left_ms <= 0:
                return None
            frames = self.source.wait(left_ms)
            if frames is None:
                return None
            raw = self._accept(frames)
            if raw is not None:
                return raw

    def _accept(self, frames: Any) -> RawFrame | None:
        depth = frames.get_depth_frame()
        if not depth:
            return None
        number = int(depth.get_frame_number())
        if number == self._last_number:
            self.repeats += 1
            return None
        if self.cfg.color:
            # a pipeline hands the newest frame of each stream: wait for this depth's colour
            color = frames.get_color_frame()
            if not color or abs(color.get_timestamp() - depth.get_timestamp()) > self._pair_ms:
                self.unpaired += 1
                return None
        self._last_number = number
        frames.keep()
        return RawFrame(frames, round(depth.get_timestamp() * 1e6), str(depth.get_frame_timestamp_domain()).rsplit(".", 1)[-1],
                        number)

    def process(self, raw: RawFrame) -> CameraFrame:
        """Filters, alignment and units of one frameset."""
        frames = raw.frameset
        for f in self._filters:
            frames = f.process(frames)
        frames = frames.as_frameset()
        color = None
        if self._align is not None and frames.get_color_frame():
            frames = self._align.process(frames)
            color = np.asanyarray(frames.get_color_frame().get_data()).copy()
        depth = frames.get_depth_frame()
        intr = depth.get_profile().as_video_stream_profile().get_intrinsics()
        return CameraFrame(
            depth=z16_to_metres(np.asanyarray(depth.get_data()), self.depth_scale),
            color=color, fx=float(intr.fx), fy=float(intr.fy), cx=float(intr.ppx) + 0.5, cy=float(intr.ppy) + 0.5,
            sensor_ns=raw.sensor_ns, number=raw.number)

    def stop(self) -> None:
        self.source.stop()
