"""The Intel RealSense D435 as a datasheet describes it: its modes, fields of view, stereo
baseline and depth error. The camera's mount on the robot is the MJCF's site ``depth_camera``
(:func:`robot_description.params.camera_mount`); the driver (``drivers/realsense``) and the
twin's camera (``sim_twin/camera.py``) both read this.
"""

from __future__ import annotations

import math

import numpy as np

# The D435's streams (Intel RealSense D400 datasheet, rev. 2023, tables 4-2 and 4-4): width,
# height -> frame rates [Hz]. Depth is Z16 from the stereo module; colour RGB8 from the RGB
# camera (OV2740).
DEPTH_MODES: dict[tuple[int, int], tuple[int, ...]] = {
    (1280, 720): (6, 15, 30),
    (848, 480): (6, 15, 30, 60, 90),
    (640, 480): (6, 15, 30, 60, 90),
    (640, 360): (6, 15, 30, 60, 90),
    (480, 270): (6, 15, 30, 60, 90),
    (424, 240): (6, 15, 30, 60, 90),
}
COLOR_MODES: dict[tuple[int, int], tuple[int, ...]] = {
    (1920, 1080): (6, 15, 30),
    (1280, 720): (6, 15, 30),
    (960, 540): (6, 15, 30, 60),
    (848, 480): (6, 15, 30, 60),
    (640, 480): (6, 15, 30, 60),
    (640, 360): (6, 15, 30, 60),
    (424, 240): (6, 15, 30, 60),
}
DEPTH_HFOV_DEG = 87.0  # stereo module field of view (datasheet: 87 x 58 deg)
DEPTH_VFOV_DEG = 58.0
COLOR_HFOV_DEG = 69.0  # RGB camera (datasheet: 69 x 42 deg)
COLOR_VFOV_DEG = 42.0
BASELINE_M = 0.050  # stereo baseline
DEPTH_UNITS_M = 0.001  # the D400's default depth unit: one z16 count is 1 mm
SUBPIXEL_RMS = 0.08  # typical subpixel disparity error of the D435 (Intel's depth-quality guide)
MAX_DECIMATION = 8  # the SDK's decimation filter: magnitude 1..8


def check_mode(kind: str, width: int, height: int, fps: int) -> None:
    """ValueError unless the D435 streams ``kind`` ("depth" or "color") at that size and rate."""
    modes = DEPTH_MODES if kind == "depth" else COLOR_MODES
    rates = modes.get((width, height))
    if rates is None or fps not in rates:
        known = ", ".join(f"{w}x{h}@{'/'.join(map(str, r))}" for (w, h), r in modes.items())
        raise ValueError(f"the D435 has no {kind} mode {width}x{height} @ {fps} Hz (it has {known})")


def nominal_focal_px(width: int, height: int, hfov_deg: float, vfov_deg: float) -> tuple[float, float]:
    """Focal lengths [px] of a pinhole with the datasheet's field of view at that size."""
    return (0.5 * width / math.tan(math.radians(hfov_deg) / 2), 0.5 * height / math.tan(math.radians(vfov_deg) / 2))


def depth_rms_m(z_m: np.ndarray | float, focal_px: float) -> np.ndarray | float:
    """The D435's depth RMS error at range ``z`` [m]: z^2 * subpixel / (focal * baseline).

    Grows with range squared (Intel, "Tuning depth cameras for best performance", eq. 1).
    """
    return np.square(z_m) * SUBPIXEL_RMS / (focal_px * BASELINE_M)
