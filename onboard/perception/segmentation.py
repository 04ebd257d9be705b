"""Traversable / occupied segmentation of an organized point cloud.

The thesis (3336) segmented traversable ground in the RGB image with a learned model
(EfficientTAM) and applied the mask to the point cloud. The default here needs no
learned weights: a RANSAC ground plane, then height above it and surface slope.
A learned segmenter plugs in through :class:`Segmenter` (anything with ``segment``),
for instance :class:`MaskSegmenter` around a function that returns a traversable mask.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from onboard.contracts.params import PerceptionParams

IGNORE = 0  # no return, or above the height band (overhangs the robot passes under)
TRAVERSABLE = 1
OCCUPIED = 2  # an obstacle: stands above the ground
UNTRAVERSABLE = 3  # ground the robot must not step on (grass beside the path): flat, so a ray passing over it clears nothing


@dataclass
class Cloud:
    """An organized point cloud and what a segmenter may use besides the points."""

    points: np.ndarray  # (h, w, 3) world [m]
    valid: np.ndarray  # (h, w) bool
    cam_pos: np.ndarray  # (3,) camera optical centre, world [m]
    image: np.ndarray | None = None  # (h, w, 3) colour aligned with the points, if any
    foot: np.ndarray | None = None  # (2,) the foot's world xy, if known (the ground under it seeds colour segmenters)


@dataclass(frozen=True)
class Plane:
    """``normal . p + offset = 0`` with a unit ``normal`` pointing up (world)."""

    normal: np.ndarray
    offset: float
    inliers: int

    def height(self, pts: np.ndarray) -> np.ndarray:
        """Signed height [m] of ``(..., 3)`` points above the plane."""
        return pts @ self.normal + self.offset


FLAT_GROUND = Plane(np.array([0.0, 0.0, 1.0]), 0.0, 0)  # fallback: the world plane z = 0


class Segmenter(Protocol):
    def segment(self, cloud: Cloud) -> np.ndarray:
        """Label per pixel ``(h, w)`` int8: IGNORE, TRAVERSABLE, OCCUPIED or UNTRAVERSABLE."""
        ...


def fit_ground_plane(pts: np.ndarray, params: PerceptionParams, rng: np.random.Generator) -> Plane | None:
    """RANSAC plane through ``(N, 3)`` points, tilted at most ``ground_tilt_max_deg``.

    Among candidate planes with the most inliers the lowest wins (a table top or a
    box face has fewer points below it than the floor), then a least-squares refit.
    """
    n = len(pts)
    if n < max(3, params.ground_min_points):
        return None
    it = params.ransac_iterations
    idx = rng.integers(0, n, size=(it, 3))
    a, b, c = pts[idx[:, 0]], pts[idx[:, 1]], pts[idx[:, 2]]
    normal = np.cross(b - a, c - a)
    length = np.linalg.norm(normal, axis=1)
    ok = length > 1e-9
    normal[ok] /= length[ok, None]
    normal[normal[:, 2] < 0] *= -1.0
    ok &= normal[:, 2] >= math.cos(math.radians(params.ground_tilt_max_deg))
    if not np.any(ok):
        return None
    normal, a = normal[ok], a[ok]
    offset = -np.einsum("ij,ij->i", normal, a)
    dist = pts @ normal.T + offset[None, :]  # (N, candidates)
    inl = np.abs(dist) <= params.ransac_inlier_m
    count = inl.sum(axis=0)
    best = int(count.max())
    if best < params.ground_min_points:
        return None
    # Most inliers, within 10 %; of those, the one with the fewest points below it.
    good = np.nonzero(count >= 0.9 * best)[0]
    below = (dist[:, good] < -params.ransac_inlier_m).sum(axis=0)
    k = int(good[np.argmin(below)])
    sel = pts[inl[:, k]]
    centroid = sel.mean(axis=0)
    _, _, vt = np.linalg.svd(sel - centroid, full_matrices=False)
    nrm = vt[2] if vt[2, 2] >= 0 else -vt[2]
    if nrm[2] < math.cos(math.radians(params.ground_tilt_max_deg)):
        nrm = normal[k]
        centroid = a[k]
    return Plane(nrm, float(-nrm @ centroid), int(inl[:, k].sum()))


def surface_normals(points: np.ndarray, valid: np.ndarray, jump: float, step: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals of an organized cloud from central differences ``step`` pixels wide.

    Returns ``(normals, ok)``; a pixel has a normal when its four neighbours at ``step``
    are valid and within ``2 step jump`` [m] (no depth discontinuity). A wider step
    averages out more depth noise and blurs small features.
    """
    h, w = valid.shape
    k = step
    nrm = np.zeros((h, w, 3))
    ok = np.zeros((h, w), dtype=bool)
    if h < 2 * k + 1 or w < 2 * k + 1:
        return nrm, ok
    p = points
    du = p[k:-k, 2 * k:] - p[k:-k, :-2 * k]
    dv = p[2 * k:, k:-k] - p[:-2 * k, k:-k]
    good = valid[k:-k, 2 * k:] & valid[k:-k, :-2 * k] & valid[2 * k:, k:-k] & valid[:-2 * k, k:-k] & valid[k:-k, k:-k]
    good &= (np.linalg.norm(du, axis=2) <= 2 * k * jump) & (np.linalg.norm(dv, axis=2) <= 2 * k * jump)
    n = np.cross(du, dv)
    length = np.linalg.norm(n, axis=2)
    good &= length > 1e-12
    n[good] /= length[good][:, None]
    n[n[..., 2] < 0] *= -1.0
    nrm[k:-k, k:-k] = n
    ok[k:-k, k:-k] = good
    return nrm, ok


class GeometricSegmenter:
    """Ground plane by RANSAC; ground = near the plane (a tolerance growing with range)
    and not steep; obstacles = the rest up to ``obstacle_height_max_m`` above the plane
    (drop-offs below it included); higher points are ignored.

    The ground changes slowly while one RANSAC draw can tilt a few degrees (which lifts
    far ground by decimetres): the previous plane is kept while it explains the view
    nearly as well (``plane_keep_fraction`` of the new plane's inliers).
    """

    def __init__(self, params: PerceptionParams = PerceptionParams()) -> None:
        self.params = params
        self.rng = np.random.default_rng(params.seed)
        self.plane: Plane = FLAT_GROUND  # the plane of the last view
        self.found = False  # whether any view had a plane of its own
        self.kept = 0  # views where the previous plane won over a new fit

    def segment(self, cloud: Cloud) -> np.ndarray:
        p = self.params
        labels = np.full(cloud.valid.shape, IGNORE, dtype=np.int8)
        pts = cloud.points[cloud.valid]
        plane = fit_ground_plane(pts, p, self.rng)
        if plane is not None:
            if self.found:
                prev = int((np.abs(self.plane.height(pts)) <= p.ransac_inlier_m).sum())
                if prev >= p.plane_keep_fraction * plane.inliers:
                    plane = Plane(self.plane.normal, self.plane.offset, prev)
                    self.kept += 1
            self.plane = plane
            self.found = True
        h = self.plane.height(cloud.points)
        nrm, has_nrm = surface_normals(cloud.points, cloud.valid, p.depth_jump_m, p.normal_step_px)
        steep = has_nrm & (nrm @ self.plane.normal < math.cos(math.radians(p.slope_max_deg)))
        rng = np.linalg.norm(cloud.points - cloud.cam_pos, axis=-1)
        near = np.abs(h) <= p.ground_tol_m + p.ground_tol_per_m * rng
        ground = cloud.valid & near & ~steep
        obstacle = cloud.valid & ~ground & (h <= p.obstacle_height_max_m)
        labels[ground] = TRAVERSABLE
        labels[obstacle] = OCCUPIED
        return labels


class MaskSegmenter:
    """Adapter for a learned segmenter: ``mask_fn(cloud) -> (h, w) bool`` traversable.

    Valid pixels in the mask are traversable; valid pixels outside it are obstacles
    when within the height band above the ground plane (found as the geometric
    segmenter does), else ignored.
    """

    def __init__(self, mask_fn: Callable[[Cloud], np.ndarray], params: PerceptionParams = PerceptionParams()) -> None:
        self.mask_fn = mask_fn
        self.geometric = GeometricSegmenter(params)

    def segment(self, cloud: Cloud) -> np.ndarray:
        mask = np.asarray(self.mask_fn(cloud), dtype=bool)
        if mask.shape != cloud.valid.shape:
            raise ValueError(f"segmentation mask {mask.shape} does not match the cloud {cloud.valid.shape}")
        geo = self.geometric.segment(cloud)
        labels = np.full(cloud.valid.shape, IGNORE, dtype=np.int8)
        labels[cloud.valid & mask] = TRAVERSABLE
        labels[cloud.valid & ~mask & (geo == OCCUPIED)] = OCCUPIED
        labels[cloud.valid & ~mask & (geo == TRAVERSABLE)] = UNTRAVERSABLE
        return labels
