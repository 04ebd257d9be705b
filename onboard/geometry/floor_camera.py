"""A camera looking at the floor: its lens (pinhole and OpenCV's distortion) and the ArUco markers
laid on the floor at known poses. One model for the overhead camera's driver, which calibrates
with it, and for the twin, which renders through it.

A marker's pose is its centre and yaw on the floor; its corners, in OpenCV's order (top-left,
top-right, bottom-right, bottom-left of the marker image), lie at (-s/2, +s/2), (+s/2, +s/2),
(+s/2, -s/2), (-s/2, -s/2) in its own frame (x to the marker image's right, y to its top).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class Marker:
    id: int
    x: float  # [m] centre on the floor, world frame
    y: float
    size: float  # [m] side of the black square
    yaw: float = 0.0  # [rad] of the marker's x axis from world x

    def corners(self) -> np.ndarray:
        """(4, 2) floor corners [m] in OpenCV's detection order."""
        h = self.size / 2
        local = np.array([[-h, h], [h, h], [h, -h], [-h, -h]])
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return local @ np.array([[c, s], [-s, c]]) + (self.x, self.y)


@dataclass(frozen=True)
class Lens:
    """Pinhole intrinsics and OpenCV's distortion (k1, k2, p1, p2, k3)."""

    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def D(self) -> np.ndarray:
        return np.array(self.dist, dtype=float)

    def undistort(self, pixels: np.ndarray) -> np.ndarray:
        """Pixel coordinates (N, 2) of the distorted image -> those of the ideal pinhole image."""
        pts = np.asarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
        if not np.any(self.D):
            return pts.reshape(-1, 2)
        return cv2.undistortPoints(pts, self.K, self.D, P=self.K).reshape(-1, 2)
