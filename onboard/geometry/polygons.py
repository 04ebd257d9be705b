"""Convex polygons: validated, converted between vertex and halfspace form, packed.

What the collision tests (:mod:`onboard.high_level.tracking.collision`), the planner and perception's
output share. Frames and units: world frame, metres. Polygons are ``(k, 2)`` vertex
arrays, stored counter-clockwise; :class:`PolygonSet` packs many for the compiled kernels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np

POLYGON_AREA_TOL = 1e-9  # [m^2] below this a polygon is degenerate
VERTEX_MERGE_TOL = 1e-9  # [m] consecutive vertices closer than this are a repeated vertex


class PolygonError(ValueError):
    """A polygon that is not a finite, non-degenerate convex polygon."""


_POLYGON_ERRORS = {
    1: "polygon needs at least 3 vertices",
    2: "polygon has a non-finite coordinate",
    3: "polygon has a repeated vertex",
    4: "polygon has zero area",
    5: "polygon is not convex",
    6: "polygon is not simple (its boundary winds more than once)",
}


@nb.njit(cache=True)
def _pack_kernel(raw, offsets):  # pragma: no cover - compiled
    """Validate polygons and build CCW vertices, outward unit normals, face offsets,
    boxes and bounding circles; ``err[i]`` is a ``_POLYGON_ERRORS`` code (0: fine)."""
    M = offsets.shape[0] - 1
    V = raw.shape[0]
    verts = np.empty((V, 2))
    normals = np.empty((V, 2))
    face = np.empty(V)
    aabb = np.empty((M, 4))
    center = np.empty((M, 2))
    radius = np.empty(M)
    err = np.zeros(M, dtype=np.int64)
    for i in range(M):
        a = offsets[i]
        n = offsets[i + 1] - a
        if n < 3:
            err[i] = 1
            continue
        finite = True
        for k in range(n):
            if not (np.isfinite(raw[a + k, 0]) and np.isfinite(raw[a + k, 1])):
                finite = False
        if not finite:
            err[i] = 2
            continue
        area2 = 0.0
        for k in range(n):
            k1 = (k + 1) % n
            area2 += raw[a + k, 0] * raw[a + k1, 1] - raw[a + k1, 0] * raw[a + k, 1]
        for k in range(n):  # counter-clockwise copy
            src = k if area2 >= 0 else n - 1 - k
            verts[a + k, 0] = raw[a + src, 0]
            verts[a + k, 1] = raw[a + src, 1]
        turning = 0.0
        for k in range(n):
            k1 = (k + 1) % n
            k2 = (k + 2) % n
            ex = verts[a + k1, 0] - verts[a + k, 0]
            ey = verts[a + k1, 1] - verts[a + k, 1]
            fx = verts[a + k2, 0] - verts[a + k1, 0]
            fy = verts[a + k2, 1] - verts[a + k1, 1]
            le = math.sqrt(ex * ex + ey * ey)
            lf = math.sqrt(fx * fx + fy * fy)
            if le <= VERTEX_MERGE_TOL or lf <= VERTEX_MERGE_TOL:
                err[i] = 3
                break
            cross = ex * fy - ey * fx
            if cross < -1e-12 * le * lf:
                err[i] = 5
            turning += math.atan2(cross, ex * fx + ey * fy)
            normals[a + k, 0] = ey / le
            normals[a + k, 1] = -ex / le
            face[a + k] = normals[a + k, 0] * verts[a + k, 0] + normals[a + k, 1] * verts[a + k, 1]
        if err[i] == 3:
            continue
        if abs(area2) / 2 <= POLYGON_AREA_TOL:
            err[i] = 4
            continue
        if err[i] != 0:
            continue
        if abs(turning - 2 * math.pi) > 1e-6:
            err[i] = 6
            continue
        x0 = y0 = np.inf
        x1 = y1 = -np.inf
        for k in range(n):
            x0 = min(x0, verts[a + k, 0])
            y0 = min(y0, verts[a + k, 1])
            x1 = max(x1, verts[a + k, 0])
            y1 = max(y1, verts[a + k, 1])
        aabb[i, 0] = x0
        aabb[i, 1] = y0
        aabb[i, 2] = x1
        aabb[i, 3] = y1
        cx = (x0 + x1) / 2
        cy = (y0 + y1) / 2
        center[i, 0] = cx
        center[i, 1] = cy
        r = 0.0
        for k in range(n):
            r = max(r, math.hypot(verts[a + k, 0] - cx, verts[a + k, 1] - cy))
        radius[i] = r
    return verts, normals, face, aabb, center, radius, err


def _as_point_array(points: object) -> np.ndarray:
    try:
        pts = np.asarray(points, dtype=float)
    except (TypeError, ValueError) as exc:
        raise PolygonError(f"polygon is not an array of [x, y] points: {exc}") from None
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise PolygonError(f"polygon must be a list of [x, y] points, got shape {pts.shape}")
    return pts


def validate_polygon(points: object) -> np.ndarray:
    """The polygon as a counter-clockwise ``(k, 2)`` float array, or :class:`PolygonError`.

    Rejected: non-finite coordinates, fewer than 3 vertices, repeated consecutive
    vertices, zero area, and non-convex polygons (a reflex corner, or a boundary that
    winds more than once). Collinear vertices are allowed.
    """
    return pack_polygons([points]).polygon(0).copy()


def polygon_from_halfspaces(A: np.ndarray, b: np.ndarray, bounds: np.ndarray | None = None) -> np.ndarray:
    """Vertices (CCW) of ``{x : A x <= b}`` in the plane, clipped to ``bounds`` if given.

    ``bounds`` is ``[[xmin, ymin], [xmax, ymax]]``; without it the set must be bounded
    (a large box is used for clipping and any vertex on it raises). Raises
    :class:`PolygonError` when the set is empty or degenerate.
    """
    A = np.asarray(A, dtype=float)
    b = np.asarray(b, dtype=float)
    if A.ndim != 2 or A.shape[1] != 2 or b.shape != (A.shape[0],):
        raise PolygonError(f"halfspaces must be A (k, 2) and b (k,), got {A.shape} and {b.shape}")
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(b))):
        raise PolygonError("halfspaces have a non-finite entry")
    big = bounds is None
    if big:
        scale = 1e6
        box = np.array([[-scale, -scale], [scale, -scale], [scale, scale], [-scale, scale]])
    else:
        (x0, y0), (x1, y1) = np.asarray(bounds, dtype=float)
        box = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    poly = clip_polygon(box, A, b)
    if big and len(poly) and np.max(np.abs(poly)) >= 1e6 * (1 - 1e-9):
        raise PolygonError("halfspaces do not bound a polygon")
    return validate_polygon(poly)


def clip_polygon(poly: np.ndarray, A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``poly`` (CCW) intersected with every halfspace ``A_i x <= b_i`` (Sutherland-Hodgman)."""
    out = np.asarray(poly, dtype=float)
    for a, c in zip(np.asarray(A, dtype=float), np.asarray(b, dtype=float)):
        if len(out) == 0:
            break
        s = out @ a - c
        keep: list[np.ndarray] = []
        n = len(out)
        for i in range(n):
            j = (i + 1) % n
            if s[i] <= 0:
                keep.append(out[i])
            if (s[i] < 0 < s[j]) or (s[j] < 0 < s[i]):
                t = s[i] / (s[i] - s[j])
                keep.append(out[i] + t * (out[j] - out[i]))
        out = np.array(keep).reshape(-1, 2)
    return out


def polygon_halfspaces(poly: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(A, b)`` with unit outward rows such that ``poly = {x : A x <= b}`` (poly CCW)."""
    edges = np.roll(poly, -1, axis=0) - poly
    normals = np.stack([edges[:, 1], -edges[:, 0]], axis=1)
    normals /= np.hypot(normals[:, 0], normals[:, 1])[:, None]
    return normals, np.einsum("ij,ij->i", normals, poly)


@dataclass(frozen=True)
class PolygonSet:
    """Convex polygons packed for the kernels (see :func:`pack_polygons`)."""

    vertices: np.ndarray  # (V, 2) CCW vertices, polygon after polygon [m]
    offsets: np.ndarray  # (M + 1,) polygon i is vertices[offsets[i]:offsets[i+1]]
    normals: np.ndarray  # (V, 2) unit outward normal of the face from vertex v to v+1
    face_offsets: np.ndarray  # (V,) normals[v] . vertices[v]: the polygon is normals x <= face_offsets
    aabb: np.ndarray  # (M, 4) xmin, ymin, xmax, ymax [m]
    center: np.ndarray  # (M, 2) bounding-circle centre [m]
    radius: np.ndarray  # (M,) bounding-circle radius [m]

    def __len__(self) -> int:
        return len(self.offsets) - 1

    def polygon(self, i: int) -> np.ndarray:
        return self.vertices[self.offsets[i]:self.offsets[i + 1]]


def pack_polygons(polygons: list | tuple) -> PolygonSet:
    """Validate and pack convex polygons (any orientation) for the kernels.

    Raises :class:`PolygonError` naming the first bad polygon (see :func:`validate_polygon`).
    """
    arrays = [_as_point_array(p) for p in polygons]
    counts = np.array([len(p) for p in arrays], dtype=np.int64)
    offsets = np.zeros(len(arrays) + 1, dtype=np.int64)
    np.cumsum(counts, out=offsets[1:])
    raw = np.ascontiguousarray(np.concatenate(arrays)) if arrays else np.zeros((0, 2))
    verts, normals, face, aabb, center, radius, err = _pack_kernel(raw, offsets)
    bad = np.flatnonzero(err)
    if len(bad):
        i = int(bad[0])
        where = f" (polygon {i})" if len(arrays) > 1 else ""
        raise PolygonError(_POLYGON_ERRORS[int(err[i])] + where)
    return PolygonSet(verts, offsets, normals, face, aabb, center, radius)
