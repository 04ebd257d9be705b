"""Kinodynamic Bezier graph planner: build, cut, search, refine (thesis ch. 7, lines 3067-3220).

Planning model: the CoM double integrator in the horizontal plane, state
``x = [px, py, vx, vy]`` (world frame, metres and m/s), input the CoM acceleration,
bounded (speed: ``PlannerParams.v_max``, an octagon; acceleration: ``a_max`` per axis).

Pipeline (Algorithm 3):

1. **Build** (:func:`onboard.high_level.planning.bezier_graph.build_graph`): ``N`` nodes over position and velocity (uniform
   random or grid), plus a lattice of nodes at rest (``rest_grid``: between two resting
   nodes the curve is a straight segment, so narrow gaps are passable stop-and-go);
   candidate pairs come from a k-d tree over positions and velocities
   scaled by the largest change one segment can make (an LP over the reachability
   test, so the pruning drops no edge the test would accept); a pair is an edge iff
   the Bezier reachability test ``F [x_i; x_j] <= G`` of :mod:`onboard.high_level.tracking.reachability`
   holds (Theorem 6.2). Each edge carries its position control points and its cost,
   the path-length bound of Property 2.49. The graph depends only on
   :class:`~onboard.high_level.planning.bezier_graph.GraphSpec`; :meth:`GraphSpec.key` names it for an on-disk cache, and
   :meth:`BezierGraph.to_arrays` / :meth:`BezierGraph.from_arrays` convert it for the
   caller, who does the file I/O.
2. **Cut** (:mod:`onboard.high_level.planning.planner_world`, with the tests of
   :mod:`onboard.high_level.tracking.collision`): edges whose control-point hull comes within
   ``robot_radius + tube`` of a convex obstacle are removed (exact separating-axis
   test), or, with free cells, edges not inside one cell. Edges leaving the planning
   region are removed too.
3. **Search** (:func:`onboard.high_level.planning.bezier_graph.search`): A* (admissible straight-line heuristic) over the
   path-length bound plus ``time_weight`` times each segment's duration (0 is the
   thesis's cost; a little of it stops the search from preferring slow, short paths) from the
   current state to the goal at rest. The start is the state itself, joined to the
   graph by the same reachability test and cut (when it cannot be, the nodes that
   contain the state in its tube, Problem 7.1); the goal, at rest, is joined the same
   way (paths end exactly there; only when it cannot be joined do graph nodes at rest
   within the goal tolerance end a path).
4. **Refine** (:meth:`GraphPlanner.refine`, :mod:`onboard.high_level.planning.refinement`): the MPC of eq. 7.2 from
   :mod:`onboard.high_level.tracking.bezier_mpc`, warm-started with the graph path, each segment kept on
   the free side of separating halfspaces to its nearest obstacles; one SQP
   iteration per call.

In-process use (the lockstep runner, the ``planner`` service and ``archer plan`` all
use it this way)::

    planner = GraphPlanner(PlannerParams(), robot_radius=0.13)
    planner.set_obstacles([poly, ...])          # convex polygons (k, 2) [m]; or set_free_cells
    planner.set_goal((x, y), tolerance=0.1)
    if planner.needs_replan(position, now_ns, params.replan_deviation):  # world/goal/tube changed, or off the path
        ref = planner.plan(position, velocity, now_ns)  # ComReference, or None: no path
    ref = planner.refine(position, velocity, now_ns)    # refined ComReference (100-200 Hz)
    hold = planner.hold_reference(position, now_ns)     # hop in place when there is no path
    wps = planner.waypoints(now_ns)                     # graph path and its convex sets
    report = planner.check_tube(tracking_tube, now_ns)  # ContractReport on a broken promise (tube grows)
    planner.drain_contract_reports()                    # the reports since the last call

Positions and velocities are the CoM's ``[x, y]`` in the world frame [m, m/s]; times
are nanoseconds on the caller's clock. Without fixed ``bounds`` the planning region
follows start, goal and obstacles. ``plan`` builds the graph itself when none fits the
region; a caller with a cache supplies it first with :meth:`GraphPlanner.graph_spec_for`
and :meth:`GraphPlanner.set_graph`. Everything here is pure: no clock, no I/O, no threads.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from scipy.spatial import cKDTree

from onboard.geometry import bezier as bz
from onboard.high_level.tracking import collision as col
from onboard.high_level.planning import densify as dn
from onboard.contracts import messages as msgs
from onboard.high_level.planning.bezier_graph import (
    DIM,
    PRUNE_SLACK,
    SPEED_NORMALS,
    BezierGraph,
    GraphSpec,
    PlanningError,
    SearchResult,
    build_graph,
    limit_speed,
    path_states,
    reach_scale,
    search,
    spec_from_params,
)
from onboard.contracts.params import PlannerParams
from onboard.high_level.planning.refinement import MpcRefinement
from onboard.high_level.planning.frontier import FrontierSearch
from onboard.high_level.planning.planner_status import PlannerStats, TubeContract
from onboard.high_level.planning.planner_world import PlannerWorld

MIN_AUTO_NODES = 500  # an automatic region never gets fewer nodes
_SPEED_ROWS = tuple((float(nx), float(ny)) for nx, ny in SPEED_NORMALS)  # the speed octagon's normals, as floats


# --- the planner -----------------------------------------------------------------------


class GraphPlanner(PlannerWorld, FrontierSearch, TubeContract, MpcRefinement):
    """The high-level planner of thesis ch. 7 as a pure object (see the module docstring).

    ``robot_radius`` [m] and the tube (``PlannerParams.tube``, changed by
    :meth:`set_tube`) inflate every obstacle: ``margin = robot_radius + tube``. Here: the goal,
    the graph, the search and the replan test; mixed in: the world and its cut
    (:class:`~onboard.high_level.planning.planner_world.PlannerWorld`), the frontier search
    (:class:`~onboard.high_level.planning.frontier.FrontierSearch`), the tube contract
    (:class:`~onboard.high_level.planning.planner_status.TubeContract`) and the references handed
    down (:class:`~onboard.high_level.planning.refinement.MpcRefinement`).
    """

    def __init__(self, params: PlannerParams, robot_radius: float, bounds: tuple[float, float, float, float] | None = None,
                 nodes: int | None = None, mpc_time_limit_s: float = 0.0) -> None:
        if not (math.isfinite(robot_radius) and robot_radius >= 0):
            raise PlanningError(f"robot radius must be finite and >= 0, got {robot_radius}")
        self.params = params
        self.robot_radius = float(robot_radius)
        self._init_world(params.tube)
        self.fixed_bounds = None if bounds is None else tuple(float(b) for b in bounds)
        self.fixed_nodes = nodes
        # [s] each MPC solve's bound (OSQP's own limit), set by a real-time caller; 0 (lockstep): none,
        # so that a run's answers do not depend on the machine's speed
        self.mpc_time_limit_s = float(mpc_time_limit_s)
        self.stats = PlannerStats()
        self.graph: BezierGraph | None = None
        self._tree: cKDTree | None = None
        self._scale: np.ndarray | None = None
        self._densifier: dn.Densifier | None = None  # what densification added to the current graph
        self.last_densify: dn.DensifyReport | None = None  # the last plan's densification (None: it needed none)
        self._unreachable: tuple | None = None  # (world version, goal, graph) densified to the finest level in vain
        self.goal: np.ndarray | None = None
        self.goal_tolerance = 0.0
        self.path: SearchResult | None = None
        self.path_t0_ns = 0  # clock time of the path's start
        self.path_world_version = -1
        self._mpc = None
        self._mpc_tube = -1.0
        self._last_solution = None
        self._last_refined: tuple | None = None  # (knot, world version, path, first knot, reference)
        self._arrived: tuple | None = None  # (path, its reference) once the robot rests at its end
        self._failed_refine: tuple | None = None  # (knot, world version, path) of the last failed refinement
        self._init_contract()
        self._init_frontier()

    # --- inputs ----------------------------------------------------------------------

    def set_goal(self, position: tuple[float, float] | np.ndarray, tolerance: float = 0.1) -> None:
        """Goal position [m] (world), reached at rest within ``tolerance`` [m]."""
        g = np.asarray(position, dtype=float).reshape(-1)
        if g.shape != (2,) or not np.all(np.isfinite(g)) or not (math.isfinite(tolerance) and tolerance >= 0):
            raise PlanningError("goal must be a finite [x, y] with a finite tolerance >= 0")
        changed = self.goal is None or not np.array_equal(g, self.goal) or tolerance != self.goal_tolerance
        self.goal = g
        self.goal_tolerance = float(tolerance)
        if changed:
            self.path = None
            self._frontier_target = None  # a new goal: explore toward it afresh

    def goal_refusal(self, position: tuple[float, float] | np.ndarray, start: np.ndarray) -> str | None:
        """Why a goal at ``position`` cannot be taken from a start at ``start`` (None when it can):
        outside the fixed bounds, or so far that no graph covering start and goal can be built.
        Checked when a goal arrives, so that a goal the planner cannot take is refused once
        instead of failing every plan."""
        g = np.asarray(position, dtype=float).reshape(-1)
        if g.shape != (2,) or not np.all(np.isfinite(g)):
            return "goal must be a finite [x, y]"
        if self.fixed_bounds is not None:
            x0, y0, x1, y1 = self.fixed_bounds
            if not (x0 <= g[0] <= x1 and y0 <= g[1] <= y1):
                return f"goal {g.tolist()} lies outside the planning bounds {list(self.fixed_bounds)}"
            return None
        try:
            self.graph_spec_for(np.asarray(start, float)[:2], g)
        except PlanningError as exc:
            return f"goal {g.tolist()} is beyond any graph the planner can build from {np.asarray(start, float)[:2].tolist()}: {exc}"
        return None

    # --- graph -------------------------------------------------------------------------

    def region_for(self, position: np.ndarray, goal: np.ndarray | None = None) -> tuple[float, float, float, float]:
        """Planning region: the fixed bounds, or start, goal (``goal``, else the one set) and obstacles (or cells) padded by
        ``bounds_padding`` plus twice the margin (room to pass an obstacle at the edge; the
        margin of a tube of at least ``region_tube``, so that a tube growing up to it needs
        no new graph), snapped outward to ``bounds_quantum``."""
        if self.fixed_bounds is not None:
            return self.fixed_bounds
        pts = [np.asarray(position, float)[:2]]
        goal = self.goal if goal is None else goal
        if goal is not None:
            pts.append(goal)
        polys = self.obstacles if self.mode == "obstacles" else self.cells
        if len(polys):
            pts.extend([polys.aabb[:, :2].min(axis=0), polys.aabb[:, 2:].max(axis=0)])
        pts_arr = np.array(pts)
        q = self.params.bounds_quantum
        pad = self.params.bounds_padding + 2 * (self.robot_radius + max(self.tube, self.params.region_tube))
        lo = np.floor((pts_arr.min(axis=0) - pad) / q) * q
        hi = np.ceil((pts_arr.max(axis=0) + pad) / q) * q
        return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])

    def graph_spec_for(self, position: np.ndarray, goal: np.ndarray | None = None) -> GraphSpec:
        """The spec of the graph :meth:`plan` needs for a start at ``position`` (and ``goal``, else the one set).

        An automatic region keeps the current graph while it covers the region needed
        (no rebuild when obstacles move inside it); its node count is ``node_density``
        times its area, at most ``nodes``.
        """
        bounds = self.region_for(position, goal)
        if self.fixed_bounds is not None:
            return spec_from_params(self.params, bounds, nodes=self.fixed_nodes)
        if self.graph is not None and _covers(self.graph.spec.bounds, bounds):
            return self.graph.spec
        area = (bounds[2] - bounds[0]) * (bounds[3] - bounds[1])
        nodes = int(min(self.params.nodes, max(MIN_AUTO_NODES, round(self.params.node_density * area))))
        return spec_from_params(self.params, bounds, nodes=nodes)

    def set_graph(self, graph: BezierGraph) -> None:
        self.graph = graph
        test = graph.reachability
        self._scale = reach_scale(test, graph.spec.a_max)
        self._tree = cKDTree(graph.nodes / self._scale)
        self._cut_key = None
        self._densifier = None
        self.path = None

    def _install_densified(self, graph: BezierGraph, free: np.ndarray) -> None:
        """Plan on ``graph``, a densified copy of the current one, with its cut ``free``."""
        assert self._scale is not None
        self.graph = graph
        self._tree = cKDTree(graph.nodes / self._scale)
        self.free = free
        self._cut_key = (id(graph), self._world_version)
        self.stats.edges_free = int(free.sum())

    def _ensure_graph(self, position: np.ndarray) -> None:
        spec = self.graph_spec_for(position)
        if self.graph is None or self.graph.spec != spec:
            self.set_graph(build_graph(spec))
            self.stats.graph_builds += 1

    # --- plan ----------------------------------------------------------------------------

    def _state(self, position: np.ndarray, velocity: np.ndarray) -> np.ndarray:
        """``[px, py, vx, vy]`` from the first two entries of each (in plain floats: this runs at the
        refinement rate, where a dozen small numpy calls cost more than the rest of a kept answer)."""
        try:
            px, py, vx, vy = float(position[0]), float(position[1]), float(velocity[0]), float(velocity[1])
        except (IndexError, KeyError, TypeError, ValueError):
            raise PlanningError("state must be finite position and velocity with at least x and y") from None
        if not (math.isfinite(px) and math.isfinite(py) and math.isfinite(vx) and math.isfinite(vy)):
            raise PlanningError("state must be finite position and velocity with at least x and y")
        # The planning model cannot start faster than its bound; the tube absorbs the rest. Near the
        # bound limit_speed decides, so the state is the same to the bit as when it always did.
        v_max = self.params.v_max
        if max(nx * vx + ny * vy for nx, ny in _SPEED_ROWS) > v_max * (1.0 - 1e-9):
            vx, vy = limit_speed(np.array([vx, vy]), v_max).tolist()
        return np.array([px, py, vx, vy])

    def _connect(self, x: np.ndarray, outgoing: bool, margin: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Nodes joined to the virtual state ``x`` by a free segment: (nodes, costs, control points)."""
        assert self.graph is not None and self._tree is not None
        near = np.array(self._tree.query_ball_point(x / self._scale, 1.0 + PRUNE_SLACK, p=np.inf), dtype=np.int64)
        if len(near) == 0:
            return near, np.zeros(0), np.zeros((0, self.graph.reachability.p + 1, DIM))
        test = self.graph.reachability
        others = self.graph.nodes[near]
        xs = np.broadcast_to(x, others.shape)
        ok = test.test(xs, others) if outgoing else test.test(others, xs)
        near, others = near[ok], others[ok]
        ctrl = test.curve(xs[: len(near)], others) if outgoing else test.curve(others, xs[: len(near)])
        if len(near):
            blocked, _ = self._blocked(col.hull_set(ctrl), margin)
            near, ctrl = near[~blocked], ctrl[~blocked]
        return near, bz.path_length_bound(ctrl), ctrl

    def plan(self, position: np.ndarray, velocity: np.ndarray, stamp_ns: int = 0,
             build: bool = True, clock: Callable[[], float] | None = None) -> msgs.ComReference | None:
        """Cut (if needed) and search from the state at ``stamp_ns``; None when there is no path.

        ``build=False`` plans on the current graph even when another would fit the region
        better (a caller building that one meanwhile); it needs a graph. The result is also
        kept in :attr:`path` for :meth:`refine` and :meth:`waypoints`.

        When the search finds no path, the graph is densified where it failed
        (:mod:`onboard.high_level.planning.densify`) for at most ``densify_budget_s`` on ``clock`` (seconds, the
        caller's; without one, until a path, the finest resolution or the node limit);
        :attr:`last_densify` says what that did and why there is still no path.
        """
        if self.goal is None:
            raise PlanningError("no goal set")
        x0 = self._stitched(self._state(position, velocity), stamp_ns)
        if build or self.graph is None:
            self._ensure_graph(x0[:2])
        if self.mode == "obstacles" and self._moving is not None:  # moving obstacles: the full windows, from here
            self._set_sweep_level(0)  # (before the cut: a cut from where the robot was is one thrown away)
            self._set_band_origin(x0[:2])
        self.cut()
        self.stats.plans += 1
        # free mode: with no frontier within reach, going nearer one comes before densifying (each
        # replan, at the perception rate, has new cells fitted around the robot; densifying every
        # time was most of a maze run's time)
        approach = self.mode == "free" and self.params.frontier_approach_weight > 0
        result, start_seeds, goal_seeds = self._search(x0, approach)
        while result is None and self.mode == "obstacles" and self._set_sweep_level(self._sweep_level + 1):
            self.cut()  # no way past the sweeps: shorter ones, down to where the obstacles are now
            self.stats.sweep_relaxed += 1
            result, start_seeds, goal_seeds = self._search(x0, approach)
        if result is not None or self.params.densify_budget_s <= 0:
            self.last_densify = None
        elif not self._settled():
            result = self._densify(x0, start_seeds, goal_seeds, clock)
        self.path = result
        self.path_t0_ns = int(stamp_ns)
        self.path_world_version = self._world_version
        self._last_solution = None
        if result is None:
            self.stats.no_path += 1
            return self.evade_reference(x0, stamp_ns) if self._moving is not None else None
        return self.committed(self.path_reference(stamp_ns), x0[:2], stamp_ns)

    def _path_state(self, stamp_ns: int) -> np.ndarray:
        """``[px, py, vx, vy]`` where the current path puts the robot at ``stamp_ns``."""
        assert self.path is not None
        t = (stamp_ns - self.path_t0_ns) * 1e-9
        return path_states(self.path.control_points, self.path.tau, np.array([t]))[0]

    def _stitched(self, x: np.ndarray, stamp_ns: int) -> np.ndarray:
        """Where a replan starts: the current path's state at ``stamp_ns`` while the robot keeps within
        the tube of it, else the measured state ``x``. A hopper lags its reference by centimetres;
        started from the measured state at every replan, each new reference began where the robot
        was, at the speed it had, and the lead that drives it forward was thrown away (sidewalk seed
        1000, onboard sensing, replanning at every view: 2.3 m in 40 s from the robot's state, 4.4 m
        from the path's). Not in free
        mode: its cells are fitted anew around where the robot is, not where its path is (free-mode
        forest seed 2 stopped 0.6 m short with the stitch, and reaches its goal without it). Nor among
        obstacles that move: a replan there dodges one, from where the robot is (sliding seeds
        1000-1009, 1011, 1012: 4 runs hit by a slider with the stitch, 2 at 1e82379 without it)."""
        if self.path is None or self.tube <= 0.0 or self.mode == "free" or self._world_moves or stamp_ns < self.path_t0_ns:
            return x
        on_path = self._path_state(stamp_ns)
        if math.hypot(x[0] - on_path[0], x[1] - on_path[1]) > self.tube:
            return x
        return self._state(on_path[:2], on_path[2:])

    def _search(self, x0: np.ndarray, approach: bool = False) -> tuple[SearchResult | None, np.ndarray, np.ndarray]:
        """Search the cut graph from state ``x0`` to the goal at rest (free mode: else to a frontier,
        failing that with ``approach`` as near one as the cells allow): the path (None: none) and
        the graph nodes joined to the start and to the goal."""
        graph = self.graph
        assert graph is not None and self.goal is not None and self.free is not None
        N = graph.n_nodes
        goal_state = np.array([self.goal[0], self.goal[1], 0.0, 0.0])
        # Start: the state itself joined by free segments (the reference starts where the
        # robot is); only when none is free, the nodes containing it in the tube (Problem 7.1).
        # Search cost: path-length bound (Property 2.49) plus time_weight per segment (its duration).
        extra = self.params.time_weight * graph.spec.tau
        start_margin = self.start_margin(x0)
        s_nodes, s_costs, s_ctrl = self._connect(x0, outgoing=True, margin=start_margin)
        s_costs = s_costs + extra
        contains = np.zeros(0, dtype=np.int64)
        if len(s_nodes) == 0:
            contains = np.flatnonzero(
                (np.hypot(*(graph.nodes[:, :2] - x0[:2]).T) <= self.tube)
                & np.all(np.abs(graph.nodes[:, 2:] - x0[2:]) <= self.params.start_speed_tol, axis=1))
        start_edge_ctrl = {int(n): c for n, c in zip(s_nodes, s_ctrl)}
        start_nodes = [s_nodes, contains]
        start_costs = [s_costs, np.zeros(len(contains))]
        for n in contains:
            start_edge_ctrl.pop(int(n), None)  # containing the start beats joining it
        direct_ok = graph.reachability.test(x0, goal_state)
        if direct_ok:
            direct = graph.reachability.curve(x0, goal_state)
            if not self._blocked(col.hull_set(direct[None]), start_margin)[0][0]:
                start_edge_ctrl[N] = direct
                start_nodes.append(np.array([N]))
                start_costs.append(np.array([bz.path_length_bound(direct) + extra]))
        # Goal: nodes joined to the goal at rest (the path ends exactly there); only when
        # none is, nodes at rest within the tolerance end a path.
        g_nodes, g_costs, g_ctrl = self._connect(goal_state, outgoing=False)
        goal_costs = np.full(N, np.inf)
        goal_costs[g_nodes] = g_costs + extra
        goal_edge_ctrl = {int(n): c for n, c in zip(g_nodes, g_ctrl)}
        at_goal = np.zeros(0, dtype=np.int64)
        if len(g_nodes) == 0 and N not in start_edge_ctrl:
            at_goal = np.flatnonzero(
                (np.hypot(*(graph.nodes[:, :2] - self.goal).T) <= self.goal_tolerance)
                & np.all(np.abs(graph.nodes[:, 2:]) <= self.params.goal_speed_tol, axis=1))
            goal_costs[at_goal] = 0.0
        all_starts = np.concatenate(start_nodes).astype(np.int64)
        all_start_costs = np.concatenate(start_costs)
        result = None
        if len(g_nodes) or len(at_goal) or N in start_edge_ctrl:  # else nothing to search to
            result = search(graph, self.free, x0, all_starts, all_start_costs, goal_state, goal_costs,
                            self.goal_tolerance if len(at_goal) else 0.0, start_edge_ctrl, goal_edge_ctrl, extra)
        self.frontier_goal = None
        if result is not None:
            self._frontier_target = None
        elif self.mode == "free":
            via_graph = all_starts < N  # the direct segment to the goal is not free, or there would be a path
            result = self._search_frontier(x0, all_starts[via_graph], all_start_costs[via_graph],
                                           {n: c for n, c in start_edge_ctrl.items() if n < N}, goal_state, extra,
                                           approach)
        return result, np.concatenate(start_nodes[:2]).astype(np.int64), np.concatenate([g_nodes, at_goal]).astype(np.int64)

    def _settled(self) -> bool:
        """The same world, goal and graph were densified to the finest level in vain: that answer
        (:attr:`last_densify`) stands, and replans at ``replan_hz`` do not spend the budget on it again."""
        u = self._unreachable
        return u is not None and u[0] == self._world_version and u[1] == tuple(self.goal) and u[2] is self.graph

    def _densify(self, x0: np.ndarray, start_seeds: np.ndarray, goal_seeds: np.ndarray,
                 clock: Callable[[], float] | None) -> SearchResult | None:
        """Densify the graph where the search failed (:mod:`onboard.high_level.planning.densify`); the path found, or None."""
        assert self.graph is not None and self.goal is not None
        prm = self.params
        if self._densifier is None:
            first = prm.rest_grid / 2 if self.graph.spec.rest_grid else prm.densify_grid
            limits = dn.DensifyLimits(prm.densify_budget_s, first, min(prm.densify_min_grid, first),
                                      prm.densify_max_nodes, prm.densify_max_edges, prm.densify_round_nodes,
                                      prm.densify_max_rounds)
            self._densifier = dn.Densifier(self.graph, limits)
        view = _PlanView(self, x0, start_seeds, goal_seeds)
        report = self._densifier.run(view, x0[:2], self.goal, self.obstacles if self.mode == "obstacles" else None,
                                     self.margin, self._world_version, clock)
        self.last_densify = report
        self._unreachable = (self._world_version, tuple(self.goal), self.graph) if report.reason == dn.UNREACHABLE else None
        self.stats.densify_plans += 1
        self.stats.densify_rounds += report.rounds
        self.stats.densify_nodes += report.nodes_added
        return view.result

    def needs_replan(self, position: np.ndarray, stamp_ns: int, deviation: float) -> bool:
        """True when there is no path, the world changed since it was planned and the rest of the
        path to the goal is no longer clear of it (free mode, or a path to a frontier: whenever the
        world changed), or the state is more than ``deviation`` [m] from where the path says it
        should be."""
        if self.path is None:
            return True
        if self.path_world_version != self._world_version:
            # Obstacles that move, or that perception refits from every view, change the world at its
            # rate; a path to the goal still clear of them (swept) is kept. Replanned at every view, a
            # hopper's reference restarted each time and it crept (sidewalk seed 1000: 5.5 m in 100 s).
            if not (self.mode == "obstacles" and self.frontier_goal is None and self._path_clear(position, stamp_ns)):
                return True
            self.path_world_version = self._world_version
        expected = self._path_state(stamp_ns)[:2]
        return float(np.hypot(*(np.asarray(position, float)[:2] - expected))) > deviation

    def _path_clear(self, position: np.ndarray, stamp_ns: int) -> bool:
        """Whether what is left of the path (from the segment under way) keeps its clearance from the
        obstacles now (swept in full; the segment under way at least what the robot has now)."""
        assert self.path is not None
        if self._moving is not None:
            self._set_sweep_level(0)
            self._set_band_origin(position)
        ctrl = self.path.control_points
        k0 = min(max(int((stamp_ns - self.path_t0_ns) * 1e-9 / self.path.tau), 0), len(ctrl) - 1)
        margin = min(self.margin, self.start_margin(position))
        return not bool(np.any(self._blocked(col.hull_set(ctrl[k0:]), margin)[0]))


class _PlanView(dn.SearchView):
    """The planner as :class:`onboard.high_level.planning.densify.Densifier` sees it during one plan call from ``x0``."""

    def __init__(self, planner: GraphPlanner, x0: np.ndarray, start_seeds: np.ndarray, goal_seeds: np.ndarray) -> None:
        self.planner = planner
        self.x0 = x0
        self.start_seeds = start_seeds
        self.goal_seeds = goal_seeds
        self.result: SearchResult | None = None

    @property
    def graph(self) -> BezierGraph:  # type: ignore[override]
        assert self.planner.graph is not None
        return self.planner.graph

    @property
    def free(self) -> np.ndarray:  # type: ignore[override]
        assert self.planner.free is not None
        return self.planner.free

    def search(self) -> bool:
        self.result, self.start_seeds, self.goal_seeds = self.planner._search(self.x0)
        return self.result is not None

    def points_free(self, points: np.ndarray) -> np.ndarray:
        return ~self.planner._blocked(col.hull_set(np.repeat(points[:, None, :], 2, axis=1)))[0]

    def edges_free(self, control_points: np.ndarray) -> np.ndarray:
        return ~self.planner._blocked(col.hull_set(control_points))[0]

    def install(self, graph: BezierGraph, free: np.ndarray) -> None:
        self.planner._install_densified(graph, free)


def _covers(outer: tuple[float, float, float, float], inner: tuple[float, float, float, float]) -> bool:
    return outer[0] <= inner[0] and outer[1] <= inner[1] and outer[2] >= inner[2] and outer[3] >= inner[3]
