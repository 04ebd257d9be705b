"""The compiled (numba) kernels behind :mod:`onboard.high_level.tracking.collision`: separating
axes of control-point hulls against convex polygons with a margin, free-cell membership, the
bounding-box grid broad phase, clearance of samples and separating halfspaces.

Called only by the collision module, whose public functions validate every input before a kernel
sees it. Compiled on first use and cached where the process says (``NUMBA_CACHE_DIR``, set by
its entry point: :mod:`services.runtime.process_env`).
"""

from __future__ import annotations

import math
import types

import numba as nb
import numpy as np

from onboard.geometry.polygons import VERTEX_MERGE_TOL

GAP_EPS = 1e-9  # [m] a gap must beat the margin by this much (float round-off)


# --- kernels ------------------------------------------------------------------


@nb.njit(cache=True)
def hull_axes_kernel(pts):  # pragma: no cover - compiled
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


def hull_clear_of_polygon_impl(pts, axes, verts, norms, offs, margin):  # pragma: no cover - compiled
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


_hull_clear_of_polygon = nb.njit(cache=True, inline="always")(hull_clear_of_polygon_impl)
hull_clear_of_polygon_py = nb.njit(cache=True)(hull_clear_of_polygon_impl)


@nb.njit(cache=True)
def bin_boxes(aabb, x0, y0, h, nx, ny):  # pragma: no cover - compiled
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


def cut_obstacles_kernel_py(pts, aabb, center, radius, axes, cell_of, order, active, curve_group,
                             verts, offsets, norms, face_offs, oaabb, ocenter, oradius, obstacle_group,
                             start, items, margin):  # pragma: no cover - compiled
    """Curve arrays come sorted by cell (neighbours share the cell's obstacles in cache);
    ``order`` maps them back for the result. With groups (``obstacle_group`` not empty) a curve
    meets only the obstacles of its own group (``curve_group``, in the curves' cell order)."""
    E = order.shape[0]
    grouped = obstacle_group.shape[0] > 0
    blocked = np.zeros(E, dtype=np.bool_)
    for e in nb.prange(E):
        if not active[order[e]]:
            continue
        c = cell_of[e]
        for k in range(start[c], start[c + 1]):
            o = items[k]
            if grouped and obstacle_group[o] != curve_group[e]:
                continue
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
def bin_grown(boxes, grow_x, grow_y, x0, y0, h, nx, ny):  # pragma: no cover - compiled
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


def free_cell_kernel_py(pts, active, norms, face_offs, offsets, start, items, x0, y0, h, nx, ny, margin):  # pragma: no cover
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
def point_polygon_distance(px, py, verts, norms, offs):  # pragma: no cover - compiled
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


def samples_clearance_kernel_py(samples, verts, offsets, norms, face_offs, oaabb, start, items, x0, y0, h, nx, ny, reach):  # pragma: no cover
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
                        d = point_polygon_distance(px, py, verts[a:b], norms[a:b], face_offs[a:b])
                        if d < best:
                            best = d
        out[e] = best
    return out


@nb.njit(cache=True)
def best_axis(pts, axes, verts, norms, offs):  # pragma: no cover - compiled
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
def halfspaces_kernel(pts, axes, verts, offsets, norms, face_offs, ocenter, oradius, margin, count, reach):  # pragma: no cover
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
            nx, ny, gap, ho = best_axis(pts[s], axes[s], verts[a:b], norms[a:b], face_offs[a:b])
            # Robot positions must satisfy n.x >= h_O(n) + margin, i.e. -n.x <= -(h_O + margin).
            out[s, filled, 0] = -nx
            out[s, filled, 1] = -ny
            out[s, filled, 2] = -(ho + margin)
    return out


# Each kernel in two builds: threads pay off on large batches only (a parallel launch
# costs milliseconds on a loaded machine, more than a small batch takes).
PARALLEL_MIN = 4096  # curves below which the serial build runs


def two_builds(func: types.FunctionType) -> tuple:
    """Serial and parallel compiled builds of ``func``. The parallel one compiles a copy
    under its own name: numba's on-disk cache is keyed by the function's name, not by
    its flags, and would otherwise hand the serial build to both."""
    twin = types.FunctionType(func.__code__, func.__globals__, func.__name__ + "_parallel", func.__defaults__, func.__closure__)
    twin.__qualname__ = func.__qualname__ + "_parallel"
    return nb.njit(cache=True)(func), nb.njit(cache=True, parallel=True)(twin)


cut_obstacles_kernel = two_builds(cut_obstacles_kernel_py)
free_cell_kernel = two_builds(free_cell_kernel_py)
samples_clearance_kernel = two_builds(samples_clearance_kernel_py)


def pick(kernels: tuple, count: int):
    return kernels[count >= PARALLEL_MIN]
