"""The floor as the overhead camera sees it: lens model, ArUco markers at known floor poses, and the
homography from the undistorted image to the floor plane (world x, y [m]).

A marker's pose is its centre and yaw on the floor; its corners, in OpenCV's order (top-left,
top-right, bottom-right, bottom-left of the marker image), lie at (-s/2, +s/2), (+s/2, +s/2),
(+s/2, -s/2), (-s/2, -s/2) in its own frame (x to the marker image's right, y to its top).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from onboard.geometry.floor_camera import Lens, Marker

DICTIONARY = cv2.aruco.DICT_4X4_50  # the markers printed for the lab floor


class CalibrationError(ValueError):
    """The frame does not show enough known markers to fix the floor."""


def detect_markers(frame: np.ndarray, dictionary: int = DICTIONARY) -> dict[int, np.ndarray]:
    """Marker id -> (4, 2) corner pixels (sub-pixel), in the frame as captured."""
    gray = frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(dictionary), params)
    corners, ids, _ = detector.detectMarkers(gray)
    if ids is None:
        return {}
    return {int(i): c.reshape(4, 2).astype(float) for i, c in zip(ids.ravel(), corners)}


@dataclass(frozen=True)
class FloorCalibration:
    """Undistorted image <-> floor homography and how well the markers fit it."""

    lens: Lens
    H: np.ndarray  # (3, 3) floor [m] -> ideal image [px]
    rms_px: float  # reprojection error of the marker corners [px, ideal image]
    rms_m: float  # the same on the floor [m]
    markers_used: tuple[int, ...]

    @classmethod
    def from_frame(cls, frame: np.ndarray, markers: list[Marker], lens: Lens, dictionary: int = DICTIONARY,
                   min_markers: int = 2) -> FloorCalibration:
        """Fit the homography to the corners of the known markers the frame shows (at least ``min_markers``)."""
        seen = detect_markers(frame, dictionary)
        known = {mk.id: mk for mk in markers}
        used = sorted(i for i in seen if i in known)
        if len(used) < min_markers:
            raise CalibrationError(f"{len(used)} known markers seen (ids {sorted(seen)}), need {min_markers}")
        img = lens.undistort(np.concatenate([seen[i] for i in used]))
        floor = np.concatenate([known[i].corners() for i in used])
        H, _ = cv2.findHomography(floor, img, 0)
        if H is None:
            raise CalibrationError("the marker corners fix no homography")
        proj = cv2.perspectiveTransform(floor.reshape(-1, 1, 2), H).reshape(-1, 2)
        back = cv2.perspectiveTransform(img.reshape(-1, 1, 2), np.linalg.inv(H)).reshape(-1, 2)
        rms_px = float(np.sqrt(np.mean(np.sum((proj - img) ** 2, axis=1))))
        rms_m = float(np.sqrt(np.mean(np.sum((back - floor) ** 2, axis=1))))
        return cls(lens, H, rms_px, rms_m, tuple(used))

    def image_to_floor(self, pixels: np.ndarray, height: float = 0.0) -> np.ndarray:
        """Captured-frame pixels (N, 2) -> points (N, 2) [m] of the horizontal plane ``height`` [m] above
        the floor (0: the floor itself) that they show."""
        ideal = self.lens.undistort(pixels)
        H = self.H if height == 0.0 else self.plane_homography(height)
        return cv2.perspectiveTransform(ideal.reshape(-1, 1, 2), np.linalg.inv(H)).reshape(-1, 2)

    def pose(self) -> tuple[np.ndarray, np.ndarray]:
        """The camera's rotation R (world -> camera) and translation t, from the floor homography and
        the lens (H = K [r1 r2 t] up to scale; R made orthonormal)."""
        M = np.linalg.inv(self.lens.K) @ self.H
        lam = 1.0 / np.linalg.norm(M[:, 0])
        if (lam * M[:, 2])[2] < 0:  # the floor lies in front of the camera
            lam = -lam
        r1, r2 = lam * M[:, 0], lam * M[:, 1]
        U, _, Vt = np.linalg.svd(np.stack([r1, r2, np.cross(r1, r2)], axis=1))
        R = U @ Vt
        return R, lam * M[:, 2]

    def plane_homography(self, height: float) -> np.ndarray:
        """(3, 3) points of the plane ``height`` [m] above the floor -> ideal-image pixels."""
        R, t = self.pose()
        H = self.lens.K @ np.stack([R[:, 0], R[:, 1], height * R[:, 2] + t], axis=1)
        return H / H[2, 2]

    def floor_to_ideal(self, points: np.ndarray) -> np.ndarray:
        """Floor points (N, 2) [m] -> ideal-image pixels (N, 2)."""
        return cv2.perspectiveTransform(np.asarray(points, dtype=np.float64).reshape(-1, 1, 2), self.H).reshape(-1, 2)

    def to_dict(self) -> dict:
        return {"H": self.H.tolist(), "rms_px": self.rms_px, "rms_m": self.rms_m, "markers": list(self.markers_used)}
