"""Traversable terrain from colour and depth together (thesis 8.2, line 3336): a segmenter behind
:class:`onboard.perception.segmentation.Segmenter` with no learned weights.

The thesis tracked the traversable region (sidewalk, brick walkway) in the RGB image with a
learned model. Here the robot's own footing says what traversable looks like: the geometric
ground (:class:`GeometricSegmenter`: near the RANSAC plane, not steep) within
``terrain_seed_range_m`` of the foot is taken to be what the robot stands on. The image,
smoothed and in CIE Lab, is clustered (K-means, the segmenter's own seeded generator); the
clusters that hold a good share of the seed pixels, or whose centre lies near the seed's
colour (remembered over views; lightness weighs less than hue, ``terrain_lightness_weight``), are
the traversable colours. A pixel is then

- ``TRAVERSABLE``: geometric ground of a traversable colour;
- ``OCCUPIED``: an obstacle by geometry;
- ``UNTRAVERSABLE``: ground of another colour (grass beside the path);
- ``IGNORE``: no return, or above the height band.

Without an image (a depth-only camera) it answers as the geometric segmenter does. A learned
segmenter replaces it through the same interface (``MaskSegmenter``).
"""

from __future__ import annotations

import cv2
import numpy as np

from onboard.contracts.params import PerceptionParams
from onboard.perception.segmentation import IGNORE, TRAVERSABLE, UNTRAVERSABLE, Cloud, GeometricSegmenter

KMEANS_SAMPLES = 4000  # pixels the clusters are fitted on (every pixel is then assigned)
KMEANS_ITERATIONS = 12


def kmeans(x: np.ndarray, k: int, rng: np.random.Generator, iterations: int = KMEANS_ITERATIONS) -> np.ndarray:
    """Centres ``(k, d)`` of ``x`` ``(n, d)`` by Lloyd's iterations from a k-means++ start."""
    n = len(x)
    centres = [x[int(rng.integers(n))]]
    d2 = np.sum((x - centres[0]) ** 2, axis=1)
    for _ in range(1, k):
        total = float(d2.sum())
        i = int(rng.choice(n, p=d2 / total)) if total > 0 else int(rng.integers(n))
        centres.append(x[i])
        d2 = np.minimum(d2, np.sum((x - x[i]) ** 2, axis=1))
    c = np.array(centres, dtype=float)
    for _ in range(iterations):
        assign = nearest(x, c)
        for j in range(k):
            members = x[assign == j]
            if len(members):
                c[j] = members.mean(axis=0)
    return c


def nearest(x: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Index of the nearest centre of each row of ``x``."""
    d = (x * x).sum(1)[:, None] - 2.0 * x @ centres.T + (centres * centres).sum(1)[None, :]
    return np.argmin(d, axis=1)


class ColorTerrainSegmenter:
    """Colour clusters seeded by the ground under the foot, and the depth's geometry."""

    def __init__(self, params: PerceptionParams = PerceptionParams()) -> None:
        if params.terrain_blur_px % 2 == 0:
            raise ValueError(f"perception.terrain_blur_px must be odd, got {params.terrain_blur_px}")
        self.params = params
        self.geometric = GeometricSegmenter(params)
        self.rng = np.random.default_rng(params.seed + 1)
        self.seed_color: np.ndarray | None = None  # Lab of what the robot stands on, remembered over views
        self.seeded_views = 0
        self.seed_jumps = 0  # views whose seed was too far from the remembered colour to be taken
        self._agreed = 0  # views in a row whose seed agreed with the memory

    @property
    def plane(self):  # the pipeline reports the ground plane's inliers
        return self.geometric.plane

    def segment(self, cloud: Cloud) -> np.ndarray:
        p = self.params
        labels = self.geometric.segment(cloud)
        if cloud.image is None:
            return labels
        image = np.asarray(cloud.image)
        if image.shape[:2] != cloud.valid.shape:
            raise ValueError(f"colour image {image.shape[:2]} does not match the cloud {cloud.valid.shape}")
        ground = labels == TRAVERSABLE
        blur = cv2.GaussianBlur(np.ascontiguousarray(image, dtype=np.uint8), (p.terrain_blur_px, p.terrain_blur_px), 0)
        lab = cv2.cvtColor(blur, cv2.COLOR_RGB2Lab).reshape(-1, 3).astype(float)
        valid = cloud.valid.reshape(-1)
        if valid.sum() < p.terrain_clusters:
            return labels
        foot = cloud.foot if cloud.foot is not None else np.asarray(cloud.cam_pos, dtype=float)[:2]
        near = np.hypot(cloud.points[..., 0] - foot[0], cloud.points[..., 1] - foot[1]) <= p.terrain_seed_range_m
        seed = (ground & near).reshape(-1)
        trusted = True  # the seed pixels are what the robot stands on
        if seed.sum() >= p.terrain_min_seed_px:
            here = np.median(lab[seed], axis=0)
            jump = self.seed_color is not None and float(np.linalg.norm(here - self.seed_color)) > p.terrain_seed_jump
            if jump and self._agreed >= p.terrain_seed_confirm:
                trusted = False  # across a boundary (PerceptionParams.terrain_seed_jump)
                self.seed_jumps += 1
            else:
                self._agreed = 0 if jump else self._agreed + 1
                w = p.terrain_memory if self.seed_color is not None else 0.0
                self.seed_color = here if self.seed_color is None else w * self.seed_color + (1.0 - w) * here
                self.seeded_views += 1
        if self.seed_color is None:
            return labels  # nothing known of what the robot stands on: geometry alone
        pool = np.nonzero(valid)[0]
        sample = lab[pool[self.rng.choice(len(pool), size=min(KMEANS_SAMPLES, len(pool)), replace=False)]]
        centres = kmeans(sample, p.terrain_clusters, self.rng)
        assign = nearest(lab, centres)
        share = np.bincount(assign[seed], minlength=p.terrain_clusters) / max(int(seed.sum()), 1)
        weight = np.array([p.terrain_lightness_weight, 1.0, 1.0])
        close = np.linalg.norm((centres - self.seed_color) * weight, axis=1) <= p.terrain_color_distance
        good = ((share >= p.terrain_seed_share) | close) if trusted else close
        colour_ok = good[assign].reshape(cloud.valid.shape).astype(np.uint8)
        kernel = np.ones((3, 3), np.uint8)  # specks of the wrong cluster inside a surface are texture
        colour_ok = cv2.morphologyEx(cv2.morphologyEx(colour_ok, cv2.MORPH_CLOSE, kernel), cv2.MORPH_OPEN, kernel) > 0
        out = labels.copy()
        out[ground & ~colour_ok] = UNTRAVERSABLE
        out[~cloud.valid] = IGNORE
        return out
