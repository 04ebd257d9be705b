"""Frame -> obstacle blobs -> tracked convex floor obstacles with velocity and covariance.

Segmentation is by colour (the lab's obstacles are painted one colour; HSV thresholds), each blob's
pixels taken to the floor through the calibration and wrapped in their convex hull. A blob's outline
is its silhouette: seen from above, a vertical prism's top shows beyond its footprint. Taken to the
plane of the obstacles' tops (``height``; the calibration knows the camera's pose) the silhouette
holds the top, which is the footprint, grown toward the camera's nadir; on the floor it holds the
base, grown away from it: the footprint lies in both, and their intersection is the polygon. Tracking: each track is
a constant-velocity Kalman filter on its centroid; blobs are given to tracks greedily by distance
within a gate, an unclaimed blob starts a track, a track unseen ``max_missed`` frames ends.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from drivers.camera_overhead.calibration import FloorCalibration
from onboard.geometry import polygons as pg


@dataclass(frozen=True)
class ColourRange:
    """Inclusive HSV bounds (OpenCV's: H 0-179, S and V 0-255)."""

    low: tuple[int, int, int] = (5, 120, 120)
    high: tuple[int, int, int] = (25, 255, 255)


def segment(frame: np.ndarray, colour: ColourRange, min_area_px: int = 40) -> list[np.ndarray]:
    """Convex hulls (k, 2) [px] of the blobs of ``colour`` at least ``min_area_px`` large."""
    hsv = cv2.cvtColor(frame, cv2.COLOR_BGR2HSV)
    mask = cv2.inRange(hsv, np.array(colour.low, np.uint8), np.array(colour.high, np.uint8))
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    return [cv2.convexHull(c).reshape(-1, 2).astype(float) for c in contours if cv2.contourArea(c) >= min_area_px]


def floor_polygon(hull_px: np.ndarray, calib: FloorCalibration, max_vertices: int = 12, tolerance_m: float = 0.01,
                  height: float = 0.0) -> np.ndarray:
    """A blob's convex hull on the floor (k, 2) [m], counter-clockwise, at most ``max_vertices`` corners
    (simplified outward: the outline simplified within ``eps`` and its faces pushed out by ``eps``, so
    nothing inside the hull is lost)."""
    hull = cv2.convexHull(calib.image_to_floor(hull_px).astype(np.float32)).reshape(-1, 2)
    if height > 0.0:
        top = _ccw(cv2.convexHull(calib.image_to_floor(hull_px, height).astype(np.float32)).reshape(-1, 2).astype(float))
        both = pg.clip_polygon(_ccw(hull.astype(float)), *pg.polygon_halfspaces(top))
        if len(both) >= 3:
            hull = cv2.convexHull(both.astype(np.float32)).reshape(-1, 2)
    poly = _ccw(hull.astype(float))
    eps = tolerance_m
    while len(poly) > max_vertices:
        inner = _ccw(cv2.convexHull(cv2.approxPolyDP(hull.reshape(-1, 1, 2), eps, True)).reshape(-1, 2).astype(float))
        if len(inner) >= 3:
            A, b = pg.polygon_halfspaces(inner)
            poly = _ccw(pg.polygon_from_halfspaces(A, b + eps))
        eps *= 2
    return poly


def _ccw(poly: np.ndarray) -> np.ndarray:
    area2 = float(np.sum(poly[:, 0] * np.roll(poly[:, 1], -1) - np.roll(poly[:, 0], -1) * poly[:, 1]))
    return poly if area2 > 0 else poly[::-1]


def centroid(poly: np.ndarray) -> np.ndarray:
    """Area centroid of a polygon (k, 2) [m]."""
    mo = cv2.moments(poly.astype(np.float32).reshape(-1, 1, 2))
    if mo["m00"] == 0.0:
        return poly.mean(axis=0)
    return np.array([mo["m10"] / mo["m00"], mo["m01"] / mo["m00"]])


@dataclass
class Track:
    id: int
    polygon: np.ndarray  # (k, 2) [m] as last seen
    x: np.ndarray  # [px, py, vx, vy] of the centroid [m, m/s]
    P: np.ndarray  # (4, 4) its covariance
    t: float  # [s] of the last update
    name: str = ""
    missed: int = 0
    hits: int = 1

    @property
    def velocity(self) -> tuple[float, float]:
        return float(self.x[2]), float(self.x[3])

    @property
    def position_cov(self) -> list[float]:
        return [float(v) for v in self.P[:2, :2].ravel()]

    def moved_polygon(self) -> np.ndarray:
        """The polygon where the filter puts the centroid now."""
        return self.polygon - centroid(self.polygon) + self.x[:2]


@dataclass
class Tracker:
    """Constant-velocity tracks of floor polygons."""

    accel_sigma: float = 1.0  # [m/s^2] the process noise: how hard an obstacle may be pushed
    measure_sigma: float = 0.02  # [m] centroid measurement noise
    gate_m: float = 0.6  # [m] a blob farther than this from a track's prediction is not it
    max_missed: int = 8  # frames a track may go unseen
    tracks: list[Track] = field(default_factory=list)
    _next_id: int = 0

    def update(self, t: float, polygons: list[np.ndarray]) -> list[Track]:
        """Predict every track to ``t`` [s], give the blobs to tracks, start and end tracks; the live tracks."""
        for tr in self.tracks:
            self._predict(tr, t)
        cents = [centroid(p) for p in polygons]
        pairs = sorted((float(np.hypot(*(c - tr.x[:2]))), i, j) for i, tr in enumerate(self.tracks) for j, c in enumerate(cents))
        used_t, used_b = set(), set()
        for d, i, j in pairs:
            if d > self.gate_m or i in used_t or j in used_b:
                continue
            used_t.add(i)
            used_b.add(j)
            self._correct(self.tracks[i], cents[j], polygons[j])
        for i, tr in enumerate(self.tracks):
            if i not in used_t:
                tr.missed += 1
        self.tracks = [tr for tr in self.tracks if tr.missed <= self.max_missed]
        for j, c in enumerate(cents):
            if j not in used_b:
                P = np.diag([self.measure_sigma ** 2] * 2 + [1.0, 1.0])  # speed unknown at birth: 1 m/s
                self.tracks.append(Track(self._next_id, polygons[j], np.array([c[0], c[1], 0.0, 0.0]), P, t))
                self._next_id += 1
        return [tr for tr in self.tracks if tr.missed == 0]

    def _predict(self, tr: Track, t: float) -> None:
        dt = max(t - tr.t, 0.0)
        F = np.eye(4)
        F[0, 2] = F[1, 3] = dt
        q = self.accel_sigma ** 2
        G = np.array([[dt * dt / 2, 0.0], [0.0, dt * dt / 2], [dt, 0.0], [0.0, dt]])
        tr.x = F @ tr.x
        tr.P = F @ tr.P @ F.T + q * (G @ G.T)
        tr.t = t

    def _correct(self, tr: Track, centroid: np.ndarray, polygon: np.ndarray) -> None:
        Hm = np.zeros((2, 4))
        Hm[0, 0] = Hm[1, 1] = 1.0
        S = Hm @ tr.P @ Hm.T + np.eye(2) * self.measure_sigma ** 2
        Kg = tr.P @ Hm.T @ np.linalg.inv(S)
        tr.x = tr.x + Kg @ (centroid - Hm @ tr.x)
        tr.P = (np.eye(4) - Kg @ Hm) @ tr.P
        tr.polygon = polygon
        tr.missed = 0
        tr.hits += 1


def speed(track: Track) -> float:
    return math.hypot(*track.velocity)
