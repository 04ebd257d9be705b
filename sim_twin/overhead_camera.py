"""The twin's overhead camera: the scene's geometry projected through a pinhole camera looking down
at the floor, with lens distortion and pixel noise (numpy and OpenCV, no OpenGL), ArUco markers
drawn on the floor at known poses. What :mod:`drivers.camera_overhead` sees in the lab, made from the
scenario: the floor, the markers, each obstacle's silhouette (a prism: the hull of its base and top
corners as projected) in the obstacles' colour, the robot as a dark cylinder.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from onboard.geometry.floor_camera import Lens, Marker

from sim_twin import scenarios as sc

# the markers printed for the lab floor (drivers.camera_overhead.calibration.DICTIONARY)
DICTIONARY = cv2.aruco.DICT_4X4_50

FLOOR_BGR = (150, 150, 150)
OBSTACLE_BGR = (0, 140, 255)  # orange: what drivers.camera_overhead.tracking.ColourRange() finds
OBSTACLE_TOP_BGR = (40, 170, 255)
ROBOT_BGR = (70, 45, 45)
ROBOT_HEIGHT = 0.6  # [m] drawn height of the robot's body
ROBOT_RADIUS = 0.13  # [m]
QUIET = 0.25  # a marker's white margin, in marker sides per side


@dataclass(frozen=True)
class OverheadCamera:
    """A camera at ``position`` [m] looking straight down, image x along world x (image y along -y)."""

    lens: Lens
    width: int
    height: int
    position: tuple[float, float, float]
    noise_sigma: float = 2.0  # [grey levels] per pixel
    yaw: float = 0.0  # [rad] of the image's x axis from world x

    def extrinsics(self) -> tuple[np.ndarray, np.ndarray]:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        R = np.array([[c, s, 0.0], [s, -c, 0.0], [0.0, 0.0, -1.0]])  # rows: camera x, y, z in world
        t = -R @ np.array(self.position)
        return cv2.Rodrigues(R)[0], t

    def project(self, points: np.ndarray, distorted: bool = False) -> np.ndarray:
        """World points (N, 3) -> pixels (N, 2) of the ideal (or distorted) image."""
        rvec, tvec = self.extrinsics()
        dist = self.lens.D if distorted else np.zeros(5)
        px, _ = cv2.projectPoints(np.asarray(points, dtype=np.float64).reshape(-1, 1, 3), rvec, tvec, self.lens.K, dist)
        return px.reshape(-1, 2)


def default_camera() -> OverheadCamera:
    """A ceiling camera over the scenarios' field (x -1..7 m, y -3..3 m) with a mild barrel lens."""
    return OverheadCamera(Lens(560.0, 560.0, 480.0, 360.0, (-0.08, 0.02, 0.0, 0.0, 0.0)), 960, 720, (3.0, 0.0, 5.0))


def default_markers() -> list[Marker]:
    """Six 0.4 m markers on the floor around the field, their poses known (the lab's survey)."""
    spots = [(-0.4, 2.4, 0.0), (3.0, 2.6, 0.3), (6.4, 2.4, 0.0), (-0.4, -2.4, 1.2), (3.0, -2.6, 0.0), (6.4, -2.4, -0.5)]
    return [Marker(i, x, y, 0.4, yaw) for i, (x, y, yaw) in enumerate(spots)]


class OverheadRenderer:
    """Renders frames of a scenario; the distortion maps and markers are made once."""

    def __init__(self, camera: OverheadCamera, markers: list[Marker], seed: int = 0) -> None:
        self.camera = camera
        self.markers = markers
        self.rng = np.random.default_rng(seed)
        w, h = camera.width, camera.height
        # the distorted frame's pixel (u, v) shows the ideal image at undistort(u, v)
        grid = np.stack(np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64)), axis=-1).reshape(-1, 2)
        ideal = camera.lens.undistort(grid).reshape(h, w, 2).astype(np.float32)
        self.map_x, self.map_y = ideal[..., 0].copy(), ideal[..., 1].copy()
        self.floor = self._floor_with_markers()

    def _floor_with_markers(self) -> np.ndarray:
        cam = self.camera
        img = np.full((cam.height, cam.width, 3), FLOOR_BGR, np.uint8)
        dictionary = cv2.aruco.getPredefinedDictionary(DICTIONARY)
        side = 120
        pad = int(round(side * QUIET))
        for mk in self.markers:
            tag = cv2.aruco.generateImageMarker(dictionary, mk.id, side)
            tag = cv2.copyMakeBorder(tag, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255)
            tag = cv2.cvtColor(tag, cv2.COLOR_GRAY2BGR)
            grown = Marker(mk.id, mk.x, mk.y, mk.size * (1 + 2 * QUIET), mk.yaw).corners()
            dst = cam.project(np.c_[grown, np.zeros(4)]).astype(np.float32)
            n = tag.shape[0]
            src = np.array([[0, 0], [n, 0], [n, n], [0, n]], np.float32)
            M = cv2.getPerspectiveTransform(src, dst)
            warped = cv2.warpPerspective(tag, M, (cam.width, cam.height), flags=cv2.INTER_AREA)
            mask = cv2.warpPerspective(np.full((n, n), 255, np.uint8), M, (cam.width, cam.height)) > 127
            img[mask] = warped[mask]
        return img

    def render(self, scenario: sc.Scenario, robot_xy: tuple[float, float] | None = None) -> np.ndarray:
        """The frame (BGR, distorted, noisy) of the scenario's obstacles where they are now and the robot."""
        cam = self.camera
        img = self.floor.copy()
        for k, ob in enumerate(scenario.obstacles):
            base = np.array(ob.vertices) + scenario.offsets[k]
            pts = np.concatenate([np.c_[base, np.zeros(len(base))], np.c_[base, np.full(len(base), ob.height)]])
            px = cam.project(pts)
            cv2.fillConvexPoly(img, np.round(cv2.convexHull(px.astype(np.float32)).reshape(-1, 2) * 16).astype(np.int32),
                               OBSTACLE_BGR, cv2.LINE_AA, 4)
            top = px[len(base):]
            cv2.fillConvexPoly(img, np.round(top * 16).astype(np.int32), OBSTACLE_TOP_BGR, cv2.LINE_AA, 4)
        if robot_xy is not None:
            ring = [(robot_xy[0] + ROBOT_RADIUS * math.cos(a), robot_xy[1] + ROBOT_RADIUS * math.sin(a), z)
                    for a in np.linspace(0, 2 * math.pi, 16, endpoint=False) for z in (0.0, ROBOT_HEIGHT)]
            px = cam.project(np.array(ring)).astype(np.float32)
            cv2.fillConvexPoly(img, np.round(cv2.convexHull(px).reshape(-1, 2) * 16).astype(np.int32), ROBOT_BGR, cv2.LINE_AA, 4)
        out = cv2.remap(img, self.map_x, self.map_y, cv2.INTER_LINEAR, borderValue=(0, 0, 0))
        if cam.noise_sigma > 0:
            noise = self.rng.normal(0.0, cam.noise_sigma, out.shape)
            out = np.clip(out.astype(np.float64) + noise, 0, 255).astype(np.uint8)
        return out
