"""Densify the Bezier graph where a search failed, until it finds a path or can say why not.

A graph of ``N`` random nodes is complete only up to its resolution: a gap that no node
pair lines up with is closed to it although a robot fits through. When the search finds
no path, :class:`Densifier` adds nodes where they are needed, in rounds, and searches
again after each:

- **where**: the *failed frontier*. ``S`` is the set of nodes the start reaches over free
  edges, ``G`` the set that reaches the goal. The region is tiled in cells of one
  segment's reach; a cell is on the frontier when it holds nodes of ``S`` and free nodes
  outside ``S`` (the search stopped there although the nodes are clear of every
  obstacle), or when it borders a cell of ``S`` without holding one itself (room ``S``
  never entered); the same for ``G``.
- **what**: nodes at rest on a lattice, spacing halving level by level from
  ``densify_grid`` (or half the graph's own rest lattice) down to ``densify_min_grid``.
  Between two resting nodes the curve is the straight segment joining them, so a fine
  lattice passes stop-and-go wherever a disc of the margin fits at that resolution.
  Narrow passages between two obstacles also get their *crossing*: resting nodes on the
  line through the midpoint of the obstacles' closest points, across the gap. Every
  point of that line keeps half the gap from both obstacles, so a gap only just wider
  than twice the margin is passable although no lattice point falls into it.
- **how far**: a level is done when it adds no node on the frontier; the finest level
  done without a path means the goal is unreachable in the graph at the finest
  resolution. Rounds stop earlier when the time budget (``densify_budget_s``, read from
  the caller's clock), the rounds of one call (``densify_max_rounds``) or the node limit
  (``densify_max_nodes`` per graph) or the edge limit (``densify_max_edges`` per graph: the memory)
  is spent.

The densified graph replaces the planner's graph (same :class:`GraphSpec`, ``densified``
counts the nodes added), so later plans in the same region reuse it; it is never written
to the graph cache (:meth:`BezierGraph.to_arrays` refuses it).

Pure: no clock is read here (the caller passes one), no I/O, no threads.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numba as nb
import numpy as np
from scipy.spatial import cKDTree

from onboard.geometry import bezier as bz
from onboard.high_level.tracking import collision as col
from onboard.geometry import polygons as pg
from onboard.high_level.planning.bezier_graph import PRUNE_SLACK, BezierGraph, assemble, reach_scale

LATTICE_LINK = 2.0  # a new resting node is joined to resting nodes within this many of its spacings (8 + 16 neighbours)
REST_SPEED = 0.0  # [m/s] nodes with exactly this speed are resting nodes (straight segments between them)

BUDGET_SPENT = "budget spent"
NODE_LIMIT = "node limit reached"
EDGE_LIMIT = "edge limit reached"
UNREACHABLE = "goal unreachable in the graph at the finest resolution"


@dataclass(frozen=True)
class DensifyReport:
    """What one plan call's densification did."""

    rounds: int  # rounds that added nodes
    nodes_added: int
    edges_added: int
    spent_s: float  # [s] on the caller's clock (0 without one)
    found: bool  # a path was found after densifying
    reason: str  # why there is still no path ("" when found)
    finest_grid: float  # [m] spacing of the finest lattice level reached


class SearchView:
    """What :class:`Densifier` needs from the planner during one plan call
    (``onboard.high_level.planning.graph_planner`` implements it)."""

    graph: BezierGraph
    free: np.ndarray  # the cut: free edges of ``graph``
    start_seeds: np.ndarray  # graph nodes joined to the start by the last search
    goal_seeds: np.ndarray  # graph nodes joined to the goal by the last search

    def search(self) -> bool:  # pragma: no cover - interface
        """Search the current graph again (updating the seeds); whether a path was found."""
        raise NotImplementedError

    def points_free(self, points: np.ndarray) -> np.ndarray:  # pragma: no cover - interface
        """Per point ``(P, 2)``: a robot resting there keeps the margin (and the region)."""
        raise NotImplementedError

    def edges_free(self, control_points: np.ndarray) -> np.ndarray:  # pragma: no cover - interface
        """Per curve ``(E, K, 2)``: the curve keeps the margin (the cut)."""
        raise NotImplementedError

    def install(self, graph: BezierGraph, free: np.ndarray) -> None:  # pragma: no cover - interface
        """Plan on ``graph`` from now on, with ``free`` as its cut."""
        raise NotImplementedError


# --- reachability over free edges -----------------------------------------------------------


@nb.njit(cache=True)
def _reach(indptr, dst, free, seeds, n):  # pragma: no cover - compiled
    seen = np.zeros(n, dtype=np.bool_)
    stack = np.empty(n, dtype=np.int64)
    top = 0
    for s in seeds:
        if not seen[s]:
            seen[s] = True
            stack[top] = s
            top += 1
    while top > 0:
        top -= 1
        u = stack[top]
        for e in range(indptr[u], indptr[u + 1]):
            if free[e]:
                v = dst[e]
                if not seen[v]:
                    seen[v] = True
                    stack[top] = v
                    top += 1
    return seen


def reached_from(graph: BezierGraph, free: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """Nodes reached from ``seeds`` over free edges ``(N,)``."""
    return _reach(graph.indptr, graph.dst, np.ascontiguousarray(free), np.asarray(seeds, dtype=np.int64), graph.n_nodes)


def reaching(graph: BezierGraph, free: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """Nodes that reach ``seeds`` over free edges ``(N,)`` (the same walk on reversed edges)."""
    order = np.argsort(graph.dst, kind="stable")
    indptr = np.zeros(graph.n_nodes + 1, dtype=np.int64)
    np.cumsum(np.bincount(graph.dst, minlength=graph.n_nodes), out=indptr[1:])
    return _reach(indptr, np.ascontiguousarray(graph.src[order]), np.ascontiguousarray(free[order]),
                  np.asarray(seeds, dtype=np.int64), graph.n_nodes)


# --- where -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CellGrid:
    """Square cells of side ``h`` [m] over ``bounds``."""

    x0: float
    y0: float
    h: float
    nx: int
    ny: int

    @classmethod
    def over(cls, bounds: tuple[float, float, float, float], h: float) -> CellGrid:
        xmin, ymin, xmax, ymax = bounds
        return cls(xmin, ymin, h, max(int(math.ceil((xmax - xmin) / h)), 1), max(int(math.ceil((ymax - ymin) / h)), 1))

    def index(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ix = np.clip(((points[:, 0] - self.x0) // self.h).astype(np.int64), 0, self.nx - 1)
        iy = np.clip(((points[:, 1] - self.y0) // self.h).astype(np.int64), 0, self.ny - 1)
        return ix, iy

    def mark(self, points: np.ndarray) -> np.ndarray:
        out = np.zeros((self.nx, self.ny), dtype=bool)
        if len(points):
            out[self.index(points)] = True
        return out


def _dilate(cells: np.ndarray) -> np.ndarray:
    out = cells.copy()
    out[1:, :] |= cells[:-1, :]
    out[:-1, :] |= cells[1:, :]
    grown = out.copy()
    grown[:, 1:] |= out[:, :-1]
    grown[:, :-1] |= out[:, 1:]
    return grown


def frontier_cells(grid: CellGrid, positions: np.ndarray, node_free: np.ndarray, reached: np.ndarray,
                   anchor: np.ndarray) -> np.ndarray:
    """Cells ``(nx, ny)`` where the set ``reached`` (plus its ``anchor`` point, the start or
    the goal) stopped: holding reached nodes and free unreached ones, or bordering a reached
    cell without holding a reached node."""
    inside = grid.mark(np.vstack([positions[reached], anchor[None]]))
    stopped = grid.mark(positions[node_free & ~reached])
    return (inside & stopped) | (_dilate(inside) & ~inside)


# --- what ----------------------------------------------------------------------------------------


def lattice_in_cells(grid: CellGrid, cells: np.ndarray, spacing: float,
                     bounds: tuple[float, float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Lattice points of ``spacing`` (origin at the region's corner) inside the marked cells:
    ``(P, 2)`` positions and their integer lattice coordinates ``(P, 2)``."""
    xmin, ymin, xmax, ymax = bounds
    per = int(math.ceil(grid.h / spacing)) + 1
    cx, cy = np.nonzero(cells)
    if len(cx) == 0:
        return np.zeros((0, 2)), np.zeros((0, 2), dtype=np.int64)
    kx, ky = np.meshgrid(np.arange(per), np.arange(per), indexing="ij")
    # lattice indices from the first point at or after each cell's corner
    ix0 = np.ceil((grid.x0 + cx * grid.h - xmin) / spacing - 1e-9).astype(np.int64)
    iy0 = np.ceil((grid.y0 + cy * grid.h - ymin) / spacing - 1e-9).astype(np.int64)
    ix = (ix0[:, None] + kx.ravel()[None, :]).ravel()
    iy = (iy0[:, None] + ky.ravel()[None, :]).ravel()
    px, py = xmin + ix * spacing, ymin + iy * spacing
    cell_x = np.repeat(cx, per * per)
    cell_y = np.repeat(cy, per * per)
    keep = ((px < grid.x0 + (cell_x + 1) * grid.h) & (py < grid.y0 + (cell_y + 1) * grid.h)
            & (px <= xmax) & (py <= ymax))
    coords = np.unique(np.column_stack([ix[keep], iy[keep]]), axis=0)
    return np.column_stack([xmin + coords[:, 0] * spacing, ymin + coords[:, 1] * spacing]), coords


@nb.njit(cache=True)
def _pair_gaps(verts, offsets, pairs):  # pragma: no cover - compiled
    """Per pair of disjoint convex polygons: distance and closest points (vertex to edge, both ways)."""
    P = pairs.shape[0]
    dist = np.full(P, np.inf)
    near = np.zeros((P, 2, 2))
    for k in range(P):
        for side in range(2):
            a, b = pairs[k, side], pairs[k, 1 - side]
            for v in range(offsets[a], offsets[a + 1]):
                px, py = verts[v, 0], verts[v, 1]
                n = offsets[b + 1] - offsets[b]
                for i in range(n):
                    x0, y0 = verts[offsets[b] + i, 0], verts[offsets[b] + i, 1]
                    x1, y1 = verts[offsets[b] + (i + 1) % n, 0], verts[offsets[b] + (i + 1) % n, 1]
                    dx, dy = x1 - x0, y1 - y0
                    d2 = dx * dx + dy * dy
                    t = 0.0 if d2 <= 0.0 else min(max(((px - x0) * dx + (py - y0) * dy) / d2, 0.0), 1.0)
                    fx, fy = x0 + t * dx, y0 + t * dy
                    d = math.hypot(px - fx, py - fy)
                    if d < dist[k]:
                        dist[k] = d
                        near[k, side, 0], near[k, side, 1] = px, py
                        near[k, 1 - side, 0], near[k, 1 - side, 1] = fx, fy
    return dist, near


def gap_crossings(obstacles: pg.PolygonSet, margin: float, widest: float, spacing: float) -> dict[tuple[int, int], np.ndarray]:
    """Resting-node rows across every gap between two obstacles wider than ``2 margin`` and at
    most ``2 margin + widest`` [m]: points every ``spacing`` on the line through the midpoint
    of the closest points, across the gap, reaching ``margin + spacing`` past both obstacles.
    Keyed by the obstacle pair."""
    out: dict[tuple[int, int], np.ndarray] = {}
    n = len(obstacles)
    if n < 2:
        return out
    reach = 2 * margin + widest
    boxes = obstacles.aabb
    tree = cKDTree(obstacles.center)
    pairs = tree.query_pairs(float(2 * obstacles.radius.max() + reach), output_type="ndarray").astype(np.int64)
    i, j = pairs[:, 0], pairs[:, 1]
    box_gap = np.maximum(np.maximum(boxes[i, 0] - boxes[j, 2], boxes[j, 0] - boxes[i, 2]),
                         np.maximum(boxes[i, 1] - boxes[j, 3], boxes[j, 1] - boxes[i, 3]))
    pairs = np.ascontiguousarray(pairs[box_gap <= reach])
    dist, near = _pair_gaps(obstacles.vertices, obstacles.offsets, pairs)
    for k in np.flatnonzero((dist > 2 * margin) & (dist <= reach)):
        a, b = obstacles.polygon(int(pairs[k, 0])), obstacles.polygon(int(pairs[k, 1]))
        p, q = near[k, 0], near[k, 1]
        mid = (p + q) / 2
        across = np.array([-(q - p)[1], (q - p)[0]]) / dist[k]
        extent = max(np.abs((a - mid) @ across).max(), np.abs((b - mid) @ across).max()) + margin + spacing
        steps = int(math.ceil(extent / spacing))
        t = spacing * np.arange(-steps, steps + 1)
        out[(int(pairs[k, 0]), int(pairs[k, 1]))] = mid[None, :] + t[:, None] * across[None, :]
    return out


# --- extending the graph -----------------------------------------------------------------------


def extend_graph(graph: BezierGraph, new_nodes: np.ndarray, link: np.ndarray,
                 scale: np.ndarray | None = None) -> tuple[BezierGraph, np.ndarray, np.ndarray]:
    """``graph`` with resting ``new_nodes`` ``(M, 4)`` appended and joined both ways to every
    node within one segment's reach that the reachability test accepts, except that two
    resting nodes are joined only within the new node's ``link`` [m] (inf-norm).

    Returns the graph, where each old edge went ``(E_old,)``, and where the new edges are
    ``(E_new,)`` (indices into the new graph's edges). ``scale``: :func:`reach_scale` of the
    graph's test when the caller has it (an LP).
    """
    N = graph.n_nodes
    nodes = np.vstack([graph.nodes, new_nodes])
    scale = reach_scale(graph.reachability, graph.spec.a_max) if scale is None else scale
    tree = cKDTree(nodes / scale)
    near = tree.query_ball_point(new_nodes / scale, 1.0 + PRUNE_SLACK, p=np.inf)
    counts = np.array([len(n) for n in near], dtype=np.int64)
    a = np.repeat(np.arange(N, N + len(new_nodes), dtype=np.int64), counts)
    b = np.concatenate([np.asarray(n, dtype=np.int64) for n in near]) if len(near) else np.zeros(0, dtype=np.int64)
    resting = np.all(nodes[b, 2:] == REST_SPEED, axis=1)
    close = np.max(np.abs(nodes[b, :2] - nodes[a, :2]), axis=1) <= np.repeat(link, counts) * (1 + PRUNE_SLACK)
    keep = (a != b) & (~resting | close)
    a, b = a[keep], b[keep]
    old = b < N  # new-new pairs come once from each side's query
    i = np.concatenate([a, b[old]])
    j = np.concatenate([b, a[old]])
    test = graph.reachability
    ok = test.edge_table(nodes).test_pairs(i, j)
    i, j = i[ok], j[ok]
    # the old edges are sorted by (source, destination) and no new edge repeats one (each has a new
    # end): the new ones are merged in, not the whole set sorted and every hull rebuilt
    total = len(nodes)
    key_old = graph.src * total + graph.dst
    by_key = np.argsort(i * total + j, kind="stable")
    i, j = i[by_key], j[by_key]
    new_at = np.searchsorted(key_old, i * total + j) + np.arange(len(i))
    is_new = np.zeros(graph.n_edges + len(i), dtype=bool)
    is_new[new_at] = True
    old_at = np.flatnonzero(~is_new)
    ctrl = test.curve(nodes[i], nodes[j])
    hulls = col.grown_hull_set(graph.hulls, ctrl, new_at)
    src = np.empty(len(is_new), dtype=np.int64)
    dst = np.empty(len(is_new), dtype=np.int64)
    cost = np.empty(len(is_new))
    src[old_at], dst[old_at], cost[old_at] = graph.src, graph.dst, graph.cost
    src[new_at], dst[new_at], cost[new_at] = i, j, bz.path_length_bound(ctrl)
    out = assemble(graph.spec, nodes, src, dst, hulls.points, cost, test, densified=graph.densified + len(new_nodes), hulls=hulls)
    return out, old_at, new_at


# --- the rounds ------------------------------------------------------------------------------


@dataclass(frozen=True)
class DensifyLimits:
    budget_s: float  # [s] on the caller's clock
    first_grid: float  # [m] lattice spacing of the first level
    min_grid: float  # [m] no level finer than this
    max_nodes: int  # nodes added to one graph at most
    max_edges: int  # edges added to one graph at most (one round may pass it)
    round_nodes: int  # nodes added per round at most (bounds one round's time)
    max_rounds: int  # rounds per call at most without a clock (lockstep's bound, the same on any machine)


class Densifier:
    """Densification state of one graph: which lattice points and gap crossings it holds."""

    def __init__(self, graph: BezierGraph, limits: DensifyLimits) -> None:
        self.limits = limits
        self.base_spec = graph.spec
        self.levels = [limits.first_grid]
        while self.levels[-1] / 2 >= limits.min_grid:
            self.levels.append(self.levels[-1] / 2)
        finest = self.levels[-1]
        xmin, ymin, xmax, ymax = graph.spec.bounds
        self._finest = finest
        # lattice points already in the graph, in units of the finest spacing
        self._present = np.zeros((int((xmax - xmin) // finest) + 2, int((ymax - ymin) // finest) + 2), dtype=bool)
        rest = graph.nodes[np.all(graph.nodes[:, 2:] == REST_SPEED, axis=1), :2]
        k = np.round((rest - [xmin, ymin]) / finest)
        on = np.all(np.abs(k * finest + [xmin, ymin] - rest) < 1e-9, axis=1)
        self._present[k[on, 0].astype(np.int64), k[on, 1].astype(np.int64)] = True
        self._scale = reach_scale(graph.reachability, graph.spec.a_max)
        self._base_edges = graph.n_edges
        self._crossed: set[tuple[int, int]] = set()  # gaps whose crossing is in the graph
        self._crossings: dict[tuple[int, int], np.ndarray] | None = None  # of the world below
        self._crossing_world = -1

    def run(self, view: SearchView, start: np.ndarray, goal: np.ndarray, obstacles: pg.PolygonSet | None,
            margin: float, world_version: int, clock: Callable[[], float] | None) -> DensifyReport:
        """Rounds of densification and search (see the module docstring) on ``view``.

        Two passes over the levels: first only where the start's and the goal's sets meet
        (neighbouring cells), where a wall with a gap too narrow for the graph separates
        them; then the whole failed frontier, which also holds passages through room that
        neither set entered.
        """
        lim = self.limits
        t0 = clock() if clock is not None else 0.0
        if world_version != self._crossing_world:
            self._crossed.clear()
            self._crossings = None
            self._crossing_world = world_version
        rounds = added = edges = 0
        level = 0
        scope = 0  # 0: where the two sets meet, 1: the whole failed frontier (see _frontiers)
        last_round_s = 0.0
        cell = float(self._scale[0])
        frontier_of: tuple | None = None  # (graph, frontier per pass) of the last graph seen
        while True:
            if clock is not None and clock() - t0 + last_round_s > lim.budget_s:
                reason = BUDGET_SPENT
                break
            if clock is None and rounds >= lim.max_rounds:
                reason = BUDGET_SPENT
                break
            room = lim.max_nodes - view.graph.densified
            if room <= 0:
                reason = NODE_LIMIT
                break
            if view.graph.n_edges - self._base_edges >= lim.max_edges:
                reason = EDGE_LIMIT
                break
            t_round = clock() if clock is not None else 0.0
            graph = view.graph
            grid = CellGrid.over(graph.spec.bounds, cell)
            if frontier_of is None or frontier_of[0] is not graph:
                frontier_of = (graph, self._frontiers(view, grid, start, goal))
            spacing = self.levels[level]
            points, links = self._new_points(grid, frontier_of[1][scope], spacing, graph.spec.bounds,
                                             obstacles, margin, view)
            if len(points) == 0:
                if level + 1 < len(self.levels):
                    level += 1
                elif scope == 0:
                    scope, level = 1, 0
                else:
                    reason = UNREACHABLE
                    break
                continue
            take = min(room, lim.round_nodes, len(points))
            order = np.argsort(_segment_distance(points, start, goal), kind="stable")[:take]
            points, links = points[order], links[order]
            self._mark(points, graph.spec.bounds)
            new_nodes = np.column_stack([points, np.zeros((len(points), 2))])
            extended, old_at, new_at = extend_graph(graph, new_nodes, links, self._scale)
            free = np.empty(extended.n_edges, dtype=bool)
            free[old_at] = view.free
            free[new_at] = view.edges_free(extended.control_points[new_at])
            view.install(extended, free)
            rounds += 1
            added += len(points)
            edges += len(new_at)
            if view.search():
                reason = ""
                break
            if clock is not None:
                last_round_s = clock() - t_round
        spent = clock() - t0 if clock is not None else 0.0
        return DensifyReport(rounds, added, edges, spent, reason == "", reason, self.levels[level])

    @staticmethod
    def _frontiers(view: SearchView, grid: CellGrid, start: np.ndarray, goal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cells where the start's and the goal's sets meet, and the whole failed frontier."""
        graph = view.graph
        positions = graph.nodes[:, :2]
        node_free = view.points_free(positions)
        from_start = reached_from(graph, view.free, view.start_seeds)
        to_goal = reaching(graph, view.free, view.goal_seeds)
        whole = (frontier_cells(grid, positions, node_free, from_start, start)
                 | frontier_cells(grid, positions, node_free, to_goal, goal))
        meet = (_dilate(grid.mark(np.vstack([positions[from_start], start[None]])))
                & _dilate(grid.mark(np.vstack([positions[to_goal], goal[None]]))))
        return meet, whole

    def _new_points(self, grid: CellGrid, frontier: np.ndarray, spacing: float, bounds: tuple[float, float, float, float],
                    obstacles: pg.PolygonSet | None, margin: float, view: SearchView) -> tuple[np.ndarray, np.ndarray]:
        """Free lattice points of ``spacing`` on the frontier not yet in the graph, and (the
        first time a gap's midpoint is on the frontier) its crossing; with each, its link [m]."""
        pts, coords = lattice_in_cells(grid, frontier, spacing, bounds)
        step = int(round(spacing / self._finest))
        fine = np.minimum(coords * step, np.array(self._present.shape) - 1)
        fresh = ~self._present[fine[:, 0], fine[:, 1]]
        pts = pts[fresh]
        links = np.full(len(pts), LATTICE_LINK * spacing)
        if obstacles is not None and len(obstacles) > 1:
            first = self.levels[0]
            if self._crossings is None:
                self._crossings = gap_crossings(obstacles, margin, first, first)
            keys = [k for k in self._crossings if k not in self._crossed]
            mids = np.array([self._crossings[k][len(self._crossings[k]) // 2] for k in keys]).reshape(-1, 2)
            on = frontier[grid.index(mids)] if len(keys) else np.zeros(0, dtype=bool)
            rows = [self._crossings[keys[k]] for k in np.flatnonzero(on)]
            self._crossed.update(keys[k] for k in np.flatnonzero(on))
            if rows:
                cross = np.vstack(rows)
                pts = np.vstack([cross, pts])
                links = np.concatenate([np.full(len(cross), LATTICE_LINK * first), links])
        if len(pts) == 0:
            return pts, links
        keep = view.points_free(pts)
        return pts[keep], links[keep]

    def _mark(self, points: np.ndarray, bounds: tuple[float, float, float, float]) -> None:
        k = np.round((points - [bounds[0], bounds[1]]) / self._finest)
        on = np.all(np.abs(k * self._finest + [bounds[0], bounds[1]] - points) < 1e-9, axis=1)
        k = np.minimum(k[on].astype(np.int64), np.array(self._present.shape) - 1)
        self._present[k[:, 0], k[:, 1]] = True


def _segment_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance [m] of each point to the segment ``a``-``b`` (new nodes nearest the straight way first)."""
    d = b - a
    t = np.clip(((points - a) @ d) / max(float(d @ d), 1e-18), 0.0, 1.0)
    return np.hypot(*(points - (a + t[:, None] * d)).T)
