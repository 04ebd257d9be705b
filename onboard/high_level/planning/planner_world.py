"""The world the planner cuts its graph against (thesis 7.1, lines 3077-3181: the cut of
Algorithm 3, step 2; 7.2, lines 3182-3216: obstacles that move while it plans).

Mixed into :class:`~onboard.high_level.planning.graph_planner.GraphPlanner`: its convex
obstacles (still, or moving and cut swept along their velocities band by band of distance,
:mod:`onboard.high_level.planning.moving_obstacles`) or its free cells, the seen space that
gates its references, the tube that inflates everything (``margin = robot_radius + tube``), and
the version that counts their changes (a replan is due). On that world it answers which curves
are blocked (the exact separating-axis cut of :mod:`onboard.high_level.tracking.collision`, or
containment in one free cell), recuts the graph's edges when something changed, says how much
clearance the start may keep, and steps out of a moving obstacle's way when there is no path.
Reads the planner's ``params``, ``robot_radius``, ``graph`` and ``stats``.
"""

from __future__ import annotations

import math

import numpy as np

from onboard.contracts import messages as msgs
from onboard.geometry import polygons as pg
from onboard.high_level.planning import moving_obstacles as mo
from onboard.high_level.planning.bezier_graph import PlanningError
from onboard.high_level.planning.seen_space import SeenSpace
from onboard.high_level.tracking import collision as col

START_SLACK = 1e-3  # [m] a start closer than the margin may leave keeping its clearance less this


class PlannerWorld:
    """Obstacles, free cells, seen space and tube of :class:`GraphPlanner`, and the cut against them (a mixin)."""

    def _init_world(self, tube: float) -> None:
        """The world before any is given: no obstacle, tube ``tube`` [m], nothing seen."""
        self.tube = float(tube)
        self.mode = "obstacles"
        self.obstacles = pg.pack_polygons([])
        self.cells = pg.pack_polygons([])
        # moving obstacles (onboard.high_level.planning.moving_obstacles): as given, their velocities, and
        # the sweep level they are cut at now (an index into SWEEP_LEVELS); None: no obstacle moves
        self._moving: tuple[list[np.ndarray], np.ndarray] | None = None
        self._sweep_level = 0
        self._static = pg.pack_polygons([])  # with moving obstacles: the still ones
        self._band_origin = np.zeros(2)  # where the robot is: the cut in time measures from here
        self._sweep_orders: list[np.ndarray | None] = []  # each moving obstacle's swept hull, by vertex (mo.sweep_orders)
        self._banded: tuple[int, pg.PolygonSet, np.ndarray] | None = None  # bands 0..n-1 packed together, each polygon's band
        self._world_moves = False  # the obstacles come with velocities (even still ones): a world that moves
        self._world_version = 0
        self._cut_key: tuple | None = None
        self.free: np.ndarray | None = None  # edge mask after the cut
        self.seen: SeenSpace | None = None  # None: the world is known (ground truth), nothing to gate
        self.require_seen = False

    # --- inputs ----------------------------------------------------------------------

    @property
    def margin(self) -> float:
        """Clearance [m] the plan keeps from every obstacle: robot radius plus tube."""
        return self.robot_radius + self.tube

    def set_obstacles(self, polygons: list, velocities: object | None = None) -> None:
        """Convex obstacles ``[(k, 2) vertices, ...]`` [m], and optionally their velocities ``(M, 2)`` [m/s]:
        a moving one is cut swept along its velocity over ``obstacle_sweep_s`` (at most
        ``obstacle_sweep_max_m``); raises :class:`PlanningError` on a bad one."""
        polygons = list(polygons)
        self._moving = None
        self._world_moves = velocities is not None
        if velocities is not None:
            try:
                vel = mo.check_velocities(velocities, len(polygons))
                polys = [pg.validate_polygon(p) for p in polygons]
            except (ValueError, pg.PolygonError) as exc:
                raise PlanningError(f"obstacle: {exc}") from None
            if mo.moving(vel):
                self._moving = (polys, vel)
                self._sweep_orders = mo.sweep_orders(polys, vel)
                self._sweep_level = 0
                self._banded = None
                still = np.hypot(vel[:, 0], vel[:, 1]) < mo.STILL
                self._static = pg.pack_polygons([p for p, s in zip(polys, still) if s])
                polygons = self._swept()
        self._set_polygons("obstacles", _packed(polygons, "obstacle"))

    def _swept(self) -> list[np.ndarray]:
        """The obstacles the robot may meet near where it is: still ones as given, moving ones over the
        first band's window (what the refinement's halfspaces and the start's clearance see)."""
        assert self._moving is not None
        polys, vel = self._moving
        still = [p for p, v in zip(polys, vel.tolist()) if math.hypot(*v) < mo.STILL]
        window = np.array([[0.0, self._band_window(0)[1]]])
        return still + mo.band_polygons(polys, vel, self._sweep_orders, window, self.params.obstacle_sweep_max_m)[0]

    def _band_window(self, band: int) -> tuple[float, float]:
        """The time window [s] in which the robot may be on curves of distance band ``band`` and must
        not meet a moving obstacle: from its earliest arrival to past the band plus the committed
        horizon, shortened by the current level."""
        prm = self.params
        t0 = band * prm.obstacle_band_m / prm.v_max
        return t0, t0 + mo.SWEEP_LEVELS[self._sweep_level] * (prm.obstacle_band_m / prm.v_max + prm.obstacle_sweep_s)

    def _bands_packed(self, count: int) -> tuple[pg.PolygonSet, np.ndarray]:
        """The moving obstacles of bands ``0..count-1`` in one set, and each polygon's band."""
        if self._banded is None or self._banded[0] < count:
            assert self._moving is not None
            polys, vel = self._moving
            windows = np.array([self._band_window(b) for b in range(count)])
            lists = mo.band_polygons(polys, vel, self._sweep_orders, windows, self.params.obstacle_sweep_max_m)
            group = np.repeat(np.arange(count, dtype=np.int64), [len(p) for p in lists])
            self._banded = (count, pg.pack_polygons([p for ps in lists for p in ps]), group)
        return self._banded[1], self._banded[2]

    def _blocked_in_time(self, hulls: col.HullSet, margin: float, active: np.ndarray) -> np.ndarray:
        """Blocked mask of curves against the still obstacles and, band by band of distance from the
        robot, the moving ones over that band's window (the cut in time: every band in one pass, each
        curve against its own band's obstacles)."""
        blocked = col.cut_obstacles(hulls, self._static, margin, active=active)
        free = active & ~blocked
        if not free.any():
            return blocked
        bands = mo.curve_bands(hulls.aabb, self._band_origin, self.params.obstacle_band_m)
        moving, band_of = self._bands_packed(int(bands[free].max()) + 1)
        return blocked | col.cut_obstacles(hulls, moving, margin, active=free, curve_group=bands, obstacle_group=band_of)

    def _set_band_origin(self, position: np.ndarray) -> None:
        """Measure the cut in time from ``position`` (a changed origin is a changed world for the cut)."""
        p = np.asarray(position, dtype=float)[:2]
        if self._moving is not None and not np.array_equal(p, self._band_origin):
            self._band_origin = p.copy()
            self._world_version += 1

    def _set_sweep_level(self, level: int) -> bool:
        """Cut the moving obstacles at sweep ``level`` from now on; whether that changed the world."""
        if self._moving is None or level == self._sweep_level or not 0 <= level < len(mo.SWEEP_LEVELS):
            return False
        self._sweep_level = level
        self._banded = None
        self.obstacles = pg.pack_polygons(self._swept())
        self._world_version += 1
        return True

    def set_free_cells(self, polygons: list) -> None:
        """Convex free cells: a curve is free iff its control points lie in one cell."""
        self._set_polygons("free", _packed(list(polygons), "free cell"))

    def _set_polygons(self, mode: str, packed: pg.PolygonSet) -> None:
        """Plan among obstacles or in free cells (``mode``) ``packed`` from now on; the same ones
        in the same mode change nothing (no recut, no replan)."""
        if self.mode == mode and _same_polygons(packed, self.obstacles if mode == "obstacles" else self.cells):
            return
        self.mode = mode
        if mode == "obstacles":
            self.obstacles = packed
        else:
            self.cells = packed
        self._world_version += 1

    def set_seen(self, seen: SeenSpace | None, required: bool = True) -> None:
        """What the camera has seen free (``onboard.high_level.planning.seen_space``). With ``required`` every
        reference is gated on it, and before the first one the robot is committed nowhere;
        ``required=False`` (a world given whole, as ground truth) gates nothing."""
        self.seen = seen
        self.require_seen = bool(required)

    def set_tube(self, tube: float) -> None:
        """Plan with tube ``tube`` [m] from now on (a larger one after a broken promise)."""
        if not (math.isfinite(tube) and tube >= 0):
            raise PlanningError(f"tube must be finite and >= 0, got {tube}")
        if tube != self.tube:
            self.tube = float(tube)
            self._world_version += 1

    @property
    def world_version(self) -> int:
        """Increments whenever obstacles, cells or the tube change (a replan is due)."""
        return self._world_version

    # --- cut ---------------------------------------------------------------------------

    def _blocked(self, hulls: col.HullSet, margin: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Blocked mask and (free mode) containing cell of arbitrary curves (``margin``: default the planner's)."""
        assert self.graph is not None
        margin = self.margin if margin is None else margin
        xmin, ymin, xmax, ymax = self.graph.spec.bounds
        outside = ((hulls.aabb[:, 0] < xmin) | (hulls.aabb[:, 1] < ymin)
                   | (hulls.aabb[:, 2] > xmax) | (hulls.aabb[:, 3] > ymax))
        if self.mode == "free":
            cell = col.free_cell_of(hulls, self.cells, margin, active=~outside)
            return outside | (cell < 0), cell
        if self._moving is not None:
            return outside | self._blocked_in_time(hulls, margin, ~outside), np.full(len(hulls), -1)
        return outside | col.cut_obstacles(hulls, self.obstacles, margin, active=~outside), np.full(len(hulls), -1)

    def cut(self) -> np.ndarray:
        """Recut the graph if the world, the tube or the graph changed; the free-edge mask."""
        assert self.graph is not None
        key = (id(self.graph), self._world_version)
        if self._cut_key != key or self.free is None:
            self.free = ~self._blocked(self.graph.hulls)[0]
            self._cut_key = key
            self.stats.cuts += 1
            self.stats.edges_free = int(self.free.sum())
        return self.free

    def start_margin(self, position: np.ndarray) -> float:
        """Clearance the segments leaving the start must keep: the margin, or, when the
        robot already stands closer to an obstacle (its tube was exceeded) or nearer the
        edge of its free cell (the cells were fitted anew around it), what it has
        now -- so that it can leave (never below the robot radius: that is a collision)."""
        p = np.asarray(position, dtype=float)[:2]
        if self.mode == "free":
            if len(self.cells) == 0:
                return self.margin
            inside = self.cells.face_offsets - self.cells.normals @ p  # per face: distance inside it
            have = float(np.max(np.minimum.reduceat(inside, self.cells.offsets[:-1])))
        elif len(self.obstacles) == 0:
            return self.margin
        else:
            have = float(col.samples_clearance(p[None, None, :], self.obstacles, reach=self.margin)[0])
        if have >= self.margin:
            return self.margin
        return max(have - START_SLACK, self.robot_radius)

    # --- no path, an obstacle coming ---------------------------------------------------------

    def evade_reference(self, x0: np.ndarray, stamp_ns: int) -> msgs.ComReference | None:
        """No path, and a moving obstacle comes at the robot: a reference stepping ``EVADE_M`` out of its
        way (a cubic from the state to rest there, at the planner's speed), in the first direction whose
        step keeps the robot radius from every obstacle where it is now; None (hold) when no obstacle
        comes within ``obstacle_sweep_max_m`` plus the margin or no step is clear. :attr:`path` stays None:
        the next replan searches again."""
        assert self._moving is not None
        polys, vel = self._moving
        k = mo.threat(x0[:2], polys, vel, self.params.obstacle_sweep_max_m + self.margin)
        if k is None or self.graph is None:
            return None
        self._set_sweep_level(len(mo.SWEEP_LEVELS) - 1)  # where the obstacles are now
        p0, v0 = x0[:2], x0[2:]
        duration = 1.5 * mo.EVADE_M / self.params.v_max  # a cubic's peak speed is 1.5 times its mean
        for d in mo.evasion_directions(p0, polys[k].mean(axis=0), vel[k]):
            end = p0 + mo.EVADE_M * d
            ctrl = np.array([p0, p0 + v0 * duration / 3.0, end, end])
            if not self._blocked(col.hull_set(ctrl[None]), self.robot_radius)[0][0]:
                self.stats.evasions += 1
                seg = msgs.BezierSegment(t0=0.0, duration=float(duration), control_points=ctrl.tolist())
                return msgs.ComReference(stamp_ns=stamp_ns, t_ref_ns=stamp_ns, segments=[seg], hold=False)
        return None


def _packed(polygons: list, what: str) -> pg.PolygonSet:
    try:
        return pg.pack_polygons(polygons)
    except pg.PolygonError as exc:
        raise PlanningError(f"{what}: {exc}") from None


def _same_polygons(a: pg.PolygonSet, b: pg.PolygonSet) -> bool:
    return a.offsets.shape == b.offsets.shape and np.array_equal(a.offsets, b.offsets) and np.array_equal(a.vertices, b.vertices)

