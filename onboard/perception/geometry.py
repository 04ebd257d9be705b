"""Convex polygons in the plane and exact tests against occupancy-grid cells.

A :class:`ConvexPolygon` carries both forms the planner needs: the H-form
``{x : A x <= b}`` (rows of ``A`` are unit outward normals) and its vertices in
counter-clockwise order. Grid cells are squares: cell ``[row, col]`` of a grid with
resolution ``res`` [m] and lower-left origin ``(ox, oy)`` [m] is
``[ox + col res, ox + (col + 1) res] x [oy + row res, oy + (row + 1) res]``
(row index along world y, column index along world x).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# Two sets "overlap" when they share more than a sliver this thin [m]: polygons are
# built to touch obstacle cells at most, and rounding must not count as overlap.
OVERLAP_TOL_M = 1e-7


@dataclass(frozen=True)
class ConvexPolygon:
    """A bounded convex polygon, world frame [m]."""

    A: np.ndarray  # (m, 2) unit outward normals
    b: np.ndarray  # (m,) offsets [m]
    vertices: np.ndarray  # (n, 2) counter-clockwise

    @property
    def area(self) -> float:
        x, y = self.vertices[:, 0], self.vertices[:, 1]
        return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))

    def contains(self, points: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        """Boolean per point (``(N, 2)`` world [m]): inside or on the boundary."""
        pts = np.atleast_2d(np.asarray(points, dtype=float))
        return np.all(pts @ self.A.T <= self.b + tol, axis=1)

    def bbox(self) -> tuple[float, float, float, float]:
        """``(xmin, ymin, xmax, ymax)`` [m]."""
        lo = self.vertices.min(axis=0)
        hi = self.vertices.max(axis=0)
        return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def polygon_from_points(points: np.ndarray) -> ConvexPolygon | None:
    """Convex hull of ``(N, 2)`` points [m] as a polygon (None if degenerate)."""
    pts = np.unique(np.asarray(points, dtype=float), axis=0)
    if len(pts) < 3:
        return None
    hull = _monotone_chain(pts)
    if len(hull) < 3:
        return None
    verts = np.array(hull)
    nxt = np.roll(verts, -1, axis=0)
    edge = nxt - verts
    length = np.hypot(edge[:, 0], edge[:, 1])
    A = np.column_stack([edge[:, 1], -edge[:, 0]]) / length[:, None]
    b = np.einsum("ij,ij->i", A, verts)
    return ConvexPolygon(A, b, verts)


def _monotone_chain(pts: np.ndarray) -> list[tuple[float, float]]:
    """Andrew's monotone chain; ``pts`` sorted-unique rows; CCW, collinear dropped."""
    p = [(float(x), float(y)) for x, y in pts]

    def cross(o: tuple[float, float], a: tuple[float, float], c: tuple[float, float]) -> float:
        return (a[0] - o[0]) * (c[1] - o[1]) - (a[1] - o[1]) * (c[0] - o[0])

    lower: list[tuple[float, float]] = []
    for q in p:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], q) <= 0.0:
            lower.pop()
        lower.append(q)
    upper: list[tuple[float, float]] = []
    for q in reversed(p):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], q) <= 0.0:
            upper.pop()
        upper.append(q)
    return lower[:-1] + upper[:-1]


def cell_squares_in_bbox(
    mask: np.ndarray, res: float, origin: tuple[float, float], bbox: tuple[float, float, float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """Row and column indices of the ``mask`` cells whose squares meet ``bbox``."""
    rows, cols = mask.shape
    xmin, ymin, xmax, ymax = bbox
    c0 = max(int(math.floor((xmin - origin[0]) / res)) - 1, 0)
    c1 = min(int(math.ceil((xmax - origin[0]) / res)) + 1, cols)
    r0 = max(int(math.floor((ymin - origin[1]) / res)) - 1, 0)
    r1 = min(int(math.ceil((ymax - origin[1]) / res)) + 1, rows)
    if c0 >= c1 or r0 >= r1:
        empty = np.zeros(0, dtype=np.intp)
        return empty, empty
    rr, cc = np.nonzero(mask[r0:r1, c0:c1])
    return rr + r0, cc + c0


def overlapping_cells(
    poly: ConvexPolygon,
    mask: np.ndarray,
    res: float,
    origin: tuple[float, float],
    tol: float = OVERLAP_TOL_M,
) -> np.ndarray:
    """``(K, 2)`` ``[row, col]`` of the ``mask`` cells whose square overlaps ``poly``.

    Exact separating-axis test between two convex sets: the square's axes (x, y) and
    the polygon's face normals. Overlap means a common part thicker than ``tol`` [m];
    touching along an edge or at a corner is not overlap.
    """
    rr, cc = cell_squares_in_bbox(mask, res, origin, poly.bbox())
    if len(rr) == 0:
        return np.zeros((0, 2), dtype=np.intp)
    x0 = origin[0] + cc * res
    y0 = origin[1] + rr * res
    xmin, ymin, xmax, ymax = poly.bbox()
    hit = (x0 + res > xmin + tol) & (x0 < xmax - tol) & (y0 + res > ymin + tol) & (y0 < ymax - tol)
    # min over the square's corners of a . x, per face: lower-left plus the negative parts.
    ax = poly.A[:, 0][None, :]
    ay = poly.A[:, 1][None, :]
    lo = ax * x0[:, None] + ay * y0[:, None] + res * (np.minimum(ax, 0.0) + np.minimum(ay, 0.0))
    hit &= np.all(lo < poly.b[None, :] - tol, axis=1)
    return np.column_stack([rr[hit], cc[hit]])


def polygons_overlap(p: ConvexPolygon, q: ConvexPolygon, tol: float = OVERLAP_TOL_M) -> bool:
    """Whether two convex polygons share an area thicker than ``tol`` [m]."""
    for poly, other in ((p, q), (q, p)):
        proj = other.vertices @ poly.A.T  # (n_other, m)
        if np.any(proj.min(axis=0) >= poly.b - tol):
            return False
    return True


def cell_centres(rows: np.ndarray, cols: np.ndarray, res: float, origin: tuple[float, float]) -> np.ndarray:
    """World positions [m] of the centres of cells ``[rows, cols]``."""
    return np.column_stack([origin[0] + (cols + 0.5) * res, origin[1] + (rows + 0.5) * res])


def covered_mask(
    polys: list[ConvexPolygon], shape: tuple[int, int], res: float, origin: tuple[float, float], tol: float = 1e-9
) -> np.ndarray:
    """Cells whose centre lies in at least one polygon."""
    covered = np.zeros(shape, dtype=bool)
    full = np.ones(shape, dtype=bool)
    for poly in polys:
        rr, cc = cell_squares_in_bbox(full, res, origin, poly.bbox())
        if len(rr) == 0:
            continue
        inside = poly.contains(cell_centres(rr, cc, res, origin), tol)
        covered[rr[inside], cc[inside]] = True
    return covered


def overlap_components(polys: list[ConvexPolygon]) -> np.ndarray:
    """Connected-component label per polygon of the graph "overlaps with area"."""
    n = len(polys)
    parent = list(range(n))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    if n:
        boxes = np.array([p.bbox() for p in polys])
        for i in range(n):
            cand = np.nonzero(
                (boxes[i + 1:, 0] < boxes[i, 2]) & (boxes[i + 1:, 2] > boxes[i, 0])
                & (boxes[i + 1:, 1] < boxes[i, 3]) & (boxes[i + 1:, 3] > boxes[i, 1])
            )[0] + i + 1
            for j in cand:
                ri, rj = find(i), find(int(j))
                if ri != rj and polygons_overlap(polys[i], polys[int(j)]):
                    parent[rj] = ri
    return np.array([find(i) for i in range(n)], dtype=np.intp)


def chain_exists(polys: list[ConvexPolygon], start: np.ndarray, goal: np.ndarray) -> bool:
    """Whether overlapping polygons link one containing ``start`` to one containing ``goal``."""
    if not polys:
        return False
    labels = overlap_components(polys)
    s = {int(labels[i]) for i, p in enumerate(polys) if p.contains(start)[0]}
    g = {int(labels[i]) for i, p in enumerate(polys) if p.contains(goal)[0]}
    return bool(s & g)
