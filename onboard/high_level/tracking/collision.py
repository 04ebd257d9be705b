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

Polygons themselves (validation, halfspaces, packing) are :mod:`onboard.geometry.polygons`; the
compiled kernels behind these tests are :mod:`onboard.high_level.tracking.collision_kernels`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import osqp
import scipy.sparse as sp

from onboard.high_level.tracking.collision_kernels import (PARALLEL_MIN as PARALLEL_MIN, best_axis,  # re-exported: callers size batches by it
                                                           bin_boxes, bin_grown, cut_obstacles_kernel, free_cell_kernel,
                                                           halfspaces_kernel, hull_axes_kernel, hull_clear_of_polygon_py, pick,
                                                           samples_clearance_kernel)
from onboard.geometry.polygons import PolygonError, PolygonSet, clip_polygon, pack_polygons, validate_polygon

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
    return hull_axes_kernel(pts)


def _checked(points: np.ndarray) -> np.ndarray:
    pts = np.ascontiguousarray(points, dtype=float)
    if pts.ndim != 3 or pts.shape[2] != 2 or pts.shape[1] < 1:
        raise ValueError(f"control points must be (E, K, 2), got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError("control points must be finite")
    return pts


def _bounds(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per curve: box ``(E, 4)``, its centre ``(E, 2)``, the bounding-circle radius ``(E,)`` and the box's half-size ``(2,)`` at most."""
    lo = pts.min(axis=1)
    hi = pts.max(axis=1)
    aabb = np.ascontiguousarray(np.concatenate([lo, hi], axis=1))
    center = np.ascontiguousarray((lo + hi) / 2)
    radius = np.sqrt(np.max(np.sum((pts - center[:, None, :]) ** 2, axis=2), axis=1)) if len(pts) else np.zeros(0)
    half_max = (hi - lo).max(axis=0) / 2 if len(pts) else np.zeros(2)
    return aabb, center, radius, half_max


def _cells(grid: _Grid, center: np.ndarray) -> np.ndarray:
    cx = np.clip(((center[:, 0] - grid.x0) // grid.h).astype(np.int64), 0, grid.nx - 1)
    cy = np.clip(((center[:, 1] - grid.y0) // grid.h).astype(np.int64), 0, grid.ny - 1)
    return cy * grid.nx + cx


def _on_grid(grid: _Grid, center: np.ndarray) -> bool:
    """Every centre falls in a cell of ``grid`` (none clipped into a border cell)."""
    if len(center) == 0:
        return True
    return bool(center[:, 0].min() >= grid.x0 and center[:, 1].min() >= grid.y0
                and ((center[:, 0].max() - grid.x0) // grid.h) < grid.nx and ((center[:, 1].max() - grid.y0) // grid.h) < grid.ny)


def hull_set(points: np.ndarray) -> HullSet:
    """Precompute boxes, circles, candidate axes and the grid for ``(E, K, 2)`` control points."""
    pts = _checked(points)
    aabb, center, radius, half_max = _bounds(pts)
    axes = np.ascontiguousarray(hull_axes(pts))
    grid = _grid_for(np.concatenate([center, center], axis=1), max(_typical_extent(aabb), MIN_CELL), 0.0)
    cell = _cells(grid, center)
    order = np.argsort(cell, kind="stable").astype(np.int64)
    by_cell = tuple(np.ascontiguousarray(a[order]) for a in (pts, aabb, center, radius, axes, cell))
    return HullSet(pts, aabb, center, radius, axes, grid, half_max, cell, order, by_cell)


def _interleave(old: np.ndarray, new: np.ndarray, is_new: np.ndarray) -> np.ndarray:
    out = np.empty((len(is_new), *old.shape[1:]), dtype=old.dtype)
    out[is_new] = new
    out[~is_new] = old
    return out


def grown_hull_set(hulls: HullSet, points: np.ndarray, new_at: np.ndarray) -> HullSet:
    """``hulls`` with the curves ``points`` ``(M, K, 2)`` inserted: curve ``m`` at index ``new_at[m]``
    of the grown set (distinct indices), the old curves in their order at the others.

    What :func:`hull_set` computes for the old curves is reused, not computed again: a graph
    grown a few hundred curves at a time (densification) costs the new curves plus one pass
    of copies, not a rebuild of every curve's box, circle and grid cell. The grid stays when
    it holds every new centre (its cell size is the broad phase's locality, not its
    correctness); else the whole set is binned again."""
    pts_new = _checked(points)
    new_at = np.asarray(new_at, dtype=np.int64)
    total = len(hulls) + len(pts_new)
    if pts_new.shape[1:] != hulls.points.shape[1:] or new_at.shape != (len(pts_new),):
        raise ValueError(f"curves {pts_new.shape} at {new_at.shape} do not fit hulls of {hulls.points.shape}")
    is_new = np.zeros(total, dtype=bool)
    is_new[new_at] = True
    if np.count_nonzero(is_new) != len(new_at):
        raise ValueError("new curves' indices must be distinct")
    order_new = np.argsort(new_at, kind="stable")  # the new curves in the grown set's order
    pts_new = pts_new[order_new]
    axes_new = np.ascontiguousarray(hull_axes(pts_new))
    aabb_new, center_new, radius_new, half_new = _bounds(pts_new)
    pts = _interleave(hulls.points, pts_new, is_new)
    aabb = _interleave(hulls.aabb, aabb_new, is_new)
    center = _interleave(hulls.center, center_new, is_new)
    radius = _interleave(hulls.radius, radius_new, is_new)
    axes_all = _interleave(hulls.axes, axes_new, is_new)
    half_max = np.maximum(hulls.half_max, half_new)
    grid = hulls.grid
    if not _on_grid(grid, center_new) or len(hulls) == 0:
        grid = _grid_for(np.concatenate([center, center], axis=1), max(_typical_extent(aabb), MIN_CELL), 0.0)
        cell = _cells(grid, center)
        order = np.argsort(cell, kind="stable").astype(np.int64)
        by_cell = tuple(np.ascontiguousarray(a[order]) for a in (pts, aabb, center, radius, axes_all, cell))
        return HullSet(pts, aabb, center, radius, axes_all, grid, half_max, cell, order, by_cell)
    cell_new = _cells(grid, center_new)
    cell = _interleave(hulls.cell, cell_new, is_new)
    # merge the two lists sorted by (cell, index in the grown set): the old one stays sorted (its indices
    # only shift up), the new one is sorted here; the merge is what a stable argsort of every cell gives
    old_index = np.flatnonzero(~is_new)[hulls.order]
    new_index = np.flatnonzero(is_new)
    key_old = hulls.by_cell[5] * total + old_index
    key_new = cell_new * total + new_index
    by_key = np.argsort(key_new, kind="stable")
    slot = np.searchsorted(key_old, key_new[by_key]) + np.arange(len(by_key))
    new_slot = np.zeros(total, dtype=bool)
    new_slot[slot] = True
    order = _interleave(old_index, new_index[by_key], new_slot)
    fresh = (pts_new, aabb_new, center_new, radius_new, axes_new, cell_new)
    by_cell = tuple(_interleave(old_sorted, added[by_key], new_slot) for old_sorted, added in zip(hulls.by_cell, fresh))
    return HullSet(pts, aabb, center, radius, axes_all, grid, half_max, cell, order, by_cell)


# --- public entry points ----------------------------------------------------------------


def cut_obstacles(hulls: HullSet, obstacles: PolygonSet, margin: float, active: np.ndarray | None = None,
                  curve_group: np.ndarray | None = None, obstacle_group: np.ndarray | None = None) -> np.ndarray:
    """``blocked[e]``: the hull of curve ``e`` comes within ``margin`` [m] of an obstacle.

    Exact for the disk-inflated obstacles (no false "free"). ``active`` restricts the
    test to some curves (the others are reported free); default all. ``curve_group`` ``(E,)``
    and ``obstacle_group`` ``(M,)`` (both or neither): each curve meets only the obstacles of
    its own group, many cuts in one pass (the cut in time: a curve's distance band, the
    obstacles swept over that band's window).
    """
    if margin < 0 or not math.isfinite(margin):
        raise ValueError(f"margin must be finite and >= 0, got {margin}")
    E = len(hulls)
    act = np.ones(E, dtype=np.bool_) if active is None else np.ascontiguousarray(active, dtype=np.bool_)
    if (curve_group is None) != (obstacle_group is None):
        raise ValueError("curve_group and obstacle_group go together")
    if curve_group is None or obstacle_group is None:
        by_cell_group = obstacle_groups = np.zeros(0, dtype=np.int64)
    else:
        if np.shape(curve_group) != (E,) or np.shape(obstacle_group) != (len(obstacles),):
            raise ValueError(f"groups must be ({E},) and ({len(obstacles)},), got {np.shape(curve_group)}, {np.shape(obstacle_group)}")
        by_cell_group = np.ascontiguousarray(np.asarray(curve_group, dtype=np.int64)[hulls.order])
        obstacle_groups = np.ascontiguousarray(obstacle_group, dtype=np.int64)
    if len(obstacles) == 0 or E == 0:
        return np.zeros(E, dtype=np.bool_)
    g = hulls.grid
    # A curve's box overlaps an obstacle's (grown by the margin) only if its centre cell
    # meets the obstacle's box grown by the margin and the largest curve half-size.
    start, items = bin_grown(obstacles.aabb, float(hulls.half_max[0] + margin), float(hulls.half_max[1] + margin),
                              g.x0, g.y0, g.h, g.nx, g.ny)
    # threads by the curves tested, not the graph's size: a cut of a few thousand of 250,000 curves
    # in a parallel launch waited 20 ms on a busy machine
    return pick(cut_obstacles_kernel, int(np.count_nonzero(act)))(
        *hulls.by_cell, hulls.order, act, by_cell_group, obstacles.vertices, obstacles.offsets, obstacles.normals,
        obstacles.face_offsets, obstacles.aabb, obstacles.center, obstacles.radius, obstacle_groups, start, items, float(margin))


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
    start, items, _ = bin_boxes(cells.aabb, grid.x0, grid.y0, grid.h, grid.nx, grid.ny)
    return pick(free_cell_kernel, int(np.count_nonzero(act)))(hulls.points, act, cells.normals, cells.face_offsets, cells.offsets,
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
    start, items, _ = bin_boxes(obstacles.aabb, grid.x0, grid.y0, grid.h, grid.nx, grid.ny)
    return pick(samples_clearance_kernel, len(samples))(samples, obstacles.vertices, obstacles.offsets, obstacles.normals,
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
    return halfspaces_kernel(pts, hull_axes(pts), obstacles.vertices, obstacles.offsets,
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
        if not hull_clear_of_polygon_py(hulls.points[0], hulls.axes[0], obstacles.vertices[a:b],
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
            nx, ny, _, ho = best_axis(hulls.points[0], hulls.axes[0], obstacles.vertices[a:c],
                                       obstacles.normals[a:c], obstacles.face_offsets[a:c])
            rows.append(np.array([-nx, -ny, -(ho + margin)]))
    raise PolygonError("no clear polygon found")


def hull_polygon_distance(points: np.ndarray, polygon: np.ndarray) -> float:
    """Exact distance [m] between conv(points) ``(K, 2)`` and a convex polygon (0 if they meet)."""
    hulls = hull_set(np.asarray(points, dtype=float)[None])
    polys = pack_polygons([polygon])
    _, _, gap, _ = best_axis(hulls.points[0], hulls.axes[0], polys.vertices, polys.normals, polys.face_offsets)
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
