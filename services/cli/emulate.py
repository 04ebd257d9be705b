"""``archer emulate drives|teensy|archer-firmware|natnet|realsense|overhead``: run an emulated device in this process.

Prints ONE JSON line on stdout telling a client how to connect, then serves until
SIGINT/SIGTERM. Only loopback TCP or UDP, or pseudo-terminals, nothing else. The counters
go to stderr as one JSON line: ``{"final": ...}`` on exit and, for the drives, a
``{"counters": ..., "monotonic_s": ...}`` line on every SIGUSR1 (a bench's window).

- ``drives``: ELMO CiA 402 drives behind a socketcand server on 127.0.0.1. The line
  holds ``interface`` and ``channel`` plus ``bus``, the complete keyword arguments of
  ``can.Bus(**bus)`` for a stock python-can client, and ``eds``, the drives' object
  dictionary as an EDS file (what a CANopen master such as the ``canopen`` package
  loads).
- ``teensy``: a Teensy on a pseudo-terminal; ``port`` is the path to open (a stable
  symlink to the pty), speaking ``docs/teensy_protocol.md``.
- ``archer-firmware``: ARCHER's own flywheel board and foot board on UDP 127.0.0.1,
  speaking ``docs/archer_firmware_protocol.md``; the line holds the board's ``host`` and
  ``port`` and the ``peer_host``/``peer_port`` it answers (and accepts packets from only).
  Its loop runs at ``archer_firmware.rate_hz`` on a :class:`DeadlineLoop` (the board's
  own clock).
- ``natnet``: an OptiTrack Motive server (:mod:`drivers.natnet`, NatNet 3.1) on
  127.0.0.1, unicast only: ``command_port`` is where a client sends NAT_CONNECT, and
  ``motioncapture`` holds the ``motioncapture.connect(type, cfg)`` arguments. It
  streams the twin's true torso pose as rigid body ``mocap.rigid_body`` at
  ``--rate`` Hz, each frame sent ``--latency`` s after its capture (the frame's
  timestamps say so, on this host's monotonic clock). ``--truth FILE`` writes each
  frame's true pose as a JSON line. Needs ``--twin``.

- ``realsense``: a D435 through librealsense's software device with the ``camera`` service
  reading it, on the twin (:mod:`services.cli.emulate_realsense`); needs ``--twin``.
- ``overhead``: the lab's overhead camera as an IP camera's MJPEG stream over HTTP on 127.0.0.1,
  the twin's rendered view of ``--twin SCENARIO`` or a ``--video FILE`` (:mod:`services.cli.emulate_overhead`).

``--twin SCENARIO`` puts the MuJoCo twin behind the emulated devices (:class:`TwinPlant`):
the torques the emulated motors apply drive the twin's actuators, and the twin's
joints and IMU become what the devices report. The ``hardware`` service and the
drivers then run unchanged against a simulated robot. The drives step the physics one
tick per SYNC (simulated time follows the host's cycle); the Teensy and the ARCHER
board step it every millisecond of their own clock.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import signal
import sys
import tempfile
import threading
import time

from drivers.archer_firmware.emulator import BoardEmulator
from drivers.elmo.emulator import SocketcandRunner, make_emulator
from drivers.elmo.od import drive_dictionary, to_eds
from drivers.teensy.emulator import TeensyEmulator
from drivers.teensy.protocol import VERSION
from drivers import natnet
from onboard.low_level.tracking.foot_control import FootPhysics
from onboard.contracts.params import ArcherFirmwareParams, HardwareParams, MocapParams
from services.runtime.config import ConfigError, load_params
from services.runtime.realtime import DeadlineLoop, make_realtime

DOCS = "docs/teensy_protocol.md"
ARCHER_FIRMWARE_DOCS = "docs/archer_firmware_protocol.md"
LOOPBACK = "127.0.0.1"  # emulators never listen beyond this machine


class TwinMotor:
    """A :class:`~drivers.elmo.emulator.MotorModel` whose motion the twin computes."""

    def __init__(self, gear: float) -> None:
        self.gear = gear  # motor turns per joint turn
        self.position = 0.0  # [rad] motor side
        self.velocity = 0.0  # [rad/s] motor side
        self.torque = 0.0  # [N m] motor side, the last the drive applied

    def step(self, torque: float, dt_s: float) -> None:
        self.torque = torque  # the physics advances in TwinPlant.step


class TwinPlant:
    """The MuJoCo twin (scenario, physics, sensors) behind an emulated device.

    ``step(now_s, joint_torques)`` applies the torques as the twin applies a torque
    command (limits, motor curve), advances one control period, and copies what the
    twin's sensors deliver into ``motors`` (joint order: three wheels, foot motor) and
    ``body`` (IMU, foot spring, contact).
    """

    def __init__(self, scenario: str, seed: int, motor_gears: tuple[float, ...]) -> None:
        import mujoco

        from onboard.contracts.params import SafetyLimits, TwinParams, with_overrides
        from robot_description import params as rd
        from sim_twin import model as tm
        from sim_twin.actuation import Actuation
        from sim_twin.sensors import SensorSuite
        from services.twin import make_scenario
        from drivers.teensy.emulator import BodyState

        # the devices carry no camera: the smallest depth image keeps the step cheap
        tp = with_overrides(TwinParams(), {"scenario": scenario, "seed": seed, "depth_width": 2, "depth_height": 2})
        self._mujoco = mujoco
        self.scenario = make_scenario(tp)
        robot = rd.robot_params(tp.variant)
        spec = tm.load_spec(tp.variant)
        self.scenario.build(spec)
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        self.scenario.initialize(self.model, self.data, robot)
        self.substeps = max(1, round((1.0 / tp.control_rate_hz) / self.model.opt.timestep))
        self.sensors = SensorSuite(self.model, tp, seed)
        self.actuation = Actuation(self.model, robot, SafetyLimits())
        self.motors = [TwinMotor(g) for g in motor_gears]
        self.body = BodyState()
        self.sim_s = 0.0
        self.dt_s = self.substeps * self.model.opt.timestep  # [s] one control period
        self._spool_dof = int(self.model.joint(rd.FOOT_MOTOR_JOINT).dofadr[0])
        self._root_qp = int(self.model.joint(rd.ROOT_JOINT).qposadr[0])
        self._lock = threading.Lock()

    def step(self, now_s: float, joint_torques: list[float]) -> None:
        from onboard.contracts.messages import TorqueCommand

        with self._lock:
            now_ns = int(now_s * 1e9)
            cmd = TorqueCommand(wheel_torque=joint_torques[:3], foot_torque=joint_torques[3], armed=True)
            self.actuation.apply(cmd, now_ns, self.data, received_ns=now_ns)
            self.scenario.before_step(self.sim_s, self.model, self.data)
            for _ in range(self.substeps):
                self._mujoco.mj_step(self.model, self.data)
            self.sim_s += self.dt_s
            for topic, msg in self.sensors.tick(self.data, now_ns):
                if topic == "imu":
                    self.body.quat, self.body.gyro, self.body.accel = tuple(msg.quat), tuple(msg.gyro), tuple(msg.accel)
                elif topic == "joints":
                    joint_pos = (*msg.wheel_pos, msg.foot_motor_pos)
                    joint_vel = (*msg.wheel_vel, float(self.data.qvel[self._spool_dof]))  # JointSensors has no spool speed
                    for m, pos, vel in zip(self.motors, joint_pos, joint_vel):
                        m.position, m.velocity = pos * m.gear, vel * m.gear
                    self.body.foot_pos, self.body.foot_vel, self.body.contact = msg.foot_pos, msg.foot_vel, msg.foot_contact

    def body_pose(self) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
        """The torso's true position [m] and attitude (w, x, y, z) in the world, now."""
        with self._lock:
            q = self.data.qpos[self._root_qp:self._root_qp + 7].tolist()
        return (q[0], q[1], q[2]), (q[3], q[4], q[5], q[6])

    def on_sync(self, now_s: float) -> None:
        """The drive emulator's hook: one physics tick per SYNC with the drives' last torques."""
        self.step(now_s, [m.torque * m.gear for m in self.motors])


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("device", choices=("drives", "teensy", "archer-firmware", "natnet", "realsense", "overhead"))
    parser.add_argument("--node-ids", help="comma-separated CANopen node ids (default: hardware.node_ids)")
    parser.add_argument("--port", type=int, default=0,
                        help="drives: TCP port, archer-firmware: UDP port, natnet: UDP command port, on 127.0.0.1 (default: a free one)")
    parser.add_argument(
        "--peer-port", type=int, default=None,
        help="archer-firmware: the computer's UDP port on 127.0.0.1, the only sender accepted (default: archer_firmware.computer_port)",
    )
    parser.add_argument("--channel", default=None, help="drives: socketcand channel name (default: hardware.can_channel)")
    parser.add_argument("--config", help="TOML file overriding parameters (sections hardware, safety, archer_firmware, mocap)")
    parser.add_argument("--rate", type=float, help="natnet: frames per second, 100-240 (default: mocap.rate_hz)")
    parser.add_argument("--latency", type=float, help="natnet: capture to transmit [s] (default: mocap.latency_s)")
    parser.add_argument("--truth", help="natnet: write every frame's true pose to this file (JSON lines)")
    parser.add_argument("--video", help="overhead: stream this video file's frames (looped) instead of --twin's view")
    parser.add_argument("--twin", metavar="SCENARIO", help="put the MuJoCo twin running SCENARIO behind the devices")
    parser.add_argument("--endpoint", default=None, help="realsense: the Zenoh endpoint its camera service joins")
    parser.add_argument("--namespace", default=None, help="realsense: the key namespace (default archer/robot0)")
    parser.add_argument("--truth-pose", action="store_true",
                        help="realsense: place the frames by the twin's true pose (no estimator running)")
    parser.add_argument("--seed", type=int, default=0, help="--twin: scenario and sensor-noise seed")
    parser.add_argument(
        "--rt-priority", type=int, default=0,
        help="SCHED_FIFO priority for the emulator's threads when permitted (0: none); the emulated "
        "devices stand in for silicon that never waits for the host's CPU",
    )


def _node_ids(text: str) -> tuple[int, ...]:
    try:
        ids = tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise ConfigError(f"--node-ids {text!r}: expected comma-separated integers") from None
    if not ids or any(not 1 <= i <= 127 for i in ids) or len(set(ids)) != len(ids):
        raise ConfigError(f"--node-ids {text!r}: distinct ids in 1..127 needed")
    return ids


def _stop_on_signal() -> threading.Event:
    """Installed before the JSON line goes out: a client may signal as soon as it reads it."""
    done = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: done.set())
    return done


def _wait(done: threading.Event) -> None:
    while not done.wait(0.5):
        pass


def _gear_ratios() -> tuple[float, ...]:
    from services.hardware import gear_ratios

    return gear_ratios()


def run_drives(params: HardwareParams, port: int, channel: str, plant: TwinPlant | None = None) -> int:
    n = len(params.node_ids)
    per_joint = {name: getattr(params, name) for name in ("torque_constant", "current_max")}
    for name, values in per_joint.items():
        if len(values) < n:  # more drives than configured joints: repeat the last joint's settings
            per_joint[name] = tuple(values) + (values[-1],) * (n - len(values))
    params = dataclasses.replace(params, **per_joint)
    done = _stop_on_signal()
    emulator = make_emulator(params, plant.motors if plant is not None else None)

    def report_counters(*_: object) -> None:  # runs on the main thread, which only waits
        line = json.dumps({"counters": emulator.summary(), "monotonic_s": time.monotonic()})
        print(line, file=sys.stderr, flush=True)

    signal.signal(signal.SIGUSR1, report_counters)
    if plant is not None:
        emulator.on_sync = plant.on_sync
    eds_dir = tempfile.mkdtemp(prefix="archer-drives-")
    eds_path = os.path.join(eds_dir, "archer_elmo.eds")
    first = params.node_ids[0]
    with open(eds_path, "w") as f:
        f.write(to_eds(drive_dictionary(first, emulator.drive(first).cfg), first))
    runner = SocketcandRunner(emulator, channel, port).start()
    bus = runner.bus_kwargs()
    print(
        json.dumps(
            {
                "device": "drives",
                "interface": bus["interface"],
                "channel": bus["channel"],
                "bus": bus,
                "bitrate": params.can_bitrate,
                "node_ids": list(params.node_ids),
                "host_node_id": params.host_node_id,
                "eds": eds_path,
                "pid": os.getpid(),
            }
        ),
        flush=True,
    )
    try:
        _wait(done)
    finally:
        runner.stop()
        os.unlink(eds_path)
        os.rmdir(eds_dir)
        print(json.dumps({"final": emulator.summary()}), file=sys.stderr, flush=True)  # counters for benches
    return 0 if runner.error is None else 1


def run_teensy(params: HardwareParams, plant: TwinPlant | None = None) -> int:
    done = _stop_on_signal()
    emulator = TeensyEmulator(params, _gear_ratios(), motors=plant.motors if plant is not None else None,
                              body=plant.body if plant is not None else None)
    if plant is not None:
        emulator.on_step = plant.step
    emulator.start()
    print(
        json.dumps(
            {
                "device": "teensy",
                "port": emulator.port,
                "pty": os.path.realpath(emulator.port),
                "protocol": DOCS,
                "version": VERSION,
                "pid": os.getpid(),
            }
        ),
        flush=True,
    )
    try:
        _wait(done)
    finally:
        emulator.stop()
        print(json.dumps({"final": emulator.counts}), file=sys.stderr, flush=True)  # counters for benches
    return 0 if emulator.error is None else 1

NATNET_RATE_HZ = (100.0, 240.0)  # what OptiTrack systems stream at


def run_natnet(params: MocapParams, plant: TwinPlant, port: int, rate_hz: float, latency_s: float,
               truth_path: str | None) -> int:
    """Stream the twin's true pose over NatNet; the twin runs unactuated at its control rate."""
    done = _stop_on_signal()
    server = natnet.NatNetServer({params.rigid_body_id: params.rigid_body}, command_port=port).start()
    ticks_per_frame = max(1, round(1.0 / (rate_hz * plant.dt_s)))
    latency_ns = round(latency_s * 1e9)
    pending: list[natnet.Frame] = []  # captured, not yet due
    truth = open(truth_path, "w") if truth_path else None
    counter = {"tick": 0, "frame": 0}
    zero = [0.0, 0.0, 0.0, 0.0]

    def tick(_deadline_s: float) -> None:
        now_ns = time.monotonic_ns()
        plant.step(now_ns / 1e9, zero)
        counter["tick"] += 1
        if counter["tick"] % ticks_per_frame == 0:
            counter["frame"] += 1
            pos, quat = plant.body_pose()
            body = natnet.RigidBodySample(params.rigid_body_id, pos, quat)
            pending.append(natnet.Frame(counter["frame"], (body,), now_ns, now_ns + latency_ns, plant.sim_s))
            if truth is not None:
                truth.write(json.dumps({"frame": counter["frame"], "exposure_ns": now_ns, "position": pos, "quat": quat}) + "\n")
        while pending and pending[0].received_ns <= now_ns:
            server.publish(pending.pop(0), now_ns)

    loop = DeadlineLoop(plant.dt_s, tick, name="natnet-twin")
    loop.start()
    print(
        json.dumps(
            {
                "device": "natnet",
                "host": server.host,
                "command_port": server.command_port,
                "data_port": server.data_port,
                "multicast": False,
                "protocol": f"NatNet {'.'.join(map(str, natnet.PROTOCOL_VERSION[:2]))}",
                "rigid_body": params.rigid_body,
                "rigid_body_id": params.rigid_body_id,
                "rate_hz": 1.0 / (ticks_per_frame * plant.dt_s),
                "latency_s": latency_ns / 1e9,
                "motioncapture": {"type": "optitrack",
                                  "cfg": {"hostname": server.host, "port_command": str(server.command_port)}},
                "pid": os.getpid(),
            }
        ),
        flush=True,
    )
    try:
        while not done.wait(0.5) and loop.error is None and server.error is None:
            pass
    finally:
        loop.stop(2.0)
        server.stop()
        if truth is not None:
            truth.close()
        print(json.dumps({"final": dict(server.counts), "overruns": loop.recorder.stats().overruns}), file=sys.stderr, flush=True)
    return 0 if loop.error is None and server.error is None else 1


def _board_geometry() -> tuple[FootPhysics, tuple[tuple[float, float, float], ...]]:
    """The foot board's spring and spool and the flywheel board's wheel axes, from the MJCF model."""
    from robot_description.params import robot_params  # the one source of physical parameters

    r = robot_params()
    return FootPhysics(r.total_mass, r.gravity, r.spring_stiffness, r.spool_radius, r.foot_travel), tuple(r.wheel_axes)


def run_archer_firmware(params: ArcherFirmwareParams, port: int, peer_port: int, plant: TwinPlant | None = None) -> int:
    done = _stop_on_signal()
    foot, axes = _board_geometry()
    try:
        emulator = BoardEmulator(
            params, foot, (LOOPBACK, port), (LOOPBACK, peer_port), time.perf_counter,  # the DeadlineLoop's clock
            wheel_axes=axes, motors=plant.motors if plant is not None else None, body=plant.body if plant is not None else None,
        )
    except OSError as exc:  # the port is taken
        print(f"archer emulate: cannot bind UDP {LOOPBACK}:{port}: {exc}", file=sys.stderr)
        return 2
    if plant is not None:
        emulator.on_step = plant.step
    loop = DeadlineLoop(1.0 / params.rate_hz, emulator.tick, name="archer-firmware-emulator")
    host, bound_port = emulator.link.local
    print(
        json.dumps(
            {
                "device": "archer-firmware",
                "host": host,
                "port": bound_port,
                "peer_host": LOOPBACK,
                "peer_port": peer_port,
                "protocol": ARCHER_FIRMWARE_DOCS,
                "rate_hz": params.rate_hz,
                "watchdog_s": params.watchdog_s,
                "twin": plant is not None,
                "pid": os.getpid(),
            }
        ),
        flush=True,
    )
    loop.start()
    try:
        while not done.wait(0.5) and loop.error is None:
            pass
    finally:
        loop.stop()
        emulator.close()
        final = {**emulator.summary(), **{f"loop_{k}": v for k, v in loop.recorder.stats().as_dict().items()}}
        print(json.dumps({"final": final}), file=sys.stderr, flush=True)  # counters for tests and benches
    return 0 if loop.error is None else 1


def run(args: argparse.Namespace) -> int:
    if args.device == "archer-firmware":
        return _run_archer_firmware(args)
    if args.device == "natnet":
        return _run_natnet(args)
    if args.device == "overhead":  # --rate: frames per second (default camera_overhead.rate_hz); --port: its HTTP port
        from services.cli import emulate_overhead

        return emulate_overhead.run(args, _stop_on_signal())
    if args.device == "realsense":
        from services.cli import emulate_realsense

        return emulate_realsense.run(args, lambda: TwinPlant(args.twin, args.seed, (1.0,) * len(_gear_ratios())))
    try:
        params = load_params(args.config, ("hardware", "safety"))["hardware"]
        if args.node_ids:
            ids = _node_ids(args.node_ids)
            params = dataclasses.replace(params, node_ids=ids)
    except ConfigError as exc:
        print(f"archer emulate: {exc}", file=sys.stderr)
        return 2
    if args.rt_priority:
        make_realtime(args.rt_priority)  # before any thread starts: they inherit the policy
    plant = None
    if args.twin:
        gears = _gear_ratios()
        if args.device == "drives":
            if len(params.node_ids) != len(gears):
                print("archer emulate: --twin needs one drive per joint (4 node ids)", file=sys.stderr)
                return 2
            plant = TwinPlant(args.twin, args.seed, gears)  # drives report motor-side values
        else:
            plant = TwinPlant(args.twin, args.seed, (1.0,) * len(gears))  # the Teensy reports joint values
    if args.device == "drives":
        return run_drives(params, args.port, args.channel or params.can_channel, plant)
    return run_teensy(params, plant)


def _run_archer_firmware(args: argparse.Namespace) -> int:
    try:
        params: ArcherFirmwareParams = load_params(args.config, ("archer_firmware",))["archer_firmware"]
    except ConfigError as exc:
        print(f"archer emulate: {exc}", file=sys.stderr)
        return 2
    peer_port = args.peer_port if args.peer_port is not None else params.computer_port
    if not (0 <= args.port <= 65535 and 1 <= peer_port <= 65535):
        print("archer emulate: --port must be in 0..65535 and --peer-port in 1..65535", file=sys.stderr)
        return 2
    if args.rt_priority:
        make_realtime(args.rt_priority)  # before any thread starts: they inherit the policy
    plant = TwinPlant(args.twin, args.seed, (1.0,) * 4) if args.twin else None  # the board reports joint values
    return run_archer_firmware(params, args.port, peer_port, plant)


def _run_natnet(args: argparse.Namespace) -> int:
    try:
        params = load_params(args.config, ("mocap",))["mocap"]
    except ConfigError as exc:
        print(f"archer emulate: {exc}", file=sys.stderr)
        return 2
    rate_hz = args.rate if args.rate is not None else params.rate_hz
    latency_s = args.latency if args.latency is not None else params.latency_s
    if not args.twin:
        print("archer emulate natnet: --twin SCENARIO is needed (the pose it streams is the twin's)", file=sys.stderr)
        return 2
    if not NATNET_RATE_HZ[0] <= rate_hz <= NATNET_RATE_HZ[1] or not 0.0 <= latency_s < 1.0:
        print(f"archer emulate natnet: --rate within {NATNET_RATE_HZ} Hz and 0 <= --latency < 1 s needed", file=sys.stderr)
        return 2
    if args.rt_priority:
        make_realtime(args.rt_priority)
    plant = TwinPlant(args.twin, args.seed, (1.0,) * len(_gear_ratios()))
    return run_natnet(params, plant, args.port, rate_hz, latency_s, args.truth)
