"""The real-time twin: the MuJoCo robot in place of the ``hardware`` service, paced to wall time.

Subscribes ``torque_cmd`` (latest value, from the one live commander: :meth:`Service.commands`) and, for its metrics only, ``reference``, ``state`` and
``contract``.
A :class:`~services.runtime.realtime.DeadlineLoop` thread runs at ``TwinParams.control_rate_hz``; every
tick it:

1. takes the newest torque command; one received more than ``SafetyLimits.command_stale_s`` ago,
   not armed or not finite gives zero torque (as the hardware's own watchdog; a ``safety`` event is
   published when commands stop being applied), otherwise clamps it to ``SafetyLimits`` and the
   motor curve (:class:`sim_twin.actuation.Actuation`);
2. advances the physics by one tick of simulated time;
3. publishes what the sensors deliver now (``imu``, ``joints``, ``pose``, ``depth``), stamped with
   the capture time on the stack's clock, exactly as the hardware service would.

It also publishes the scenario's ``goal`` and ground-truth ``polytopes`` (``publish_world``; the
obstacles not with ``publish_obstacles`` false, when the perception service makes them).

Setting ``twin.seed`` on the running twin (its parameter query) puts the robot back, as a person
picks up a fallen robot in a long test: between two ticks the physics restarts from the
scenario's initial state (upright, at rest, over the start) and the sensors' noise is drawn anew
from that seed; simulated time goes on, the world stays as built and ``falls`` counts every fall
(a put-back robot that stands for ``RECOVERY_S`` ends the episode).
The other ``twin`` parameters fix the model and the world at start: changing them is refused.
Simulated time advances one tick per loop tick; an overrun (a tick later than the next deadline)
skips deadlines, so the real-time factor (simulated / wall seconds) drops below 1 and is reported
with the overruns in the status (``archer status``), together with the physics metrics.

:class:`ScenarioReferenceService` stands in for the planner when there is none: it publishes the
scenario's own CoM reference (as ``archer sim --planner scenario`` does in lockstep).
"""

from __future__ import annotations

import asyncio
import threading
import time
from typing import Any

import msgspec
import mujoco

from onboard.contracts import messages as msgs
from onboard.contracts.binary_messages import DepthImage, encode_depth
from onboard.contracts.params import TwinParams, as_dict
from onboard.contracts.topics import TOPICS
from robot_description import params as rd
from services.runtime.realtime import DeadlineLoop
from services.runtime.service import Service
from sim_twin import model as tm
from sim_twin import scenarios as sc
from sim_twin.actuation import Actuation
from sim_twin.metrics import PhysicsMetrics
from sim_twin import model_error as me
from sim_twin.drift import EstimateDrift
from sim_twin.sensors import SensorSuite
from sim_twin.stack import TruthEstimator

NS = 1_000_000_000
STATUS_POLL_S = 0.2  # how often main() checks the loop and republishes the world
REFERENCE_PERIOD_S = 0.1  # [s] the scenario reference is republished this often (fresh for the low level)
LIVE_TWIN_PARAMS = ("seed",)  # what a running twin takes (and restarts its scenario for)


def make_scenario(tp: TwinParams) -> sc.Scenario:
    return sc.make(tp.scenario, tp.seed, None if tp.obstacles < 0 else tp.obstacles,
                   sc.cruise_speed_for(rd.robot_params(tp.variant)))


class TwinService(Service):
    name = "twin"
    params_sections = ("twin", "safety")
    subscribes = ("torque_cmd", "reference", "state", "contract")

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.loop: DeadlineLoop | None = None
        self.sim_ns = 0
        self._wall0 = 0.0
        self._applying = False
        self._put_back_requested = False
        self.contract_violations = 0

    # --- what it subscribes and builds ------------------------------------------------------

    async def setup(self) -> None:
        tp: TwinParams = self.params["twin"]
        self.scenario = make_scenario(tp)
        self.robot = rd.robot_params(tp.variant)
        self.safety = rd.safety_limits_for(self.params["safety"], rd.robot_params(tp.variant))
        spec = tm.load_spec(tp.variant)
        self.scenario.build(spec)
        self.model = spec.compile()
        self.model_error = me.draw(me.load_profile(tp.model_error), tp.seed)  # the stack keeps the nominal robot
        self.model_error.apply_model(self.model)
        self.data = mujoco.MjData(self.model)
        if self.model_error.values:
            me.finish_model(self.model, self.data)
        self.scenario.initialize(self.model, self.data, self.robot)
        period_s = 1.0 / tp.control_rate_hz
        substeps = period_s / self.model.opt.timestep
        if abs(substeps - round(substeps)) > 1e-9 or round(substeps) < 1:
            raise ValueError(f"control period {period_s} s is not a whole number of physics steps")
        self.substeps = int(round(substeps))
        self.tick_ns = int(round(period_s * NS))
        self.sensors = self._sensor_suite(tp)
        self.actuation = Actuation(self.model, self.model_error.actuation_robot(self.robot), self.safety)
        self.truth = TruthEstimator(self.model, me.truth_robot(self.model, self.robot) if self.model_error.values else self.robot)
        self.metrics = PhysicsMetrics(self.model, self.scenario, self.truth, self.safety)

        self.torque_slot = self.commands("torque_cmd")  # from the live commander only
        # for the metrics only: decoded when read (the estimate every TRACE_EVERY ticks)
        self.reference_slot = self.latest_sampled("reference")
        self.state_slot = self.latest_sampled("state")
        self.subscribe("contract", self._on_contract)
        self.pubs = {name: self.publisher(name) for name in ("imu", "joints", "pose", "depth")}
        self.safety_pub = self.publisher("safety")
        self.goal_pub = self.publisher("goal") if tp.publish_world else None
        self.poly_pub = self.publisher("polytopes") if tp.publish_world and tp.publish_obstacles else None
        self.loop = DeadlineLoop(period_s, self._tick, name="twin-loop")

    # --- every tick: command in, physics, sensors out ---------------------------------------------

    def _tick(self, deadline: float) -> None:
        if self._put_back_requested:
            self._put_back_requested = False
            self._put_back()
        now_ns = self.clock.now_ns()
        data = self.data
        cmd, recv_ns = self._command(now_ns)
        t = self.sim_ns / NS
        self.scenario.before_step(t, self.model, data)
        act = self.actuation
        applied_before = act.counters["applied"]
        # staleness by receipt time on this clock (the commander's clock is not ours to trust)
        act.apply(cmd, now_ns, data, received_ns=recv_ns)
        applying = act.counters["applied"] != applied_before
        if self._applying and not applying:
            self._publish_trip(cmd, now_ns, recv_ns)
        self._applying = applying
        for _ in range(self.substeps):
            mujoco.mj_step(self.model, data)
        self.sim_ns += self.tick_ns
        for topic, msg in self.sensors.tick(data, now_ns):
            self._deliver(topic, msg)
        self._after_step(now_ns)
        ref = self.reference_slot.get()
        state = self.state_slot.get() if self.metrics.traces_next_tick() else None
        self.metrics.update(self.sim_ns / NS, now_ns, data, ref[0] if ref else None, state[0] if state else None,
                            act.last_applied)
        self.rate("tick").tick()

    def _command(self, now_ns: int) -> tuple[msgs.TorqueCommand | None, int]:
        """The command for this tick and when it was received (stack clock)."""
        slot = self.torque_slot.get()
        return slot if slot is not None else (None, 0)

    def _deliver(self, topic: str, msg: Any) -> None:
        """What a sensor delivers this tick goes out on its topic."""
        if isinstance(msg, DepthImage):
            self.pubs[topic].put_bytes(encode_depth(msg))
        else:
            self.pubs[topic].put(msg)

    def _after_step(self, now_ns: int) -> None:
        """After the physics and the sensors of a tick (the devices a subclass runs)."""

    def _sensor_suite(self, tp: TwinParams) -> SensorSuite:
        suite = SensorSuite(self.model, self.model_error.twin_params(tp), tp.seed)
        if (mount := self.model_error.imu_misalignment) is not None:
            suite.set_imu_misalignment(*mount)
        return suite

    def _put_back(self) -> None:
        """On the loop thread, between ticks: the scenario's initial state, new sensor noise."""
        tp: TwinParams = self.params["twin"]
        self.scenario.initialize(self.model, self.data, self.robot)
        self.sensors = self._sensor_suite(tp)
        self.count("put_back")
        self.log.warning("robot put back", extra={"fields": {"seed": tp.seed, "falls": self.metrics.falls}})

    def accept_params(self, updated: dict[str, Any]) -> None:
        new = updated.get("twin")
        if new is None:
            return
        old = as_dict(self.params["twin"])
        fixed = sorted(f"twin.{k}" for k, v in as_dict(new).items() if v != old[k] and k not in LIVE_TWIN_PARAMS)
        if fixed:
            raise ValueError(f"{fixed} are fixed while the twin runs; only {['twin.' + k for k in LIVE_TWIN_PARAMS]} can change")

    def on_params_changed(self, section: str) -> None:
        if section == "twin":
            self._put_back_requested = True

    async def _on_contract(self, report: msgs.ContractReport) -> None:
        if report.violated:
            self.contract_violations += 1

    def _publish_trip(self, cmd: msgs.TorqueCommand | None, now_ns: int, recv_ns: int) -> None:
        age = (now_ns - recv_ns) / NS if cmd is not None else float("inf")
        trip = "command_stale" if cmd is not None and cmd.armed and age > self.safety.command_stale_s else "command_refused"
        self.count(f"trip.{trip}")
        limit = self.safety.command_stale_s
        self.safety_pub.put(msgs.SafetyEvent(trip=trip, value=min(age, 1e9), limit=limit, armed=False,
                                             count=self.counters.get(f"trip.{trip}")))

    def _publish_world(self) -> None:
        goal = self.scenario.goal()
        if self.goal_pub is not None and goal is not None:
            self.goal_pub.put(goal)
        if self.poly_pub is not None:
            # obstacles that move: where they are now, stamped now (the scenario moves them on the twin loop)
            self.poly_pub.put(self.scenario.polytopes(self.clock.now_ns() if self.scenario.movers else 0))

    # --- lifecycle --------------------------------------------------------------------------------------

    async def main(self) -> None:
        assert self.loop is not None
        tp: TwinParams = self.params["twin"]
        self._wall0 = time.perf_counter()
        self.loop.start()
        next_world = 0.0
        # obstacles that move are published at the world topic's rate, not only for late joiners
        world_period = min(tp.world_period_s, 1.0 / TOPICS["polytopes"].rate_hz) if self.scenario.movers else tp.world_period_s
        try:
            while not self.stopping.is_set():
                now = time.perf_counter()
                if now >= next_world:
                    self._publish_world()
                    next_world = now + world_period
                await asyncio.sleep(STATUS_POLL_S)
                if self.loop.error is not None:
                    self.fail(f"twin loop crashed: {self.loop.error!r}")
                    raise RuntimeError("twin loop crashed") from self.loop.error
                self.state = "degraded" if self.metrics.fell else "running"
        finally:
            self.loop.stop()

    @property
    def physics_wall_s(self) -> float:
        """Wall time since the physics started (0 before)."""
        return time.perf_counter() - self._wall0 if self._wall0 else 0.0

    @property
    def realtime_factor(self) -> float:
        wall = self.physics_wall_s
        return self.sim_ns / NS / wall if wall > 0 else 0.0

    def summary(self) -> dict[str, Any]:
        """Physics metrics and pacing figures of the run so far."""
        out: dict[str, Any] = {"sim_time_s": round(self.sim_ns / NS, 4),
                               "realtime_factor": round(self.realtime_factor, 3)}
        if self.loop is not None:
            out.update({f"loop_{k}": v for k, v in self.loop.recorder.stats().as_dict().items()})
        out.update(self.metrics.summary(self.data, self.actuation))
        out["contract_violations"] = self.contract_violations
        # commands that never reached the motors because of who sent them (onboard/contracts/commander.py)
        out["commands_refused_commander"] = dict(self.commander_latch.refused) if self.commander_latch is not None else {}
        if self.model_error.values:  # the twin's drawn physics, as the lockstep report has it
            out["model_error"] = self.model_error.report()
        return out

    def progress(self) -> bool:
        return self.loop is not None and self.loop.progressing()

    def status_extra(self) -> dict[str, float]:
        out: dict[str, float] = {"sim_time_s": self.sim_ns / NS, "realtime_factor": self.realtime_factor}
        if self.loop is not None:
            for key, value in self.loop.recorder.stats().as_dict().items():
                out[f"loop.{key}"] = float(value)
        mt = self.metrics
        out.update({"hops": float(mt.hops), "falls": float(mt.falls), "recoveries": float(mt.recoveries), "collisions": float(mt.collisions),
                    "max_wheel_speed_rad_s": mt.max_wheel, "torque_saturation_fraction": self.actuation.saturation_fraction})
        for key, value in self.actuation.counters.items():
            out[f"commands.{key}"] = float(value)
        for name, vals in self.model_error.values.items():  # what was drawn
            for i, v in enumerate(vals):
                out[f"model_error.{name}" + (f".{i}" if len(vals) > 1 else "")] = v
        return out


class FirmwareTwinService(TwinService):
    """The twin behind ARCHER's own boards and an OptiTrack stream instead of topics.

    The emulated flywheel and foot boards (:class:`drivers.archer_firmware.emulator.BoardEmulator`,
    on UDP) and the NatNet server (:class:`drivers.natnet.NatNetServer`) are built by the caller
    before the stack starts, so that their ports can go into the ``hardware`` and ``mocap``
    services' configuration; this service runs them on its tick, in the twin's clock:

    1. the board reads the packets waiting, answers each with its state (what the twin's IMU,
       encoders and foot sensors delivered last tick), runs its PD and foot cycle: its motor
       torques are this tick's command (limits and motor curve apply as for any command);
    2. physics, as the twin;
    3. the IMU and joint readings go to the board, not to topics (the ``hardware`` service
       publishes what the board reports); the depth camera still publishes;
    4. the torso's true pose is captured at ``mocap.rate_hz`` and each frame streamed
       ``mocap.latency_s`` later (the ``mocap`` service publishes it as ``pose``).

    Physics metrics (falls, hops, goal error) are the twin's, as in every realtime run.
    """

    def __init__(self, *args: Any, board: Any, natnet_server: Any, mocap: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.board = board
        self.natnet = natnet_server
        self.mocap = mocap
        self._board_torques = [0.0, 0.0, 0.0, 0.0]
        self._frames: list[Any] = []  # captured, not yet due
        self._frame_no = 0

    async def setup(self) -> None:
        await super().setup()
        from drivers.elmo.emulator import InertiaLoad
        from drivers.teensy.emulator import BodyState

        self.board.body = BodyState()
        self.board.motors = [InertiaLoad() for _ in range(4)]  # positions and speeds written from the twin's sensors
        self.board.on_step = self._on_board_step
        self._spool_dof = int(self.model.joint(rd.FOOT_MOTOR_JOINT).dofadr[0])
        self._root_qp = int(self.model.joint(rd.ROOT_JOINT).qposadr[0])
        self._ticks_per_frame = max(1, round(self.params["twin"].control_rate_hz / self.mocap.rate_hz))
        self._latency_ns = round(self.mocap.latency_s * NS)

    def _on_board_step(self, _now_s: float, torques: list[float]) -> None:
        self._board_torques = torques

    def _command(self, now_ns: int) -> tuple[msgs.TorqueCommand | None, int]:
        self.board.tick(now_ns / NS)
        w = self._board_torques
        return msgs.TorqueCommand(stamp_ns=now_ns, wheel_torque=w[:3], foot_torque=w[3], armed=True), now_ns

    def _deliver(self, topic: str, msg: Any) -> None:
        body, motors = self.board.body, self.board.motors
        if topic == "imu":
            body.quat, body.gyro, body.accel = tuple(msg.quat), tuple(msg.gyro), tuple(msg.accel)
        elif topic == "joints":
            for k in range(3):
                motors[k].position, motors[k].velocity = msg.wheel_pos[k], msg.wheel_vel[k]
            motors[3].position, motors[3].velocity = msg.foot_motor_pos, float(self.data.qvel[self._spool_dof])  # no spool speed in JointSensors
            body.foot_pos, body.foot_vel, body.contact = msg.foot_pos, msg.foot_vel, msg.foot_contact
        elif topic == "depth":
            super()._deliver(topic, msg)

    def _after_step(self, now_ns: int) -> None:
        from drivers import natnet

        if self.sim_ns // self.tick_ns % self._ticks_per_frame == 0:
            self._frame_no += 1
            q = self.data.qpos[self._root_qp:self._root_qp + 7].tolist()
            body = natnet.RigidBodySample(self.mocap.rigid_body_id, (q[0], q[1], q[2]), (q[3], q[4], q[5], q[6]))
            self._frames.append(natnet.Frame(self._frame_no, (body,), now_ns, now_ns + self._latency_ns, self.sim_ns / NS))
        while self._frames and self._frames[0].received_ns <= now_ns:
            self.natnet.publish(self._frames.pop(0), now_ns)

    def summary(self) -> dict[str, Any]:
        out = super().summary()
        out["board"] = self.board.summary()
        out["natnet"] = dict(self.natnet.counts)
        return out


NOT_ON_BOARD = ("pose", "depth")  # outdoors: no motion capture; the D435 (the camera service) instead of the twin's depth
DRIFT_EVERY_TICKS = 100  # the estimate against the truth at 10 Hz: the drift changes over hops, not ticks


class OnboardSensing:
    """A twin without motion capture, outdoors as ARCHER is built (``archer sim --mode realtime
    --sensing onboard``; mixed into :class:`TwinService` or :class:`FirmwareTwinService`).

    It publishes no ``pose`` and none of its own depth images: the D435 is ``depth_camera``
    (:class:`services.cli.realsense_realtime.RealsenseRig`), started on this twin's compiled model and
    handed the scene every tick. The estimate's drift from the truth (:class:`sim_twin.drift.EstimateDrift`)
    is measured on the loop at ``DRIFT_EVERY_TICKS`` and goes into the summary.
    """

    def __init__(self, *args: Any, depth_camera: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.depth_camera = depth_camera
        self.drift: EstimateDrift | None = None
        self._drift_ticks = 0

    async def setup(self) -> None:
        await super().setup()  # type: ignore[misc]
        self.drift = EstimateDrift(self.truth)  # type: ignore[attr-defined]
        self.depth_camera.start(self.model, self.scenario.traversable, self.params["twin"].seed)  # type: ignore[attr-defined]

    def _sensor_suite(self, tp: TwinParams) -> SensorSuite:
        suite = super()._sensor_suite(tp)  # type: ignore[misc]
        suite.capture_depth = False  # nobody reads the twin's own depth: no ray casting on the loop
        return suite

    def _deliver(self, topic: str, msg: Any) -> None:
        if topic not in NOT_ON_BOARD:
            super()._deliver(topic, msg)  # type: ignore[misc]

    def _after_step(self, now_ns: int) -> None:
        super()._after_step(now_ns)  # type: ignore[misc]
        data = self.data  # type: ignore[attr-defined]
        self.depth_camera.write(now_ns, data)
        self._drift_ticks += 1
        if self._drift_ticks % DRIFT_EVERY_TICKS == 0 and self.drift is not None:
            got = self.state_slot.get()  # type: ignore[attr-defined]
            if got is not None and got[0].valid:
                self.drift.update(now_ns, data, _estimate_at(got[0], now_ns))

    async def main(self) -> None:
        # The physics starts once the camera is up, as the robot's camera unit is before it hops: the rig's
        # start-up (spawning Python, loading MuJoCo, librealsense and Zenoh) took the cores from the 1 kHz
        # loops and the robot fell in its first 2 s (tests/test_onboard_realtime.py, 3 of 5 runs)
        while not self.depth_camera.ready:
            failure = self.depth_camera.poll()
            if failure is not None:
                self.fail(failure)  # type: ignore[attr-defined]
                raise RuntimeError(failure)
            await asyncio.sleep(STATUS_POLL_S)
        physics = asyncio.create_task(super().main())  # type: ignore[misc]
        try:
            while not physics.done():
                await asyncio.wait({physics}, timeout=STATUS_POLL_S)
                failure = self.depth_camera.poll()
                if failure is not None:
                    self.fail(failure)  # type: ignore[attr-defined]
                    raise RuntimeError(failure)
            physics.result()
        finally:
            physics.cancel()
            await asyncio.gather(physics, return_exceptions=True)

    def summary(self) -> dict[str, Any]:
        out = super().summary()  # type: ignore[misc]
        out["sensing"] = "onboard"
        if self.drift is not None:
            out.update(self.drift.summary())
        return out


def _estimate_at(state: msgs.StateEstimate, now_ns: int) -> msgs.StateEstimate:
    """The estimate moved on by its velocity to ``now_ns`` (a few ms older than the truth it is held
    against: at a hop's 1 m/s, millimetres of drift that are only age)."""
    dt = (now_ns - state.stamp_ns) / NS
    moved = [p + v * dt for p, v in zip(state.position, state.velocity)]
    return msgspec.structs.replace(state, position=moved)


class OnboardTwinService(OnboardSensing, TwinService):
    """:class:`TwinService` without motion capture (:class:`OnboardSensing`)."""


class OnboardFirmwareTwinService(OnboardSensing, FirmwareTwinService):
    """:class:`FirmwareTwinService` without motion capture (:class:`OnboardSensing`)."""


class ScenarioReferenceService(Service):
    """Publishes the twin scenario's own CoM reference under the planner's name (no planner running)."""

    name = "planner"
    params_sections = ("twin",)

    async def main(self) -> None:
        scenario = make_scenario(self.params["twin"])
        pub = self.publisher("reference")
        t_ref_ns = self.clock.now_ns()
        while not self.stopping.is_set():
            pub.put(scenario.reference(t_ref_ns))
            self.rate("reference").tick()
            try:
                await asyncio.wait_for(self.stopping.wait(), REFERENCE_PERIOD_S)
            except asyncio.TimeoutError:
                pass


class OverheadTwinService(TwinService):
    """The twin with the indoor lab's overhead camera (issue 28): at ``rate_hz`` of wall time it samples
    the scene as it is now (where the obstacles have been moved, where the robot stands), stamped on the
    stack's clock, and hands it to ``stream`` (:class:`services.cli.overhead_realtime.SceneStream`),
    whose own process draws the frame and serves it as an IP camera's MJPEG stream, which the
    ``camera_overhead`` service reads through ``cv2.VideoCapture``. Drawing a frame takes tens of
    milliseconds of a core: not in this process, whose loop runs at the twin's real-time priority
    and whose GIL a drawing thread would hold."""

    def __init__(self, *args: Any, stream: Any, rate_hz: float, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.stream = stream
        self.camera_rate_hz = rate_hz
        self.camera_error: BaseException | None = None
        self._camera_stop = threading.Event()
        self._camera_thread: threading.Thread | None = None

    async def setup(self) -> None:
        await super().setup()
        self._root_qp = int(self.model.joint(rd.ROOT_JOINT).qposadr[0])
        self._camera_thread = threading.Thread(target=self._camera_loop, name="twin-overhead-camera", daemon=True)

    def _camera_loop(self) -> None:
        period = 1.0 / self.camera_rate_hz
        next_t = time.monotonic()
        try:
            while not self._camera_stop.wait(max(0.0, next_t - time.monotonic())):
                next_t = max(next_t + period, time.monotonic())
                # the loop thread moves the obstacles meanwhile: a copy, as they are now
                offsets = self.scenario.offsets.copy()
                robot_xy = (float(self.data.qpos[self._root_qp]), float(self.data.qpos[self._root_qp + 1]))
                self.stream.send(self.clock.now_ns(), offsets, robot_xy)
        except BaseException as exc:  # reported by main(): the twin goes to error
            self.camera_error = exc

    async def main(self) -> None:
        assert self._camera_thread is not None
        self._camera_thread.start()
        physics = asyncio.create_task(super().main())
        try:
            while not physics.done():
                await asyncio.wait({physics}, timeout=STATUS_POLL_S)
                if self.camera_error is not None:
                    self.fail(f"overhead camera: {self.camera_error!r}")
                    raise RuntimeError("the twin's overhead camera failed") from self.camera_error
            physics.result()
        finally:
            physics.cancel()
            await asyncio.gather(physics, return_exceptions=True)
            self._camera_stop.set()
            await asyncio.to_thread(self._camera_thread.join, 2.0)
