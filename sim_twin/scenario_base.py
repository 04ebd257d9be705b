"""What every scenario is made of: the :class:`Scenario` base, obstacles, references, the registry.

The scenarios themselves are :mod:`sim_twin.scenarios` (and :mod:`sim_twin.scenarios_thesis`);
import that module to look one up, so that all are registered.
"""


from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import mujoco
import numpy as np

from onboard.contracts import messages as m
from robot_description import params as rd

OBSTACLE_PREFIX = "obstacle_"
TERRAIN_PREFIX = "terrain_"
OBSTACLE_HEIGHT = 1.0  # [m] taller than the robot's hop: it cannot hop over an obstacle
START_DROP = 0.05  # [m] the robot starts upright at rest with its foot this high above the ground
GOAL_TOLERANCE = 0.10  # [m] issue 4: "arrives within 0.10 m"
REF_SPEED = 0.25  # [m/s] cruise speed of the scenarios' own references (ASSUMPTION, hop-sized)
CUBIC_PEAK = 1.5  # a straight reference's peak speed, in cruise speeds (straight_reference)
WORLD_RGBA = [0.55, 0.35, 0.3, 1.0]


@dataclass(frozen=True)
class Obstacle:
    """A vertical prism over a convex polygon (counter-clockwise vertices, world xy, metres)."""

    vertices: tuple[tuple[float, float], ...]
    height: float = OBSTACLE_HEIGHT

    def polytope(self, offset: tuple[float, float] = (0.0, 0.0), velocity: tuple[float, float] = (0.0, 0.0)) -> m.Polytope:
        """Its H- and V-form, shifted by ``offset`` [m] (a moving obstacle's displacement), moving at ``velocity`` [m/s]."""
        ox, oy = offset
        vs = tuple((x + ox, y + oy) for x, y in self.vertices) if (ox or oy) else self.vertices
        a, b = [], []
        for i in range(len(vs)):
            (x0, y0), (x1, y1) = vs[i], vs[(i + 1) % len(vs)]
            nx, ny = y1 - y0, x0 - x1  # outward normal of a CCW edge
            n = math.hypot(nx, ny)
            a.append([nx / n, ny / n])
            b.append((nx * x0 + ny * y0) / n)
        if velocity[0] or velocity[1]:
            return m.Polytope(A=a, b=b, vertices=[list(v) for v in vs], velocity=(float(velocity[0]), float(velocity[1])))
        return m.Polytope(A=a, b=b, vertices=[list(v) for v in vs])


def _ccw_hull(points: np.ndarray) -> tuple[tuple[float, float], ...]:
    """Convex hull, counter-clockwise (monotone chain)."""
    pts = sorted(map(tuple, points.tolist()))

    def half(seq: list) -> list:
        out: list = []
        for p in seq:
            while len(out) >= 2 and (out[-1][0] - out[-2][0]) * (p[1] - out[-2][1]) - (out[-1][1] - out[-2][1]) * (p[0] - out[-2][0]) <= 0:
                out.pop()
            out.append(p)
        return out

    lower, upper = half(pts), half(pts[::-1])
    return tuple((float(x), float(y)) for x, y in lower[:-1] + upper[:-1])


def _box(cx: float, cy: float, hx: float, hy: float) -> Obstacle:
    return Obstacle(((cx - hx, cy - hy), (cx + hx, cy - hy), (cx + hx, cy + hy), (cx - hx, cy + hy)))


def _segment(t0: float, duration: float, points: list[list[float]]) -> m.BezierSegment:
    return m.BezierSegment(t0=t0, duration=duration, control_points=[[float(v) for v in p] for p in points])


def straight_reference(start: tuple[float, float], goal: tuple[float, float], t0: float = 0.0,
                       speed: float = REF_SPEED) -> list[m.BezierSegment]:
    """A cubic from ``start`` to ``goal`` leaving and arriving at rest (peak speed ``CUBIC_PEAK`` x ``speed``)."""
    dist = math.dist(start, goal)
    if dist < 1e-9:
        return [_segment(t0, 1.0, [list(start)])]
    dur = dist / speed
    return [_segment(t0, dur, [list(start), list(start), list(goal), list(goal)])]


def polyline_reference(points: list[tuple[float, float]], t0: float = 0.0, speed: float = REF_SPEED) -> list[m.BezierSegment]:
    """Constant-speed straight segments through ``points`` (degree-1 Beziers)."""
    segs, t = [], t0
    for a, b in zip(points[:-1], points[1:]):
        dur = math.dist(a, b) / speed
        segs.append(_segment(t, dur, [list(a), list(b)]))
        t += dur
    return segs


def sample_reference(segments: list[m.BezierSegment], t_s: float) -> tuple[float, float]:
    """Reference position at ``t_s`` [s]; before the first / after the last segment: its end point."""
    first, last = segments[0], segments[-1]
    if t_s <= first.t0:
        p = first.control_points[0]
        return p[0], p[1]
    if t_s >= last.t0 + last.duration:
        p = last.control_points[-1]
        return p[0], p[1]
    for seg in segments:
        if seg.t0 <= t_s < seg.t0 + seg.duration:
            pts = seg.control_points
            n = len(pts) - 1
            s = (t_s - seg.t0) / seg.duration
            x = y = 0.0
            for j, p in enumerate(pts):
                w = math.comb(n, j) * s**j * (1.0 - s) ** (n - j)
                x += w * p[0]
                y += w * p[1]
            return x, y
    p = last.control_points[-1]
    return p[0], p[1]


class Scenario:
    """Base scenario: flat floor, start at the origin, no goal, hop in place."""

    name: ClassVar[str] = ""
    description: ClassVar[str] = ""
    default_duration_s: ClassVar[float] = 20.0
    # geoms the camera's ground truth calls traversable: a name, or a prefix ending in "_"
    traversable: ClassVar[tuple[str, ...]] = ("floor", TERRAIN_PREFIX)

    def __init__(self, seed: int = 0, obstacles: int | None = None, cruise_speed: float = REF_SPEED) -> None:
        if not 0.0 < cruise_speed <= REF_SPEED:
            raise ValueError(f"cruise speed {cruise_speed} m/s outside (0, {REF_SPEED}]")
        self.seed = seed
        self.cruise_speed = cruise_speed  # [m/s] of the scenario's own reference (cruise_speed_for)
        # a slower robot is given the time its way takes (a scenario's setup may set it exactly)
        self.default_duration_s = type(self).default_duration_s * REF_SPEED / cruise_speed
        self.rng = np.random.default_rng(seed)
        self.start: tuple[float, float] = (0.0, 0.0)
        self.start_ground: float = 0.0  # ground height under the start [m]
        self.goal_xy: tuple[float, float] | None = None
        self.obstacles: list[Obstacle] = []
        self.keep_out: list[Obstacle] = []  # ground the robot must not hop on: in the ground-truth polytopes, no geom
        self.terrain: list[tuple[str, dict]] = []  # (name, MjsGeom keyword arguments)
        self.segments: list[m.BezierSegment] = []
        # [s] when the operator asks the low level for a flip; in a scenario that asks, the body turns
        # over in flight on purpose, so a tilt counts as a fall only on the ground (sim_twin.metrics)
        self.flip_requests_s: list[float] = []
        # obstacles that move during the run (indices into ``obstacles``): MuJoCo mocap bodies, displaced
        # by ``offsets`` [m] at ``velocities`` [m/s], both set by the scenario's before_step
        self.movers: list[int] = []
        self.setup(obstacles)
        self.offsets = np.zeros((len(self.obstacles), 2))
        self.velocities = np.zeros((len(self.obstacles), 2))
        self._mocap: list[int] | None = None  # mocap ids of the movers, once the model is known

    # --- to override ------------------------------------------------------------

    def setup(self, obstacles: int | None) -> None:
        """Decide everything (using ``self.rng``): start, goal, obstacles, terrain, reference."""
        self.segments = [_segment(0.0, 1.0, [list(self.start)])]

    def before_step(self, t_s: float, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        """Disturbances, called before every control tick."""

    # --- common -------------------------------------------------------------------

    def build(self, spec: mujoco.MjSpec) -> None:
        """Add terrain and obstacles to the robot's spec."""
        for name, kw in self.terrain:
            spec.worldbody.add_geom(name=TERRAIN_PREFIX + name, contype=1, conaffinity=2, group=0, condim=3,
                                    friction=[1.0, 0.005, 0.0001], rgba=[0.6, 0.6, 0.55, 1.0], **kw)
        for k, ob in enumerate(self.obstacles):
            verts = [[x, y, z] for x, y in ob.vertices for z in (0.0, ob.height)]
            mesh_name = f"{OBSTACLE_PREFIX}{k}_mesh"
            spec.add_mesh(name=mesh_name, uservert=np.array(verts, dtype=float).reshape(-1).tolist())
            # a mover hangs from a mocap body at the origin: moving that body moves it, with contacts
            parent = spec.worldbody.add_body(name=f"{OBSTACLE_PREFIX}{k}_body", mocap=True) if k in self.movers else spec.worldbody
            parent.add_geom(name=f"{OBSTACLE_PREFIX}{k}", type=mujoco.mjtGeom.mjGEOM_MESH, meshname=mesh_name,
                                    contype=1, conaffinity=2, group=0, rgba=WORLD_RGBA)

    def initialize(self, model: mujoco.MjModel, data: mujoco.MjData, robot: rd.RobotParams) -> None:
        """Upright at rest over the start, foot ``START_DROP`` above the ground."""
        mujoco.mj_resetData(model, data)
        adr = int(model.joint(rd.ROOT_JOINT).qposadr[0])
        data.qpos[adr:adr + 3] = [self.start[0], self.start[1], self.start_ground + robot.leg_length + START_DROP]
        data.qpos[adr + 3:adr + 7] = [1.0, 0.0, 0.0, 0.0]
        mujoco.mj_forward(model, data)

    def goal(self) -> m.Goal | None:
        if self.goal_xy is None:
            return None
        return m.Goal(position=list(self.goal_xy), tolerance=GOAL_TOLERANCE)

    def target(self) -> tuple[float, float]:
        """Where the robot should end: the goal, or the start for in-place scenarios."""
        return self.goal_xy if self.goal_xy is not None else self.start

    def world_summary(self) -> dict:
        """What was placed (for a run's report)."""
        return {"obstacles": len(self.obstacles), "goal": list(self.goal_xy) if self.goal_xy is not None else None}

    def reference(self, t_ref_ns: int = 0) -> m.ComReference:
        hold = self.goal_xy is None and len(self.segments) == 1 and len(self.segments[0].control_points) == 1
        return m.ComReference(t_ref_ns=t_ref_ns, segments=list(self.segments), hold=hold)

    def polytopes(self, stamp_ns: int = 0) -> m.PolytopeSet:
        """The ground-truth obstacles where they are now (movers displaced, with their velocity)."""
        if not self.movers:
            polys = [o.polytope() for o in self.obstacles]
        else:
            off, vel = self.offsets.tolist(), self.velocities.tolist()
            polys = [o.polytope(tuple(off[k]), tuple(vel[k])) for k, o in enumerate(self.obstacles)]
        polys += [o.polytope() for o in self.keep_out]  # still: the verges a robot must keep off
        return m.PolytopeSet(stamp_ns=stamp_ns, mode="obstacles", polytopes=polys, source="ground_truth")

    def move_obstacles(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        """Put the movers' mocap bodies where ``offsets`` says (the physics follows at the next step)."""
        if self._mocap is None:
            self._mocap = [int(model.body_mocapid[model.body(f"{OBSTACLE_PREFIX}{k}_body").id]) for k in self.movers]
        for k, mid in zip(self.movers, self._mocap):
            data.mocap_pos[mid, 0] = self.offsets[k, 0]
            data.mocap_pos[mid, 1] = self.offsets[k, 1]


SCENARIOS: dict[str, type[Scenario]] = {}


def register(cls: type[Scenario]) -> type[Scenario]:
    if not cls.name or cls.name in SCENARIOS:
        raise ValueError(f"scenario name {cls.name!r} empty or taken")
    SCENARIOS[cls.name] = cls
    return cls


def cruise_speed_for(robot: rd.RobotParams) -> float:
    """The scenarios' cruise speed for ``robot``: ``REF_SPEED``, or slower where the robot's
    sustained hopping speed (``hop_speed_max``) is under a straight reference's peak."""
    return min(REF_SPEED, robot.hop_speed_max / CUBIC_PEAK)


def make(name: str, seed: int = 0, obstacles: int | None = None, cruise_speed: float = REF_SPEED) -> Scenario:
    try:
        cls = SCENARIOS[name]
    except KeyError:
        raise ValueError(f"unknown scenario {name!r}; known: {', '.join(SCENARIOS)}") from None
    return cls(seed=seed, obstacles=obstacles, cruise_speed=cruise_speed)
