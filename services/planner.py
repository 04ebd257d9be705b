"""The ``planner`` service: Bezier graph planning and MPC refinement (thesis ch. 6-7).

Subscribes (latest value): ``state`` (StateEstimate), ``goal`` (Goal), ``polytopes``
(PolytopeSet: convex obstacles or free cells), ``grid`` (the occupancy grid: with perceived
obstacles the robot is committed only over ground it saw free, ``onboard.high_level.planning.seen_space``),
``tube`` (TrackingTube, the low level's measured guarantee).
Computes: :class:`onboard.high_level.planning.graph_planner.GraphPlanner`. Every tick (``refine_hz``,
100 Hz by default) one SQP iteration of the MPC refines the current path; when the
goal changed, the world or the tube changed and the rest of the path is no longer clear
of it, or the CoM strayed ``replan_deviation`` from the path, it recuts and replans, at
most ``replan_hz`` times a second (``GraphPlanner.needs_replan``). The graph is built
(or loaded from the on-disk cache) in a background thread when the planning region
changes; until it is ready the robot holds.
Publishes: ``reference`` (ComReference: the refined path, or a hold reference -- hop in
place -- when there is no path; at once when it changed, else every 0.1 s to keep it
fresh, so that the 1 kHz receiver does not decode the same 10 kB at 100 Hz), ``waypoints`` (the graph path and
its convex sets, after each replan), ``contract`` (ContractReport on every broken
promise: the low level's tube p95 above the tube planned with; the planner then plans
with the achieved tube times ``tube_growth``).
Status: ``path`` (1/0), planning and refinement times, edges, tube, violations,
``world_to_plan_ms_p50`` / ``_p99`` (a world's stamp, e.g. the overhead frame's receipt, to the end
of the first tick that planned or refined on it, over the last ``LATENCY_WINDOW`` worlds),
densifications (``densify_plans``, ``densify_rounds``, ``densify_nodes``: a failed search
densifies the graph for at most ``densify_budget_s``, and later plans reuse it); the
state is ``degraded`` with ``last_error`` saying so, and why, while there is no path.

Also here: the on-disk graph cache (:func:`load_or_build_graph`).
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import dataclasses
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from onboard.high_level.tracking import collision as col

from onboard.geometry import polygons as pg
from onboard.high_level.planning import bezier_graph as bg
from onboard.high_level.planning import graph_planner as gp
from onboard.contracts import messages as msgs
from onboard.contracts.params import PlannerParams
from onboard.high_level.planning.seen_space import SeenSpace
from robot_description import params as rd
from services.runtime.service import Service

CACHE_ENV = "ARCHER_CACHE_DIR"
REFERENCE_KEEPALIVE_NS = 100_000_000  # an unchanged reference is republished every 0.1 s (staleness is 0.5 s)
WARM_NODES = 300  # throwaway graph that loads the kernels at start
REFINE_BUDGET_SHARE = 0.4  # of a refine period, each MPC solve attempt's time limit (two attempts at most)
WARM_BOUNDS = (0.0, 0.0, 2.0, 2.0)  # [m]
LATENCY_WINDOW = 256  # worlds whose stamp-to-plan latency the status's percentiles cover


# --- graph cache (file I/O lives here, not in onboard) ---------------------------------------


def graph_cache_dir() -> Path:
    """``$ARCHER_CACHE_DIR/graphs``, else systemd's ``$CACHE_DIRECTORY/graphs`` (a unit with
    ``CacheDirectory=``), else ``$XDG_CACHE_HOME/archer/graphs``, else ``~/.cache/archer/graphs``."""
    for env in (CACHE_ENV, "CACHE_DIRECTORY"):
        root = os.environ.get(env)
        if root:
            return Path(root.split(":")[0]) / "graphs"
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "archer" / "graphs"


def load_or_build_graph(spec: bg.GraphSpec, cache_dir: Path | None) -> tuple[bg.BezierGraph, bool]:
    """The graph for ``spec`` from ``cache_dir/<key>.npz`` if it is there and sound, else
    built and written there (atomically). Returns ``(graph, from_cache)``; no cache with
    ``cache_dir=None``. A corrupt or foreign file is rebuilt over."""
    path = None if cache_dir is None else Path(cache_dir) / f"{spec.key()}.npz"
    if path is not None and path.exists():
        try:
            with np.load(path, allow_pickle=False) as data:
                return bg.BezierGraph.from_arrays(spec, dict(data)), True
        except (OSError, ValueError, KeyError):
            pass  # rebuilt below
    graph = bg.build_graph(spec)
    if path is not None:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".npz.tmp")
        except OSError:
            return graph, False  # a read-only or missing cache: plan without it
        try:
            with os.fdopen(fd, "wb") as fh:
                np.savez(fh, **graph.to_arrays())
            os.replace(tmp, path)
        except OSError:
            Path(tmp).unlink(missing_ok=True)
    return graph, False


def robot_footprint_radius(variant: str = rd.DEFAULT_VARIANT) -> float:
    """Radius [m] of the robot's collision shapes about its spine, from the MJCF (via ``RobotParams``)."""
    return rd.robot_params(variant).footprint_radius


# --- the service ------------------------------------------------------------------------------


def warm_up(params: PlannerParams, robot_radius: float) -> None:
    """Plan and refine once on a small throwaway scene (loads or compiles the numba kernels)."""
    small = gp.GraphPlanner(dataclasses.replace(params, nodes=WARM_NODES, rest_grid=0.0), robot_radius,
                            bounds=WARM_BOUNDS, nodes=WARM_NODES)
    small.set_obstacles([np.array([[0.9, 0.9], [1.1, 0.9], [1.1, 1.1], [0.9, 1.1]])])
    small.set_goal((1.8, 1.8))
    if small.plan((0.2, 0.2), (0.0, 0.0)) is not None:
        small.refine((0.2, 0.2), (0.0, 0.0), 0)
    small.waypoints()
    col.cut_obstacles(col.hull_set(np.zeros((col.PARALLEL_MIN, 4, 2))), small.obstacles, 0.1)  # the parallel build


def polygons_from_message(msg: msgs.PolytopeSet) -> list[np.ndarray]:
    """Vertices of each polytope; H-form only polytopes get exact vertices. Raises PolygonError."""
    out = []
    for k, p in enumerate(msg.polytopes):
        try:
            if p.vertices:
                out.append(pg.validate_polygon(p.vertices))
            else:
                out.append(pg.polygon_from_halfspaces(np.array(p.A, dtype=float).reshape(-1, 2), np.array(p.b, dtype=float)))
        except pg.PolygonError as exc:
            raise pg.PolygonError(f"polytope {k}: {exc}") from None
    return out


class PlannerService(Service):
    name = "planner"
    params_sections = ("planner",)
    subscribes = ("goal", "grid", "polytopes", "state", "tube")

    def __init__(self, *, robot_radius: float | None = None, cache_dir: Path | None | bool = True, **kw: Any) -> None:
        super().__init__(**kw)
        self._robot_radius = robot_radius
        self._cache_dir = graph_cache_dir() if cache_dir is True else (None if cache_dir is False else cache_dir)
        self._builder = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="planner-graph")
        self._build: concurrent.futures.Future | None = None
        self._hold_xy: list[float] | None = None
        self._hold_ref: msgs.ComReference | None = None
        self._sent: msgs.ComReference | None = None  # the reference last published
        self._sent_ns = 0
        self._last_plan_ns = -(10**18)
        self._plan_ms = 0.0
        self._refine_ms = 0.0
        self._has_path = False
        self._world_stamp_ns: int | None = None  # the stamp of a world taken but not yet planned on
        self._world_to_plan_ms: collections.deque[float] = collections.deque(maxlen=LATENCY_WINDOW)

    @property
    def prm(self) -> PlannerParams:
        return self.params["planner"]

    async def setup(self) -> None:
        robot = rd.robot_params(self.prm.robot)
        radius = self._robot_radius
        if radius is None:
            radius = self.prm.robot_radius or robot.footprint_radius
        params = rd.planner_params_for(self.prm, robot)  # no faster than the robot hops
        # the refinement never blocks the planner: each MPC solve ends within its share of a tick
        self.planner = gp.GraphPlanner(params, radius, mpc_time_limit_s=REFINE_BUDGET_SHARE / params.refine_hz)
        self.planner.set_seen(None, required=self.prm.require_seen)  # nothing seen yet, no world given
        # Load every compiled kernel now, before the service reports ready: done later, it
        # would cost the robot's first seconds CPU that the hard-rate loops need.
        await asyncio.to_thread(warm_up, params, radius)
        self.state_in = self.latest_sampled("state")  # 1 kHz, read at the tick: only what is read is decoded
        self.goal_in = self.latest("goal")
        self._pending_goal: msgs.Goal | None = None  # arrived, judged once a state says where the robot is
        self.polytopes_in = self.latest("polytopes")
        self.grid_in = self.latest("grid")
        self.tube_in = self.latest("tube")
        self.pub_reference = self.publisher("reference")
        self.pub_waypoints = self.publisher("waypoints")
        self.pub_contract = self.publisher("contract")

    async def teardown(self) -> None:
        self._builder.shutdown(wait=False, cancel_futures=True)

    def status_extra(self) -> dict[str, float]:
        st = self.planner.stats
        graph = self.planner.graph
        return {
            "path": float(self._has_path),
            "plans": st.plans,
            "no_path": st.no_path,
            "cuts": st.cuts,
            "edges_free": st.edges_free,
            "graph_nodes": graph.n_nodes if graph else 0,
            "graph_edges": graph.n_edges if graph else 0,
            "plan_ms": round(self._plan_ms, 3),
            "refine_ms": round(self._refine_ms, 3),
            "refine_solves": st.refines,
            "refine_reused": st.refine_reused,
            "refine_failures": st.refine_failures,
            "refine_numerical_errors": st.refine_numerical_errors,
            "unseen_holds": st.unseen_holds,
            "densify_plans": st.densify_plans,
            "densify_rounds": st.densify_rounds,
            "densify_nodes": st.densify_nodes,
            "tube_m": self.planner.tube,
            "margin_m": self.planner.margin,
            "contract_violations": self.planner.contract_violations,
            **_percentiles("world_to_plan_ms", self._world_to_plan_ms),
        }

    async def main(self) -> None:
        period = 1.0 / self.prm.refine_hz
        rate = self.rate("tick")
        while not self.stopping.is_set():
            started = time.monotonic()
            try:
                await asyncio.to_thread(self.tick)
            except Exception as exc:  # keep serving; the low level holds on a stale reference
                self.fail(f"tick: {exc!r}")
                self.log.exception("planner tick failed")
            rate.tick()
            await asyncio.sleep(max(0.0, period - (time.monotonic() - started)))

    # --- one tick (runs in a worker thread; the only user of self.planner) -------------------

    def tick(self) -> None:
        now = self.clock.now_ns()
        self._ingest()
        got = self.state_in.get()
        if got is None:
            return
        est, _ = got
        if not est.valid or (now - est.stamp_ns) * 1e-9 > self.prm.state_stale_s:
            self.count("stale_state")
            return
        pos = np.array(est.position[:2])
        vel = np.array(est.velocity[:2])
        if self.planner.goal is None:
            return
        if not self._graph_ready(pos):
            self._publish_hold(pos, now)
            return
        due = now - self._last_plan_ns >= 1e9 / self.prm.replan_hz
        if due and self.planner.needs_replan(pos, now, self.prm.replan_deviation):
            t0 = time.perf_counter()
            # the wall clock bounds a densification; the tick is late by at most densify_budget_s
            ref = self.planner.plan(pos, vel, now, build=False, clock=time.perf_counter)
            self._plan_ms = (time.perf_counter() - t0) * 1e3
            self._last_plan_ns = now
            self.rate("plan").tick()
            self._has_path = ref is not None
            if ref is None:
                self.state = "degraded"
                why = self.planner.last_densify.reason if self.planner.last_densify else "densification off"
                self.last_error = f"no path to goal {self.planner.goal.tolist()}: {why}"
                self.count("no_path")
            elif self.planner.path is None:  # no path, an obstacle coming: the step out of its way, held
                self._has_path = False  # until a replan finds a path (it searches again at the next one)
                self._hold_xy = list(ref.segments[-1].control_points[-1])
                self._hold_ref = ref
                self.count("evasions")
            else:
                self.state = "running"
                self._hold_xy = None
                self._hold_ref = None
                self.pub_waypoints.put(self.planner.waypoints(now))
        if not self._has_path:
            self._publish_hold(pos, now)
            self._planned_on_world()
            return
        t0 = time.perf_counter()
        ref = self.planner.refine(pos, vel, now)
        self._refine_ms = (time.perf_counter() - t0) * 1e3
        if ref is not None:
            self._send_reference(ref, now)
        self._planned_on_world()

    def _planned_on_world(self) -> None:
        """This tick planned on the world taken last (or held for want of a path in it): its latency."""
        if self._world_stamp_ns is not None:
            self._world_to_plan_ms.append((self.clock.now_ns() - self._world_stamp_ns) / 1e6)
            self._world_stamp_ns = None

    def _send_reference(self, ref: msgs.ComReference, now: int) -> None:
        """Publish a reference that changed at once, an unchanged one at the keep-alive rate:
        a long reference costs its receiver (the 1 kHz process) a decode each time."""
        last = self._sent
        changed = (last is None or ref.segments is not last.segments or ref.t_ref_ns != last.t_ref_ns
                   or ref.hold != last.hold)
        if changed or now - self._sent_ns >= REFERENCE_KEEPALIVE_NS:
            ref.stamp_ns = now
            self.pub_reference.put(ref)
            self._sent = ref
            self._sent_ns = now

    def _publish_hold(self, pos: np.ndarray, now: int) -> None:
        if self._hold_xy is None or self._hold_ref is None:
            self._hold_xy = [float(pos[0]), float(pos[1])]  # hold where the robot was: no drift
            self._hold_ref = self.planner.hold_reference(self._hold_xy, now)
        self._send_reference(self._hold_ref, now)

    def _graph_ready(self, pos: np.ndarray) -> bool:
        """Whether there is a graph to plan on; starts building (or loading) the one the
        region needs when it is not the current one. The current graph stays in use while
        the new one builds if it still holds the robot and the goal."""
        spec = self.planner.graph_spec_for(pos)
        graph = self.planner.graph
        if graph is not None and graph.spec == spec:
            return True
        # A build in flight is never replaced: the region follows the obstacles' extent, which a
        # camera's silhouettes change a little every frame, and a build replaced at each frame was
        # never installed (a real-time overhead run planned nothing in 60 s)
        if self._build is None:
            self._build = self._builder.submit(load_or_build_graph, spec, self._cache_dir)
        if self._build.done():
            build, self._build = self._build, None
            try:
                g, cached = build.result()
            except Exception as exc:
                self.fail(f"graph build: {exc!r}")
                return False
            self.count("graph_cache_hits" if cached else "graph_builds")
            if _holds(g.spec.bounds, pos, self.planner.goal):  # else the next tick builds the region needed now
                self.planner.set_graph(g)
                return True
        return graph is not None and _holds(graph.spec.bounds, pos, self.planner.goal)

    def _take_goal(self) -> None:
        """The goal that arrived, once a state tells where the robot starts: refused once, with its
        reason in the log and the status (``last_error``, ``rejected.goal_unreachable``), when the planner cannot take it; the
        robot then keeps its last goal and plan."""
        state = self.state_in.get()
        if state is None:
            return  # judged against the first state
        goal, self._pending_goal = self._pending_goal, None
        assert goal is not None
        why = self.planner.goal_refusal(goal.position, np.array(state[0].position[:2]))
        if why is None:
            try:
                self.planner.set_goal(goal.position, goal.tolerance)
                return
            except gp.PlanningError as exc:
                why = str(exc)
        self.count("rejected.goal_unreachable")
        self.last_error = f"goal refused: {why}"  # the status says why; no plan fails over it
        self.log.warning("goal refused, keeping the last one", extra={"fields": {"goal": list(goal.position), "reason": why}})

    def _ingest(self) -> None:
        got = self.goal_in.take()
        if got is not None:
            self._pending_goal = got[0]
        if self._pending_goal is not None:
            self._take_goal()
        got = self.polytopes_in.take()
        if got is not None:
            msg, _ = got
            try:
                polys = polygons_from_message(msg)
                if msg.mode == "free":
                    self.planner.set_free_cells(polys)
                else:
                    # obstacles that move carry their velocities (a static world's default to zero)
                    vel = [p.velocity for p in msg.polytopes]
                    self.planner.set_obstacles(polys, vel if any(v[0] or v[1] for v in vel) else None)
                # perceived obstacles leave the unseen free: commit only to what the grid saw;
                # free cells are seen free, and a world given whole has nothing unseen
                required = self.prm.require_seen and msg.mode == "obstacles" and msg.source != "ground_truth"
                if required != self.planner.require_seen:
                    self.planner.set_seen(self.planner.seen, required=required)
                if msg.stamp_ns > 0:  # an unstamped world (a hand-made message) has no latency
                    self._world_stamp_ns = msg.stamp_ns
            except (pg.PolygonError, gp.PlanningError) as exc:
                self.count("rejected.polytopes_geometry")
                self.fail(f"polytopes: {exc}")
        got = self.grid_in.take()
        if got is not None:
            try:
                self.planner.set_seen(SeenSpace.from_grid(got[0]), required=self.planner.require_seen)
            except ValueError as exc:
                self.count("rejected.grid_geometry")
                self.fail(f"grid: {exc}")
        got = self.tube_in.take()
        if got is not None:
            self._check_contract(got[0])

    def _check_contract(self, tube: msgs.TrackingTube) -> None:
        report = self.planner.check_tube(tube, self.clock.now_ns())
        self.planner.drain_contract_reports()  # published here instead
        if report is None:
            if tube.hops >= self.prm.contract_min_hops and tube.impact_err_p95 <= self.planner.tube:
                self.contract_state = "ok"
            return
        self.count("contract_violations")
        self.contract_state = "violated"
        self.pub_contract.put(report)
        self.log.warning("contract violated", extra={"fields": {"promised": report.promised, "achieved": report.achieved,
                                                               "tube": self.planner.tube}})


def _percentiles(name: str, values: collections.deque[float]) -> dict[str, float]:
    """``name_p50`` and ``name_p99`` of ``values`` (none while empty)."""
    if not values:
        return {}
    p50, p99 = np.percentile(list(values), [50, 99])  # list(): one step under the GIL, the tick may append
    return {f"{name}_p50": round(float(p50), 2), f"{name}_p99": round(float(p99), 2)}


def _holds(bounds: tuple[float, float, float, float], *points: np.ndarray | None) -> bool:
    xmin, ymin, xmax, ymax = bounds
    return all(p is None or (xmin <= p[0] <= xmax and ymin <= p[1] <= ymax) for p in points)
