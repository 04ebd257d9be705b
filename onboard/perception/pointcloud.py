"""Depth image to a world-frame point cloud.

Pinhole model with the twin's and the RealSense's convention: the centre of pixel
``[row i, column j]`` is at image coordinates ``(j + 0.5, i + 0.5)``, its ray in the
camera frame (x right, y down, z forward) is ``((u - cx) / fx, (v - cy) / fy, 1)``, and
the depth is the distance along z. The camera pose at capture time (``cam_pos``,
``cam_quat`` camera -> world, ``[w, x, y, z]``) places the points in the world.
"""

from __future__ import annotations

import math

import numpy as np

from onboard.contracts.binary_messages import DepthImage
from onboard.geometry.quaternion import to_matrix


def camera_rotation(quat: np.ndarray) -> np.ndarray:
    """Camera -> world rotation matrix of a (normalized) ``[w, x, y, z]`` quaternion."""
    q = np.asarray(quat, dtype=float)
    n = float(np.linalg.norm(q))
    if not (math.isfinite(n) and n > 0.0):
        raise ValueError("camera quaternion is not finite or is zero")
    return np.array(to_matrix(q / n))


def depth_to_points(img: DepthImage, max_range: float = math.inf, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Organized point cloud of a depth image.

    Returns ``(points, valid)``: ``points`` ``(h, w, 3)`` world [m] for every
    ``stride``-th pixel in both directions, ``valid`` ``(h, w)`` where the pixel has a
    finite return with ``0 < depth <= max_range`` [m].
    """
    if stride < 1:
        raise ValueError("stride must be >= 1")
    if not all(math.isfinite(v) for v in (img.fx, img.fy, img.cx, img.cy)) or img.fx <= 0 or img.fy <= 0:
        raise ValueError("depth image needs finite, positive focal lengths")
    depth = np.asarray(img.depth, dtype=float)[::stride, ::stride]
    rows, cols = np.asarray(img.depth).shape
    v = (np.arange(0, rows, stride) + 0.5 - img.cy) / img.fy
    u = (np.arange(0, cols, stride) + 0.5 - img.cx) / img.fx
    valid = np.isfinite(depth) & (depth > 0.0) & (depth <= max_range)
    z = np.where(valid, depth, 0.0)
    cam = np.empty(depth.shape + (3,))
    cam[..., 0] = u[None, :] * z
    cam[..., 1] = v[:, None] * z
    cam[..., 2] = z
    rot = camera_rotation(img.cam_quat)
    pts = cam @ rot.T + np.asarray(img.cam_pos, dtype=float)
    return pts, valid
