"""Exploration toward a goal beyond the known free cells (free mode: thesis 7.2, lines 3182-3216,
and the perceived world of 8.2, lines 3328-3339).

Mixed into :class:`~onboard.high_level.planning.graph_planner.GraphPlanner`: when the search
finds no path to the goal inside the free cells fitted so far, a path to the frontier of what
the camera has seen (:meth:`onboard.high_level.planning.seen_space.SeenSpace.frontier`), ending
at rest at the graph node whose cost (its distance to the goal, plus how far it falls short of
the frontier when only approaching one is possible) is least, with hysteresis toward the
frontier already headed for. Reads the planner's ``params``, ``graph``, ``free``, ``goal``,
``seen``, ``margin`` and ``stats``.
"""

from __future__ import annotations

import math

import numpy as np

from onboard.high_level.planning.bezier_graph import SearchResult, search


class FrontierSearch:
    """The frontier costs and the frontier search of :class:`GraphPlanner` (a mixin)."""

    def _init_frontier(self) -> None:
        self.frontier_goal: np.ndarray | None = None  # free mode: where the current path ends short of the goal
        self._frontier_target: np.ndarray | None = None  # the last frontier a path was found to (kept while none reaches the goal)

    def frontier_costs(self, position: np.ndarray, approach: bool = False) -> np.ndarray:
        """Per graph node, the cost of ending a path there toward a goal beyond the known free
        cells: ``frontier_weight`` times its distance to the goal for nodes at rest near a
        frontier cell (:meth:`SeenSpace.frontier`: connected to ``position`` through free cells,
        beside unknown ground as wide as the robot) at least ``frontier_min`` from ``position``:
        within the margin plus ``frontier_reach`` over free ground (4-connected cells: up to
        sqrt(2) times the straight line, so the reach is allowed as much; a node beside a wall
        with the frontier behind it is not near it). With ``approach``, every node at rest
        connected to such a cell, plus ``frontier_approach_weight`` per metre it falls short of
        that reach. Inf elsewhere, and everywhere without a seen space."""
        assert self.graph is not None and self.goal is not None
        prm = self.params
        nodes = self.graph.nodes
        costs = np.full(len(nodes), np.inf)
        if self.seen is None:
            return costs
        here = np.asarray(position, dtype=float)[:2]
        pts = self.seen.frontier(2 * self.robot_radius, here)
        pts = pts[np.hypot(*(pts - here).T) >= prm.frontier_min]
        if len(pts) == 0:
            return costs
        rest = np.flatnonzero(np.all(np.abs(nodes[:, 2:]) <= prm.goal_speed_tol, axis=1))
        d = self.seen.distance_through_free(pts, nodes[rest, :2])
        short = np.maximum(d - math.sqrt(2.0) * (self.margin + prm.frontier_reach), 0.0)
        ok = np.isfinite(short) if approach else short == 0.0
        costs[rest[ok]] = (prm.frontier_weight * np.hypot(*(nodes[rest[ok], :2] - self.goal).T)
                           + prm.frontier_approach_weight * short[ok])
        return costs

    def _search_frontier(self, x0: np.ndarray, start_nodes: np.ndarray, start_costs: np.ndarray,
                         start_edge_ctrl: dict[int, np.ndarray], goal_state: np.ndarray, extra: float,
                         approach: bool = False) -> SearchResult | None:
        """Free mode, no path to the goal in the known cells: the path to the frontier node of
        least path cost plus :meth:`frontier_costs` (the goal's straight line keeps the search's
        heuristic admissible, every frontier cost being at least it). With ``approach``, when the
        cells reach no frontier (a wall's gap whose cells overlap too thinly for the margin), the
        path as near one as they let the robot go, where the cells fitted around it may join up."""
        assert self.graph is not None and self.free is not None and self.goal is not None
        prm = self.params
        if len(start_nodes) == 0:
            return None
        for near in (False, True) if approach else (False,):
            costs = self.frontier_costs(x0[:2], near)
            if not np.isfinite(costs).any():
                continue
            if self._frontier_target is not None:  # hysteresis: the frontier already headed for keeps an advantage
                nodes = self.graph.nodes[:, :2]
                kept = np.isfinite(costs) & (np.hypot(*(nodes - self._frontier_target).T) <= max(prm.rest_grid, 1e-9))
                # never below the straight line to the goal: the search's heuristic stays admissible
                costs[kept] = np.maximum(costs[kept] - prm.frontier_hysteresis, np.hypot(*(nodes[kept] - self.goal).T))
            result = search(self.graph, self.free, x0, start_nodes, start_costs, goal_state, costs, 0.0,
                            start_edge_ctrl, {}, extra)
            if result is not None:
                self.frontier_goal = result.states[-1, :2].copy()
                self._frontier_target = self.frontier_goal
                self.stats.frontier_plans += 1
                return result
        return None
