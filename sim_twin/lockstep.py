"""Lockstep runner: physics and the onboard stack stepped together on simulated time.

One control tick (1 ms by default) is, in order:

1. the scenario's disturbances (``Scenario.before_step``);
2. the torque command computed on the previous tick goes to the motors through
   :class:`sim_twin.actuation.Actuation` (staleness, SafetyLimits clamp, speed-torque curve), so the
   stack always has one tick of computation delay, as on the robot;
3. ``control_period / timestep`` physics steps (two at 0.5 ms);
4. the sensors capture what is due and deliver what their latency releases; the estimator eats
   them and produces the StateEstimate at the new time;
5. the planner (or the scenario's reference) updates the ComReference at its own rate;
6. the low level computes the next TorqueCommand.

The run is deterministic for a seed: the sensor noise, the scenario and every other random choice
derive from it and nothing reads a wall clock except the realtime-factor figure. The metrics are
computed from the physics (true CoM, true contacts, true tilt), never from the stack's belief:

- ``hops``: completed flights (lift-off then touchdown of the foot, airborne >= ``MIN_FLIGHT_S``);
- ``falls``: tilt over ``SafetyLimits.tilt_max``, or any robot geom other than the foot touching the
  ground (floor or terrain); the run stops at the first fall unless told otherwise;
- ``collisions``: contact episodes between the robot and an obstacle;
- tracking errors: horizontal distance between the true CoM and the active reference evaluated at
  the same time, at every touchdown (``rms_/max_tracking_error_m``, the issue-4 definition) and over
  the whole run sampled every trace step (``*_continuous_m``);
- ``goal_reached``: the final CoM is within the goal tolerance of the target (the goal, or the
  start for in-place scenarios) and the robot did not fall.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import mujoco
import numpy as np

from onboard import messages as m
from onboard.params import SafetyLimits, TwinParams, with_overrides
from sim_twin import model as tm
from sim_twin import scenarios as sc
from sim_twin import stack as st
from sim_twin.actuation import Actuation
from sim_twin.sensors import SensorSuite

NS = 1_000_000_000
MIN_FLIGHT_S = 0.08  # [s] an airborne spell shorter than this (apex < 8 mm) is a chatter, not a hop
TRACE_EVERY = 10  # ticks between trace samples (plots, continuous tracking error)
PROGRESS_EVERY_S = 0.5  # [s of sim] between progress callbacks


@dataclass
class RunConfig:
    scenario: str
    seed: int = 0
    duration_s: float | None = None  # None: the scenario's default
    variant: str = tm.DEFAULT_VARIANT
    estimator: str = "truth"
    planner: str = "auto"
    controller: str = "lowlevel"
    obstacles: int | None = None  # forest: number of obstacles
    twin: TwinParams = field(default_factory=TwinParams)
    safety: SafetyLimits | None = None  # None: defaults (raised to the variant's peak for sim15nm)
    estimator_params: object | None = None
    planner_params: object | None = None
    control_params: object | None = None
    stop_on_fall: bool = True
    record: bool = False  # keep every message for --record


@dataclass
class Trace:
    t: list[float] = field(default_factory=list)
    com: list[tuple[float, float, float]] = field(default_factory=list)
    est: list[tuple[float, float, float]] = field(default_factory=list)
    ref: list[tuple[float, float]] = field(default_factory=list)
    wheel_vel: list[tuple[float, float, float]] = field(default_factory=list)
    torque: list[tuple[float, float, float, float]] = field(default_factory=list)
    tracking_error: list[float] = field(default_factory=list)
    impacts: list[tuple[float, float, float, float, float]] = field(default_factory=list)  # t, x, y, ref x, ref y


@dataclass
class RunResult:
    metrics: dict
    trace: Trace
    scenario: sc.Scenario
    messages: list[tuple[str, int, object]]  # (topic, log time ns, message) when recording


class _ContactClassifier:
    """Which geoms are robot, foot, ground (floor / terrain) and obstacles."""

    def __init__(self, model: mujoco.MjModel) -> None:
        torso = model.body(tm.TORSO).id
        foot = model.body(tm.FOOT).id
        n = model.ngeom
        self.robot = np.zeros(n, bool)
        self.foot = np.zeros(n, bool)
        self.ground = np.zeros(n, bool)
        self.obstacle = np.zeros(n, bool)
        for g in range(n):
            b = int(model.geom_bodyid[g])
            chain = [b]
            while chain[-1] != 0:
                chain.append(int(model.body_parentid[chain[-1]]))
            name = model.geom(g).name
            if torso in chain:
                self.robot[g] = True
                self.foot[g] = foot in chain
            elif name == "floor" or name.startswith(sc.TERRAIN_PREFIX):
                self.ground[g] = True
            elif name.startswith(sc.OBSTACLE_PREFIX):
                self.obstacle[g] = True
        self.robot_l, self.foot_l = self.robot.tolist(), self.foot.tolist()
        self.ground_l, self.obstacle_l = self.ground.tolist(), self.obstacle.tolist()

    def classify(self, data: mujoco.MjData) -> tuple[bool, bool, bool]:
        """(foot on ground, other robot part on ground, robot touching an obstacle)."""
        foot_ground = body_ground = obstacle = False
        geoms = data.contact.geom
        rob, fo, gr, ob = self.robot_l, self.foot_l, self.ground_l, self.obstacle_l
        for k in range(data.ncon):
            a, b = int(geoms[k, 0]), int(geoms[k, 1])
            if rob[b] and not rob[a]:
                a, b = b, a
            if not rob[a]:
                continue
            if gr[b]:
                if fo[a]:
                    foot_ground = True
                else:
                    body_ground = True
            elif ob[b]:
                obstacle = True
        return foot_ground, body_ground, obstacle


class LockstepRunner:
    """One run of one scenario; build, then :meth:`run`."""

    def __init__(self, cfg: RunConfig) -> None:
        self.cfg = cfg
        self.scenario = sc.make(cfg.scenario, cfg.seed, cfg.obstacles)
        self.robot = tm.robot_params(cfg.variant)
        safety = cfg.safety or SafetyLimits()
        if cfg.safety is None and cfg.variant == "sim15nm":  # the thesis's raised simulation limit
            safety = with_overrides(safety, {"wheel_torque_max": self.robot.wheel_torque_peak})
        self.safety = safety
        spec = tm.load_spec(cfg.variant)
        self.scenario.build(spec)
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        self.scenario.initialize(self.model, self.data, self.robot)
        control_dt = 1.0 / cfg.twin.control_rate_hz
        substeps = control_dt / self.model.opt.timestep
        if abs(substeps - round(substeps)) > 1e-9 or round(substeps) < 1:
            raise ValueError(f"control period {control_dt} s is not a whole number of physics steps {self.model.opt.timestep} s")
        self.substeps = int(round(substeps))
        self.tick_ns = int(round(control_dt * NS))
        self.duration_s = cfg.duration_s if cfg.duration_s is not None else self.scenario.default_duration_s
        if not (self.duration_s > 0 and math.isfinite(self.duration_s)):
            raise ValueError(f"duration must be positive, got {self.duration_s}")
        self.sensors = SensorSuite(self.model, cfg.twin, cfg.seed)
        self.actuation = Actuation(self.model, self.robot, safety)
        self.truth = st.TruthEstimator(self.model, self.robot)
        self.estimator = self.truth if cfg.estimator == "truth" else st.make_estimator(cfg.estimator, self.model, self.robot, cfg.estimator_params)
        self.planner = st.make_planner(cfg.planner, self.scenario, self.robot, cfg.planner_params)
        self.controller = st.make_controller(cfg.controller, cfg.variant, safety, cfg.control_params)
        self.contacts = _ContactClassifier(self.model)

    def run(self, progress: Callable[[float, float], None] | None = None) -> RunResult:
        cfg, model, data = self.cfg, self.model, self.data
        scenario, sensors, actuation = self.scenario, self.sensors, self.actuation
        estimator, planner, controller, truth = self.estimator, self.planner, self.controller, self.truth
        contacts, safety = self.contacts, self.safety
        tick_ns, substeps = self.tick_ns, self.substeps
        n_ticks = int(round(self.duration_s * NS / tick_ns))
        wheel_dof = [int(model.joint(n).dofadr[0]) for n in tm.WHEEL_JOINTS]
        qp_root = int(model.joint(tm.ROOT_JOINT).qposadr[0])
        cos_tilt_max = math.cos(safety.tilt_max)
        record = cfg.record
        messages: list[tuple[str, int, object]] = []
        trace = Trace()
        target = scenario.target()

        goal = scenario.goal()
        if record:
            if goal is not None:
                messages.append(("goal", 0, goal))
            messages.append(("polytopes", 0, scenario.polytopes(0)))

        cmd: m.TorqueCommand | None = None
        joints: m.JointSensors | None = None
        reference: m.ComReference | None = None
        last_ref_seen: m.ComReference | None = None
        on_ground = False
        airborne_since = 0.0
        hops = falls = collisions = 0
        in_collision = False
        fell = False
        fall_reason = ""
        fall_time = math.nan
        max_wheel = 0.0
        wheel_over_limit = 0
        impact_err: list[float] = []
        cont_err: list[float] = []
        est_err: list[float] = []
        safety_events = 0
        phase_events = 0
        contract_violations = 0
        progress_ticks = max(1, int(PROGRESS_EVERY_S * NS / tick_ns))
        mj_step = mujoco.mj_step
        now_ns = 0
        t = 0.0
        wall0 = time.perf_counter()
        k = 0
        for k in range(1, n_ticks + 1):
            scenario.before_step(t, model, data)
            actuation.apply(cmd, now_ns, data)
            for _ in range(substeps):
                mj_step(model, data)
            now_ns += tick_ns
            t = now_ns / NS

            # --- sensors -> estimator -> planner -> controller --------------------------
            for topic, msg in sensors.tick(data, now_ns):
                estimator.feed(topic, msg)
                if topic == "joints":
                    joints = msg
                if record:
                    messages.append((topic, now_ns, msg))
            state = estimator.estimate(now_ns, data)
            reference = planner.update(now_ns, state)
            cmd = controller.step(now_ns, state, reference, joints)
            if record:
                messages.append(("state", now_ns, state))
                messages.append(("torque_cmd", now_ns, cmd))
                if reference is not last_ref_seen and reference is not None:
                    messages.append(("reference", now_ns, reference))
                for ev in controller.drain_phase_events():
                    messages.append(("phase", now_ns, ev))
                    phase_events += 1
                for ev in controller.drain_safety_events():
                    messages.append(("safety", now_ns, ev))
                    safety_events += 1
            else:
                phase_events += len(controller.drain_phase_events())
                safety_events += len(controller.drain_safety_events())
            last_ref_seen = reference

            # --- metrics from the physics ------------------------------------------------
            if data.ncon:
                foot_ground, body_ground, obstacle = contacts.classify(data)
            else:
                foot_ground = body_ground = obstacle = False
            if foot_ground and not on_ground:
                if airborne_since and t - airborne_since >= MIN_FLIGHT_S:
                    hops += 1
                if reference is not None:
                    (px, py, _), _ = truth.com(data)
                    rx, ry = _ref_at(reference, now_ns)
                    impact_err.append(math.hypot(px - rx, py - ry))
                    trace.impacts.append((t, px, py, rx, ry))
                on_ground = True
            elif not foot_ground and on_ground:
                on_ground = False
                airborne_since = t
            elif not foot_ground and airborne_since == 0.0:
                airborne_since = t  # the initial drop counts as a flight start only for timing
            if obstacle and not in_collision:
                collisions += 1
            in_collision = obstacle
            qpos = data.qpos.tolist()
            qvel = data.qvel.tolist()
            qx, qy = qpos[qp_root + 4], qpos[qp_root + 5]
            if not fell and (body_ground or 1.0 - 2.0 * (qx * qx + qy * qy) < cos_tilt_max):
                fell = True
                falls += 1
                fall_time = t
                fall_reason = "body on the ground" if body_ground else "tilt"
            for dof in wheel_dof:
                s = abs(qvel[dof])
                if s > max_wheel:
                    max_wheel = s
            if max_wheel > safety.wheel_speed_max:
                wheel_over_limit += 1

            if k % TRACE_EVERY == 0:
                (px, py, pz), _ = truth.com(data)
                rx, ry = _ref_at(reference, now_ns) if reference is not None else target
                err = math.hypot(px - rx, py - ry)
                cont_err.append(err)
                sp = state.position
                est_err.append(math.dist((px, py, pz), sp))
                trace.t.append(t)
                trace.com.append((px, py, pz))
                trace.est.append((sp[0], sp[1], sp[2]))
                trace.ref.append((rx, ry))
                trace.wheel_vel.append(tuple(float(data.qvel[d]) for d in wheel_dof))
                trace.torque.append(actuation.last_applied)
                trace.tracking_error.append(err)
            if progress is not None and k % progress_ticks == 0:
                progress(t, self.duration_s)
            if fell and cfg.stop_on_fall:
                break
        wall = time.perf_counter() - wall0
        if progress is not None:
            progress(t, self.duration_s)

        for rep in planner.drain_contract_reports():
            contract_violations += int(rep.violated)
            if record:
                messages.append(("contract", rep.stamp_ns, rep))

        (px, py, _), _ = truth.com(data)
        final_err = math.hypot(px - target[0], py - target[1])
        tol = goal.tolerance if goal is not None else sc.GOAL_TOLERANCE
        metrics = {
            "scenario": cfg.scenario,
            "seed": cfg.seed,
            "mode": "lockstep",
            "variant": cfg.variant,
            "estimator": estimator.name,
            "planner": planner.name,
            "controller": controller.name,
            "sim_time_s": round(t, 6),
            "wall_time_s": round(wall, 4),
            "realtime_factor": round(t / wall, 2) if wall > 0 else math.inf,
            "tick_us_mean": round(wall / max(k, 1) * 1e6, 2),
            "hops": hops,
            "falls": falls,
            "fall_time_s": None if math.isnan(fall_time) else round(fall_time, 4),
            "fall_reason": fall_reason,
            "collisions": collisions,
            "goal_reached": bool(final_err <= tol and not fell),
            "final_goal_error_m": round(final_err, 4),
            "rms_tracking_error_m": _rms(impact_err),
            "max_tracking_error_m": round(max(impact_err), 4) if impact_err else None,
            "rms_tracking_error_continuous_m": _rms(cont_err),
            "max_tracking_error_continuous_m": round(max(cont_err), 4) if cont_err else None,
            "estimate_rms_error_m": _rms(est_err),
            "max_wheel_speed_rad_s": round(max_wheel, 3),
            "wheel_speed_over_limit_ticks": wheel_over_limit,
            "torque_saturation_fraction": round(actuation.saturation_fraction, 5),
            "contract_violations": contract_violations,
            "safety_events": safety_events,
            "phase_events": phase_events,
            "commands_refused": {k2: v for k2, v in actuation.counters.items() if k2 != "applied" and v},
            "estimator_counters": estimator.counters(),
        }
        if isinstance(planner, st.GraphPlannerPlug):
            metrics["planner_plans"] = planner.plans
            metrics["planner_no_path"] = planner.no_path
        return RunResult(metrics=metrics, trace=trace, scenario=scenario, messages=messages)


def _rms(values: list[float]) -> float | None:
    if not values:
        return None
    return round(math.sqrt(sum(v * v for v in values) / len(values)), 4)


def _ref_at(ref: m.ComReference, now_ns: int) -> tuple[float, float]:
    if ref.hold:
        p = ref.segments[0].control_points[0]
        return p[0], p[1]
    return sc.sample_reference(ref.segments, (now_ns - ref.t_ref_ns) / NS)


def run(cfg: RunConfig, progress: Callable[[float, float], None] | None = None) -> RunResult:
    return LockstepRunner(cfg).run(progress)


def config_with(cfg: RunConfig, **changes) -> RunConfig:
    return dataclasses.replace(cfg, **changes)
