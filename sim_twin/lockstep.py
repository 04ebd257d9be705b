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
derive from it and nothing reads a wall clock except the realtime-factor figure. The metrics come
from the physics (:mod:`sim_twin.metrics`), never from the stack's belief; the run stops at the
first fall unless told otherwise.
"""

from __future__ import annotations

import dataclasses
import gc
import math
import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import mujoco
import numpy as np
from threadpoolctl import threadpool_limits

from onboard.contracts import messages as m
from onboard.contracts.binary_messages import DepthImage
from onboard.geometry import quaternion as quat
from onboard.contracts.params import (ControlParams, EstimatorParams, SafetyLimits, TwinParams,
                                      with_overrides)
from onboard.contracts.topics import TOPICS
from robot_description import params as rd
from sim_twin import compiled
from sim_twin import model as tm
from sim_twin import model_error as me
from sim_twin import perception_plug
from sim_twin import scenarios as sc
from sim_twin import stack as st
from sim_twin.actuation import Actuation
from sim_twin.drift import EstimateDrift
from sim_twin.metrics import PhysicsMetrics, Trace
from sim_twin.sensors import SensorOutage, SensorSuite

NS = 1_000_000_000
PROGRESS_EVERY_S = 0.5  # [s of sim] between progress callbacks
BLAS_THREADS = 1  # see LockstepRunner.run


@dataclass
class RunConfig:
    scenario: str
    seed: int = 0
    duration_s: float | None = None  # None: the scenario's default
    variant: str = rd.DEFAULT_VARIANT
    estimator: str = "truth"
    planner: str = "auto"
    controller: str = "lowlevel"
    obstacles: int | None = None  # forest: number of obstacles
    twin: TwinParams = field(default_factory=TwinParams)
    safety: SafetyLimits | None = None  # None: defaults (raised to the variant's peak for sim15nm)
    estimator_params: object | None = None
    planner_params: object | None = None
    control_params: object | None = None
    gmpc_params: object | None = None  # the geometric MPC's, when control_params.mid_level says so
    perception: str = "truth"  # "depth": the planner sees what onboard.perception makes of the depth camera
    perception_params: object | None = None
    stop_on_fall: bool = True
    record: bool = False  # keep every message for --record
    sink: Callable[[str, int, object], None] | None = None  # also hand every message to this as it happens (a live view)
    sensor_outages: tuple[SensorOutage, ...] = ()  # windows in which a sensor's samples are lost
    # the world the planner is told, in place of the ground truth: given the scenario, a function of the
    # time [ns] and the robot's estimate giving a new PolytopeSet or None (e.g. the overhead camera's)
    world: Callable[[sc.Scenario], Callable[[int, m.StateEstimate], m.PolytopeSet | None]] | None = None
    model_error: str | None = None  # the twin's physics drawn per seed around the MJCF (sim_twin.model_error profile)
    # "onboard": no motion capture (outdoors): the estimator gets no pose and keeps an odometry frame
    # (estimator.position_source = "odometry"); the run reports its drift per metre travelled
    sensing: str = "mocap"


@dataclass
class RunResult:
    metrics: dict
    trace: Trace
    scenario: sc.Scenario
    messages: list[tuple[str, int, object]]  # (topic, log time ns, message) when recording


class _Tee(list):
    """The run's message list that also hands each message to a sink (kept only when recording)."""

    def __init__(self, sink: Callable[[str, int, object], None], keep: bool) -> None:
        super().__init__()
        self._sink = sink
        self._keep = keep

    def append(self, item: tuple[str, int, object]) -> None:
        self._sink(*item)
        if self._keep:
            super().append(item)

    def extend(self, items: Iterable[tuple[str, int, object]]) -> None:
        for item in items:
            self.append(item)


def _identified_control(control: ControlParams | None, estimator: EstimatorParams | None) -> ControlParams | None:
    """The controller's parameters with the estimator's identified robot (``[estimator] identified``):
    a robot runs both with the same file, so a config that names it once names it for both; two
    different files are refused."""
    est_file = estimator.identified if estimator is not None else ""
    ctrl_file = control.identified if control is not None else ""
    if est_file and ctrl_file and est_file != ctrl_file:
        raise ValueError(f"[estimator] identified = {est_file!r} and [control] identified = {ctrl_file!r}: one robot, one file")
    if not est_file or ctrl_file:
        return control
    return with_overrides(control or ControlParams(), {"identified": est_file})


class LockstepRunner:
    """One run of one scenario; build, then :meth:`run`."""

    def __init__(self, cfg: RunConfig) -> None:
        compiled.check_fresh()
        self.cfg = cfg
        self.robot = rd.robot_params(cfg.variant)
        self.scenario = sc.make(cfg.scenario, cfg.seed, cfg.obstacles, sc.cruise_speed_for(self.robot))
        self.safety = cfg.safety or rd.safety_limits_for(SafetyLimits(), self.robot)
        spec = tm.load_spec(cfg.variant)
        self.scenario.build(spec)
        self.model = spec.compile()
        # the twin's physics drawn around the MJCF; the stack keeps self.robot, the nominal description
        self.model_error = me.draw(me.load_profile(cfg.model_error), cfg.seed)
        self.model_error.apply_model(self.model)
        self.data = mujoco.MjData(self.model)
        if self.model_error.values:
            me.finish_model(self.model, self.data)
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
        self.sensors = SensorSuite(self.model, self.model_error.twin_params(cfg.twin), cfg.seed, cfg.sensor_outages)
        if (mount := self.model_error.imu_misalignment) is not None:
            self.sensors.set_imu_misalignment(*mount)
        self.actuation = Actuation(self.model, self.model_error.actuation_robot(self.robot), self.safety)
        self.delay_ticks = int(round(self.model_error.actuator_delay_s / control_dt))
        # the metrics measure the twin's own CoM, not where the stack believes it is
        self.truth = st.TruthEstimator(self.model, me.truth_robot(self.model, self.robot) if self.model_error.values else self.robot)
        if cfg.sensing not in SENSING:
            raise ValueError(f"sensing must be one of {SENSING}, got {cfg.sensing!r}")
        estimator_params = cfg.estimator_params
        if cfg.sensing == "onboard":
            if cfg.estimator == "truth":
                raise ValueError("--sensing onboard is the onboard estimator's (--estimator kalman)")
            estimator_params = with_overrides(estimator_params or EstimatorParams(), {"position_source": "odometry"})
        self.estimator = self.truth if cfg.estimator == "truth" else st.make_estimator(cfg.estimator, self.model, self.robot, estimator_params)
        # the D435's apex frames through the visual odometry into the estimator (estimator.visual_odometry)
        self.visual_odometry = None
        if cfg.sensing == "onboard" and getattr(estimator_params, "visual_odometry", False):
            from sim_twin.visual_odometry_plug import ApexVisualOdometry

            self.visual_odometry = ApexVisualOdometry(self.model, self.scenario.traversable, cfg.variant, estimator_params,
                                                      cfg.twin, cfg.seed, perception=cfg.perception_params)
        self.planner = perception_plug.make_planner(cfg.planner, cfg.perception, self.scenario, self.robot, cfg.planner_params,
                                                    cfg.perception_params)
        if cfg.world is not None:
            if not isinstance(self.planner, st.GraphPlannerPlug) or isinstance(self.planner, perception_plug.PerceivedGraphPlannerPlug):
                raise ValueError("a world source feeds the graph planner on ground truth (--planner graph, --perception truth)")
            self.planner.use_world(cfg.world(self.scenario))
        self.controller = st.make_controller(cfg.controller, cfg.variant, self.safety,
                                             _identified_control(cfg.control_params, estimator_params), cfg.gmpc_params)
        self.metrics = PhysicsMetrics(self.model, self.scenario, self.truth, self.safety)

    def step_reference(self) -> None:
        """Replace the planner by a bare step to the scenario's target: hold there from the
        start (thesis Fig. 5.22), no smooth reference to follow."""
        goal = self.scenario.target()
        ref = m.ComReference(t_ref_ns=0, hold=True, segments=[m.BezierSegment(t0=0.0, duration=1.0, control_points=[list(goal)])])

        def update(now_ns: int, _state: m.StateEstimate) -> m.ComReference:
            ref.stamp_ns = now_ns  # fresh, as a planner republishes it
            return ref

        self.planner.update = update  # type: ignore[method-assign]

    def run(self, progress: Callable[[float, float], None] | None = None) -> RunResult:
        """The run, with BLAS on one thread and the build's objects out of the collector's sight.

        One BLAS thread: a multithreaded LAPACK solve (the planner's MPC polish) rounds differently
        with each thread count, so a run's bits would depend on the machine's cores (and
        ``OPENBLAS_NUM_THREADS``); and two spinning BLAS threads on a shared 2-core machine made
        runs up to 7x slower. gc.freeze: a full collection walks every object the build left
        (MuJoCo, numba, the planner's graph) again and again; frozen, only the run's own
        allocations are walked. Unfrozen afterwards, so a worker doing many runs frees each one.
        """
        gc.freeze()  # no collection first: one costs ~40 ms here, 4 us a tick of a 10 s run
        try:
            with threadpool_limits(limits=BLAS_THREADS, user_api="blas"):
                return self._run(progress)
        finally:
            gc.unfreeze()

    def _run(self, progress: Callable[[float, float], None] | None) -> RunResult:
        cfg, model, data = self.cfg, self.model, self.data
        scenario, sensors, actuation = self.scenario, self.sensors, self.actuation
        estimator, planner, controller, metrics = self.estimator, self.planner, self.controller, self.metrics
        tick_ns, substeps = self.tick_ns, self.substeps
        n_ticks = int(round(self.duration_s * NS / tick_ns))
        record = cfg.record or cfg.sink is not None
        messages: list[tuple[str, int, object]] = _Tee(cfg.sink, cfg.record) if cfg.sink is not None else []
        goal = scenario.goal()
        if record:
            if goal is not None:
                messages.append(("goal", 0, goal))
            messages.append(("polytopes", 0, scenario.polytopes(0)))

        cmd: m.TorqueCommand | None = None
        joints: m.JointSensors | None = None
        state: m.StateEstimate | None = None
        reference: m.ComReference | None = None
        last_ref_seen: m.ComReference | None = None
        last_world: object = None  # moving obstacles: the last world the planner was handed (recorded when new)
        safety_events = phase_events = contract_violations = 0
        progress_ticks = max(1, int(PROGRESS_EVERY_S * NS / tick_ns))
        mj_step = mujoco.mj_step
        now_ns = 0
        t = 0.0
        k = 0
        no_pose = cfg.sensing == "onboard"
        drift = EstimateDrift(self.truth) if no_pose else None
        vo = self.visual_odometry
        planner_feed = getattr(planner, "feed", None)
        perceives = isinstance(planner, perception_plug.PerceivedGraphPlannerPlug)
        # A perceiving planner eats the depth images: the D435's apex frames, depth and colour, where the
        # robot carries one (onboard sensing), as the camera service hands them to perception on the
        # robot; else the twin's stand-in depth camera, as the twin service publishes it.
        apex_frames = vo is not None and perceives
        sensor_feed = planner_feed if perceives and not apex_frames else None
        # ray casting nobody reads is skipped (only a perceiving planner or a recording reads depth)
        sensors.capture_depth = record or sensor_feed is not None
        # The low level's tube reaches the planner at the topic's rate (the contract check).
        tube_ns = int(NS / TOPICS["tube"].rate_hz) if planner_feed is not None and hasattr(controller, "tube") else 0
        next_tube_ns = tube_ns
        wall0 = time.perf_counter()
        # a scenario without disturbances keeps the base class's empty before_step: not called
        disturb = scenario.before_step
        if getattr(disturb, "__func__", None) is sc.Scenario.before_step:
            disturb = None
        flip_requests = list(scenario.flip_requests_s)  # the operator's flip requests, as the param would carry them
        request_flip = getattr(controller, "request_flip", None)
        delayed: deque[m.TorqueCommand | None] = deque([None] * self.delay_ticks)  # commands still on their way (model error)
        for k in range(1, n_ticks + 1):
            if disturb is not None:
                disturb(t, model, data)
            if flip_requests and t >= flip_requests[0]:
                flip_requests.pop(0)
                if request_flip is not None:
                    request_flip()
            if delayed:
                delayed.append(cmd)
                actuation.apply(delayed.popleft(), now_ns, data)
            else:
                actuation.apply(cmd, now_ns, data)
            for _ in range(substeps):
                mj_step(model, data)
            now_ns += tick_ns
            t = now_ns / NS

            # sensors -> estimator -> planner -> controller
            if vo is not None:
                for delta in vo.due(now_ns):  # late by the camera's and the VO's latency, stamped at capture
                    estimator.feed("visual_odometry", delta, now_ns)
            for topic, msg in sensors.tick(data, now_ns):
                if no_pose:
                    if topic == "pose":
                        continue  # no motion capture on the robot
                    if topic == "depth":
                        if state is None or not state.valid:
                            continue  # no estimate can place it (the camera service refuses it too)
                        # placed by the estimate, as the camera service places a frame: the map and the
                        # plan live in the drifting odometry frame, obstacles seen relative to the robot
                        msg = _as_estimated(msg, self.truth.estimate(now_ns, data), state)
                estimator.feed(topic, msg, now_ns)
                if sensor_feed is not None:
                    sensor_feed(topic, msg)
                if topic == "joints":
                    joints = msg
                if record:
                    messages.append((topic, now_ns, msg))
            state = estimator.estimate(now_ns, data)
            reference = planner.update(now_ns, state)
            cmd = controller.step(now_ns, state, reference, joints)
            if tube_ns and now_ns >= next_tube_ns:
                next_tube_ns += tube_ns
                planner_feed("tube", controller.tube(now_ns))
            phase = controller.drain_phase_events()
            if vo is not None and any(ev.event == "apex" for ev in phase):
                frame = vo.on_apex(now_ns, data, state, self.truth.estimate(now_ns, data).position)
                if apex_frames and frame is not None:
                    planner_feed("color", frame[1])
                    planner_feed("depth", frame[0])
            trips = controller.drain_safety_events()
            phase_events += len(phase)
            safety_events += len(trips)
            if record:
                messages.append(("state", now_ns, state))
                messages.append(("torque_cmd", now_ns, cmd))
                if reference is not last_ref_seen and reference is not None:
                    messages.append(("reference", now_ns, reference))
                world = getattr(planner, "world", None)
                if world is not last_world and world is not None:
                    messages.append(("polytopes", now_ns, world))
                    last_world = world
                messages.extend(("phase", now_ns, ev) for ev in phase)
                messages.extend(("safety", now_ns, ev) for ev in trips)
            last_ref_seen = reference

            metrics.update(t, now_ns, data, reference, state, actuation.last_applied)
            if drift is not None and k % DRIFT_EVERY_TICKS == 0:
                drift.update(now_ns, data, state)
            if progress is not None and k % progress_ticks == 0:
                progress(t, self.duration_s)
            if metrics.fell and cfg.stop_on_fall:
                break
        wall = time.perf_counter() - wall0
        if progress is not None:
            progress(t, self.duration_s)

        for rep in planner.drain_contract_reports():
            contract_violations += int(rep.violated)
            if record:
                messages.append(("contract", rep.stamp_ns, rep))

        out = {
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
        }
        out.update(metrics.summary(data, actuation))
        if cfg.model_error is not None:
            out["model_error"] = self.model_error.report()
        if drift is not None:
            drift.update(now_ns, data, state)
            out["sensing"] = "onboard"
            out.update(drift.summary())
            if vo is not None:
                out["visual_odometry"] = vo.report(estimator.counters())
                out["segmentation"] = vo.segmentation_report()
        out.update({
            "contract_violations": contract_violations,
            "safety_events": safety_events,
            "phase_events": phase_events,
            "estimator_counters": estimator.counters(),
        })
        if scenario.flip_requests_s and request_flip is not None:
            flip = controller.ctrl.flip
            out["flip"] = flip.counters()
            if flip.last_refusal:
                out["flip_refusal"] = flip.last_refusal
        mid = getattr(controller, "mid_level", None)
        if mid is not None:
            out["mid_level"] = "geometric_mpc"
            out["mid_level_solves"] = mid.solves
            out["mid_level_rejected"] = mid.rejected
            out["mid_level_ticks"] = controller.ctrl.mid_level_ticks
            out["mid_level_fallback_ticks"] = controller.ctrl.mid_level_fallback_ticks
        if isinstance(planner, st.GraphPlannerPlug):
            out["planner_plans"] = planner.plans
            out["planner_no_path"] = planner.no_path
            out["planner_unseen_holds"] = planner.planner.stats.unseen_holds  # refined references held back: not yet seen
            if scenario.movers:  # obstacles that move: how often the planner planned anew, and around shorter sweeps
                out["planner_replans_per_s"] = round(planner.plans / t, 3) if t > 0 else 0.0
                out["planner_sweep_relaxed"] = planner.planner.stats.sweep_relaxed
        return RunResult(metrics=out, trace=metrics.trace, scenario=scenario, messages=messages)


SENSING = ("mocap", "onboard")


def _as_estimated(img: DepthImage, truth: m.StateEstimate, est: m.StateEstimate) -> DepthImage:
    """The depth image with the camera placed by the estimate instead of the truth: the camera's pose
    relative to the body is kept, the body's is the estimate's (CoM and attitude)."""
    rel_q = quat.mul(est.quat, quat.conj(truth.quat))  # true world -> estimated world, about the CoM
    offset = quat.rotate(rel_q, [c - t for c, t in zip(img.cam_pos, truth.position)])
    cam_pos = np.array([e + o for e, o in zip(est.position, offset)])
    cam_quat = np.array(quat.normalize(quat.mul(rel_q, list(img.cam_quat))))
    return DepthImage(img.depth, img.fx, img.fy, img.cx, img.cy, cam_pos, cam_quat, img.stamp_ns, img.seq)


DRIFT_EVERY_TICKS = 10  # drift and distance sampled every 10 ms of a 1 kHz run


class SimulationError(RuntimeError):
    """The run itself failed (a bug or a numerical failure), not its configuration."""


def run(cfg: RunConfig, progress: Callable[[float, float], None] | None = None) -> RunResult:
    """Run ``cfg``; a bad configuration raises as it is (ValueError), a failure while
    stepping raises :class:`SimulationError` (its cause chained)."""
    runner = LockstepRunner(cfg)
    try:
        return runner.run(progress)
    except Exception as exc:
        raise SimulationError(f"internal error during the run: {type(exc).__name__}: {exc}") from exc


def config_with(cfg: RunConfig, **changes) -> RunConfig:
    return dataclasses.replace(cfg, **changes)
