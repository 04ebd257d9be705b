"""What the planner hands down: the graph path as a reference, its refinement (Algorithm 3,
step 4: the Bezier MPC of eq. 7.2 around the graph path) and the gate on seen ground.

Mixed into :class:`~onboard.high_level.planning.graph_planner.GraphPlanner`, whose path, world,
tube and statistics it reads: the MPC is warm-started with the last solution (or the graph
path), each segment kept on the free side of separating halfspaces to its nearest obstacles
(or inside its free cell), certified by the MPC and then by the exact cut; with a perceived
world, a reference whose committed part crosses ground not seen free is held back. Also the convex
sets {X_k} the planner publishes with its waypoints, built by the same rules.
"""

from __future__ import annotations

import math

import msgspec
import numpy as np

from onboard.contracts import messages as msgs
from onboard.contracts.reference import sample_reference
from onboard.geometry import polygons as pg
from onboard.high_level.planning.bezier_graph import DIM, chain_tail, path_states, speed_limits
from onboard.high_level.tracking import collision as col
from onboard.high_level.tracking import reachability as reach
from onboard.high_level.tracking.bezier_mpc import BezierMpc, MpcWeights

# MPC cost (eq. 7.2): stay near the graph path, but prefer a shorter, smoother curve
# (thesis: "path length cost was scaled significantly higher than tracking cost").
MPC_WEIGHTS = MpcWeights(state=(1.0, 1.0, 0.1, 0.1), terminal=(10.0, 10.0, 1.0, 1.0), effort=0.01, path=50.0)
MPC_MIN_RADIUS = 2e-4  # [m, m/s] initial-state radii below this become equalities (MPC margin)


class MpcRefinement:
    """The references, the refinement and the sets of :class:`GraphPlanner` (a mixin: it owns no state of its own
    but the MPC and its warm start, created by the planner's constructor)."""

    # --- the references handed down ----------------------------------------------------

    def path_reference(self, stamp_ns: int = 0) -> msgs.ComReference:
        """The graph path as the CoM reference (time 0 at the path's start)."""
        assert self.path is not None
        segs = [msgs.BezierSegment(t0=float(k * self.path.tau), duration=float(self.path.tau), control_points=c.tolist())
                for k, c in enumerate(self.path.control_points)]
        return msgs.ComReference(stamp_ns=stamp_ns, t_ref_ns=self.path_t0_ns, segments=segs, hold=False)

    def hold_reference(self, position: np.ndarray, stamp_ns: int = 0) -> msgs.ComReference:
        """Hop in place at ``position``: one constant segment, ``hold=True``."""
        p = [float(v) for v in np.asarray(position, dtype=float).reshape(-1)[:2]]
        tau = self.params.segment_s
        seg = msgs.BezierSegment(t0=0.0, duration=tau, control_points=[p] * 4)
        return msgs.ComReference(stamp_ns=stamp_ns, t_ref_ns=stamp_ns, segments=[seg], hold=True)

    def heading(self, ref: msgs.ComReference, position: np.ndarray, stamp_ns: int) -> float | None:
        """The yaw [rad] that points the camera along ``ref``: at the first place, every
        ``heading_lookahead_s`` along it, at least ``heading_min_m`` from ``position`` (a path
        from rest starts slowly); None (keep the heading) when the whole reference is near."""
        if ref.hold or not ref.segments:
            return None
        prm = self.params
        t = (stamp_ns - ref.t_ref_ns) * 1e-9
        end = ref.segments[-1].t0 + ref.segments[-1].duration
        while True:
            t = min(t + prm.heading_lookahead_s, end)
            x, y, _, _ = sample_reference(ref, t)
            dx, dy = x - float(position[0]), y - float(position[1])
            if math.hypot(dx, dy) >= prm.heading_min_m:
                return math.atan2(dy, dx)
            if t >= end:
                return None

    def committed(self, ref: msgs.ComReference, position: np.ndarray, stamp_ns: int) -> msgs.ComReference:
        """With a perceived world (:meth:`set_seen`): ``ref`` with the heading that shows the
        camera its way, when the robot's footprint stays on seen-free ground along its first
        ``commit_s`` (the tube's clearance from what was seen occupied is the cut's); else hop in
        place where the robot is, turned that way, until the camera has seen it
        (``stats.unseen_holds``). Free cells are seen free by construction: in free mode ``ref``
        only gains the heading."""
        if not self.require_seen and self.mode != "free":  # a world given whole: no camera to point, nothing unseen
            return ref
        yaw = self.heading(ref, position, stamp_ns)  # free cells are seen free, but the camera must find more
        if self.require_seen and not ref.hold:
            prm = self.params
            t0 = (stamp_ns - ref.t_ref_ns) * 1e-9
            steps = int(math.ceil(prm.commit_s / prm.commit_step_s))
            samples = np.array([sample_reference(ref, t0 + k * prm.commit_step_s)[:2] for k in range(steps + 1)])
            here = np.asarray(position, dtype=float)[:2]
            if self.seen is None or self.seen.first_unseen(samples, self.robot_radius, here, self.margin) is not None:
                self.stats.unseen_holds += 1
                return msgspec.structs.replace(self.hold_reference(here, stamp_ns), yaw=yaw)
        return msgspec.structs.replace(ref, yaw=yaw)

    # --- refine ------------------------------------------------------------------------------

    def _ensure_mpc(self, planes: int) -> BezierMpc:
        if self._mpc is None or self._mpc_tube != self.tube or self._mpc.max_planes < planes:
            prm = self.params
            model = reach.double_integrator(DIM)
            inf = math.inf
            test = reach.BezierReachability(model, speed_limits(prm.a_max, prm.v_max, tube=self.tube, tube_norm=2), prm.mpc_dt)
            self._mpc = BezierMpc(test, prm.mpc_horizon, MPC_WEIGHTS, trust_region=[prm.mpc_trust, prm.mpc_trust, inf, inf],
                                  init_radius=self._init_radius(),
                                  max_planes=max(planes, prm.halfspaces), terminal="equal", time_limit_s=self.mpc_time_limit_s)
            self._mpc_tube = self.tube
            self._last_solution = None
        return self._mpc

    def refine(self, position: np.ndarray, velocity: np.ndarray, stamp_ns: int) -> msgs.ComReference | None:
        """The refined reference (:meth:`refine_path`), gated on seen ground (:meth:`committed`)."""
        ref = self.refine_path(position, velocity, stamp_ns)
        return None if ref is None else self.committed(ref, position, stamp_ns)

    def refine_path(self, position: np.ndarray, velocity: np.ndarray, stamp_ns: int) -> msgs.ComReference | None:
        """One SQP iteration of the MPC of eq. 7.2 around the current path; the refined reference.

        Knots sit every ``mpc_dt`` from the path's start (so they meet the graph
        segments' junctions); the first within the tube of the state, the last on the
        graph path (7.2e), each within ``mpc_trust`` of it. Each MPC segment keeps to
        halfspaces separating it (as warm-started: the last solution shifted, else the
        graph path) from its nearest obstacles, or to its free cell. The solution is
        certified by the MPC and then checked by the exact cut; when either fails the
        graph path itself is returned (it is collision free). None without a path.

        Between two knots the QP only changes by the measured state: while the last
        solution's first knot still lies within the tube of the state (it stays feasible)
        and nothing else changed, that solution is returned again without a solve
        (``stats.refine_reused``). Once every knot lies past the path's end and the state rests
        within the tube of that end, the MPC's answer is the end itself: the graph path is
        returned, without a solve, until the robot is pushed out of the tube (``stats.refine_idle``).
        """
        if self.path is None:
            return None
        prm = self.params
        x = self._state(position, velocity)
        dt, N = prm.mpc_dt, prm.mpc_horizon
        path = self.path
        j0 = max(0, int(round((stamp_ns - self.path_t0_ns) * 1e-9 / dt)))
        if j0 * dt >= path.duration and self._at_path_end(x):
            # arrived: every knot would sit on the path's end at rest, a problem whose answer is that
            # end; the graph path holds the robot there, with no solve until it is pushed out of the tube
            self.stats.refine_idle += 1
            if self._arrived is None or self._arrived[0] is not path:
                self._arrived = (path, self.path_reference(stamp_ns))
            return msgspec.structs.replace(self._arrived[1], stamp_ns=stamp_ns)
        kept = self._last_refined
        if (kept is not None and kept[0] == j0 and kept[1] == self._world_version and kept[2] is path
                and np.all(np.abs(kept[3] - x) <= self._init_radius())):
            self.stats.refine_reused += 1
            return msgspec.structs.replace(kept[4], stamp_ns=stamp_ns)
        failed = self._failed_refine
        if self.mode == "free" and failed is not None and failed[:2] == (j0, self._world_version) and failed[2] is path:
            # Free mode: the cell faces the path runs along are active constraints and a QP that ran out of
            # iterations at this knot does so again ten milliseconds later (it differs by the measured state
            # only), at the full iteration budget and polish each time (most of a free-mode run's time when
            # retried at refine_hz): the graph path until the next knot, path or world
            self.stats.refine_skipped += 1
            return self.path_reference(stamp_ns)
        times = (j0 + np.arange(N + 1)) * dt
        ref = path_states(path.control_points, path.tau, times)
        warm = ref.copy()
        last = self._last_solution
        if last is not None:
            shift = j0 - last[0]
            if 0 <= shift <= N:
                warm[: N + 1 - shift] = last[1][shift:]
        mpc = self._ensure_mpc(prm.halfspaces)
        warm_ctrl = mpc.reach.curve(warm[:-1], warm[1:])
        hs = self.segment_halfspaces(warm_ctrl, self.robot_radius, mpc.max_planes)  # the MPC adds the tube
        self.stats.refines += 1
        try:
            sol = mpc.solve(x, ref, planes=(np.ascontiguousarray(hs[..., :2]), np.ascontiguousarray(hs[..., 2])),
                            warm_start=warm)
        except (np.linalg.LinAlgError, ArithmeticError, ValueError) as exc:
            # a numerical failure is a failed refinement (the graph path below), never a crash
            # of the loop that called it: the service and the lockstep runner alike
            sol = None
            self.stats.refine_numerical_errors += 1
            self.stats.last_refine_error = f"{type(exc).__name__}: {exc}"
        t_ref_ns = self.path_t0_ns + int(round(j0 * dt * 1e9))
        if sol is not None and sol.ok:
            hulls = col.hull_set(sol.control_points)
            blocked, _ = self._blocked(hulls)
            if not blocked.any():
                self._last_solution = (j0, sol.waypoints)
                segs = [msgs.BezierSegment(t0=float(k * dt), duration=float(dt), control_points=c.tolist())
                        for k, c in enumerate(sol.control_points)]
                t = N * dt
                for dur, c in chain_tail(path.control_points, path.tau, float(times[-1])):
                    segs.append(msgs.BezierSegment(t0=float(t), duration=float(dur), control_points=c.tolist()))
                    t += dur
                out = msgs.ComReference(stamp_ns=stamp_ns, t_ref_ns=t_ref_ns, segments=segs, hold=False)
                self._last_refined = (j0, self._world_version, path, sol.waypoints[0].copy(), out)
                return out
        self.stats.refine_failures += 1
        self._last_solution = None
        self._last_refined = None
        self._failed_refine = (j0, self._world_version, path)
        return self.path_reference(stamp_ns)

    def _at_path_end(self, x: np.ndarray) -> bool:
        """Whether the state lies within the tube of the path's end at rest (the MPC's first-knot radius)."""
        assert self.path is not None
        px, py = self.path.control_points[-1, -1].tolist()
        rp, rv = self._init_radii()
        x0, x1, x2, x3 = x.tolist()
        return abs(x0 - px) <= rp and abs(x1 - py) <= rp and abs(x2) <= rv and abs(x3) <= rv

    def _init_radii(self) -> tuple[float, float]:
        """How far the MPC's first knot may sit from the state (7.2b) in position and in speed: the
        tube and the speed tolerance, each 0 (an equality) below MPC_MIN_RADIUS."""
        rp, rv = self.tube, self.params.start_speed_tol
        return (rp if rp > MPC_MIN_RADIUS else 0.0), (rv if rv > MPC_MIN_RADIUS else 0.0)

    def _init_radius(self) -> np.ndarray:
        """:meth:`_init_radii` per state coordinate ``[px, py, vx, vy]``."""
        rp, rv = self._init_radii()
        return np.array([rp, rp, rv, rv])

    # --- sets ------------------------------------------------------------------------------

    def segment_halfspaces(self, ctrl: np.ndarray, margin: float, count: int) -> np.ndarray:
        """``(S, count, 3)`` halfspaces ``a . x <= b`` keeping each segment ``margin`` [m] clear.

        Obstacle mode: separating planes to the nearest obstacles. Free mode: the faces
        of the cell holding the segment, its ``count`` nearest when it has more (as the
        nearest obstacles: a far face is not what a short segment runs into, and every
        face costs the MPC ``p + 1`` rows per segment; the exact cut checks the answer
        against them all); the rest padded.
        """
        S = len(ctrl)
        if self.mode == "obstacles":
            return col.separating_halfspaces(ctrl, self.obstacles, margin, count, self.params.halfspace_reach)
        hulls = col.hull_set(ctrl)
        # a cell holding the segment margin deep (as the cut found the graph path), else any holding it
        cells = col.free_cell_of(hulls, self.cells, self.margin)
        shallow = cells < 0
        if shallow.any():
            cells[shallow] = col.free_cell_of(hulls, self.cells, 0.0, active=shallow)[shallow]
        out = np.zeros((S, count, 3))
        out[:, :, 2] = np.inf
        for s, c in enumerate(cells):
            if c < 0:
                continue
            a = self.cells.normals[self.cells.offsets[c]:self.cells.offsets[c + 1]]
            b = self.cells.face_offsets[self.cells.offsets[c]:self.cells.offsets[c + 1]] - margin
            if len(a) > count:
                slack = np.min(b[:, None] - a @ ctrl[s].T, axis=1)  # nearest control point's room to each face
                keep = np.argsort(slack, kind="stable")[:count]
                a, b = a[keep], b[keep]
            out[s, :len(a), :2] = a
            out[s, :len(a), 2] = b
        return out

    def waypoints(self, stamp_ns: int = 0) -> msgs.Waypoints:
        """The graph path's node positions and the convex set of the segment leaving each.

        Obstacle mode: the planning region cut by separating halfspaces until every point
        of the set keeps the margin from every obstacle
        (:func:`onboard.high_level.tracking.collision.free_polygon`); free mode: the cell. A set that could
        not be built is sent empty.
        """
        assert self.graph is not None and self.path is not None
        ctrl = self.path.control_points
        bounds = self.graph.spec.bounds
        if self.mode == "free":
            cells = col.free_cell_of(col.hull_set(ctrl), self.cells, self.margin)
            polys = [self.cells.polygon(c) if c >= 0 else None for c in cells]
        else:
            polys = []
            for c in ctrl:
                try:
                    polys.append(col.free_polygon(c, self.obstacles, self.margin, np.array(bounds).reshape(2, 2),
                                                  self.params.halfspaces, self.params.halfspace_reach))
                except pg.PolygonError:
                    polys.append(None)
        sets = []
        for poly in polys + polys[-1:]:
            if poly is None:
                sets.append(msgs.Polytope(A=[], b=[], vertices=[]))
                continue
            A, b = pg.polygon_halfspaces(poly)
            sets.append(msgs.Polytope(A=A.tolist(), b=b.tolist(), vertices=poly.tolist()))
        points = [[float(s[0]), float(s[1])] for s in self.path.states]
        return msgs.Waypoints(stamp_ns=stamp_ns, points=points, sets=sets)
