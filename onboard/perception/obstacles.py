"""Convex obstacles from the occupied cells of a grid (thesis 3116, "union of convex obstacles").

Each 8-connected group of occupied cells becomes one convex polygon that contains all
of its cell squares: the convex hull of the squares (``method="hull"``) or the
minimum-area rectangle around them (``method="rect"``, what the thesis fitted with
OpenCV). A group that fills too little of its hull (an L-shaped wall, a ring of trees
seen as one blob), or leaves more than ``obstacle_slack_m2`` of it empty, is split with
K-means into pieces that are each hulled, so the obstacles do not swallow the free space
between their arms: the grass round a sidewalk, seen from its start, is one U-shaped blob
whose hull held the whole paving. The largest groups are split first, within
``obstacles_max`` splits (far terrain seen at the pixel stride comes as hundreds of specks,
each its own group; they left no budget to split the U). The mask is not closed first:
closed over single cells, the colour segmenter's specks on a forest floor grew into
obstacles that shut the ways between the trees (forest seeds 1007 and 1008 missed their goals).
"""

from __future__ import annotations

import math
import cv2
import numpy as np

from onboard.contracts.params import PerceptionParams
from onboard.perception.clustering import kmeans_labels
from onboard.perception.geometry import ConvexPolygon

_SQUARE = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.int32)


def obstacles_from_mask(
    occupied: np.ndarray, res: float, origin: tuple[float, float], params: PerceptionParams = PerceptionParams()
) -> list[ConvexPolygon]:
    """Convex polygons [m, world] covering every cell square of ``occupied`` (bool).

    Rows of ``occupied`` run along world y, columns along x; ``origin`` [m] is the
    lower-left corner of cell [0, 0] and ``res`` [m] the cell side.
    """
    if params.obstacle_method not in ("hull", "rect"):
        raise ValueError(f"obstacle_method must be 'hull' or 'rect', got {params.obstacle_method!r}")
    occ = np.ascontiguousarray(occupied, dtype=np.uint8)
    n, labels = cv2.connectedComponents(occ, connectivity=8)
    if n <= 1:
        return []
    rr, cc = np.nonzero(occ)
    lab = labels[rr, cc]
    order = np.argsort(lab, kind="stable")
    groups = np.split(order, np.cumsum(np.bincount(lab, minlength=n))[:-1])[1:]
    groups.sort(key=len, reverse=True)
    cells = np.column_stack([cc, rr]).astype(np.int32)  # lower-left corners, cell units
    rng = np.random.default_rng(params.seed)
    pieces: list[np.ndarray] = []
    budget = params.obstacles_max
    slack_cells = params.obstacle_slack_m2 / (res * res)
    for g in groups:
        budget = _split(cells[g], params, slack_cells, params.obstacle_split_depth, budget, pieces, rng)
    o = np.asarray(origin, dtype=float)
    out = []
    for corners in pieces:
        poly = _cover(corners, params.obstacle_method)
        out.append(ConvexPolygon(poly.A, res * poly.b + poly.A @ o, poly.vertices * res + o))
    return out


def _squares_hull_area(cells: np.ndarray) -> float:
    """Area [cells^2] of the convex hull of unit squares with lower-left corners ``cells``:
    the hull of the corners is the corners' hull grown by the square, whose area is the
    hull's area plus its x and y widths plus one (Minkowski sum with a unit square)."""
    hull = cv2.convexHull(cells)
    lo, hi = cells.min(axis=0), cells.max(axis=0)
    return float(cv2.contourArea(hull)) + float(hi[0] - lo[0]) + float(hi[1] - lo[1]) + 1.0


def _split(cells: np.ndarray, params: PerceptionParams, slack_cells: float, depth: int, budget: int,
           out: list[np.ndarray], rng: np.random.Generator) -> int:
    """Append ``cells`` (int lower-left corners) or its K-means halves to ``out``; returns the budget left."""
    if depth > 0 and budget > 0 and len(cells) >= params.obstacle_split_min_cells:
        hull = _squares_hull_area(cells)
        if len(cells) < params.obstacle_solidity_min * hull or hull - len(cells) > slack_cells:
            lab = kmeans_labels(cells, 2, rng)
            if 0 < int(lab.sum()) < len(lab):
                budget -= 1
                budget = _split(cells[lab == 0], params, slack_cells, depth - 1, budget, out, rng)
                return _split(cells[lab == 1], params, slack_cells, depth - 1, budget, out, rng)
    out.append(cells)
    return budget


def _cover(cells: np.ndarray, method: str) -> ConvexPolygon:
    """Convex polygon [cells] containing the unit squares with lower-left corners ``cells``.

    Integer corners, so OpenCV's hull is exact; collinear vertices are dropped.
    """
    hull = cv2.convexHull(cells).reshape(-1, 2)
    corners = (hull[:, None, :] + _SQUARE[None]).reshape(-1, 2).astype(np.int32)
    v = cv2.convexHull(corners, clockwise=False).reshape(-1, 2).astype(float)
    e_in = v - np.roll(v, 1, axis=0)
    e_out = np.roll(v, -1, axis=0) - v
    v = v[e_in[:, 0] * e_out[:, 1] - e_in[:, 1] * e_out[:, 0] != 0]
    edge = np.roll(v, -1, axis=0) - v
    length = np.hypot(edge[:, 0], edge[:, 1])
    A = np.column_stack([edge[:, 1], -edge[:, 0]]) / length[:, None]
    poly = ConvexPolygon(A, np.einsum("ij,ij->i", A, v), v)
    if method == "hull":
        return poly
    return _min_area_rect(poly.vertices)


def _min_area_rect(hull: np.ndarray) -> ConvexPolygon:
    """Smallest rectangle containing a convex polygon: one side lies on a hull edge."""
    best: tuple[float, float, float, float, float, float] | None = None
    n = len(hull)
    for i in range(n):
        e = hull[(i + 1) % n] - hull[i]
        ang = math.atan2(e[1], e[0])
        c, s = math.cos(ang), math.sin(ang)
        u = hull[:, 0] * c + hull[:, 1] * s
        v = -hull[:, 0] * s + hull[:, 1] * c
        area = float((u.max() - u.min()) * (v.max() - v.min()))
        if best is None or area < best[0]:
            best = (area, ang, float(u.min()), float(u.max()), float(v.min()), float(v.max()))
    assert best is not None
    _, ang, u0, u1, v0, v1 = best
    c, s = math.cos(ang), math.sin(ang)
    ax, ay = np.array([c, s]), np.array([-s, c])
    verts = np.array([u0 * ax + v0 * ay, u1 * ax + v0 * ay, u1 * ax + v1 * ay, u0 * ax + v1 * ay])
    A = np.array([ay * -1.0, ax, ay, -ax])
    b = np.array([-v0, u1, v1, -u0])
    return ConvexPolygon(A, b, verts)
