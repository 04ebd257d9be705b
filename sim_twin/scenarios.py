"""Scenarios, registered by name: the world, the start, the goal and the scenario's own reference.

A scenario is a small class (as a dm_control task): it adds its world to the robot's MJCF spec
(:meth:`Scenario.build`), places the robot (:meth:`Scenario.initialize`), may push it
(:meth:`Scenario.before_step`), and states the goal, the ground-truth obstacles (2D convex
polygons as :class:`onboard.contracts.messages.Polytope`, and the same shapes as MuJoCo geoms named
``obstacle_*``) and a CoM reference of its own (:meth:`Scenario.reference`) used when no planner
runs. Terrain geoms (``floor``, ``terrain_*``) are ground: the foot may touch them, nothing else
of the robot may. Every random choice comes from the scenario's seed.

Reference trajectories are Bezier segments in the horizontal plane on the time base of the run
(``t_ref_ns`` = start of the run); after the last segment the reference holds its end point.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from robot_description import params as rd
from sim_twin.scenario_base import (  # noqa: F401  (the scenarios' vocabulary, looked up here by their users)
    OBSTACLE_PREFIX, TERRAIN_PREFIX, OBSTACLE_HEIGHT, START_DROP, GOAL_TOLERANCE, REF_SPEED, CUBIC_PEAK,
    WORLD_RGBA, Obstacle, _ccw_hull, _box, _segment, straight_reference, polyline_reference, sample_reference,
    Scenario, SCENARIOS, register, cruise_speed_for, make,
)


@register
class HopInPlace(Scenario):
    name = "hop-in-place"
    description = "hop on the spot (thesis: 3000 stable hops)"
    default_duration_s = 30.0


@register
class Setpoint(Scenario):
    name = "setpoint"
    description = "go to a goal 2 m away (thesis Fig. 5.22)"
    default_duration_s = 20.0
    DISTANCE = 2.0

    def setup(self, obstacles: int | None) -> None:
        heading = float(self.rng.uniform(-math.pi, math.pi)) if self.seed else 0.0
        self.goal_xy = (self.DISTANCE * math.cos(heading), self.DISTANCE * math.sin(heading))
        self.segments = straight_reference(self.start, self.goal_xy, speed=self.cruise_speed)


@register
class Square(Scenario):
    name = "square"
    description = "two laps of a 1 m square (thesis Fig. 5.23)"
    default_duration_s = 40.0
    SIDE = 1.0
    LAPS = 2

    def setup(self, obstacles: int | None) -> None:
        s = self.SIDE
        corners = [(0.0, 0.0), (s, 0.0), (s, s), (0.0, s)]
        pts = corners * self.LAPS + [corners[0]]
        self.segments = polyline_reference(pts, speed=self.cruise_speed)
        self.default_duration_s = self.segments[-1].t0 + self.segments[-1].duration + 4.0


@register
class Lissajous(Scenario):
    name = "lissajous"
    description = "a 1:2 Lissajous figure, 1 m wide (thesis Fig. 5.12)"
    default_duration_s = 45.0
    AMPLITUDE = 0.5  # [m]
    PERIOD = 40.0  # [s] of the slow axis
    KNOTS = 80  # cubic Hermite pieces per period

    def setup(self, obstacles: int | None) -> None:
        a, w = self.AMPLITUDE, 2 * math.pi / self.PERIOD

        def p(t: float) -> tuple[float, float]:
            return a * math.sin(w * t), a * math.sin(2 * w * t)

        def v(t: float) -> tuple[float, float]:
            return a * w * math.cos(w * t), 2 * a * w * math.cos(2 * w * t)

        h = self.PERIOD / self.KNOTS
        segs = []
        for k in range(self.KNOTS):
            t0, t1 = k * h, (k + 1) * h
            p0, p1, v0, v1 = p(t0), p(t1), v(t0), v(t1)
            segs.append(_segment(t0, h, [p0, (p0[0] + v0[0] * h / 3, p0[1] + v0[1] * h / 3),
                                         (p1[0] - v1[0] * h / 3, p1[1] - v1[1] * h / 3), p1]))
        self.segments = segs
        self.default_duration_s = self.PERIOD + 5.0


@register
class Push(Scenario):
    name = "push"
    description = "hop in place under lateral impulses"
    default_duration_s = 30.0
    IMPULSE = 2.0  # [N s] per push (0.34 m/s on the indoor robot)
    PUSH_TIME = 0.05  # [s] each push lasts this long
    FIRST = 5.0  # [s] first push
    EVERY = 5.0  # [s] then every

    def setup(self, obstacles: int | None) -> None:
        super().setup(obstacles)
        n = 64
        self.push_angles = self.rng.uniform(-math.pi, math.pi, n).tolist()
        self.pushes_applied = 0

    def before_step(self, t_s: float, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        torso = model.body(rd.TORSO).id
        k = int((t_s - self.FIRST) // self.EVERY)
        active = t_s >= self.FIRST and (t_s - self.FIRST - k * self.EVERY) < self.PUSH_TIME
        if active:
            f = self.IMPULSE / self.PUSH_TIME
            ang = self.push_angles[k % len(self.push_angles)]
            data.xfrc_applied[torso, :3] = [f * math.cos(ang), f * math.sin(ang), 0.0]
            self.pushes_applied = max(self.pushes_applied, k + 1)
        else:
            data.xfrc_applied[torso, :3] = 0.0


@register
class Flip(Scenario):
    name = "flip"
    description = "hop in place and flip twice: a full turn about a horizontal axis in one flight (thesis Fig. 5.13)"
    default_duration_s = 14.0
    FIRST = 3.0  # [s] the first request, then a random share of a hop later (the hop's phase varies)
    EVERY = 5.0  # [s] the second request after the first
    PHASE_SPREAD = 0.6  # [s] about one hop cycle

    def setup(self, obstacles: int | None) -> None:
        super().setup(obstacles)
        first = self.FIRST + float(self.rng.uniform(0.0, self.PHASE_SPREAD))
        self.flip_requests_s = [first, first + self.EVERY]


@register
class Shove(Push):
    name = "shove"
    description = "hop in place under lateral impulses three times the push's (1 m/s on the indoor robot)"
    IMPULSE = 6.0  # [N s] per push


@register
class Step(Scenario):
    name = "step"
    description = "hop up a 3.8 cm step to a goal on it"
    default_duration_s = 20.0
    HEIGHT = 0.038
    EDGE = 0.6  # [m] step edge from the start

    def setup(self, obstacles: int | None) -> None:
        h = self.HEIGHT
        self.terrain = [("step", dict(type=mujoco.mjtGeom.mjGEOM_BOX, size=[2.0, 2.0, h / 2],
                                      pos=[self.EDGE + 2.0, 0.0, h / 2]))]
        self.goal_xy = (self.EDGE + 0.9, 0.0)
        self.segments = straight_reference(self.start, self.goal_xy, speed=self.cruise_speed)


@register
class Ramp(Scenario):
    name = "ramp"
    description = "hop down a 20 degree ramp from a platform to a goal on the floor"
    default_duration_s = 25.0
    ANGLE = math.radians(20.0)
    LENGTH = 1.0  # [m] horizontal run of the ramp
    TOP = 0.5  # [m] ramp top edge from the start
    THICK = 0.2  # [m] ramp slab thickness

    def setup(self, obstacles: int | None) -> None:
        a, L = self.ANGLE, self.LENGTH
        top = L * math.tan(a)
        self.start_ground = top
        slab = L / math.cos(a)
        # Slab rotated about y by +a: its top face runs from (TOP, top) down to (TOP + L, 0).
        mid = np.array([self.TOP + L / 2, 0.0, top / 2]) - np.array([math.sin(a), 0.0, math.cos(a)]) * self.THICK / 2
        self.terrain = [
            ("platform", dict(type=mujoco.mjtGeom.mjGEOM_BOX, size=[1.0, 1.5, top / 2], pos=[self.TOP - 1.0, 0.0, top / 2])),
            ("ramp", dict(type=mujoco.mjtGeom.mjGEOM_BOX, size=[slab / 2, 1.5, self.THICK / 2], pos=mid.tolist(),
                          quat=[math.cos(a / 2), 0.0, math.sin(a / 2), 0.0])),
        ]
        self.goal_xy = (self.TOP + L + 0.8, 0.0)
        self.segments = straight_reference(self.start, self.goal_xy, speed=self.cruise_speed)


@register
class BlindSide(Scenario):
    """The goal lies to the camera's side (it looks along +x at the start), behind a post it
    cannot see from there: what the first plans cross is ground not yet seen (issue 16's
    collision: the robot moved sideways into an unseen tree)."""

    name = "blind-side"
    description = "a goal 3 m to the camera's side, behind a post it cannot see from the start"
    default_duration_s = 30.0
    POST_CENTRE = (0.0, -1.5)
    POST_RADIUS = 0.3  # [m] circumradius of the hexagonal post
    GOAL = (0.0, -3.0)

    def setup(self, obstacles: int | None) -> None:
        (cx, cy), r = self.POST_CENTRE, self.POST_RADIUS
        corners = tuple((cx + r * math.cos(a), cy + r * math.sin(a)) for a in np.arange(6) * (math.pi / 3))
        self.obstacles = [Obstacle(corners)]
        self.goal_xy = self.GOAL
        self.segments = straight_reference(self.start, self.goal_xy, speed=self.cruise_speed)


@register
class Forest(Scenario):
    name = "forest"
    description = ("random convex obstacles between the start and a goal beyond them (--obstacles N; a count "
                   "the field cannot hold at the minimum gap grows the field, and the goal moves beyond it)")
    default_duration_s = 60.0
    DEFAULT_COUNT = 10
    REGION = ((0.8, 5.0), (-1.5, 1.5))  # [m] x and y range of obstacle centres
    BLOCKER_X = (2.0, 4.0)  # [m] x range of the first obstacle, placed on the start-goal line
    RADIUS = (0.15, 0.35)  # [m] circumradius range
    GAP = 0.45  # [m] minimum free gap between obstacles (the robot is 0.26 m wide)
    GOAL_BEYOND = 1.0  # [m] the goal stands this far past the field's far edge, on the x axis
    PLACEMENT_TRIES = 20000  # random centres tried in one field before it grows
    FIELD_GROWTH = 1.1  # each growth stretches the field's length and width by this
    FIELD_GROWTHS_MAX = 20
    COUNT_MAX = 200  # a forest, not a wall: the field holds this many within its growths

    def setup(self, obstacles: int | None) -> None:
        count = self.DEFAULT_COUNT if obstacles is None else obstacles
        if not 0 <= count <= self.COUNT_MAX:
            raise ValueError(f"forest obstacle count must be within 0..{self.COUNT_MAX}, got {count}")
        region = self.REGION
        for _ in range(self.FIELD_GROWTHS_MAX + 1):
            placed = self._place(count, region)
            if placed is not None:
                break
            (x0, x1), (y0, y1) = region
            region = ((x0, x0 + (x1 - x0) * self.FIELD_GROWTH), (y0 * self.FIELD_GROWTH, y1 * self.FIELD_GROWTH))
        else:
            raise ValueError(f"cannot place {count} obstacles with {self.GAP} m gaps even in a field "
                             f"{self.FIELD_GROWTH}^{self.FIELD_GROWTHS_MAX} times the default")
        self.region = region
        self.obstacles = placed
        self.goal_xy = (round(region[0][1] + self.GOAL_BEYOND, 6), 0.0)
        # the default duration covers the default walk; a grown field's longer walk takes longer
        self.default_duration_s = self.default_duration_s * self.goal_xy[0] / (self.REGION[0][1] + self.GOAL_BEYOND)
        self.segments = straight_reference(self.start, self.goal_xy, speed=self.cruise_speed)

    def _place(self, count: int, region: tuple[tuple[float, float], tuple[float, float]]) -> list[Obstacle] | None:
        """``count`` obstacles in ``region`` at least ``GAP`` apart, or None when they do not fit."""
        placed: list[tuple[float, float, float]] = []
        out: list[Obstacle] = []
        (x0, x1), (y0, y1) = region
        tries = 0
        while len(placed) < count:
            tries += 1
            if tries > self.PLACEMENT_TRIES:
                return None
            r = float(self.rng.uniform(*self.RADIUS))
            if not placed:  # the first one stands on the straight line to the goal: a path must go around
                cx, cy = float(self.rng.uniform(*self.BLOCKER_X)), float(self.rng.uniform(-0.05, 0.05))
            else:
                cx, cy = float(self.rng.uniform(x0, x1)), float(self.rng.uniform(y0, y1))
            if any(math.dist((cx, cy), (px, py)) < r + pr + self.GAP for px, py, pr in placed):
                continue
            placed.append((cx, cy, r))
            # 3-6 vertices on the circumcircle, evenly spaced with jitter: no slivers
            nv = int(self.rng.integers(3, 7)) if len(placed) > 1 else 6  # the blocker: a fat hexagon
            ang = (np.arange(nv) + self.rng.uniform(-0.3, 0.3, nv)) * (2 * math.pi / nv) + self.rng.uniform(0, 2 * math.pi)
            pts = np.stack([cx + r * np.cos(ang), cy + r * np.sin(ang)], axis=1)
            out.append(Obstacle(_ccw_hull(pts)))
        return out

    def world_summary(self) -> dict:
        (x0, x1), (y0, y1) = self.region
        area = (x1 - x0) * (y1 - y0)
        return {**super().world_summary(), "field_m": [[round(x0, 3), round(x1, 3)], [round(y0, 3), round(y1, 3)]], "min_gap_m": self.GAP,
                "obstacles_per_m2": round(len(self.obstacles) / area, 3)}


@register
class ForestThesis(Forest):
    """Thesis Fig. 7.5's count: 500 random convex obstacles (the forest's shapes and 0.45 m gaps,
    in the field that holds them) between the start and a goal beyond them."""

    name = "forest-500"
    description = "thesis Fig. 7.5's scale: 500 random convex obstacles between the start and a goal beyond them"
    DEFAULT_COUNT = 500
    COUNT_MAX = 500
    FIELD_GROWTHS_MAX = 40


@register
class Maze(Scenario):
    name = "maze"
    description = "three walls with one random gap each between the start and the goal, inside a corridor"
    default_duration_s = 90.0
    WALL_X = (1.2, 2.4, 3.6)  # [m]
    HALF_WIDTH = 2.0  # [m] corridor half width
    GAP = 0.8  # [m] gap width
    THICK = 0.1  # [m] wall thickness

    def setup(self, obstacles: int | None) -> None:
        w, t = self.HALF_WIDTH, self.THICK / 2
        walls = [_box(2.15, w + t, 2.65, t), _box(2.15, -w - t, 2.65, t), _box(-0.5 - t, 0.0, t, w + 2 * t),
                 _box(4.8 + t, 0.0, t, w + 2 * t)]
        for x in self.WALL_X:
            gy = float(self.rng.uniform(-w + self.GAP, w - self.GAP))
            lo, hi = gy - self.GAP / 2, gy + self.GAP / 2
            walls.append(_box(x, (-w + lo) / 2, t, (lo + w) / 2))
            walls.append(_box(x, (hi + w) / 2, t, (w - hi) / 2))
        self.obstacles = walls
        self.goal_xy = (4.3, float(self.rng.uniform(-w + 0.5, w - 0.5)))
        self.segments = straight_reference(self.start, self.goal_xy, speed=self.cruise_speed)


# --- obstacles that move during the run (issue 28: thesis 7.2, people kick the obstacles around) ---------------


def _centre_radius(ob: Obstacle) -> tuple[float, float, float]:
    """Centroid of the vertices and the circumradius about it [m]."""
    vs = np.array(ob.vertices)
    c = vs.mean(axis=0)
    return float(c[0]), float(c[1]), float(np.max(np.hypot(*(vs - c).T)))


def _segment_distance(p: tuple[float, float], a: tuple[float, float], b: tuple[float, float]) -> float:
    """Distance from point ``p`` to the segment ``a``-``b`` [m]."""
    ax, ay = a
    dx, dy = b[0] - ax, b[1] - ay
    L2 = dx * dx + dy * dy
    s = 0.0 if L2 == 0.0 else min(1.0, max(0.0, ((p[0] - ax) * dx + (p[1] - ay) * dy) / L2))
    return math.hypot(p[0] - ax - s * dx, p[1] - ay - s * dy)


class _Movers:
    """What the moving scenarios share: the robot's true horizontal position, read in before_step."""

    def __init__(self) -> None:
        self._root: int | None = None

    def robot_xy(self, model: mujoco.MjModel, data: mujoco.MjData) -> tuple[float, float]:
        if self._root is None:
            self._root = int(model.joint(rd.ROOT_JOINT).qposadr[0])
        return float(data.qpos[self._root]), float(data.qpos[self._root + 1])


@register
class Kicked(Forest):
    """A forest whose obstacles people kick around: at random times (every ``KICK_EVERY`` s on
    average) one is shoved up to ``KICK_MAX`` m in a random direction within ``KICK_S`` s (a
    sudden jump, far faster than the robot hops). As a person would, the kicker never kicks an
    obstacle into the robot (its sweep keeps ``KICK_CLEAR`` from the robot's true position at the
    kick), onto the goal, out of the field or onto another obstacle; such a kick is skipped."""

    name = "kicked"
    description = "a forest whose obstacles are kicked at random times: sudden jumps of up to 0.5 m"
    DEFAULT_COUNT = 8
    KICK_FIRST = 2.0  # [s] no kick before
    KICK_EVERY = 2.0  # [s] mean time between kicks (exponential)
    KICK_MIN, KICK_MAX = 0.2, 0.5  # [m] displacement range
    KICK_S = 0.2  # [s] a kick's displacement takes this long (up to 2.5 m/s)
    KICK_CLEAR = 0.5  # [m] a kick's sweep keeps this far from the robot's centre, beyond the obstacle's circumradius
    GOAL_CLEAR = 0.5  # [m] and from the goal
    OBSTACLE_GAP = 0.1  # [m] a kicked obstacle lands at least this far from the others (circumcircles)
    FIELD_SLACK = 0.5  # [m] a kicked obstacle's centre stays within the field grown by this
    KICKS = 256  # drawn ahead (more than a run uses)
    KICK_TRIES = 8  # (obstacle, direction, distance) drawn per kick; the first the kicker may make is made

    def setup(self, obstacles: int | None) -> None:
        super().setup(obstacles)
        self.movers = list(range(len(self.obstacles)))
        n = max(len(self.obstacles), 1)
        rng = self.rng
        self.kick_times = (self.KICK_FIRST + np.cumsum(rng.exponential(self.KICK_EVERY, self.KICKS))).tolist()
        shape = (self.KICKS, self.KICK_TRIES)
        self.kick_which = rng.integers(0, n, shape).tolist()
        self.kick_angle = rng.uniform(-math.pi, math.pi, shape).tolist()
        self.kick_dist = rng.uniform(self.KICK_MIN, self.KICK_MAX, shape).tolist()
        self.geometry = [_centre_radius(o) for o in self.obstacles]
        self.kicks_applied = self.kicks_skipped = 0
        self._next = 0
        self._active: dict[int, tuple[float, float, float, float, float]] = {}  # k -> (t0, from x, y, velocity x, y)
        self._robot = _Movers()

    def _admissible(self, k: int, dx: float, dy: float, robot: tuple[float, float]) -> bool:
        cx, cy, r = self.geometry[k]
        ox, oy = self.offsets[k]
        a, b = (cx + ox, cy + oy), (cx + ox + dx, cy + oy + dy)
        (x0, x1), (y0, y1) = self.region
        e = self.FIELD_SLACK
        if not (x0 - e <= b[0] <= x1 + e and y0 - e <= b[1] <= y1 + e):
            return False
        if _segment_distance(robot, a, b) < r + self.KICK_CLEAR:
            return False
        if self.goal_xy is not None and math.dist(b, self.goal_xy) < r + self.GOAL_CLEAR:
            return False
        for j, (qx, qy, rj) in enumerate(self.geometry):
            if j != k and math.dist(b, (qx + self.offsets[j, 0], qy + self.offsets[j, 1])) < r + rj + self.OBSTACLE_GAP:
                return False
        return True

    def before_step(self, t_s: float, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        if not self.obstacles:
            return
        while self._next < len(self.kick_times) and t_s >= self.kick_times[self._next]:
            i = self._next
            self._next += 1
            robot = self._robot.robot_xy(model, data)
            for k, d, ang in zip(self.kick_which[i], self.kick_dist[i], self.kick_angle[i]):
                dx, dy = d * math.cos(ang), d * math.sin(ang)
                if k not in self._active and self._admissible(k, dx, dy, robot):
                    self.kicks_applied += 1
                    self._active[k] = (t_s, float(self.offsets[k, 0]), float(self.offsets[k, 1]),
                                       dx / self.KICK_S, dy / self.KICK_S)
                    break
            else:
                self.kicks_skipped += 1
        for k, (t0, fx, fy, vx, vy) in list(self._active.items()):
            s = min(t_s - t0, self.KICK_S)
            self.offsets[k] = (fx + vx * s, fy + vy * s)
            if t_s - t0 >= self.KICK_S:
                del self._active[k]
                self.velocities[k] = (0.0, 0.0)
            else:
                self.velocities[k] = (vx, vy)
        self.move_obstacles(model, data)

    def world_summary(self) -> dict:
        return {**super().world_summary(), "kicks": self.kicks_applied, "kicks_skipped": self.kicks_skipped}


@register
class Sliding(Forest):
    """A forest whose obstacles slide back and forth, each along its own random line, ``AMPLITUDE``
    m either side of where it was placed, at a constant speed of up to ``SPEED`` m/s (at least half
    of it), turning at the ends; a line that would bring an obstacle within ``CLEAR`` of the start or
    the goal is drawn again (or the obstacle stays put)."""

    name = "sliding"
    description = "a forest whose obstacles slide back and forth at up to 0.25 m/s (slower than the robot hops)"
    DEFAULT_COUNT = 6
    GAP = 0.6  # [m] wider gaps than the static forest's: the obstacles sweep across them
    SPEED = 0.25  # [m/s] the fastest an obstacle slides
    AMPLITUDE = (0.3, 0.7)  # [m] range of the slide either side of its centre
    CLEAR = 0.6  # [m] a slide keeps this far from the start and the goal, beyond its circumradius
    LINE_TRIES = 50

    def setup(self, obstacles: int | None) -> None:
        super().setup(obstacles)
        rng = self.rng
        self.slides: list[tuple[float, float, float, float, float]] = []  # (axis x, y, amplitude, speed, phase [m])
        for ob in self.obstacles:
            cx, cy, r = _centre_radius(ob)
            speed = float(rng.uniform(0.5, 1.0)) * self.SPEED
            slide = (1.0, 0.0, 0.0, 0.0, 0.0)
            for _ in range(self.LINE_TRIES):
                ang, amp = float(rng.uniform(-math.pi, math.pi)), float(rng.uniform(*self.AMPLITUDE))
                ax, ay = math.cos(ang), math.sin(ang)
                a, b = (cx - amp * ax, cy - amp * ay), (cx + amp * ax, cy + amp * ay)
                if all(_segment_distance(p, a, b) >= r + self.CLEAR for p in (self.start, self.target())):
                    slide = (ax, ay, amp, speed, float(rng.uniform(0.0, 4.0 * amp)))
                    break
            self.slides.append(slide)
        self.movers = [k for k, s in enumerate(self.slides) if s[2] > 0.0]

    def before_step(self, t_s: float, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        for k in self.movers:
            ax, ay, amp, speed, phase = self.slides[k]
            # a triangle wave over one period 4 amp: from -amp up to +amp and back
            u = (speed * t_s + phase) % (4.0 * amp)
            s, ds = (u - amp, speed) if u < 2.0 * amp else (3.0 * amp - u, -speed)
            self.offsets[k] = (ax * s, ay * s)
            self.velocities[k] = (ax * ds, ay * ds)
        self.move_obstacles(model, data)

    def world_summary(self) -> dict:
        speeds = [s[3] for k, s in enumerate(self.slides) if k in self.movers]
        return {**super().world_summary(), "sliding": len(self.movers), "slide_speed_max": round(max(speeds, default=0.0), 3)}


@register
class SlidingFast(Sliding):
    name = "sliding-fast"
    description = "the sliding forest at up to 0.5 m/s: faster than the robot hops (0.375 m/s indoors)"
    SPEED = 0.5


@register
class Crossing(Scenario):
    """Someone walks across the robot's way: the goal lies ``DISTANCE`` m ahead; a walker (a
    hexagon ``WALKER_RADIUS`` m round) stands ``SIDE`` m to one side of the straight line and,
    when the robot comes within a lead of where it will cross, walks across at ``SPEED`` m/s
    (no faster than the robot hops), timed to reach the line as a robot going straight at cruise
    speed would, and on until it is ``SIDE`` m beyond it, where it stops."""

    name = "crossing"
    description = "a person walks across the robot's straight way to a goal 5 m ahead, timed to meet it"
    default_duration_s = 40.0
    DISTANCE = 5.0  # [m]
    CROSS_X = (1.5, 3.5)  # [m] range of where the walker crosses the line
    SIDE = 2.0  # [m] the walker starts (and ends) this far from the line
    SLANT = math.radians(20.0)  # its way is at most this far from square to the line
    SPEED = 0.3  # [m/s] walking speed
    WALKER_RADIUS = 0.2  # [m]
    TIMING = (0.8, 1.2)  # the robot's speed the walker times itself to, in cruise speeds

    def setup(self, obstacles: int | None) -> None:
        rng = self.rng
        self.goal_xy = (self.DISTANCE, 0.0)
        self.segments = straight_reference(self.start, self.goal_xy, speed=self.cruise_speed)
        xc = float(rng.uniform(*self.CROSS_X))
        side = 1.0 if rng.uniform() < 0.5 else -1.0
        slant = float(rng.uniform(-self.SLANT, self.SLANT))
        dx, dy = math.sin(slant) * side, -math.cos(slant) * side  # walking direction, toward the line
        half = self.SIDE / math.cos(slant)  # path length to the line
        sx, sy = xc - dx * half, -dy * half
        r = self.WALKER_RADIUS
        ang = np.arange(6) * (math.pi / 3)
        self.obstacles = [Obstacle(tuple((sx + r * math.cos(a), sy + r * math.sin(a)) for a in ang))]
        self.movers = [0]
        self.walk = (dx * self.SPEED, dy * self.SPEED, 2.0 * half / self.SPEED)  # velocity, walking time
        lead = self.cruise_speed * float(rng.uniform(*self.TIMING)) * half / self.SPEED
        self.trigger_x = xc - lead  # the walker sets off when the robot's x passes this
        self.walk_start: float | None = None
        self._robot = _Movers()

    def before_step(self, t_s: float, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        if self.walk_start is None and self._robot.robot_xy(model, data)[0] >= self.trigger_x:
            self.walk_start = t_s
        if self.walk_start is not None:
            vx, vy, dur = self.walk
            s = min(t_s - self.walk_start, dur)
            self.offsets[0] = (vx * s, vy * s)
            self.velocities[0] = (vx, vy) if t_s - self.walk_start < dur else (0.0, 0.0)
        self.move_obstacles(model, data)

    def world_summary(self) -> dict:
        return {**super().world_summary(), "walk_start_s": None if self.walk_start is None else round(self.walk_start, 3)}


@register
class Sidewalk(Scenario):
    """Outdoors (thesis 8.2): a paved sidewalk between kerbs and grass, obstacles standing on it."""

    name = "sidewalk"
    description = ("a sidewalk with kerbs between grass verges to a goal at its end, random posts and bins on it "
                   "(--obstacles N); the grass is not to be hopped on")
    default_duration_s = 60.0
    traversable = (TERRAIN_PREFIX + "sidewalk",)
    LENGTH = 7.0  # [m] of sidewalk ahead of the start
    HALF_WIDTH = 0.9  # [m] paved half width
    SLAB = 0.01  # [m] the paving's thickness above the grass
    KERB = (0.08, 0.06)  # [m] kerb height above the paving, width
    GRASS_RGBA = [0.30, 0.52, 0.18, 1.0]
    PAVING_RGBA = [0.66, 0.64, 0.60, 1.0]
    KERB_RGBA = [0.80, 0.79, 0.76, 1.0]
    DEFAULT_COUNT = 3
    RADIUS = (0.12, 0.22)  # [m] circumradius of a post or bin
    X_RANGE = (1.2, 5.5)  # [m] obstacle centres along the sidewalk
    GAP = 0.45  # [m] free gap kept beside every obstacle (the robot is 0.26 m wide)
    GOAL_BEFORE_END = 0.5  # [m]
    VERGE = 3.0  # [m] of grass kept out of beside the kerbs
    END_GRASS = 1.0  # [m] of grass kept out of past either end of the paving

    def setup(self, obstacles: int | None) -> None:
        count = self.DEFAULT_COUNT if obstacles is None else obstacles
        if not 0 <= count <= 10:
            raise ValueError(f"sidewalk obstacle count must be within 0..10, got {count}")
        w, length, slab = self.HALF_WIDTH, self.LENGTH, self.SLAB
        x0, x1 = -1.0, length
        kh, kw = self.KERB
        self.start_ground = slab
        self.terrain = [("sidewalk", {"type": mujoco.mjtGeom.mjGEOM_BOX, "size": [(x1 - x0) / 2, w, slab / 2],
                                      "pos": [(x0 + x1) / 2, 0.0, slab / 2]})]
        self.colors = {"sidewalk": self.PAVING_RGBA}
        for side, sign in (("left", 1.0), ("right", -1.0)):
            self.terrain.append((f"kerb_{side}", {"type": mujoco.mjtGeom.mjGEOM_BOX, "size": [(x1 - x0) / 2, kw / 2, (slab + kh) / 2],
                                                  "pos": [(x0 + x1) / 2, sign * (w + kw / 2), (slab + kh) / 2]}))
            self.colors[f"kerb_{side}"] = self.KERB_RGBA
        # the grass round the paving: keep out (as far as the planner is concerned, walls). The verges
        # beyond the kerbs, and the grass past either end of the paving: with open ends, a planner that
        # found no way between the posts went round the verges across the grass behind the start.
        a, b, wide = x0 - self.END_GRASS, x1 + self.END_GRASS, w + self.VERGE
        for x_lo, y_lo, x_hi, y_hi in ((a, w, b, wide), (a, -wide, b, -w), (a, -w, x0, w), (x1, -w, b, w)):
            self.keep_out.append(Obstacle(_ccw_hull(np.array([[x_lo, y_lo], [x_hi, y_lo], [x_hi, y_hi], [x_lo, y_hi]]))))
        placed: list[tuple[float, float, float]] = []
        tries = 0
        while len(placed) < count:
            tries += 1
            if tries > 20000:
                raise ValueError(f"cannot place {count} obstacles on the sidewalk")
            r = float(self.rng.uniform(*self.RADIUS))
            cx = float(self.rng.uniform(*self.X_RANGE))
            cy = float(self.rng.uniform(-w + r, w - r))
            # a way past on one side at least, and room between obstacles
            if w - (cy + r) < self.GAP and (cy - r) + w < self.GAP:
                continue
            if any(math.dist((cx, cy), (px, py)) < r + pr + self.GAP for px, py, pr in placed):
                continue
            placed.append((cx, cy, r))
            nv = int(self.rng.integers(4, 9))
            ang = np.arange(nv) * (2 * math.pi / nv) + self.rng.uniform(0, 2 * math.pi)
            self.obstacles.append(Obstacle(_ccw_hull(np.stack([cx + r * np.cos(ang), cy + r * np.sin(ang)], axis=1))))
        self.goal_xy = (length - self.GOAL_BEFORE_END, 0.0)
        self.segments = straight_reference(self.start, self.goal_xy, speed=self.cruise_speed)

    def build(self, spec: mujoco.MjSpec) -> None:
        spec.geom("floor").rgba = self.GRASS_RGBA
        super().build(spec)
        for name, rgba in self.colors.items():  # the base gives terrain one colour; paving and kerbs have their own
            spec.geom(TERRAIN_PREFIX + name).rgba = rgba

    def world_summary(self) -> dict:
        return {**super().world_summary(), "sidewalk_half_width_m": self.HALF_WIDTH, "kerb_m": list(self.KERB),
                "widest_way_m": round(widest_way(self.obstacles, -self.HALF_WIDTH, self.HALF_WIDTH), 3)}


def _polygon_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Distance between two disjoint convex polygons ``(N, 2)`` [m]: the nearest vertex-to-edge pair."""
    def one_way(p: np.ndarray, q: np.ndarray) -> float:
        return min(_segment_distance(tuple(v), tuple(q[i]), tuple(q[(i + 1) % len(q)])) for v in p for i in range(len(q)))
    return min(one_way(a, b), one_way(b, a))


def widest_way(obstacles: list[Obstacle], y_low: float, y_high: float) -> float:
    """The width [m] of the widest way along a strip between ``y_low`` and ``y_high`` past disjoint
    convex ``obstacles``: a disc that wide passes iff no chain of obstacles, each nearer than that to
    the next, joins one side to the other. The widest way is then the minimax chain (Dijkstra with
    the largest link for a path's length). What the scenario promises, and what a run's miss is
    weighed against: the planner needs twice its robot radius plus its tube."""
    polys = [np.asarray(ob.vertices, dtype=float) for ob in obstacles]
    low, high = len(polys), len(polys) + 1

    def gap(i: int, j: int) -> float:
        if {i, j} == {low, high}:
            return y_high - y_low
        if i in (low, high):
            i, j = j, i
        if j == low:
            return float(polys[i][:, 1].min() - y_low)
        if j == high:
            return float(y_high - polys[i][:, 1].max())
        return _polygon_distance(polys[i], polys[j])

    best = {low: 0.0}
    todo = set(range(len(polys) + 2))
    while todo:
        node = min(todo, key=lambda k: best.get(k, math.inf))
        if node == high:
            return best[high]
        todo.discard(node)
        for other in todo:
            width = max(best[node], gap(node, other))
            if width < best.get(other, math.inf):
                best[other] = width
    return best[high]


# the thesis's own terrains and worlds at its scale (issue 29), registered beside these
from sim_twin import scenarios_thesis  # noqa: E402,F401
