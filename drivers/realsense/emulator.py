"""An emulated D435: librealsense's own ``rs.software_device`` fed with images (the twin's).

Two sensors as on the camera ("Stereo Module": z16 depth with its ``depth_units`` option;
"RGB Camera": RGB8 colour), their intrinsics, the depth-to-colour extrinsic and a
frame matcher: what comes out (:meth:`SoftwareD435.wait`) is a frameset that librealsense
built, filters and aligns exactly like one from a camera. With ``record_to`` an
``rs.recorder`` writes everything fed to a file (librealsense 2.59 writes ROS 2 bags,
``.db3``) that ``rs.config.enable_device_from_file`` plays back.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import ModuleType
from typing import Any

import numpy as np

from drivers.realsense.device import StreamConfig
from drivers.realsense.frames import metres_to_z16
from robot_description.d435 import DEPTH_UNITS_M

SERIAL = "EMULATED-D435"
QUEUE = 16  # framesets the syncer holds for a slow reader


@dataclass(frozen=True)
class Intrinsics:
    """A pinhole as the stack's images have it: pixel (i, j) centred at (i + 0.5, j + 0.5)."""

    fx: float  # [px]
    fy: float
    cx: float
    cy: float


class SoftwareD435:
    """``rs.software_device`` with a D435's depth and colour streams, fed by :meth:`push`."""

    def __init__(self, rs: ModuleType, cfg: StreamConfig, depth_intrinsics: Intrinsics,
                 color_intrinsics: Intrinsics | None = None, depth_to_color_m: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 depth_units: float = DEPTH_UNITS_M, record_to: str = "", global_time: bool = False) -> None:
        cfg.check()
        self.rs = rs
        # global_time: what :meth:`push` is given is the host's wall clock [ms], as librealsense stamps a
        # camera's frames with its global time on; else the camera's own clock (hardware_clock)
        self._domain = rs.timestamp_domain.global_time if global_time else rs.timestamp_domain.hardware_clock
        self.cfg = cfg
        self.depth_scale = depth_units
        self.device = dev = rs.software_device()
        dev.register_info(rs.camera_info.name, "Intel RealSense D435 (software device)")
        dev.register_info(rs.camera_info.serial_number, SERIAL)
        self._depth_sensor = dev.add_sensor("Stereo Module")
        self._depth_profile = self._depth_sensor.add_video_stream(
            self._stream(rs.stream.depth, 0, cfg.width, cfg.height, cfg.fps, 2, rs.format.z16, depth_intrinsics), True)
        self._depth_sensor.add_read_only_option(rs.option.depth_units, depth_units)
        self._color_sensor = self._color_profile = None
        if cfg.color:
            self._color_sensor = dev.add_sensor("RGB Camera")
            self._color_profile = self._color_sensor.add_video_stream(
                self._stream(rs.stream.color, 1, cfg.color_width, cfg.color_height, cfg.color_fps, 3, rs.format.rgb8,
                             color_intrinsics or depth_intrinsics), True)
            ex = rs.extrinsics()
            ex.rotation = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
            ex.translation = list(depth_to_color_m)
            self._depth_profile.register_extrinsics_to(self._color_profile, ex)
        # depth, then colour of the same number: one frameset per pushed pair
        dev.create_matcher(rs.matchers.dlr_c if cfg.color else rs.matchers.default)
        self._recorder = rs.recorder(record_to, dev) if record_to else None
        self._sync = rs.syncer(QUEUE)
        self._sensors = [(self._depth_sensor, self._depth_profile)]
        if self._color_sensor is not None:
            self._sensors.append((self._color_sensor, self._color_profile))
        for sensor, profile in self._sensors:
            sensor.open(profile)
            sensor.start(self._sync)
        self._latest: dict[bool, Any] = {}  # depth (True) and colour (False) frames not yet joined
        self._joining: Any = None
        self._join = rs.processing_block(self._compose)
        self._joined = rs.frame_queue(1)
        self._join.start(self._joined)
        self._number = 0
        self._stopped = False

    def _stream(self, kind: Any, uid: int, w: int, h: int, fps: int, bpp: int, fmt: Any, k: Intrinsics) -> Any:
        rs = self.rs
        intr = rs.intrinsics()
        intr.width, intr.height = w, h
        intr.fx, intr.fy, intr.ppx, intr.ppy = k.fx, k.fy, k.cx - 0.5, k.cy - 0.5  # librealsense: pixel centres at (i, j)
        intr.model = rs.distortion.none  # the D435's depth stream is rectified; the twin renders a pinhole
        intr.coeffs = [0.0] * 5
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid = kind, 0, uid
        vs.width, vs.height, vs.fps, vs.bpp, vs.fmt = w, h, fps, bpp, fmt
        vs.intrinsics = intr
        return vs

    def _frame(self, pixels: np.ndarray, bpp: int, width: int, profile: Any, sensor_ms: float) -> Any:
        rs = self.rs
        f = rs.software_video_frame()
        f.pixels = pixels
        f.bpp = bpp
        f.stride = width * bpp
        f.timestamp = sensor_ms
        f.domain = self._domain
        f.frame_number = self._number
        f.profile = profile.as_video_stream_profile()
        return f

    def push(self, depth_m: np.ndarray, color: np.ndarray | None, sensor_ms: float) -> int:
        """Feed one depth image [m] (and its colour, RGB uint8) captured at ``sensor_ms``; its frame number."""
        cfg = self.cfg
        if depth_m.shape != (cfg.height, cfg.width):
            raise ValueError(f"depth image {depth_m.shape}, the stream is {cfg.height}x{cfg.width}")
        self._number += 1
        z16 = np.ascontiguousarray(metres_to_z16(depth_m, self.depth_scale))
        self._depth_sensor.on_video_frame(self._frame(z16, 2, cfg.width, self._depth_profile, sensor_ms))
        if self._color_sensor is not None:
            if color is None or color.shape != (cfg.color_height, cfg.color_width, 3) or color.dtype != np.uint8:
                raise ValueError(f"colour image must be ({cfg.color_height}, {cfg.color_width}, 3) uint8")
            self._color_sensor.on_video_frame(self._frame(np.ascontiguousarray(color), 3, cfg.color_width,
                                                          self._color_profile, sensor_ms))
        return self._number

    def wait(self, timeout_ms: int) -> Any | None:
        """The next frameset: depth and colour of one pushed number, or None after ``timeout_ms``.

        The syncer hands the two sensors' frames over one at a time; a processing block
        joins a depth frame and the colour frame of its number into one composite frame, as
        the camera's pipeline would.
        """
        while True:
            ok, frames = self._sync.try_wait_for_frames(timeout_ms)
            if not ok:
                return None
            for f in frames:
                f.keep()
                self._latest[f.get_profile().stream_type() == self.rs.stream.depth] = f
            depth, color = self._latest.get(True), self._latest.get(False)
            if depth is None:
                continue
            if self._color_sensor is None:
                self._latest.clear()
                return frames
            if color is not None and color.get_frame_number() == depth.get_frame_number():
                self._latest.clear()
                self._joining = color
                self._join.invoke(depth)
                return self._joined.wait_for_frame(timeout_ms).as_frameset()

    def _compose(self, depth: Any, source: Any) -> None:
        source.frame_ready(source.allocate_composite_frame([depth, self._joining]))

    def stop(self) -> None:
        """Stop the sensors and close the recording (the file is complete after this)."""
        if self._stopped:
            return
        self._stopped = True
        for sensor, _ in self._sensors:
            sensor.stop()
            sensor.close()
        if self._recorder is not None:
            self._recorder.pause()
            self._recorder = None
