"""The onboard stack as the lockstep runner drives it: estimator, planner, low-level controller.

Each piece is a small adapter around the ``onboard`` class that the matching service runs, so the
lockstep run exercises the same code as the robot:

- estimator: ``kalman`` = :class:`onboard.estimation.estimator.StateEstimator` fed with the twin's sensor
  messages; ``truth`` = :class:`TruthEstimator`, the StateEstimate built from the twin's true state
  (no sensors, no filter; for isolating the controller from estimation, and for runs before an
  estimator exists);
- planner: ``scenario`` = the scenario's own CoM reference (straight line, square, Lissajous...);
  ``graph`` = :class:`onboard.high_level.planning.graph_planner.GraphPlanner` on the ground-truth obstacles at its
  replanning / refinement rates; ``auto`` = graph when the scenario has obstacles;
- controller: ``lowlevel`` = :class:`onboard.low_level.controller.LowLevelController` as
  :func:`robot_description.controller.build_controller` builds it; ``passive`` = no torque at all (the
  physics alone, for checks of the model).

Adapters expose ``feed(topic, msg, now_ns)`` (``now_ns``: when the message arrived) / ``estimate(now_ns, data)``, ``update(now_ns, state)`` and
``step(now_ns, state, reference, joints)``; the runner knows nothing else about them.
"""

from __future__ import annotations

import math
from typing import Protocol

import mujoco
import numpy as np

from onboard.contracts import messages as m
from onboard.contracts.params import SafetyLimits
from onboard.contracts.topics import TOPICS
from robot_description import identified
from robot_description import params as rd
from sim_twin.scenarios import Scenario

NS = 1_000_000_000
ESTIMATORS = ("kalman", "truth")
PLANNERS = ("auto", "scenario", "graph")
CONTROLLERS = ("lowlevel", "passive")
TRUTH_CONTACT_N = 1.0  # [N] foot load that the truth estimator calls contact
_ZERO_COV36 = [0.0] * 36


class Estimator(Protocol):
    name: str

    def feed(self, topic: str, msg: object, now_ns: int) -> None: ...

    def estimate(self, now_ns: int, data: mujoco.MjData) -> m.StateEstimate: ...

    def counters(self) -> dict[str, int]: ...


class TruthEstimator:
    """The StateEstimate from the twin's true state (``--estimator truth``).

    Position and velocity are the whole robot's CoM (torso pose plus the CoM offset of
    :class:`RobotParams`, which moves with the foot's compression); attitude and body rate are the
    torso's; contact is the foot's load over :data:`TRUTH_CONTACT_N`. Covariances are zero.
    """

    name = "truth"

    def __init__(self, model: mujoco.MjModel, robot: rd.RobotParams) -> None:
        root = model.joint(rd.ROOT_JOINT)
        self._qp, self._qv = int(root.qposadr[0]), int(root.dofadr[0])
        self._wheel_qv = [int(model.joint(n).dofadr[0]) for n in rd.WHEEL_JOINTS]
        self._foot_qp = int(model.joint(rd.FOOT_JOINT).qposadr[0])
        self._foot_qv = int(model.joint(rd.FOOT_JOINT).dofadr[0])
        self._touch = int(model.sensor(rd.FOOT_TOUCH_SENSOR).adr[0])
        self._c = robot.com_offset_body
        self._foot_share = robot.foot_mass / robot.total_mass
        self._seq = 0

    def feed(self, topic: str, msg: object, now_ns: int) -> None:
        """Sensor messages are not needed: the truth is read from the physics."""

    def counters(self) -> dict[str, int]:
        return {}

    def com(self, data: mujoco.MjData) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """Whole-robot CoM position and velocity in world [m, m/s]."""
        return self._com(data.qpos.tolist(), data.qvel.tolist())  # plain floats: numpy scalars are slow

    def _com(self, qp: list[float], qv: list[float]) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        i, j = self._qp, self._qv
        w, x, y, z = qp[i + 3], qp[i + 4], qp[i + 5], qp[i + 6]
        s = qp[self._foot_qp]
        sd = qv[self._foot_qv]
        cx, cy, cz = self._c
        cz += self._foot_share * s
        ox, oy, oz = qv[j + 3], qv[j + 4], qv[j + 5]
        # body-frame velocity of the CoM relative to the torso origin: w x c + foot share of s'
        rx = oy * cz - oz * cy
        ry = oz * cx - ox * cz
        rz = ox * cy - oy * cx + self._foot_share * sd
        r00, r01, r02 = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
        r10, r11, r12 = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
        r20, r21, r22 = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
        pos = (qp[i] + r00 * cx + r01 * cy + r02 * cz, qp[i + 1] + r10 * cx + r11 * cy + r12 * cz,
               qp[i + 2] + r20 * cx + r21 * cy + r22 * cz)
        vel = (qv[j] + r00 * rx + r01 * ry + r02 * rz, qv[j + 1] + r10 * rx + r11 * ry + r12 * rz,
               qv[j + 2] + r20 * rx + r21 * ry + r22 * rz)
        return pos, vel

    def estimate(self, now_ns: int, data: mujoco.MjData) -> m.StateEstimate:
        qp, qv = data.qpos.tolist(), data.qvel.tolist()
        i, j = self._qp, self._qv
        pos, vel = self._com(qp, qv)
        contact = bool(data.sensordata[self._touch] > TRUTH_CONTACT_N)
        wq = self._wheel_qv
        self._seq += 1
        return m.StateEstimate(
            stamp_ns=now_ns,
            seq=self._seq,
            position=list(pos),
            velocity=list(vel),
            quat=qp[i + 3:i + 7],
            omega=qv[j + 3:j + 6],
            wheel_vel=[qv[wq[0]], qv[wq[1]], qv[wq[2]]],
            foot_pos=qp[self._foot_qp],
            foot_vel=qv[self._foot_qv],
            contact=contact,
            phase="stance" if contact else "flight",
            pos_vel_cov=_ZERO_COV36,
            att_cov=[0.0, 0.0, 0.0],
            valid=True,
        )


class KalmanEstimator:
    """``onboard.estimation.estimator.StateEstimator`` fed with the twin's sensor messages (``--estimator kalman``)."""

    name = "kalman"

    def __init__(self, robot: rd.RobotParams, params: object | None = None) -> None:
        from onboard.estimation.estimator import StateEstimator
        from onboard.contracts.params import EstimatorParams

        params = params or EstimatorParams()
        self.est = StateEstimator(params, identified.apply(robot, identified.load(params.identified)) if params.identified else robot)
        self.feed = self.est.feed  # the loop calls the estimator's own entry point: a frame less a message

    def estimate(self, now_ns: int, data: mujoco.MjData) -> m.StateEstimate:
        return self.est.estimate(now_ns)

    def counters(self) -> dict[str, int]:
        return dict(getattr(self.est, "counters", {}))


def make_estimator(name: str, model: mujoco.MjModel, robot: rd.RobotParams, params: object | None = None) -> Estimator:
    if name == "truth":
        return TruthEstimator(model, robot)
    if name == "kalman":
        return KalmanEstimator(robot, params)
    raise ValueError(f"unknown estimator {name!r}; known: {', '.join(ESTIMATORS)}")


# --- planners -----------------------------------------------------------------------------


class ScenarioReference:
    """The scenario's own CoM reference, fixed for the run (``--planner scenario``)."""

    name = "scenario"

    def __init__(self, scenario: Scenario, t_ref_ns: int = 0) -> None:
        self.reference = scenario.reference(t_ref_ns)

    def update(self, now_ns: int, state: m.StateEstimate) -> m.ComReference | None:
        # a planner republishes its reference at the topic rate: the low level treats an old
        # stamp as a dead planner (SafetyLimits.reference_stale_s) and hops in place
        self.reference.stamp_ns = now_ns
        return self.reference

    def drain_contract_reports(self) -> list[m.ContractReport]:
        return []


class GraphPlannerPlug:
    """``onboard.high_level.planning.graph_planner.GraphPlanner`` on the scenario's ground-truth obstacles (``--planner graph``).

    Plans once at start, replans at ``replan_hz`` when the planner says it must (no path, world
    changed, robot off its path), refines at ``refine_hz`` when the planner offers refinement.
    Without a path it holds the robot in place (the planner's hold reference).
    """

    name = "graph"
    REPLAN_DEVIATION_M = 0.3  # [m] off the path by more than this: search again

    def __init__(self, scenario: Scenario, robot: rd.RobotParams, params: object | None = None) -> None:
        from onboard.high_level.planning.graph_planner import GraphPlanner
        from onboard.contracts.params import PlannerParams

        p = rd.planner_params_for(params or PlannerParams(), robot)
        radius = p.robot_radius if p.robot_radius > 0 else robot.footprint_radius
        self.planner = GraphPlanner(p, robot_radius=radius)
        self.planner.set_obstacles([np.array(poly.vertices, dtype=float) for poly in scenario.polytopes().polytopes])
        # obstacles that move: the ground truth where they are now, with their velocities, at the world topic's rate
        self.scenario = scenario
        self.world: m.PolytopeSet | None = None  # the last world handed to the planner (recorded by the runner)
        self._world_ns = int(NS / TOPICS["polytopes"].rate_hz) if scenario.movers else 0
        self._next_world = 0
        self._world_fn = None  # a world source in place of the ground truth (use_world)
        goal = scenario.target()
        self.planner.set_goal(goal, tolerance=scenario.goal().tolerance if scenario.goal() else 0.1)
        self._replan_ns = int(NS / p.replan_hz)
        self._refine_ns = int(NS / p.refine_hz) if p.refine_hz > 0 else 0
        self._next_replan = 0
        self._next_refine = 0
        self.reference: m.ComReference | None = None
        self.plans = 0
        self.no_path = 0

    def update(self, now_ns: int, state: m.StateEstimate) -> m.ComReference | None:
        pl = self.planner
        if self._world_ns and now_ns >= self._next_world:
            self._next_world = now_ns + self._world_ns
            self.world = world = self.scenario.polytopes(now_ns)
            pl.set_obstacles([np.array(p.vertices, dtype=float) for p in world.polytopes], [p.velocity for p in world.polytopes])
        if self._world_fn is not None:
            world = self._world_fn(now_ns, state)
            if world is not None:
                self.world = world
                pl.set_obstacles([np.array(p.vertices, dtype=float) for p in world.polytopes], [p.velocity for p in world.polytopes])
        replan_due = now_ns >= self._next_replan
        refine_due = self._refine_ns and now_ns >= self._next_refine and pl.path is not None and hasattr(pl, "refine")
        if not (replan_due or refine_due):  # most ticks: the reference republished
            if self.reference is not None:
                self.reference.stamp_ns = now_ns
            return self.reference
        pos = np.array(state.position[:2])
        vel = np.array(state.velocity[:2])
        if replan_due:
            self._next_replan = now_ns + self._replan_ns
            if self.reference is None or pl.needs_replan(pos, now_ns, self.REPLAN_DEVIATION_M):
                # no clock: planning takes no simulated time, and a densification cut short by the
                # wall clock would make a run differ from machine to machine; densify_max_rounds
                # bounds it instead
                ref = pl.plan(pos, vel, now_ns)
                self.plans += 1
                if ref is None:
                    self.no_path += 1
                    ref = pl.hold_reference(pos, now_ns)
                self.reference = ref
                self._next_refine = now_ns + self._refine_ns
                return self.reference
        if refine_due:
            self._next_refine = now_ns + self._refine_ns
            ref = pl.refine(pos, vel, now_ns)
            if ref is not None:
                self.reference = ref
        if self.reference is not None:  # republished at the topic rate (see ScenarioReference)
            self.reference.stamp_ns = now_ns
        return self.reference

    def use_world(self, world_fn) -> None:
        """Take the world from ``world_fn(now_ns, state) -> PolytopeSet | None`` (None: nothing new)
        instead of the scenario's ground truth; nothing is known before its first answer."""
        self._world_fn = world_fn
        self._world_ns = 0
        self.planner.set_obstacles([], [])

    def feed(self, topic: str, msg: object) -> None:
        """The low level's measured tube: a broken promise is reported and planned around."""
        if topic == "tube":
            self.planner.check_tube(msg, msg.stamp_ns)  # type: ignore[arg-type]

    def drain_contract_reports(self) -> list[m.ContractReport]:
        drain = getattr(self.planner, "drain_contract_reports", None)
        return list(drain()) if drain else []


def make_planner(name: str, scenario: Scenario, robot: rd.RobotParams, params: object | None = None):
    if name == "auto":
        name = "graph" if scenario.obstacles else "scenario"
    if name == "scenario":
        return ScenarioReference(scenario)
    if name == "graph":
        return GraphPlannerPlug(scenario, robot, params)
    raise ValueError(f"unknown planner {name!r}; known: {', '.join(PLANNERS)}")


# --- controllers --------------------------------------------------------------------------


class PassiveController:
    """No torque at all (``--controller passive``): the robot's physics alone."""

    name = "passive"

    def step(self, now_ns: int, state: m.StateEstimate, reference: m.ComReference | None,
             joints: m.JointSensors | None) -> m.TorqueCommand:
        return m.TorqueCommand(stamp_ns=now_ns, wheel_torque=[0.0, 0.0, 0.0], foot_torque=0.0, armed=False)

    def drain_phase_events(self) -> list[m.PhaseEvent]:
        return []

    def drain_safety_events(self) -> list[m.SafetyEvent]:
        return []


class LowLevelPlug:
    """The low level (``--controller lowlevel``), built from the MJCF and armed at start."""

    name = "lowlevel"

    def __init__(self, variant: str, safety: SafetyLimits, params: object | None = None, gmpc: object | None = None) -> None:
        from robot_description.controller import build_controller, build_gmpc_mid_level

        self.ctrl = build_controller(variant, params, safety)
        self.ctrl.request_arm()
        self.drain_phase_events = self.ctrl.drain_phase_events
        self.drain_safety_events = self.ctrl.drain_safety_events
        self.request_flip = self.ctrl.request_flip
        # mid_level = "geometric_mpc": the MPC solves every 1 / gmpc.rate_hz of simulated time on the
        # tick's estimate; its answer reaches the loop one solve period later, as from its own process
        self.mid_level = None
        if self.ctrl.p.mid_level == "geometric_mpc":
            self.mid_level = build_gmpc_mid_level(variant, gmpc, self.ctrl.p, safety)
            self._solve_ns = int(round(NS / self.mid_level.p.rate_hz))
        self._next_solve_ns = 0
        self._pending: m.MidLevelSetpoint | None = None
        self._setpoint: m.MidLevelSetpoint | None = None
        self._setpoint_due_ns = 0
        if self.mid_level is None:  # nothing to interleave: the loop calls the low level itself (a frame less a tick)
            self.step = self.ctrl.step  # type: ignore[method-assign]

    def step(self, now_ns: int, state: m.StateEstimate, reference: m.ComReference | None,
             joints: m.JointSensors | None = None) -> m.TorqueCommand:
        if self.mid_level is not None:
            if now_ns >= self._setpoint_due_ns and self._pending is not None:
                self._setpoint, self._pending = self._pending, None
            if now_ns >= self._next_solve_ns:
                self._next_solve_ns = now_ns + self._solve_ns
                self._setpoint_due_ns = now_ns + self._solve_ns
                self._pending = self.mid_level.step(now_ns, state, reference)
        return self.ctrl.step(now_ns, state, reference, joints, self._setpoint)

    def tube(self, stamp_ns: int) -> m.TrackingTube:
        return self.ctrl.tube(stamp_ns)


def make_controller(name: str, variant: str, safety: SafetyLimits, params: object | None = None, gmpc: object | None = None):
    if name == "passive":
        return PassiveController()
    if name == "lowlevel":
        return LowLevelPlug(variant, safety, params, gmpc)
    raise ValueError(f"unknown controller {name!r}; known: {', '.join(CONTROLLERS)}")


def tilt(quat: list[float] | tuple[float, ...]) -> float:
    """Angle [rad] between the body z axis and world up."""
    _, x, y, _ = quat
    c = 1.0 - 2.0 * (x * x + y * y)
    return math.acos(max(-1.0, min(1.0, c)))
