"""k-means on 2D points with the caller's random generator (no global random state).

OpenCV's ``cv2.kmeans`` draws its k-means++ seeds from OpenCV's process-wide generator, so
a caller had to reseed that global before each call; here the generator is an argument.
"""

from __future__ import annotations

import numpy as np

MAX_ITERATIONS = 20  # Lloyd iterations at most
CENTER_SHIFT_TOL = 0.1  # [point units] stop when no centre moves more than this


def kmeans_labels(points: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """Cluster index (0..k-1) of each row of ``points`` (n x 2): k-means++ seeding, then Lloyd."""
    pts = np.asarray(points, dtype=float)
    n = len(pts)
    if not 1 <= k <= n:
        raise ValueError(f"k must be within 1..{n}, got {k}")
    centers = np.empty((k, pts.shape[1]))
    centers[0] = pts[rng.integers(n)]
    nearest = np.sum((pts - centers[0]) ** 2, axis=1)
    for j in range(1, k):
        total = nearest.sum()
        # every point already a centre: any point will do
        pick = rng.integers(n) if total <= 0.0 else rng.choice(n, p=nearest / total)
        centers[j] = pts[pick]
        nearest = np.minimum(nearest, np.sum((pts - centers[j]) ** 2, axis=1))
    labels = np.zeros(n, dtype=np.int32)
    for _ in range(MAX_ITERATIONS):
        dist = ((pts[:, None, :] - centers[None, :, :]) ** 2).sum(axis=2)
        labels = np.argmin(dist, axis=1).astype(np.int32)
        moved = 0.0
        for j in range(k):
            members = pts[labels == j]
            if len(members):  # an empty cluster keeps its centre
                new = members.mean(axis=0)
                moved = max(moved, float(np.linalg.norm(new - centers[j])))
                centers[j] = new
        if moved < CENTER_SHIFT_TOL:
            break
    return labels
