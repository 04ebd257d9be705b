"""The kinodynamic Bezier graph: build and search (thesis ch. 7, lines 3067-3220).

Planning model and pipeline: :mod:`onboard.high_level.planning.graph_planner`, which cuts this graph against
the world and refines its paths. Here:

- :func:`build_graph`: ``N`` nodes over position and velocity (uniform random or grid),
  plus a lattice of nodes at rest; candidate pairs from a k-d tree over positions and
  velocities scaled by the largest change one segment can make (:func:`reach_scale`, an
  LP over the reachability test, so the pruning drops no edge the test would accept); a
  pair is an edge iff the Bezier reachability test of :mod:`onboard.high_level.tracking.reachability` holds.
  Each edge carries its position control points and its cost, the path-length bound of
  Property 2.49. The graph depends only on :class:`GraphSpec`; :meth:`GraphSpec.key`
  names it for an on-disk cache, :meth:`BezierGraph.to_arrays` /
  :meth:`BezierGraph.from_arrays` convert it for the caller, who does the file I/O.
- :func:`search`: A* (admissible straight-line heuristic) over the edges left free.
- :func:`path_states`, :func:`chain_tail`: sampling a path's Bezier chain.

Pure: no clock, no I/O, no threads.
"""

from __future__ import annotations

import hashlib
import heapq
import json
import math
from dataclasses import asdict, dataclass, field

import numba as nb
import numpy as np
from scipy.spatial import cKDTree

from onboard.geometry import bezier as bz
from onboard.high_level.tracking import collision as col
from onboard.high_level.tracking import reachability as reach
from onboard.contracts.params import PlannerParams

GRAPH_FORMAT = 2  # bump when the arrays or the build change meaning (invalidates caches)
DIM = 2  # horizontal plane
PRUNE_SLACK = 1e-9  # relative slack on the k-d tree radius (pairs exactly at the reach)
SAMPLING = ("uniform", "grid")
MAX_LATTICE = 200_000  # rest-lattice nodes at most (memory)
# The planned speed bound: the regular octagon of inradius v_max in the velocity plane. The box
# |vx|, |vy| <= v_max let a diagonal path run 41 % faster than an axis-aligned one, and the
# hopper's wheels gather momentum hop by hop at that speed (forest at twice the density: falls
# at 0.49 m/s, none at 0.35). The octagon's corners are 8 % beyond v_max (1 / cos(pi / 8)).
_DIAG = math.sqrt(0.5)
SPEED_NORMALS = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0],
                          [_DIAG, _DIAG], [-_DIAG, -_DIAG], [_DIAG, -_DIAG], [-_DIAG, _DIAG]])


class PlanningError(ValueError):
    """Invalid planner input (bad obstacle, state outside the planning model, ...)."""


# --- graph --------------------------------------------------------------------------------


@dataclass(frozen=True)
class GraphSpec:
    """Everything that shapes a graph; two equal specs give the same graph."""

    bounds: tuple[float, float, float, float]  # xmin, ymin, xmax, ymax of node positions [m]
    nodes: int
    v_max: float  # [m/s]
    a_max: float  # [m/s^2]
    tau: float  # [s] segment duration
    sampling: str = "uniform"
    seed: int = 0
    grid_velocities: int = 3
    rest_grid: float = 0.0  # [m] spacing of extra nodes at rest on a lattice (0: none)

    def __post_init__(self) -> None:
        xmin, ymin, xmax, ymax = self.bounds
        values = (*self.bounds, self.v_max, self.a_max, self.tau)
        if not all(math.isfinite(v) for v in values):
            raise PlanningError("graph spec has a non-finite value")
        if not (xmax > xmin and ymax > ymin):
            raise PlanningError(f"empty planning region {self.bounds}")
        if self.nodes < 2 or self.v_max <= 0 or self.a_max <= 0 or self.tau <= 0:
            raise PlanningError("need nodes >= 2 and positive v_max, a_max, tau")
        if self.sampling not in SAMPLING:
            raise PlanningError(f"sampling must be one of {SAMPLING}, got {self.sampling!r}")
        if self.grid_velocities < 1:
            raise PlanningError("grid_velocities must be >= 1")
        if not (math.isfinite(self.rest_grid) and self.rest_grid >= 0):
            raise PlanningError("rest_grid must be finite and >= 0")
        if self.rest_grid and self.lattice_size() > MAX_LATTICE:
            raise PlanningError(f"rest_grid {self.rest_grid} m gives more than {MAX_LATTICE} lattice nodes")

    def lattice_size(self) -> int:
        """Nodes of the rest lattice (0 without one)."""
        if not self.rest_grid:
            return 0
        xmin, ymin, xmax, ymax = self.bounds
        return (int((xmax - xmin) // self.rest_grid) + 1) * (int((ymax - ymin) // self.rest_grid) + 1)

    @property
    def total_nodes(self) -> int:
        return self.nodes + self.lattice_size()

    def key(self) -> str:
        """Cache key: a hash of every field and the format version."""
        blob = json.dumps({"format": GRAPH_FORMAT, **asdict(self)}, sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()[:24]

    def reachability(self) -> reach.BezierReachability:
        """The edge test: the speed bound ``v_max`` (:func:`speed_limits`) and the input bound
        ``a_max`` over segments of ``tau``.

        Positions are not limited here: the planning region and the obstacles are
        handled by the cut, so the graph does not depend on them or on the tube.
        """
        return reach.BezierReachability(reach.double_integrator(DIM), speed_limits(self.a_max, self.v_max), self.tau)


def speed_limits(a_max: float, v_max: float, tube: float = 0.0, tube_norm: float = math.inf) -> reach.ReachLimits:
    """Limits of the planning model ``[x, y, vx, vy]``: speed within the octagon of inradius
    ``v_max`` (``SPEED_NORMALS``), acceleration ``|a|_inf <= a_max``, the tracking tube."""
    state_A = np.hstack([np.zeros((len(SPEED_NORMALS), DIM)), SPEED_NORMALS])
    return reach.ReachLimits(u_max=a_max, state_A=state_A, state_b=np.full(len(SPEED_NORMALS), v_max),
                             tube=tube, tube_norm=tube_norm)


def within_speed_bound(velocities: np.ndarray, v_max: float) -> np.ndarray:
    """Which rows of ``velocities`` ``(k, 2)`` lie in the speed octagon."""
    return np.all(np.asarray(velocities, float) @ SPEED_NORMALS.T <= v_max * (1.0 + 1e-12), axis=1)


def limit_speed(velocity: np.ndarray, v_max: float) -> np.ndarray:
    """``velocity`` (2,) scaled down onto the speed octagon when it lies outside."""
    v = np.asarray(velocity, float)
    worst = float(np.max(SPEED_NORMALS @ v))
    return v * (v_max / worst) if worst > v_max else v.copy()


def spec_from_params(params: PlannerParams, bounds: tuple[float, float, float, float],
                     nodes: int | None = None, seed: int | None = None) -> GraphSpec:
    return GraphSpec(bounds=tuple(float(b) for b in bounds), nodes=int(params.nodes if nodes is None else nodes),
                     v_max=params.v_max, a_max=params.a_max, tau=params.segment_s, sampling=params.sampling,
                     seed=int(params.seed if seed is None else seed), grid_velocities=params.grid_velocities,
                     rest_grid=params.rest_grid)


@dataclass(frozen=True, eq=False)
class BezierGraph:
    """Directed graph of Bezier segments; edges sorted by source (CSR via ``indptr``)."""

    spec: GraphSpec
    nodes: np.ndarray  # (N, 4) [px, py, vx, vy]
    src: np.ndarray  # (E,) int64
    dst: np.ndarray  # (E,) int64
    indptr: np.ndarray  # (N + 1,) edges of node i are indptr[i]:indptr[i+1]
    control_points: np.ndarray  # (E, p + 1, 2) position control points [m]
    cost: np.ndarray  # (E,) path-length bound [m] (Property 2.49)
    reachability: reach.BezierReachability = field(repr=False)
    hulls: col.HullSet = field(repr=False)
    densified: int = 0  # nodes added after the build (onboard.high_level.planning.densify), appended after the spec's

    @property
    def n_nodes(self) -> int:
        return len(self.nodes)

    @property
    def n_edges(self) -> int:
        return len(self.src)

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Arrays that :meth:`from_arrays` restores (for an ``np.savez`` cache); refused for a
        densified graph, which is not its spec's graph and must not replace it in a cache."""
        if self.densified:
            raise PlanningError(f"a graph densified by {self.densified} nodes is not its spec's graph")
        return {"key": np.array(self.spec.key()), "nodes": self.nodes, "src": self.src, "dst": self.dst,
                "control_points": self.control_points, "cost": self.cost}

    @classmethod
    def from_arrays(cls, spec: GraphSpec, arrays: dict[str, np.ndarray]) -> BezierGraph:
        """Rebuild from :meth:`to_arrays`; raises :class:`PlanningError` if they are not ``spec``'s."""
        try:
            key = str(arrays["key"])
            nodes = np.asarray(arrays["nodes"], dtype=float)
            src = np.asarray(arrays["src"], dtype=np.int64)
            dst = np.asarray(arrays["dst"], dtype=np.int64)
            ctrl = np.asarray(arrays["control_points"], dtype=float)
            cost = np.asarray(arrays["cost"], dtype=float)
        except KeyError as exc:
            raise PlanningError(f"graph arrays lack {exc}") from None
        if key != spec.key():
            raise PlanningError("graph arrays belong to another spec")
        E = len(src)
        if (nodes.shape != (spec.total_nodes, 4) or dst.shape != (E,) or cost.shape != (E,) or ctrl.ndim != 3
                or ctrl.shape[0] != E or ctrl.shape[2] != DIM or (E and (src.min() < 0 or dst.max() >= spec.total_nodes))
                or np.any(np.diff(src) < 0)):
            raise PlanningError("graph arrays are inconsistent")
        return assemble(spec, nodes, src, dst, ctrl, cost, spec.reachability())


def assemble(spec: GraphSpec, nodes: np.ndarray, src: np.ndarray, dst: np.ndarray, ctrl: np.ndarray,
             cost: np.ndarray, test: reach.BezierReachability, densified: int = 0,
             hulls: col.HullSet | None = None) -> BezierGraph:
    """A graph from edges sorted by source (the CSR index and, unless the caller has them for
    ``ctrl``, the hulls computed here)."""
    indptr = np.zeros(len(nodes) + 1, dtype=np.int64)
    np.cumsum(np.bincount(src, minlength=len(nodes)), out=indptr[1:])
    return BezierGraph(spec, np.ascontiguousarray(nodes), np.ascontiguousarray(src), np.ascontiguousarray(dst),
                       indptr, np.ascontiguousarray(ctrl), np.ascontiguousarray(cost), test, col.hull_set(ctrl) if hulls is None else hulls,
                       densified)


def sample_nodes(spec: GraphSpec) -> np.ndarray:
    """Graph nodes ``(spec.total_nodes, 4)``: ``spec.nodes`` with positions in the region and
    velocities in the speed octagon (:func:`speed_limits`), then the rest lattice (if any).

    The lattice of resting nodes makes narrow passages passable: between two resting
    nodes the curve is the straight segment joining them (its hull is that segment), so
    a row of the lattice through a gap crosses it stop-and-go even where no random
    node pair lines up.
    """
    nodes = _sample(spec)
    if not spec.rest_grid:
        return nodes
    xmin, ymin, xmax, ymax = spec.bounds
    g = spec.rest_grid
    xs = xmin + g * np.arange(int((xmax - xmin) // g) + 1)
    ys = ymin + g * np.arange(int((ymax - ymin) // g) + 1)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    lattice = np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size), np.zeros(X.size)])
    return np.vstack([nodes, lattice])


def _sample(spec: GraphSpec) -> np.ndarray:
    xmin, ymin, xmax, ymax = spec.bounds
    v = spec.v_max
    if spec.sampling == "uniform":
        rng = np.random.default_rng(spec.seed)
        pos = rng.uniform([xmin, ymin], [xmax, ymax], size=(spec.nodes, 2))
        vel = np.empty((0, 2))
        while len(vel) < spec.nodes:  # uniform in the octagon: box draws, those outside dropped
            draw = rng.uniform(-v, v, size=(spec.nodes, 2))
            vel = np.vstack([vel, draw[within_speed_bound(draw, v)]])
        return np.column_stack([pos, vel[: spec.nodes]])
    nv = spec.grid_velocities
    per_cell = nv * nv
    positions = max(spec.nodes // per_cell, 1)
    aspect = (xmax - xmin) / (ymax - ymin)
    nx = max(int(round(math.sqrt(positions * aspect))), 1)
    ny = max(positions // nx, 1)
    xs = np.linspace(xmin, xmax, nx) if nx > 1 else np.array([(xmin + xmax) / 2])
    ys = np.linspace(ymin, ymax, ny) if ny > 1 else np.array([(ymin + ymax) / 2])
    vs = np.linspace(-v, v, nv) if nv > 1 else np.zeros(1)
    X, Y, VX, VY = np.meshgrid(xs, ys, vs, vs, indexing="ij")
    vel = np.column_stack([VX.ravel(), VY.ravel()])
    vel = np.array([limit_speed(row, v) for row in vel]) if len(vel) else vel  # the box's corners onto the octagon
    grid = np.column_stack([X.ravel(), Y.ravel(), vel])
    if len(grid) < spec.nodes:  # fill the remainder uniformly so the node count is exact
        rest = GraphSpec(spec.bounds, spec.nodes - len(grid), spec.v_max, spec.a_max, spec.tau, "uniform", spec.seed)
        grid = np.vstack([grid, _sample(rest)])
    return grid[: spec.nodes]


def reach_scale(test: reach.BezierReachability, a_max: float) -> np.ndarray:
    """Per-coordinate bound on ``|x_j - x_i|`` over every pair the test accepts ``(4,)``.

    Positions: an LP over the test (:meth:`BezierReachability.reach_radius`). Velocities:
    the acceleration bound holds along the whole curve, so ``|dv| <= a_max tau``.
    """
    pos = test.reach_radius()
    return np.array([pos[0], pos[1], a_max * test.tau, a_max * test.tau])


def candidate_pairs(nodes: np.ndarray, scale: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ordered pairs ``(i, j)``, ``i != j``, with ``|x_j - x_i| <= scale`` per coordinate (k-d tree)."""
    tree = cKDTree(nodes / scale)
    pairs = tree.query_pairs(1.0 + PRUNE_SLACK, p=np.inf, output_type="ndarray")
    i = np.concatenate([pairs[:, 0], pairs[:, 1]]).astype(np.int64)
    j = np.concatenate([pairs[:, 1], pairs[:, 0]]).astype(np.int64)
    return i, j


def build_graph(spec: GraphSpec) -> BezierGraph:
    """Sample nodes and connect every pair the reachability test accepts (see module docstring)."""
    test = spec.reachability()
    nodes = sample_nodes(spec)
    i, j = candidate_pairs(nodes, reach_scale(test, spec.a_max))
    ok = test.edge_table(nodes).test_pairs(i, j)
    i, j = i[ok], j[ok]
    order = np.lexsort((j, i))
    i, j = i[order], j[order]
    ctrl = test.curve(nodes[i], nodes[j])
    return assemble(spec, nodes, i, j, ctrl, bz.path_length_bound(ctrl), test)


# --- search --------------------------------------------------------------------------------


@nb.njit(cache=True)
def _astar(indptr, dst, cost, extra, free, pos, start_nodes, start_costs, goal_costs, goal_x, goal_y, h_slack):  # pragma: no cover
    """A* over graph nodes 0..N-1 plus a virtual start (its edges: start_nodes/start_costs)
    and a virtual goal (edge from node n of cost goal_costs[n]; inf: none). Every graph
    edge costs ``cost[e] + extra``.

    Returns (pred_node, pred_edge, goal_pred, total): pred_edge -1 marks a virtual start
    edge; goal_pred is the node before the goal (-1: none found).
    """
    N = pos.shape[0]
    dist = np.full(N, np.inf)
    pred = np.full(N, -2, dtype=np.int64)  # -2 unvisited, -1 reached from the start
    pred_edge = np.full(N, -1, dtype=np.int64)
    closed = np.zeros(N, dtype=np.bool_)
    heap = [(0.0, np.int64(0))]
    heap.pop()
    for k in range(start_nodes.shape[0]):
        n = start_nodes[k]
        if start_costs[k] < dist[n]:
            dist[n] = start_costs[k]
            pred[n] = -1
            h = max(math.hypot(pos[n, 0] - goal_x, pos[n, 1] - goal_y) - h_slack, 0.0)
            heapq.heappush(heap, (dist[n] + h, n))
    best_goal = np.inf
    goal_pred = -1
    while len(heap) > 0:
        f, n = heapq.heappop(heap)
        if closed[n]:
            continue
        if f >= best_goal:
            break
        closed[n] = True
        if dist[n] + goal_costs[n] < best_goal:
            best_goal = dist[n] + goal_costs[n]
            goal_pred = n
        for e in range(indptr[n], indptr[n + 1]):
            if not free[e]:
                continue
            m = dst[e]
            d = dist[n] + cost[e] + extra
            if d < dist[m]:
                dist[m] = d
                pred[m] = n
                pred_edge[m] = e
                h = max(math.hypot(pos[m, 0] - goal_x, pos[m, 1] - goal_y) - h_slack, 0.0)
                heapq.heappush(heap, (d + h, m))
    return pred, pred_edge, goal_pred, best_goal


@dataclass(frozen=True)
class SearchResult:
    """A path from the start to the goal: node states and the segments between them."""

    states: np.ndarray  # (K + 1, 4) the start, graph nodes, the goal
    control_points: np.ndarray  # (K, p + 1, 2) position control points of each segment [m]
    tau: float  # [s] duration of every segment
    cost: float  # [m] sum of path-length bounds
    nodes: np.ndarray  # (K + 1,) graph node index per state, -1 for the virtual start / goal

    @property
    def duration(self) -> float:
        return self.tau * len(self.control_points)


def search(graph: BezierGraph, free: np.ndarray, start_state: np.ndarray, start_nodes: np.ndarray,
           start_costs: np.ndarray, goal_state: np.ndarray, goal_costs: np.ndarray, goal_slack: float,
           start_edge_ctrl: dict[int, np.ndarray], goal_edge_ctrl: dict[int, np.ndarray],
           edge_extra: float = 0.0) -> SearchResult | None:
    """A* over ``graph`` with edge mask ``free`` between a virtual start and goal.

    ``start_nodes``/``start_costs``: nodes reachable from the start and at what cost
    (``start_edge_ctrl[n]`` the segment, absent for nodes that contain the start: no
    segment). ``goal_costs[n]``: cost of ending at the goal from node ``n`` (``inf``:
    not allowed; ``goal_edge_ctrl[n]`` the segment, absent when ``n`` is itself at the
    goal). ``goal_slack`` [m] keeps the heuristic admissible for such nodes. Graph edges
    cost their path-length bound plus ``edge_extra`` (the virtual edges' costs include it).
    The virtual start-to-goal segment is node index ``N`` in both tables.
    """
    N = graph.n_nodes
    pos = graph.nodes[:, :2]
    direct = start_edge_ctrl.get(N)
    sn = np.ascontiguousarray(start_nodes[start_nodes < N], dtype=np.int64)
    sc = np.ascontiguousarray(start_costs[start_nodes < N], dtype=float)
    pred, pred_edge, goal_pred, total = _astar(graph.indptr, graph.dst, graph.cost, float(edge_extra), free, pos, sn, sc,
                                               np.ascontiguousarray(goal_costs[:N]), float(goal_state[0]),
                                               float(goal_state[1]), float(goal_slack))
    direct_cost = float(start_costs[start_nodes == N][0]) if direct is not None else math.inf
    if direct is not None and direct_cost <= total:
        return SearchResult(np.stack([start_state, goal_state]), direct[None], graph.spec.tau, direct_cost,
                            np.array([-1, -1]))
    if goal_pred < 0 or not math.isfinite(total):
        return None
    chain = [int(goal_pred)]
    while pred[chain[-1]] >= 0:
        chain.append(int(pred[chain[-1]]))
    chain.reverse()
    states = [start_state]
    ctrl = []
    first = chain[0]
    if first in start_edge_ctrl:
        ctrl.append(start_edge_ctrl[first])
        states.append(graph.nodes[first])
    else:  # the first node contains the start: the path begins there
        states = [graph.nodes[first]]
    for n in chain[1:]:
        ctrl.append(graph.control_points[pred_edge[n]])
        states.append(graph.nodes[n])
    node_ids = ([-1] if first in start_edge_ctrl else []) + chain
    if goal_pred in goal_edge_ctrl:
        ctrl.append(goal_edge_ctrl[goal_pred])
        states.append(goal_state)
        node_ids.append(-1)
    if not ctrl:  # already at a goal node: a zero-length stay
        ctrl.append(np.repeat(graph.nodes[first][None, :2], graph.reachability.p + 1, axis=0))
        states.append(graph.nodes[first])
        node_ids.append(first)
    return SearchResult(np.array(states), np.array(ctrl), graph.spec.tau, float(total), np.array(node_ids))


# --- path sampling ---------------------------------------------------------------------


def path_states(ctrl: np.ndarray, tau: float, times: np.ndarray) -> np.ndarray:
    """States ``[px, py, vx, vy]`` ``(len(times), 4)`` of a chain of segments at ``times`` [s].

    Times before 0 read the start; times after the end read the last point at rest
    (the path ends at rest at the goal).
    """
    times = np.asarray(times, dtype=float)
    K = len(ctrl)
    end = K * tau
    t = np.clip(times, 0.0, end)
    seg = np.minimum((t / tau).astype(np.int64), K - 1)
    local = t - seg * tau
    s = local / tau
    Z = bz.bernstein(ctrl.shape[1] - 1, s)  # (T, p + 1)
    pos = np.einsum("tj,tjm->tm", Z, ctrl[seg])
    vel_pts = bz.derivative_points(ctrl, tau, 1)  # (K, p + 1, 2)
    vel = np.einsum("tj,tjm->tm", Z, vel_pts[seg])
    vel[times >= end] = 0.0
    return np.column_stack([pos, vel])


def chain_tail(ctrl: np.ndarray, tau: float, t_from: float) -> list[tuple[float, np.ndarray]]:
    """Segments of a chain from time ``t_from`` on, as ``(duration, control points)``."""
    K = len(ctrl)
    if t_from >= K * tau:
        return []
    k = int(t_from // tau)
    a = (t_from - k * tau) / tau
    out: list[tuple[float, np.ndarray]] = []
    if a > 1e-9:
        Q = bz.split_matrix(ctrl.shape[1] - 1, float(a), 1.0)
        out.append(((1.0 - a) * tau, Q.T @ ctrl[k]))
        k += 1
    out.extend((tau, ctrl[i]) for i in range(k, K))
    return out
