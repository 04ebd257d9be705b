"""Exact collision tests between Bezier control-point hulls and convex planar sets.

The graph cut (thesis 3149-3181) removes every edge whose curve could touch an
obstacle. By the convex hull property (Property 2.43) a Bezier curve lies in the hull
of its control points, so an edge is safe when that hull keeps a distance larger than
``margin`` (robot radius plus the low level's tube) from every obstacle.

Obstacles are inflated by a disk of radius ``margin`` (the exact Minkowski sum, not
an offset polygon), and the test is exact for that set: the distance between two
convex polygons is the largest gap ``min_P n.p - max_O n.o`` over the axes ``n``
that can carry it -- the obstacle's face normals, the normals of the directions
between control points (which include the hull's faces), and the directions between
a control point and an obstacle vertex (vertex-vertex closest pairs). The hull is
kept iff some axis has a gap above ``margin``: the separating axis test with a
margin, no QP needed. A bounding-box grid broad phase and a bounding-circle test
discard most pairs before the compiled (numba) kernel runs.

Free-space mode (thesis "union of convex free spaces") keeps an edge iff every
control point lies, ``margin`` deep, inside one convex free cell.

The thesis's Cut-QP is kept only where no closed form is used: hulls and polytopes in
dimension other than 2 or polytopes known only by ``A x <= b``
(:func:`hull_polytope_distance_qp`, OSQP). Two-dimensional H-polytopes get their
vertices exactly from :func:`polygon_from_halfspaces` instead.

Frames and units: world frame, metres. Polygons are ``(k, 2)`` vertex arrays; they
are stored counter-clockwise.

Polygons themselves (validation, halfspaces, packing) are :mod:`onboard.geometry.polygons`. The
numba kernels are compiled on first use and cached where the process says
(``NUMBA_CACHE_DIR``, set by its entry point: :mod:`services.runtime.process_env`).
"""

from __future__ import annotations

import math
import types
from dataclasses import dataclass

import numba as nb
import numpy as np
import osqp
import scipy.sparse as sp

from onboard.geometry.polygons import VERTEX_MERGE_TOL, PolygonError, PolygonSet, clip_polygon, pack_polygons, validate_polygon

GAP_EPS = 1e-9  # [m] a gap must beat the margin by this much (float round-off)
QP_TOL = 1e-7  # OSQP absolute/relative tolerance for the distance QP
QP_MARGIN_SLACK = 1e-4  # [m] the QP answer is trusted only this far from the margin
SET_TOL = 1e-8  # [m] round-off accepted on the faces of a free polygon
EMPTY_CELL_SIZE = 1.0  # [m] broad-phase cell when there is nothing to size it by
MIN_CELL = 0.05  # [m] smallest broad-phase cell


# --- control-point hulls -------------------------------------------------------------


@dataclass(frozen=True)
class _Grid:
    x0: float
    y0: float
    h: float
    nx: int
    ny: int


def _grid_for(boxes: np.ndarray, cell: float, pad: float) -> _Grid:
    if len(boxes) == 0:
        return _Grid(0.0, 0.0, EMPTY_CELL_SIZE, 1, 1)
    x0 = float(boxes[:, 0].min() - pad)
    y0 = float(boxes[:, 1].min() - pad)
    x1 = float(boxes[:, 2].max() + pad)
    y1 = float(boxes[:, 3].max() + pad)
    h = max(cell, 1e-6)
    # Bound the cell count (memory) for very sparse, very wide scenes.
    while (x1 - x0) / h * (y1 - y0) / h > 4e6:
        h *= 2
    return _Grid(x0, y0, h, int((x1 - x0) // h) + 1, int((y1 - y0) // h) + 1)


def _typical_extent(boxes: np.ndarray) -> float:
    if len(boxes) == 0:
        return EMPTY_CELL_SIZE
    return float(np.median(np.maximum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1])))


@dataclass(frozen=True)
class HullSet:
    """Control-point sets of many curves, with what the kernels precompute once.

    Built once per graph: the cut then only touches obstacle data. The curves are
    binned by the centre of their box on a uniform grid (``cell`` per curve, ``order``
    sorting them by cell); a cut bins the obstacles on the same grid, grown by the
    largest curve half-size and the margin, so each curve reads one cell.
    """

    points: np.ndarray  # (E, K, 2) position control points [m]
    aabb: np.ndarray  # (E, 4) xmin, ymin, xmax, ymax [m]
    center: np.ndarray  # (E, 2) bounding-circle centre (box centre) [m]
    radius: np.ndarray  # (E,) bounding-circle radius [m]
    axes: np.ndarray  # (E, K (K-1) / 2, 2) unit normals to the directions between control points; 0 if coincident
    grid: _Grid  # over the box centres
    half_max: np.ndarray  # (2,) largest box half-size [m]
    cell: np.ndarray  # (E,) grid cell of each curve
    order: np.ndarray  # (E,) curves sorted by cell
    by_cell: tuple[np.ndarray, ...]  # points, aabb, center, radius, axes, cell in ``order`` (memory locality)

    def __len__(self) -> int:
        return len(self.points)


def hull_axes(points: np.ndarray) -> np.ndarray:
    """Unit normals ``(E, K (K-1) / 2, 2)`` to the directions between the control points of
    ``(E, K, 2)`` sets (0 for coincident points): the hulls' candidate separating axes."""
    pts = np.ascontiguousarray(points, dtype=float)
    if pts.ndim != 3 or pts.shape[2] != 2:
        raise ValueError(f"control points must be (E, K, 2), got {pts.shape}")
    return _hull_axes_kernel(pts)


def hull_set(points: np.ndarray, axes: np.ndarray | None = None) -> HullSet:
    """Precompute boxes, circles, candidate axes and the grid for ``(E, K, 2)`` control points
    (``axes``: :func:`hull_axes` of ``points`` when the caller has them, e.g. a grown graph)."""
    pts = np.ascontiguousarray(points, dtype=float)
    if pts.ndim != 3 or pts.shape[2] != 2 or pts.shape[1] < 1:
        raise ValueError(f"control points must be (E, K, 2), got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError("control points must be finite")
    lo = pts.min(axis=1)
    hi = pts.max(axis=1)
    aabb = np.ascontiguousarray(np.concatenate([lo, hi], axis=1))
    center = np.ascontiguousarray((lo + hi) / 2)
    radius = np.sqrt(np.max(np.sum((pts - center[:, None, :]) ** 2, axis=2), axis=1)) if len(pts) else np.zeros(0)
    axes = hull_axes(pts) if axes is None else axes
    half_max = (hi - lo).max(axis=0) / 2 if len(pts) else np.zeros(2)
    grid = _grid_for(np.concatenate([center, center], axis=1), max(_typical_extent(aabb), MIN_CELL), 0.0)
    cx = np.clip(((center[:, 0] - grid.x0) // grid.h).astype(np.int64), 0, grid.nx - 1)
    cy = np.clip(((center[:, 1] - grid.y0) // grid.h).astype(np.int64), 0, grid.ny - 1)
    cell = cy * grid.nx + cx
    order = np.argsort(cell, kind="stable").astype(np.int64)
    axes = np.ascontiguousarray(axes)
    by_cell = tuple(np.ascontiguousarray(a[order]) for a in (pts, aabb, center, radius, axes, cell))
    return HullSet(pts, aabb, center, radius, axes, grid, half_max, cell, order, by_cell)


# --- compiled kernels ------------------------------------------------------------------


@nb.njit(cache=True)
def _hull_axes_kernel(pts):  # pragma: no cover - compiled
    """:func:`hull_axes` in one pass (a whole graph's edges: numpy's temporaries cost 0.2 s)."""
    E, K = pts.shape[0], pts.shape[1]
    axes = np.zeros((E, K * (K - 1) // 2, 2))
    for e in range(E):
        a = 0
        for i in range(K):
            for j in range(i + 1, K):
                dx = pts[e, j, 0] - pts[e, i, 0]
                dy = pts[e, j, 1] - pts[e, i, 1]
                length = np.hypot(dx, dy)
                if length > VERTEX_MERGE_TOL:
                    axes[e, a, 0] = -dy / length
                    axes[e, a, 1] = dx / length
                a += 1
    return axes


def _hull_clear_of_polygon_impl(pts, axes, verts, norms, offs, margin):  # pragma: no cover - compiled
    """True iff dist(conv(pts), polygon) > margin (exact; see the module docstring)."""
    K = pts.shape[0]
    n = verts.shape[0]
    thresh = margin + GAP_EPS
    # Obstacle faces: the cheapest separating axes.
    for f in range(n):
        nx = norms[f, 0]
        ny = norms[f, 1]
        mn = np.inf
        for k in range(K):
            s = nx * pts[k, 0] + ny * pts[k, 1]
            if s < mn:
                mn = s
        if mn - offs[f] > thresh:
            return True
    # A control point within the margin puts the hull within it: the cheap "blocked".
    for k in range(K):
        px = pts[k, 0]
        py = pts[k, 1]
        worst = -np.inf
        for f in range(n):
            worst = max(worst, norms[f, 0] * px + norms[f, 1] * py - offs[f])
        if worst <= 0.0:
            return False  # inside the obstacle
        if worst <= thresh:  # near a face: the exact distance decides
            for f in range(n):
                ax = verts[f, 0]
                ay = verts[f, 1]
                g = f + 1 if f + 1 < n else 0
                bx = verts[g, 0] - ax
                by = verts[g, 1] - ay
                t = ((px - ax) * bx + (py - ay) * by) / (bx * bx + by * by)
                t = min(max(t, 0.0), 1.0)
                dx = px - ax - t * bx
                dy = py - ay - t * by
                if dx * dx + dy * dy <= thresh * thresh:
                    return False
    # Directions between control points (hull faces among them), both sides.
    for a in range(axes.shape[0]):
        ax = axes[a, 0]
        ay = axes[a, 1]
        if ax == 0.0 and ay == 0.0:
            continue
        pmin = np.inf
        pmax = -np.inf
        for k in range(K):
            s = ax * pts[k, 0] + ay * pts[k, 1]
            pmin = min(pmin, s)
            pmax = max(pmax, s)
        omin = np.inf
        omax = -np.inf
        for v in range(n):
            s = ax * verts[v, 0] + ay * verts[v, 1]
            omin = min(omin, s)
            omax = max(omax, s)
        if pmin - omax > thresh or omin - pmax > thresh:
            return True
    # Vertex-vertex directions.
    for k in range(K):
        for v in range(n):
            dx = pts[k, 0] - verts[v, 0]
            dy = pts[k, 1] - verts[v, 1]
            d = math.sqrt(dx * dx + dy * dy)
            if d <= thresh:
                return False  # a control point and an obstacle point are within the margin
            dx /= d
            dy /= d
            pmin = np.inf
            for kk in range(K):
                pmin = min(pmin, dx * pts[kk, 0] + dy * pts[kk, 1])
            omax = -np.inf
            for vv in range(n):
                omax = max(omax, dx * verts[vv, 0] + dy * verts[vv, 1])
            if pmin - omax > thresh:
                return True
    return False


_hull_clear_of_polygon = nb.njit(cache=True, inline="always")(_hull_clear_of_polygon_impl)
_hull_clear_of_polygon_py = nb.njit(cache=True)(_hull_clear_of_polygon_impl)


@nb.njit(cache=True)
def _bin_boxes(aabb, x0, y0, h, nx, ny):  # pragma: no cover - compiled
    """Uniform-grid bins of boxes: CSR (start, items) over cells, and each box's cell range."""
    m = aabb.shape[0]
    ranges = np.empty((m, 4), dtype=np.int64)
    counts = np.zeros(nx * ny + 1, dtype=np.int64)
    for i in range(m):
        ix0 = min(max(int(math.floor((aabb[i, 0] - x0) / h)), 0), nx - 1)
        iy0 = min(max(int(math.floor((aabb[i, 1] - y0) / h)), 0), ny - 1)
        ix1 = min(max(int(math.floor((aabb[i, 2] - x0) / h)), 0), nx - 1)
        iy1 = min(max(int(math.floor((aabb[i, 3] - y0) / h)), 0), ny - 1)
        ranges[i, 0] = ix0
        ranges[i, 1] = iy0
        ranges[i, 2] = ix1
        ranges[i, 3] = iy1
        for cy in range(iy0, iy1 + 1):
            for cx in range(ix0, ix1 + 1):
                counts[cy * nx + cx + 1] += 1
    start = np.cumsum(counts)
    fill = start[:-1].copy()
    items = np.empty(start[-1], dtype=np.int64)
    for i in range(m):
        for cy in range(ranges[i, 1], ranges[i, 3] + 1):
            for cx in range(ranges[i, 0], ranges[i, 2] + 1):
                c = cy * nx + cx
                items[fill[c]] = i
                fill[c] += 1
    return start, items, ranges


def _cut_obstacles_kernel_py(pts, aabb, center, radius, axes, cell_of, order, active,
                             verts, offsets, norms, face_offs, oaabb, ocenter, oradius,
                             start, items, margin):  # pragma: no cover - compiled
    """Curve arrays come sorted by cell (neighbours share the cell's obstacles in cache);
    ``order`` maps them back for the result."""
    E = order.shape[0]
    blocked = np.zeros(E, dtype=np.bool_)
    for e in nb.prange(E):
        if not active[order[e]]:
            continue
        c = cell_of[e]
        for k in range(start[c], start[c + 1]):
            o = items[k]
            if (aabb[e, 0] - oaabb[o, 2] > margin or oaabb[o, 0] - aabb[e, 2] > margin
                    or aabb[e, 1] - oaabb[o, 3] > margin or oaabb[o, 1] - aabb[e, 3] > margin):
                continue
            dx = center[e, 0] - ocenter[o, 0]
            dy = center[e, 1] - ocenter[o, 1]
            reach = radius[e] + oradius[o] + margin
            if dx * dx + dy * dy > reach * reach:
                continue
            a = offsets[o]
            b = offsets[o + 1]
            if not _hull_clear_of_polygon(pts[e], axes[e], verts[a:b], norms[a:b], face_offs[a:b], margin):
                blocked[order[e]] = True
                break
    return blocked


@nb.njit(cache=True)
def _bin_grown(boxes, grow_x, grow_y, x0, y0, h, nx, ny):  # pragma: no cover - compiled
    """CSR (start, items) of boxes grown by (grow_x, grow_y) over the cells they touch;
    boxes entirely off the grid are left out."""
    m = boxes.shape[0]
    x1 = x0 + nx * h
    y1 = y0 + ny * h
    ranges = np.full((m, 4), -1, dtype=np.int64)
    counts = np.zeros(nx * ny + 1, dtype=np.int64)
    for i in range(m):
        bx0 = boxes[i, 0] - grow_x
        by0 = boxes[i, 1] - grow_y
        bx1 = boxes[i, 2] + grow_x
        by1 = boxes[i, 3] + grow_y
        if bx1 < x0 or by1 < y0 or bx0 > x1 or by0 > y1:
            continue
        ranges[i, 0] = min(max(int(math.floor((bx0 - x0) / h)), 0), nx - 1)
        ranges[i, 1] = min(max(int(math.floor((by0 - y0) / h)), 0), ny - 1)
        ranges[i, 2] = min(max(int(math.floor((bx1 - x0) / h)), 0), nx - 1)
        ranges[i, 3] = min(max(int(math.floor((by1 - y0) / h)), 0), ny - 1)
        for cy in range(ranges[i, 1], ranges[i, 3] + 1):
            for cx in range(ranges[i, 0], ranges[i, 2] + 1):
                counts[cy * nx + cx + 1] += 1
    start = np.cumsum(counts)
    fill = start[:-1].copy()
    items = np.empty(start[-1], dtype=np.int64)
    for i in range(m):
        if ranges[i, 0] < 0:
            continue
        for cy in range(ranges[i, 1], ranges[i, 3] + 1):
            for cx in range(ranges[i, 0], ranges[i, 2] + 1):
                c = cy * nx + cx
                items[fill[c]] = i
                fill[c] += 1
    return start, items


def _free_cell_kernel_py(pts, active, norms, face_offs, offsets, start, items, x0, y0, h, nx, ny, margin):  # pragma: no cover
    """Index of the first cell holding every control point ``margin`` deep, or -1."""
    E = pts.shape[0]
    K = pts.shape[1]
    found = np.full(E, -1, dtype=np.int64)
    for e in nb.prange(E):
        if not active[e]:
            continue
        cx = int(math.floor((pts[e, 0, 0] - x0) / h))
        cy = int(math.floor((pts[e, 0, 1] - y0) / h))
        if not (0 <= cx < nx and 0 <= cy < ny):
            continue
        c = cy * nx + cx
        for kk in range(start[c], start[c + 1]):
            o = items[kk]
            inside = True
            for f in range(offsets[o], offsets[o + 1]):
                lim = face_offs[f] - margin - GAP_EPS
                for k in range(K):
                    if norms[f, 0] * pts[e, k, 0] + norms[f, 1] * pts[e, k, 1] > lim:
                        inside = False
                        break
                if not inside:
                    break
            if inside:
                found[e] = o
                break
    return found


@nb.njit(cache=True, inline="always")
def _point_polygon_distance(px, py, verts, norms, offs):  # pragma: no cover - compiled
    """Signed distance [m] from a point to a convex polygon (negative inside)."""
    n = verts.shape[0]
    worst = -np.inf
    for f in range(n):
        s = norms[f, 0] * px + norms[f, 1] * py - offs[f]
        if s > worst:
            worst = s
    if worst <= 0.0:
        return worst
    best = np.inf
    for f in range(n):
        ax = verts[f, 0]
        ay = verts[f, 1]
        g = (f + 1) % n
        bx = verts[g, 0] - ax
        by = verts[g, 1] - ay
        t = ((px - ax) * bx + (py - ay) * by) / (bx * bx + by * by)
        t = min(max(t, 0.0), 1.0)
        dx = px - ax - t * bx
        dy = py - ay - t * by
        d = math.sqrt(dx * dx + dy * dy)
        if d < best:
            best = d
    return best


def _samples_clearance_kernel_py(samples, verts, offsets, norms, face_offs, oaabb, start, items, x0, y0, h, nx, ny, reach):  # pragma: no cover
    """Per curve, the smallest signed distance of its samples to any polygon within ``reach``."""
    E = samples.shape[0]
    S = samples.shape[1]
    out = np.full(E, np.inf)
    for e in nb.prange(E):
        best = np.inf
        for s in range(S):
            px = samples[e, s, 0]
            py = samples[e, s, 1]
            cx = min(max(int(math.floor((px - x0) / h)), 0), nx - 1)
            cy = min(max(int(math.floor((py - y0) / h)), 0), ny - 1)
            # The polygons near a point are in the cells within ``reach`` of it.
            r = int(math.ceil(reach / h))
            for yy in range(max(cy - r, 0), min(cy + r, ny - 1) + 1):
                for xx in range(max(cx - r, 0), min(cx + r, nx - 1) + 1):
                    c = yy * nx + xx
                    for k in range(start[c], start[c + 1]):
                        o = items[k]
                        if (px < oaabb[o, 0] - reach or px > oaabb[o, 2] + reach
                                or py < oaabb[o, 1] - reach or py > oaabb[o, 3] + reach):
                            continue
                        a = offsets[o]
                        b = offsets[o + 1]
                        d = _point_polygon_distance(px, py, verts[a:b], norms[a:b], face_offs[a:b])
                        if d < best:
                            best = d
        out[e] = best
    return out


@nb.njit(cache=True)
def _best_axis(pts, axes, verts, norms, offs):  # pragma: no cover - compiled
    """The axis with the largest gap between conv(pts) and the polygon: (nx, ny, gap, h_O)."""
    K = pts.shape[0]
    n = verts.shape[0]
    best_gap = -np.inf
    bx = 0.0
    by = 0.0
    bh = 0.0
    for f in range(n):
        nx = norms[f, 0]
        ny = norms[f, 1]
        mn = np.inf
        for k in range(K):
            mn = min(mn, nx * pts[k, 0] + ny * pts[k, 1])
        if mn - offs[f] > best_gap:
            best_gap = mn - offs[f]
            bx, by, bh = nx, ny, offs[f]
    for a in range(axes.shape[0]):
        for sign in (-1.0, 1.0):
            ax = sign * axes[a, 0]
            ay = sign * axes[a, 1]
            if ax == 0.0 and ay == 0.0:
                continue
            pmin = np.inf
            for k in range(K):
                pmin = min(pmin, ax * pts[k, 0] + ay * pts[k, 1])
            omax = -np.inf
            for v in range(n):
                omax = max(omax, ax * verts[v, 0] + ay * verts[v, 1])
            if pmin - omax > best_gap:
                best_gap = pmin - omax
                bx, by, bh = ax, ay, omax
    for k in range(K):
        for v in range(n):
            dx = pts[k, 0] - verts[v, 0]
            dy = pts[k, 1] - verts[v, 1]
            d = math.sqrt(dx * dx + dy * dy)
            if d <= 0.0:
                continue
            dx /= d
            dy /= d
            pmin = np.inf
            for kk in range(K):
                pmin = min(pmin, dx * pts[kk, 0] + dy * pts[kk, 1])
            omax = -np.inf
            for vv in range(n):
                omax = max(omax, dx * verts[vv, 0] + dy * verts[vv, 1])
            if pmin - omax > best_gap:
                best_gap = pmin - omax
                bx, by, bh = dx, dy, omax
    return bx, by, best_gap, bh


@nb.njit(cache=True)
def _halfspaces_kernel(pts, axes, verts, offsets, norms, face_offs, ocenter, oradius, margin, count, reach):  # pragma: no cover
    """For each hull, halfspaces ``a.x <= b`` from its ``count`` nearest polygons (within reach)."""
    S = pts.shape[0]
    M = offsets.shape[0] - 1
    out = np.zeros((S, count, 3))
    out[:, :, 2] = np.inf  # unused rows: 0.x <= inf
    for s in range(S):
        cxs = 0.0
        cys = 0.0
        K = pts.shape[1]
        for k in range(K):
            cxs += pts[s, k, 0] / K
            cys += pts[s, k, 1] / K
        rs = 0.0
        for k in range(K):
            rs = max(rs, math.hypot(pts[s, k, 0] - cxs, pts[s, k, 1] - cys))
        # The ``count`` nearest by bounding circles (insertion into a short sorted list).
        best_gap = np.full(count, np.inf)
        best_o = np.full(count, -1, dtype=np.int64)
        for o in range(M):
            gap = math.hypot(cxs - ocenter[o, 0], cys - ocenter[o, 1]) - oradius[o] - rs
            if gap > reach or gap >= best_gap[count - 1]:
                continue
            i = count - 1
            while i > 0 and best_gap[i - 1] > gap:
                best_gap[i] = best_gap[i - 1]
                best_o[i] = best_o[i - 1]
                i -= 1
            best_gap[i] = gap
            best_o[i] = o
        for filled in range(count):
            o = best_o[filled]
            if o < 0:
                break
            a = offsets[o]
            b = offsets[o + 1]
            nx, ny, gap, ho = _best_axis(pts[s], axes[s], verts[a:b], norms[a:b], face_offs[a:b])
            # Robot positions must satisfy n.x >= h_O(n) + margin, i.e. -n.x <= -(h_O + margin).
            out[s, filled, 0] = -nx
            out[s, filled, 1] = -ny
            out[s, filled, 2] = -(ho + margin)
    return out


# Each kernel in two builds: threads pay off on large batches only (a parallel launch
# costs milliseconds on a loaded machine, more than a small batch takes).
PARALLEL_MIN = 4096  # curves below which the serial build runs


def _two_builds(func: types.FunctionType) -> tuple:
    """Serial and parallel compiled builds of ``func``. The parallel one compiles a copy
    under its own name: numba's on-disk cache is keyed by the function's name, not by
    its flags, and would otherwise hand the serial build to both."""
    twin = types.FunctionType(func.__code__, func.__globals__, func.__name__ + "_parallel", func.__defaults__, func.__closure__)
    twin.__qualname__ = func.__qualname__ + "_parallel"
    return nb.njit(cache=True)(func), nb.njit(cache=True, parallel=True)(twin)


_cut_obstacles_kernel = _two_builds(_cut_obstacles_kernel_py)
_free_cell_kernel = _two_builds(_free_cell_kernel_py)
_samples_clearance_kernel = _two_builds(_samples_clearance_kernel_py)


def _pick(kernels: tuple, count: int):
    return kernels[count >= PARALLEL_MIN]


# --- public entry points ----------------------------------------------------------------


def cut_obstacles(hulls: HullSet, obstacles: PolygonSet, margin: float, active: np.ndarray | None = None) -> np.ndarray:
    """``blocked[e]``: the hull of curve ``e`` comes within ``margin`` [m] of an obstacle.

    Exact for the disk-inflated obstacles (no false "free"). ``active`` restricts the
    test to some curves (the others are reported free); default all.
    """
    if margin < 0 or not math.isfinite(margin):
        raise ValueError(f"margin must be finite and >= 0, got {margin}")
    E = len(hulls)
    act = np.ones(E, dtype=np.bool_) if active is None else np.ascontiguousarray(active, dtype=np.bool_)
    if len(obstacles) == 0 or E == 0:
        return np.zeros(E, dtype=np.bool_)
    g = hulls.grid
    # A curve's box overlaps an obstacle's (grown by the margin) only if its centre cell
    # meets the obstacle's box grown by the margin and the largest curve half-size.
    start, items = _bin_grown(obstacles.aabb, float(hulls.half_max[0] + margin), float(hulls.half_max[1] + margin),
                              g.x0, g.y0, g.h, g.nx, g.ny)
    return _pick(_cut_obstacles_kernel, E)(
        *hulls.by_cell, hulls.order, act, obstacles.vertices, obstacles.offsets, obstacles.normals, obstacles.face_offsets,
        obstacles.aabb, obstacles.center, obstacles.radius, start, items, float(margin))


def free_cell_of(hulls: HullSet, cells: PolygonSet, margin: float, active: np.ndarray | None = None) -> np.ndarray:
    """Per curve, the index of a free cell holding every control point ``margin`` [m] deep, or -1.

    Inactive curves get -1.
    """
    if margin < 0 or not math.isfinite(margin):
        raise ValueError(f"margin must be finite and >= 0, got {margin}")
    E = len(hulls)
    act = np.ones(E, dtype=np.bool_) if active is None else np.ascontiguousarray(active, dtype=np.bool_)
    if len(cells) == 0 or E == 0:
        return np.full(E, -1, dtype=np.int64)
    grid = _grid_for(cells.aabb, max(_typical_extent(hulls.aabb), _typical_extent(cells.aabb) / 4), 0.0)
    start, items, _ = _bin_boxes(cells.aabb, grid.x0, grid.y0, grid.h, grid.nx, grid.ny)
    return _pick(_free_cell_kernel, E)(hulls.points, act, cells.normals, cells.face_offsets, cells.offsets,
                             start, items, grid.x0, grid.y0, grid.h, grid.nx, grid.ny, float(margin))


def cut_free_cells(hulls: HullSet, cells: PolygonSet, margin: float, active: np.ndarray | None = None) -> np.ndarray:
    """``blocked[e]``: no single free cell holds every control point of active curve ``e`` ``margin`` deep."""
    blocked = free_cell_of(hulls, cells, margin, active) < 0
    if active is not None:
        blocked &= np.asarray(active, dtype=bool)
    return blocked


def samples_clearance(samples: np.ndarray, obstacles: PolygonSet, reach: float) -> np.ndarray:
    """Per curve, the least signed distance [m] from its sample points ``(E, S, 2)`` to any obstacle.

    Polygons farther than ``reach`` [m] are ignored (the result is then ``inf``).
    For checks against dense sampling of the true curve (tests, benchmark).
    """
    samples = np.ascontiguousarray(samples, dtype=float)
    if len(obstacles) == 0:
        return np.full(len(samples), np.inf)
    grid = _grid_for(obstacles.aabb, max(_typical_extent(obstacles.aabb), reach), reach)
    start, items, _ = _bin_boxes(obstacles.aabb, grid.x0, grid.y0, grid.h, grid.nx, grid.ny)
    return _pick(_samples_clearance_kernel, len(samples))(samples, obstacles.vertices, obstacles.offsets, obstacles.normals,
                                     obstacles.face_offsets, obstacles.aabb, start, items,
                                     grid.x0, grid.y0, grid.h, grid.nx, grid.ny, float(reach))


def separating_halfspaces(points: np.ndarray, obstacles: PolygonSet, margin: float, count: int,
                          reach: float) -> np.ndarray:
    """Halfspaces that keep each control-point set clear of its nearest obstacles.

    ``points`` is ``(S, K, 2)``. Returns ``(S, count, 3)`` rows ``[a_x, a_y, b]``: a
    position ``x`` with ``a . x <= b`` is at least ``margin`` [m] from that obstacle.
    The plane is the one on which the hull's gap to the obstacle is largest (the
    thesis's adjacentHyperplane). Obstacles whose bounding circle is farther than
    ``reach`` [m] from the hull's are skipped; unused rows are ``[0, 0, inf]``.
    """
    pts = np.ascontiguousarray(points, dtype=float)
    if len(obstacles) == 0 or count <= 0:
        out = np.zeros((len(pts), max(count, 0), 3))
        out[:, :, 2] = np.inf
        return out
    return _halfspaces_kernel(pts, hull_axes(pts), obstacles.vertices, obstacles.offsets,
                              obstacles.normals, obstacles.face_offsets, obstacles.center,
                              obstacles.radius, float(margin), int(count), float(reach))


def _obstacles_near(points: np.ndarray, obstacles: PolygonSet, margin: float) -> np.ndarray:
    """Indices of obstacles within ``margin`` of conv(points) ``(K, 2)`` (exact)."""
    hulls = hull_set(points[None])
    lo, hi = hulls.aabb[0, :2] - margin, hulls.aabb[0, 2:] + margin
    box = obstacles.aabb
    cand = np.flatnonzero(np.all(box[:, :2] <= hi, axis=1) & np.all(box[:, 2:] >= lo, axis=1))
    hits = []
    for o in cand:
        a, b = obstacles.offsets[o], obstacles.offsets[o + 1]
        if not _hull_clear_of_polygon_py(hulls.points[0], hulls.axes[0], obstacles.vertices[a:b],
                                         obstacles.normals[a:b], obstacles.face_offsets[a:b], margin):
            hits.append(o)
    return np.array(hits, dtype=np.int64)


def free_polygon(points: np.ndarray, obstacles: PolygonSet, margin: float, bounds: np.ndarray,
                 seed_planes: int = 4, reach: float = 2.0, max_rounds: int = 20) -> np.ndarray:
    """A convex polygon (CCW) holding conv(points) ``(K, 2)``, inside ``bounds``, ``margin`` clear of every obstacle.

    Starts from the separating halfspaces to the ``seed_planes`` nearest obstacles and
    adds the separating halfspace of any obstacle still within ``margin`` of the polygon
    until none is. ``points`` must themselves be clear by ``margin``. Raises
    :class:`PolygonError` when that does not hold or the rounds run out.
    """
    pts = np.asarray(points, dtype=float)
    if len(_obstacles_near(pts, obstacles, margin)):
        raise PolygonError("the points are not clear of the obstacles")
    rows = separating_halfspaces(pts[None], obstacles, margin, seed_planes, reach)[0]
    rows = [r for r in rows if np.isfinite(r[2])]
    hulls = hull_set(pts[None])
    (x0, y0), (x1, y1) = np.asarray(bounds, dtype=float)
    box = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    for _ in range(max_rounds):
        A = np.array([r[:2] for r in rows]).reshape(-1, 2)
        b = np.array([r[2] for r in rows])
        poly = validate_polygon(clip_polygon(box, A, b))
        # The planes put the polygon exactly at the margin: accept round-off below it.
        near = _obstacles_near(poly, obstacles, max(margin - SET_TOL, 0.0))
        if len(near) == 0:
            return poly
        for o in near:
            a, c = obstacles.offsets[o], obstacles.offsets[o + 1]
            nx, ny, _, ho = _best_axis(hulls.points[0], hulls.axes[0], obstacles.vertices[a:c],
                                       obstacles.normals[a:c], obstacles.face_offsets[a:c])
            rows.append(np.array([-nx, -ny, -(ho + margin)]))
    raise PolygonError("no clear polygon found")


def hull_polygon_distance(points: np.ndarray, polygon: np.ndarray) -> float:
    """Exact distance [m] between conv(points) ``(K, 2)`` and a convex polygon (0 if they meet)."""
    hulls = hull_set(np.asarray(points, dtype=float)[None])
    polys = pack_polygons([polygon])
    _, _, gap, _ = _best_axis(hulls.points[0], hulls.axes[0], polys.vertices, polys.normals, polys.face_offsets)
    return max(float(gap), 0.0)


# --- Cut-QP (general dimension, H-polytopes) ---------------------------------------------


def hull_polytope_distance_qp(points: np.ndarray, A: np.ndarray, b: np.ndarray) -> float:
    """Distance [m] between conv(points) ``(K, d)`` and ``{y : A y <= b}`` by a QP (OSQP).

    ``min |P lam - y|^2  s.t.  A y <= b, lam >= 0, sum(lam) = 1``. Used where no closed
    form is used (``d != 2``, or polytopes known only in H-form); in the plane the
    separating-axis kernels answer the same question exactly. Raises ``RuntimeError``
    when OSQP does not solve the problem.
    """
    P = np.asarray(points, dtype=float)
    A = np.asarray(A, dtype=float)
    b = np.asarray(b, dtype=float)
    K, d = P.shape
    if A.shape[1] != d:
        raise ValueError(f"polytope dimension {A.shape[1]} != point dimension {d}")
    # Variables z = [lam (K), y (d)]; residual r = P^T lam - y.
    M = np.hstack([P.T, -np.eye(d)])
    H = sp.csc_matrix(2 * M.T @ M + 1e-10 * np.eye(K + d))
    q = np.zeros(K + d)
    rows = [np.hstack([np.zeros((A.shape[0], K)), A]),  # A y <= b
            np.hstack([np.eye(K), np.zeros((K, d))]),  # lam >= 0
            np.hstack([np.ones((1, K)), np.zeros((1, d))])]  # sum lam = 1
    C = sp.csc_matrix(np.vstack(rows))
    lo = np.concatenate([np.full(A.shape[0], -np.inf), np.zeros(K), [1.0]])
    hi = np.concatenate([b, np.full(K, np.inf), [1.0]])
    solver = osqp.OSQP()
    solver.setup(H, q, C, lo, hi, eps_abs=QP_TOL, eps_rel=QP_TOL, max_iter=20000, polishing=True, verbose=False)
    res = solver.solve(raise_error=False)
    if res.info.status_val not in (osqp.SolverStatus.OSQP_SOLVED, osqp.SolverStatus.OSQP_SOLVED_INACCURATE):
        raise RuntimeError(f"Cut-QP: OSQP status {res.info.status}")
    z = res.x
    return float(np.linalg.norm(M @ z))


def cut_qp(points: np.ndarray, polytopes: list[tuple[np.ndarray, np.ndarray]], margin: float) -> np.ndarray:
    """``blocked[e]`` for hulls ``(E, K, d)`` against H-polytopes ``[(A, b), ...]`` by Cut-QP.

    Sound: a pair is kept free only when the QP distance beats ``margin`` by
    ``QP_MARGIN_SLACK`` (solver tolerance). Bounding boxes are not available for
    H-polytopes, so every pair is solved: this is the slow path.
    """
    pts = np.asarray(points, dtype=float)
    blocked = np.zeros(len(pts), dtype=bool)
    for e in range(len(pts)):
        for A, b in polytopes:
            if hull_polytope_distance_qp(pts[e], A, b) <= margin + QP_MARGIN_SLACK:
                blocked[e] = True
                break
    return blocked
