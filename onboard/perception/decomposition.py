"""Convex free-space decomposition of an occupancy grid (thesis Algorithm 4, 3100-3116).

DECOMPOSEFREESPACE, as the thesis describes it:

1. K-means (OpenCV) splits the free cells into k clusters.
2. For each cluster, and each pair of clusters, FITELLIPSE outer-approximates the
   cluster's points by the ellipse of three standard deviations of their covariance,
   centred on the free point closest to their mean.
3. The blocked cells inside the ellipse are mapped into the unit circle and FITFREE
   (Zhong et al., "Generating large convex polytopes directly on point clouds") runs
   there: sphere flipping ``p -> p + 2 (R - |p|) p / |p|`` and the convex hull of the
   flipped points find the blocked points visible from the centre; each visible point,
   nearest first, contributes the halfplane tangent to the circle through it, and
   every point behind that halfplane is dropped.
4. The polygon is mapped back to the world.

Where this module departs from the thesis, and why:

- Blocked cells are squares, not points: each square is represented by its point
  nearest the centre (in the ellipse metric), whose tangent halfplane leaves the whole
  square on its far side, and a square is dropped only when all four corners are behind
  a chosen halfplane. After the visible points every remaining square in reach gets the
  same treatment, so no polygon overlaps a blocked square (exact, not at cell centres).
- Only pairs of clusters that touch get a pair ellipse: the mean of two distant
  clusters lies in neither, and its polygon adds nothing but time.
- Coverage rounds: the free cells the polygons missed (in pieces of a useful size) are
  fitted again, seeded at each piece's deepest cell, a bounded number of times.
- The robot's own cells: with a start (the robot), polygons are fitted seeded at the
  robot itself, whatever already covers it: one in a large circle, and a few in long
  ellipses in evenly spread directions. The clusters' polygons may hold the robot near
  an edge, and a plan leaving it needs the robot deep in one cell (the planner's margin)
  that also reaches out: in the circle metric the faces are tangent at the nearest
  blocked cells, and the unseen ground just beside the robot's blind zone makes that a
  short wedge; in an ellipse metric those faces run along its axis, a corridor out of
  the blind zone.
- Connectivity repair: a multi-source search from the cells each group of overlapping
  polygons covers finds where groups meet; along the 4-connected path of free cells
  between them, a polygon seeded (circular metric) on the shared edge of two cells
  holds both centres in its interior, so consecutive polygons overlap. Where the free
  space is connected, the polygons then form one overlapping chain.

Everything below works in cell units (cell ``[r, c]`` is ``[c, c+1] x [r, r+1]``) and
converts to world metres at the end.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from onboard.contracts.params import PerceptionParams
from onboard.perception import _kernels as K
from onboard.perception.clustering import kmeans_labels
from onboard.perception.geometry import ConvexPolygon

FLIP_RADIUS_FACTOR = 3.0  # R of the sphere flip, relative to the farthest point (Katz et al.)
MARGIN_CELLS = 1e-6  # halfplanes stop this short of a blocked square [cells]
ELLIPSE_REGULARISATION_CELLS = 1.0  # keeps a one-cell-wide cluster's ellipse from collapsing
INTERIOR_TOL_CELLS = 1e-3  # "strictly inside": a cell centre this far within every face
OVERLAP_TOL_CELLS = 1e-6  # polygons share more than this to count as overlapping


@dataclass
class DecompositionStats:
    polygons: int = 0
    clusters: int = 0
    pair_fits: int = 0
    coverage_fits: int = 0
    repair_fits: int = 0
    failed_fits: int = 0
    dropped_for_overlap: int = 0  # fitted, then dropped by the final check for overlapping a blocked square
    groups: int = 0  # groups of overlapping polygons in the result
    coverage: float = 0.0  # of the target free cells, by cell centre strictly inside


class _Decomposer:
    """Fits on one grid, and the cells their interiors cover so far."""

    def __init__(self, free: np.ndarray, target: np.ndarray, stats: DecompositionStats) -> None:
        self.free = free
        self.target = target
        self.stats = stats
        self.rows, self.cols = free.shape
        self.blocked = ~free
        near_free = cv2.dilate(free.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        # Only blocked cells touching free space can bound a convex set grown from a
        # free point: reaching any other blocked cell means crossing one of these first.
        rr, cc = np.nonzero(self.blocked & near_free)
        self.bu = cc.astype(float)
        self.bv = rr.astype(float)
        self.polys: list[ConvexPolygon] = []  # cell units
        self.covered = np.zeros(free.shape, dtype=bool)
        self.owner = np.full(free.shape, -1, dtype=np.int64)  # one polygon per covered cell

    def fit(self, seed: tuple[float, float], L: np.ndarray) -> ConvexPolygon | None:
        A, b, V = K.fit_free(
            float(seed[0]), float(seed[1]), float(L[0, 0]), float(L[1, 0]), float(L[1, 1]),
            self.bu, self.bv, self.cols, self.rows, MARGIN_CELLS, FLIP_RADIUS_FACTOR,
        )
        if len(V) < 3:
            self.stats.failed_fits += 1
            return None
        poly = ConvexPolygon(A, b, V)
        K.mark_interior(A, b, V, self.covered, self.owner, len(self.polys), INTERIOR_TOL_CELLS)
        self.polys.append(poly)
        return poly

    def fit_moments(self, moments: np.ndarray, sigmas: float, seeds: np.ndarray | None = None) -> None:
        """One ellipse fit per row of ``moments`` = ``(n, sum u, sum v, sum uu, sum uv, sum vv)``
        of a set of cell centres. The seed is the free cell closest to the set's mean,
        or the given ``seeds`` row [cells]."""
        for t, (n, su, sv, suu, suv, svv) in enumerate(moments):
            if n <= 0:
                continue
            mu, mv = su / n, sv / n
            cuu, cuv, cvv = suu / n - mu * mu, suv / n - mu * mv, svv / n - mv * mv
            if seeds is None:
                seed = self.closest_target((mu, mv))
            else:
                seed = (float(seeds[t, 0]), float(seeds[t, 1]))
            m = sigmas * sigmas * np.array([[cuu, cuv], [cuv, cvv]]) + (ELLIPSE_REGULARISATION_CELLS ** 2) * np.eye(2)
            self.fit(seed, np.linalg.cholesky(m))

    def closest_target(self, p: tuple[float, float]) -> tuple[float, float]:
        """Centre [cells] of the target cell closest to ``p`` [cells]."""
        r, c = int(math.floor(p[1])), int(math.floor(p[0]))
        if 0 <= r < self.rows and 0 <= c < self.cols and self.target[r, c]:
            return c + 0.5, r + 0.5
        half = 8
        while True:
            r0, r1 = max(r - half, 0), min(r + half + 1, self.rows)
            c0, c1 = max(c - half, 0), min(c + half + 1, self.cols)
            rr, cc = np.nonzero(self.target[r0:r1, c0:c1])
            if len(rr) or (r0 == 0 and c0 == 0 and r1 == self.rows and c1 == self.cols):
                break
            half *= 2
        d2 = (cc + c0 + 0.5 - p[0]) ** 2 + (rr + r0 + 0.5 - p[1]) ** 2
        i = int(np.argmin(d2))
        # A closer cell may sit just outside the window's inscribed circle: widen once.
        reach = math.sqrt(float(d2[i])) + 1.0
        r0, r1 = max(int(p[1] - reach), 0), min(int(p[1] + reach) + 1, self.rows)
        c0, c1 = max(int(p[0] - reach), 0), min(int(p[0] + reach) + 1, self.cols)
        rr, cc = np.nonzero(self.target[r0:r1, c0:c1])
        d2 = (cc + c0 + 0.5 - p[0]) ** 2 + (rr + r0 + 0.5 - p[1]) ** 2
        i = int(np.argmin(d2))
        return float(cc[i] + c0 + 0.5), float(rr[i] + r0 + 0.5)

    def groups(self) -> np.ndarray:
        if not self.polys:
            return np.zeros(0, dtype=np.int64)
        A, b, h_off, V, v_off = _pack(self.polys)
        return K.overlap_groups(A, b, h_off, V, v_off, OVERLAP_TOL_CELLS)

    def strictly_inside(self, poly: ConvexPolygon, r: int, c: int) -> bool:
        x, y = c + 0.5, r + 0.5
        return bool(np.all(poly.A[:, 0] * x + poly.A[:, 1] * y < poly.b - INTERIOR_TOL_CELLS))

    def repair(self, radius: float) -> bool:
        """Chain groups of polygons that meet through free cells; True if none left apart."""
        group = self.groups()
        if len(np.unique(group)) <= 1:
            return True
        label = np.where(self.covered & self.target, group[np.maximum(self.owner, 0)], -1).astype(np.int64).ravel()
        tflat = self.target.ravel().copy()
        dist, parent = K.bfs_labels(tflat, label, self.rows, self.cols)
        lab = label.reshape(self.rows, self.cols)
        dd = dist.reshape(self.rows, self.cols)
        meets: list[tuple[int, int, int]] = []  # (path length, flat u, flat v)
        for a, b_, da, db, step in (
            (lab[:, :-1], lab[:, 1:], dd[:, :-1], dd[:, 1:], 1),
            (lab[:-1, :], lab[1:, :], dd[:-1, :], dd[1:, :], self.cols),
        ):
            rr, cc = np.nonzero((a >= 0) & (b_ >= 0) & (a != b_))
            if len(rr) == 0:
                continue
            u = rr * self.cols + cc
            cost = da[rr, cc] + db[rr, cc]
            # One meeting edge per pair of groups: the shortest path.
            pair = np.minimum(a[rr, cc], b_[rr, cc]) * (len(group) + 1) + np.maximum(a[rr, cc], b_[rr, cc])
            order = np.lexsort((cost, pair))
            first = np.ones(len(order), dtype=bool)
            first[1:] = pair[order][1:] != pair[order][:-1]
            for t in order[first]:
                meets.append((int(cost[t]), int(u[t]), int(u[t] + step)))
        meets.sort()
        parent_g = {int(g): int(g) for g in np.unique(group)}

        def find(g: int) -> int:
            while parent_g[g] != g:
                parent_g[g] = parent_g[parent_g[g]]
                g = parent_g[g]
            return g

        L = np.array([[radius, 0.0], [0.0, radius]])
        for _, u, v in meets:
            gu, gv = find(int(label[u])), find(int(label[v]))
            if gu == gv:
                continue
            path = _trace(parent, u)[::-1] + _trace(parent, v)
            if self._walk(path, L):
                parent_g[gv] = gu
        return len({find(g) for g in parent_g}) <= 1

    def _walk(self, path: list[int], L: np.ndarray) -> bool:
        """Polygons along ``path`` (flat cells, covered at both ends) so that each step
        stays inside one polygon or passes into an overlapping new one."""
        cols = self.cols
        current = self.polys[int(self.owner.flat[path[0]])]
        for i in range(len(path) - 1):
            r1, c1 = divmod(path[i + 1], cols)
            if self.strictly_inside(current, r1, c1):
                continue
            r0, c0 = divmod(path[i], cols)
            new = self.fit(((c0 + c1) * 0.5 + 0.5, (r0 + r1) * 0.5 + 0.5), L)
            if new is None:
                return False
            self.stats.repair_fits += 1
            current = new
        return True


def _trace(parent: np.ndarray, i: int) -> list[int]:
    out = [i]
    while parent[i] >= 0:
        i = int(parent[i])
        out.append(i)
    return out


def _pack(polys: list[ConvexPolygon]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    h_off = np.zeros(len(polys) + 1, dtype=np.int64)
    v_off = np.zeros(len(polys) + 1, dtype=np.int64)
    h_off[1:] = np.cumsum([len(p.b) for p in polys])
    v_off[1:] = np.cumsum([len(p.vertices) for p in polys])
    A = np.concatenate([p.A for p in polys])
    b = np.concatenate([p.b for p in polys])
    V = np.concatenate([p.vertices for p in polys])
    return A, b, h_off, V, v_off


def _moments(labels: np.ndarray, u: np.ndarray, v: np.ndarray, k: int) -> np.ndarray:
    """Per label: ``(n, sum u, sum v, sum uu, sum uv, sum vv)``, shape ``(k, 6)``."""
    out = np.empty((k, 6))
    out[:, 0] = np.bincount(labels, minlength=k)
    for j, w in enumerate((u, v, u * u, u * v, v * v)):
        out[:, j + 1] = np.bincount(labels, weights=w, minlength=k)
    return out


def _kmeans_label_image(target: np.ndarray, k: int, params: PerceptionParams) -> np.ndarray:
    """K-means cluster per target cell (-1 elsewhere).

    K-means runs on blocks of ``f x f`` cells holding any target cell (``f`` keeps the
    point count near ``kmeans_max_points``); every cell takes its block's cluster.
    """
    rows, cols = target.shape
    n = int(target.sum())
    f = max(1, int(math.ceil(math.sqrt(n / params.kmeans_max_points))))
    rc, cc_ = -(-rows // f), -(-cols // f)
    padded = np.zeros((rc * f, cc_ * f), dtype=bool)
    padded[:rows, :cols] = target
    blocks = padded.reshape(rc, f, cc_, f).any(axis=(1, 3))
    br, bc = np.nonzero(blocks)
    k = max(1, min(k, len(br)))
    if k == 1:
        block_labels = np.zeros(len(br), dtype=np.int32)
    else:
        pts = np.column_stack([(bc + 0.5) * f, (br + 0.5) * f]).astype(np.float32)
        block_labels = kmeans_labels(pts, k, np.random.default_rng(params.seed))
    coarse = np.full((rc, cc_), -1, dtype=np.int64)
    coarse[br, bc] = block_labels
    full = np.repeat(np.repeat(coarse, f, axis=0), f, axis=1)[:rows, :cols]
    full[~target] = -1
    # Renumber so that clusters left without a target cell leave no gaps.
    used = np.unique(full[full >= 0])
    remap = np.full(int(full.max()) + 2, -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return remap[full]


def _touching_pairs(label_img: np.ndarray) -> list[tuple[int, int]]:
    """Cluster pairs (i < j) that own 4-adjacent cells."""
    base = int(label_img.max()) + 1
    codes: list[np.ndarray] = []
    for a, b in ((label_img[:, :-1], label_img[:, 1:]), (label_img[:-1, :], label_img[1:, :])):
        m = (a >= 0) & (b >= 0) & (a != b)
        codes.append(np.minimum(a[m], b[m]) * base + np.maximum(a[m], b[m]))
    u = np.unique(np.concatenate(codes))
    return [(int(c // base), int(c % base)) for c in u]


def target_region(
    free: np.ndarray, res: float, origin: tuple[float, float], start: tuple[float, float] | None
) -> np.ndarray:
    """The free cells to decompose: all, or those 4-connected to ``start`` [m]."""
    if start is None:
        return free.copy()
    cell = world_to_cell(start, res, origin)
    rows, cols = free.shape
    if cell is None or not (0 <= cell[0] < rows and 0 <= cell[1] < cols) or not free[cell]:
        return np.zeros_like(free)
    _, comp = cv2.connectedComponents(free.astype(np.uint8), connectivity=4)
    return comp == comp[cell]


def world_to_cell(p: tuple[float, float], res: float, origin: tuple[float, float]) -> tuple[int, int] | None:
    """``(row, col)`` of the cell holding world point ``p`` [m] (None if not finite)."""
    u = (p[0] - origin[0]) / res
    v = (p[1] - origin[1]) / res
    if not (math.isfinite(u) and math.isfinite(v)):
        return None
    return int(math.floor(v)), int(math.floor(u))


def decompose_free_space(
    free: np.ndarray,
    res: float,
    origin: tuple[float, float],
    params: PerceptionParams = PerceptionParams(),
    start: tuple[float, float] | None = None,
    must_cover: tuple[tuple[float, float], ...] = (),
) -> tuple[list[ConvexPolygon], DecompositionStats]:
    """Convex polygons [m, world] inside the free cells of ``free`` (bool, rows along y).

    ``res`` [m] and ``origin`` [m, lower-left corner of cell [0, 0]] place the grid in
    the world. With ``start`` (world [m]) only the free cells 4-connected to the start
    cell are decomposed; otherwise all free cells are. Points of ``must_cover`` (world
    [m]) in those cells end up inside a polygon. Every polygon is checked against every
    non-free cell (as a square) before it is returned: none overlaps one.
    """
    free = np.ascontiguousarray(free, dtype=bool)
    stats = DecompositionStats()
    target = target_region(free, res, origin, start)
    n_target = int(target.sum())
    if n_target == 0:
        return [], stats
    dec = _Decomposer(free, target, stats)
    rr, cc = np.nonzero(target)
    pu, pv = cc + 0.5, rr + 0.5

    # K-means, then each cluster and each touching pair of clusters.
    k = int(np.clip(round(n_target / params.cluster_cells), params.clusters_min, params.clusters_max))
    label_img = _kmeans_label_image(target, k, params)
    labels = label_img[rr, cc]
    k = int(labels.max()) + 1
    stats.clusters = k
    moments = _moments(labels, pu, pv, k)
    dec.fit_moments(moments, params.ellipse_sigmas)
    pairs = _touching_pairs(label_img)
    stats.pair_fits = len(pairs)
    if pairs:
        ij = np.array(pairs)
        dec.fit_moments(moments[ij[:, 0]] + moments[ij[:, 1]], params.ellipse_sigmas)

    # Coverage rounds on what is left.
    for _ in range(params.coverage_rounds):
        if dec.covered[target].mean() >= params.coverage_target:
            break
        residual = (target & ~dec.covered).astype(np.uint8)
        n_comp, comp = cv2.connectedComponents(residual, connectivity=4)
        if n_comp <= 1:
            break
        at = comp[rr, cc]
        sizes = np.bincount(at, minlength=n_comp)
        big = np.nonzero(sizes >= params.residual_min_cells)[0]
        big = big[big > 0]
        if len(big) == 0:
            break
        # A residual piece often wraps around an obstacle, so its mean can sit in the
        # obstacle: seed at the piece's deepest cell instead.
        depth = cv2.distanceTransform(residual, cv2.DIST_L2, cv2.DIST_MASK_3)[rr, cc]
        order = np.lexsort((depth, at))
        last = np.cumsum(sizes) - 1  # the deepest cell of each piece in ``order``
        deepest = order[last[big]]
        seeds = np.column_stack([pu[deepest], pv[deepest]])
        stats.coverage_fits += len(big)
        dec.fit_moments(_moments(at, pu, pv, n_comp)[big], params.ellipse_sigmas, seeds)

    if start is not None and params.start_fit_radius_m > 0:
        big = params.start_fit_radius_m / res
        su = ((start[0] - origin[0]) / res, (start[1] - origin[1]) / res)
        cell = world_to_cell(start, res, origin)
        if cell is not None and 0 <= cell[0] < dec.rows and 0 <= cell[1] < dec.cols and target[cell]:
            dec.fit(su, np.array([[big, 0.0], [0.0, big]]))
            n_dir = params.start_fit_directions
            short = big / params.start_fit_aspect
            for k in range(n_dir):
                c, s_ = math.cos(math.pi * k / n_dir), math.sin(math.pi * k / n_dir)
                rot = np.array([[c, -s_], [s_, c]])
                dec.fit(su, np.linalg.cholesky(rot @ np.diag([big * big, short * short]) @ rot.T))

    radius = params.repair_radius_cells
    circle = np.array([[radius, 0.0], [0.0, radius]])
    for p in must_cover:
        u = ((p[0] - origin[0]) / res, (p[1] - origin[1]) / res)
        cell = world_to_cell(p, res, origin)
        if cell is None or not (0 <= cell[0] < dec.rows and 0 <= cell[1] < dec.cols) or not target[cell]:
            continue
        if not any(np.all(q.A @ np.array(u) < q.b - INTERIOR_TOL_CELLS) for q in dec.polys):
            # At the point itself when it is clear of blocked squares, else at its cell centre.
            if dec.fit(u, circle) is None:
                dec.fit((cell[1] + 0.5, cell[0] + 0.5), circle)

    for _ in range(params.repair_rounds):
        if dec.repair(radius):
            break

    kept, stats.dropped_for_overlap = clear_of_blocked(dec.polys, dec.blocked)
    polys = [_to_world(cell_poly, res, origin) for cell_poly in kept]
    stats.polygons = len(polys)
    if kept:
        A, b, h_off, V, v_off = _pack(kept)
        stats.groups = len(np.unique(K.overlap_groups(A, b, h_off, V, v_off, OVERLAP_TOL_CELLS)))
    covered = dec.covered
    if stats.dropped_for_overlap:  # what the dropped polygons covered is not covered
        covered = np.zeros_like(dec.covered)
        owner = np.full(covered.shape, -1, dtype=np.int64)
        for i, q in enumerate(kept):
            K.mark_interior(q.A, q.b, q.vertices, covered, owner, i, INTERIOR_TOL_CELLS)
    stats.coverage = float(covered[target].mean())
    return polys, stats


def clear_of_blocked(cell_polys: list[ConvexPolygon], blocked: np.ndarray) -> tuple[list[ConvexPolygon], int]:
    """The polygons [cell units] that overlap no square of ``blocked``, and how many did.

    The fits cut every blocked square away already; this last check keeps that promise
    whatever a fit got wrong, and the count says how often it had to.
    """
    blocked = np.ascontiguousarray(blocked, dtype=bool)
    kept = [p for p in cell_polys if not K.overlaps_blocked(p.A, p.b, p.vertices, blocked, OVERLAP_TOL_CELLS)]
    return kept, len(cell_polys) - len(kept)


def _to_world(poly: ConvexPolygon, res: float, origin: tuple[float, float]) -> ConvexPolygon:
    """Cell units to world metres: ``x = origin + res u`` keeps the unit normals."""
    o = np.asarray(origin, dtype=float)
    return ConvexPolygon(poly.A.copy(), res * poly.b + poly.A @ o, poly.vertices * res + o)
