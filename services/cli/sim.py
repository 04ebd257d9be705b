"""``archer sim``: run a scenario on the digital twin with the onboard stack in the loop.

``--mode lockstep`` (default) steps physics and stack together on simulated time, as fast as the
machine goes, deterministically per seed.

``--mode realtime`` is software in the loop: the twin service (:mod:`services.twin`) runs in
this process paced to wall time, and every other service of the stack (``estimator``, ``control``,
``planner``; whichever ``archer run`` knows) runs as its own process (``archer run NAME``) on the
same Zenoh endpoint, exactly as on the robot with the twin in place of the hardware. With
``--planner scenario`` (or ``auto`` in a scenario without obstacles) the scenario's own reference is
published by :class:`services.twin.ScenarioReferenceService` instead of the planner.

``--hardware archer-firmware`` (realtime) runs the robot as it is built: the twin sits behind
emulated ARCHER boards (flywheel board with its attitude PD, foot board with its hop cycle; UDP,
``docs/archer_firmware_protocol.md``) and an OptiTrack NatNet stream of its pose, all on
127.0.0.1 with free ports (:class:`services.twin.FirmwareTwinService`); the stack adds the
``hardware`` service (``hardware.backend = "archer-firmware"``) and the ``mocap`` service, and
control runs in attitude mode (``control.output = "attitude"``). The services get these settings
(and the ports) in a generated config file next to ``--config``'s. The physics metrics are the
twin's, as in any realtime run, plus the boards' and the NatNet server's counters.

With ``--json`` the last line of stdout is one JSON object of metrics (definitions in
:mod:`sim_twin.metrics`).
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import json
import logging
import math
import os
import signal
import sys
import tempfile
import threading
import time
import tomllib
from pathlib import Path
from typing import Any

from drivers.udp import free_udp_port
from onboard.contracts.params import as_dict, with_overrides
from robot_description import params as rd
from services.runtime.config import ConfigError, load_params
from services.runtime.service import EXIT_SIGINT
from sim_twin import scenarios as sc
from sim_twin import stack as st
from sim_twin.lockstep import RunConfig, run
from services.cli.overhead_world import overhead_world

log = logging.getLogger("archer.sim")

MODES = ("lockstep", "realtime")
STACK_SERVICES = ("estimator", "control", "planner")  # spawned in realtime mode when archer run knows them
HARDWARE = ("twin", "archer-firmware")
FIRMWARE_SERVICES = ("hardware", "mocap")  # with --hardware archer-firmware, before the stack's
LOOPBACK = "127.0.0.1"
PLANNER_COUNTS = ("plans", "no_path", "unseen_holds")  # of the planner's status, into a real-time run's report
START_TIMEOUT_S = 20.0  # [s] for the twin to open its session
ROUTINE_UNIT_EVENTS = ("start", "ready")  # the rest says why a unit went down
SERVICES_START_TIMEOUT_S = 120.0  # [s] for every service to report READY (the planner compiles its kernels)
STOP_DEADLINE_S = 2.9  # [s] after SIGINT/SIGTERM the run is gone by then, its services with it
PROGRESS_MIN_S = 10.0  # [s of sim] shorter runs get no progress bar
# A real-time run lasts --duration of the twin's time, so that the scenario's events (pushes,
# flips, all in its time) happen alike on a busy machine, whose twin falls behind the wall;
# it ends anyway after this many times the duration of wall time (the twin stalled).
REALTIME_WALL_CAP = 3.0
BAR_WIDTH = 30
FINAL_STATUS_TRIES = 3  # the run's end is a busy moment on a small host: a status query may time out once


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", required=True, choices=list(sc.SCENARIOS), help="what to run")
    parser.add_argument("--seed", type=int, default=0, help="seeds every random choice (sensor noise, world, pushes)")
    parser.add_argument("--duration", type=float, default=None, help="simulated seconds (default: the scenario's)")
    parser.add_argument("--mode", choices=MODES, default="lockstep",
                        help="lockstep: as fast as possible, deterministic; realtime: twin + services as processes, wall time")
    parser.add_argument("--variant", choices=rd.VARIANTS, default=rd.DEFAULT_VARIANT, help="robot model variant")
    parser.add_argument("--estimator", choices=st.ESTIMATORS, default="kalman",
                        help="kalman: the onboard estimator on the twin's sensors; truth: the twin's true state")
    parser.add_argument("--planner", choices=st.PLANNERS, default="auto",
                        help="scenario: the scenario's own reference; graph: the onboard planner; auto: graph when there are obstacles")
    parser.add_argument("--controller", choices=st.CONTROLLERS, default="lowlevel", help="passive: no torque (physics only)")
    parser.add_argument("--mid-level", choices=("zdp", "geometric_mpc"), default=None,
                        help="the low level's planning layer (default: control.mid_level of the config, zdp)")
    parser.add_argument("--perception", choices=("truth", "depth"), default="truth",
                        help="the planner sees ground-truth obstacles, or what perception makes of the depth camera "
                             "(in real time: the perception service)")
    parser.add_argument("--obstacles-from", choices=("truth", "overhead"), default="truth",
                        help="lockstep: the planner's world from the ground truth, or from the twin's rendered overhead "
                             "view through the camera_overhead pipeline at camera_overhead.rate_hz; realtime: the twin "
                             "streams that view (MJPEG over HTTP, 127.0.0.1) to the camera_overhead service")
    parser.add_argument("--sensing", choices=("mocap", "onboard"), default="mocap",
                        help="onboard: no motion capture (outdoors); the estimator keeps an odometry frame from the IMU, "
                             "leg kinematics and the D435's visual odometry, and the run reports its drift per metre "
                             "(realtime: the D435 through librealsense's software device, triggered at each apex)")
    parser.add_argument("--obstacles", type=int, default=None, help="forest: number of obstacles")
    parser.add_argument("--config", default=None, help="TOML file overriding onboard.contracts.params sections")
    parser.add_argument("--no-noise", action="store_true", help="sensors read the true state")
    parser.add_argument("--model-error", default=None, metavar="PROFILE",
                        help="the twin's physics drawn per seed around the MJCF, the stack nominal: nominal, calibrated, "
                             "datasheet (sim_twin/model_errors/), a TOML file, or name=value;... (sim_twin.model_error)")
    parser.add_argument("--keep-going", action="store_true", help="do not stop at the first fall")
    parser.add_argument("--json", action="store_true", help="print the metrics as one JSON object (last stdout line)")
    parser.add_argument("--record", default=None, metavar="FILE.mcap", help="write every message to an MCAP file")
    parser.add_argument("--plot", default=None, metavar="FILE.png", help="write a PNG summary")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--endpoint", default=None, help="realtime: Zenoh endpoint (default tcp/127.0.0.1:7447)")
    parser.add_argument("--namespace", default=None, help="realtime: key namespace (default archer/robot0)")
    parser.add_argument("--join", action="store_true",
                        help="realtime: join the router already serving the endpoint (default: refuse to start)")
    parser.add_argument("--hardware", choices=HARDWARE, default="twin",
                        help="realtime: twin: the twin publishes the sensors and takes torques; archer-firmware: the twin "
                             "behind emulated ARCHER boards (UDP) and an OptiTrack stream, driven by the hardware and mocap services")
    parser.add_argument("--view", action="store_true",
                        help="a live Foxglove view on ws://127.0.0.1:8765 (realtime: the view service beside the twin; "
                             "lockstep: the run paced to wall time, started once a viewer subscribes or after view.lockstep_wait_s)")
    parser.add_argument("--view-port", type=int, default=None, metavar="N",
                        help="with --view: the view's WebSocket port (default view.port, 8765)")
    parser.add_argument("--standby", action="store_true",
                        help="realtime: a hot standby beside the estimator and control (units <name>_standby), which "
                             "takes over when the first one's liveliness goes (kill -9, crash)")
    parser.add_argument("--services", default="auto",
                        help="realtime: comma list of services to run as processes, or 'none' "
                             "(auto: estimator, control and planner, each if archer run knows it)")


class _Progress:
    """A progress bar on stderr: redrawn in place on a terminal, a line per 10 % otherwise."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self.tty = sys.stderr.isatty()
        self.t0 = time.perf_counter()
        self.last_decile = -1

    def __call__(self, sim_t: float, total: float) -> None:
        if not self.enabled or total <= 0:
            return
        frac = min(1.0, sim_t / total)
        wall = time.perf_counter() - self.t0
        rtf = sim_t / wall if wall > 0 else math.inf
        text = f"[{'#' * int(frac * BAR_WIDTH):<{BAR_WIDTH}}] {sim_t:7.1f}/{total:.1f} s sim  {rtf:5.1f}x real time"
        if self.tty:
            sys.stderr.write("\r" + text + ("\n" if frac >= 1.0 else ""))
            sys.stderr.flush()
        elif int(frac * 10) > self.last_decile:
            self.last_decile = int(frac * 10)
            print(text, file=sys.stderr, flush=True)


def build_config(args: argparse.Namespace) -> RunConfig:
    params = load_params(args.config)
    if getattr(args, "mid_level", None):
        params["control"] = with_overrides(params["control"], {"mid_level": args.mid_level})
    twin = params["twin"]
    if args.no_noise:
        twin = with_overrides(twin, {"noise": False})
    return RunConfig(
        scenario=args.scenario,
        seed=args.seed,
        duration_s=args.duration,
        variant=args.variant,
        estimator=args.estimator,
        planner=args.planner,
        controller=args.controller,
        obstacles=args.obstacles,
        twin=twin,
        safety=with_overrides(params["safety"], robot_safety(args)) if args.config else None,
        estimator_params=params.get("estimator"),
        planner_params=params.get("planner"),
        control_params=params.get("control"),
        gmpc_params=params.get("gmpc"),
        perception=args.perception,
        perception_params=params.get("perception"),
        stop_on_fall=not args.keep_going,
        record=bool(args.record),
        world=overhead_world(load_params(args.config, ("camera_overhead",))["camera_overhead"])
        if getattr(args, "obstacles_from", "truth") == "overhead" else None,
        model_error=getattr(args, "model_error", None),
        sensing=getattr(args, "sensing", "mocap"),
    )


def run_lockstep(args: argparse.Namespace) -> dict:
    if getattr(args, "hardware", "twin") != "twin":
        raise ValueError("--hardware archer-firmware is a realtime option (the boards run on their own clocks)")
    view = _LockstepView(args) if getattr(args, "view", False) else None
    cfg = build_config(args)
    if view is not None:
        cfg = dataclasses.replace(cfg, sink=view)
    duration = cfg.duration_s if cfg.duration_s is not None else sc.SCENARIOS[cfg.scenario](cfg.seed, cfg.obstacles).default_duration_s
    progress = _Progress(enabled=not args.quiet and duration >= PROGRESS_MIN_S)
    try:
        if view is not None:
            view.wait_for_viewer()
        result = run(cfg, progress)
    finally:
        if view is not None:
            view.close()
    if args.record:
        from onboard.contracts.topics import TOPICS, namespace
        from services.scene import SceneRecording
        from sim_twin.record import write_mcap

        # the scene channels beside the raw topics, drawn as the live view draws them; lockstep times start at 0
        ns = args.namespace or namespace()
        scene = SceneRecording(ns, with_overrides(load_params(args.config, ("view",))["view"], {"variant": args.variant}))

        def scene_records(topic: str, log_ns: int, msg: object):
            rate = TOPICS[topic].rate_hz if topic in TOPICS else 0.0
            return scene.records(topic, msg, log_ns) if scene.due(topic, rate, log_ns) else ()

        result.metrics["recorded_messages"] = write_mcap(args.record, result.messages, ns, extra=scene_records)
    if args.plot:
        from sim_twin.plot import plot_run

        plot_run(result, args.plot)
    return result.metrics


class _LockstepView:
    """``--view`` in lockstep: the run paced to wall time and shown on a Foxglove server as it goes.

    No Zenoh here: the runner hands each message over (``RunConfig.sink``); fast topics are
    thinned to ``view.max_rate_hz`` of simulated time, as the view service does.
    """

    def __init__(self, args: argparse.Namespace) -> None:
        from onboard.contracts.topics import namespace
        from services.view import FoxgloveBridge

        changes: dict[str, Any] = {"variant": args.variant}
        if args.view_port is not None:
            changes["port"] = args.view_port
        self.params = with_overrides(load_params(args.config, ("view",))["view"], changes)
        self.bridge = FoxgloveBridge(args.namespace or namespace(), self.params)
        self.period_ns = int(1e9 / self.params.max_rate_hz)
        self.last_ns: dict[str, int] = {}
        self.wall0: float | None = None  # set by the run's first message: building the run takes its time
        self.epoch0 = 0
        print(f"archer sim: live view on ws://{self.params.host}:{self.bridge.port} (Foxglove: open connection)", file=sys.stderr)

    def wait_for_viewer(self) -> None:
        deadline = time.monotonic() + self.params.lockstep_wait_s
        while not self.bridge.watched() and time.monotonic() < deadline:
            time.sleep(0.05)

    def __call__(self, topic_name: str, sim_ns: int, msg: object) -> None:
        from onboard.contracts.topics import TOPICS

        topic = TOPICS[topic_name]
        if self.wall0 is None:
            self.wall0 = time.monotonic() - sim_ns / 1e9
            self.epoch0 = time.time_ns() - sim_ns
        if topic.rate_hz > self.params.max_rate_hz:
            if sim_ns - self.last_ns.get(topic_name, -self.period_ns) < self.period_ns:
                return
            self.last_ns[topic_name] = sim_ns
        ahead = sim_ns / 1e9 - (time.monotonic() - self.wall0)
        if ahead > 0.0:  # paced: simulated time never runs ahead of the wall clock
            time.sleep(ahead)
        self.bridge.send(topic, msg, self.epoch0 + sim_ns)

    def close(self) -> None:
        self.bridge.stop()


def _take_twin_priority() -> None:
    """This process runs the twin: give it the twin unit's scheduling before any thread
    starts, so that its Zenoh threads share it (the supervised services get their own)."""
    from services.runtime.supervisor import apply_unit_scheduling, spec_from_unit

    for what, detail in apply_unit_scheduling(spec_from_unit("twin", []), 0):
        log.warning("twin scheduling refused", extra={"fields": {"event": what, "detail": detail}})


def _toml(data: dict[str, dict[str, Any]]) -> str:
    """Tables of scalars and arrays as TOML (a JSON scalar or array is TOML's, NaN and inf aside)."""
    lines = []
    for section, table in data.items():
        lines.append(f"[{section}]")
        lines += [f"{key} = {json.dumps(list(v) if isinstance(v, tuple) else v)}" for key, v in table.items()]
        lines.append("")
    return "\n".join(lines)


class FirmwareRig:
    """The emulated ARCHER boards and the NatNet server of ``--hardware archer-firmware``, bound
    before the stack starts, and the config file that tells the services where they are."""

    def __init__(self, config: str | None, variant: str) -> None:
        from drivers.archer_firmware.emulator import BoardEmulator
        from drivers.natnet import NatNetServer
        from onboard.low_level.tracking.foot_control import FootPhysics

        params = load_params(config, ("archer_firmware", "mocap", "control"))
        user = tomllib.loads(Path(config).read_text()) if config else {}
        self.firmware, self.mocap = params["archer_firmware"], params["mocap"]
        if not {"kp_tilt", "kp_yaw", "kd_tilt", "kd_yaw"} & set(user.get("archer_firmware", {})):
            # the board configured as the control gains say: its PD acts on Im(q), the loop's on 2 Im(q)
            c = params["control"]
            self.firmware = with_overrides(self.firmware, {"kp_tilt": 2.0 * c.kp_tilt, "kp_yaw": 2.0 * c.kp_yaw,
                                                           "kd_tilt": c.kd_tilt, "kd_yaw": c.kd_yaw})
        r = rd.robot_params(variant)
        foot = FootPhysics(r.total_mass, r.gravity, r.spring_stiffness, r.spool_radius, r.foot_travel)
        computer_port = free_udp_port()
        self.board = BoardEmulator(self.firmware, foot, (LOOPBACK, 0), (LOOPBACK, computer_port), time.monotonic,
                                   wheel_axes=r.wheel_axes)
        try:
            self.natnet = NatNetServer({self.mocap.rigid_body_id: self.mocap.rigid_body}, host=LOOPBACK).start()
        except BaseException:
            self.board.close()
            raise
        overrides = {
            "hardware": {"backend": "archer-firmware"},
            "archer_firmware": {"board_host": LOOPBACK, "board_port": self.board.link.local[1],
                                "computer_host": LOOPBACK, "computer_port": computer_port},
            "mocap": {"system": "optitrack", "host": LOOPBACK, "port": self.natnet.command_port},
            "control": {"output": "attitude"},
        }
        for section, table in overrides.items():
            user[section] = {**user.get(section, {}), **table}
        fd, self.config_path = tempfile.mkstemp(prefix="archer-firmware-", suffix=".toml")
        with os.fdopen(fd, "w") as f:
            f.write(_toml(user))

    def close(self) -> None:
        self.natnet.stop()
        self.board.close()
        os.unlink(self.config_path)


ROBOT_SECTIONS = ("control", "estimator", "planner")  # the services that read the robot's parameters


def robot_safety(args: argparse.Namespace) -> dict[str, Any]:
    """The safety limits of the robot ``--variant`` where they differ from the defaults (sim15nm: its
    raised wheel torque and speed), under those the user's ``--config`` file sets itself."""
    given = load_params(args.config)["safety"]
    user = tomllib.loads(Path(args.config).read_text()).get("safety", {}) if args.config else {}
    before = as_dict(given)
    robots = as_dict(rd.safety_limits_for(given, rd.robot_params(args.variant)))
    return {**{k: v for k, v in robots.items() if v != before[k]}, **user}


def run_config(args: argparse.Namespace) -> dict[str, Any]:
    """The config the services of a real-time run read: the user's file, with the robot
    ``--variant`` (the twin's, so every service reads the robot it drives) and ``--mid-level``."""
    load_params(args.config)  # the user's whole file is valid before anything is written
    user = tomllib.loads(Path(args.config).read_text()) if args.config else {}
    for section in ROBOT_SECTIONS:
        user[section] = {**user.get(section, {}), "robot": args.variant}
    safety = robot_safety(args)
    if safety:
        user["safety"] = safety
    mid_level = getattr(args, "mid_level", None)
    if mid_level:
        user["control"] = {**user["control"], "mid_level": mid_level}
    model_error = getattr(args, "model_error", None)
    if model_error:
        user["twin"] = {**user.get("twin", {}), "model_error": model_error}
    return user


def run_realtime(args: argparse.Namespace) -> dict:
    """The services read their parameters from the config file: :func:`run_config`, in a
    temporary file for the run."""
    user = run_config(args)
    fd, path = tempfile.mkstemp(prefix="archer-sim-", suffix=".toml")
    with os.fdopen(fd, "w") as f:
        f.write(_toml(user))
    try:
        return _run_realtime(argparse.Namespace(**{**vars(args), "config": path}))
    finally:
        os.unlink(path)


def _run_realtime(args: argparse.Namespace) -> dict:
    from services.table import SERVICES, missing_dependencies
    from services.runtime.service import exit_by_deadline, stop_signal_exit_code
    from services.runtime.peers import request_once
    from services.runtime.supervisor import Supervisor, process_of, sim_specs
    from onboard.contracts.topics import STANDBY_SERVICES, STANDBY_SUFFIX
    from services.runtime.zenoh_session import default_endpoint, endpoint_holder, endpoint_in_use
    from onboard.contracts.topics import namespace
    from services.twin import (FirmwareTwinService, OnboardFirmwareTwinService, OnboardTwinService, OverheadTwinService,
                               ScenarioReferenceService, TwinService)
    from services.cli.overhead_realtime import ObstacleProbe, OverheadRig
    from services.cli.realsense_realtime import RealsenseRig

    if args.estimator != "kalman" or args.controller != "lowlevel":
        raise ValueError("realtime mode runs the estimator and control services: --estimator kalman --controller lowlevel only")
    if args.record or args.plot:
        raise ValueError("--record and --plot are lockstep options (the flight recorder service records real-time runs)")
    params = load_params(args.config)
    overhead_wanted = getattr(args, "obstacles_from", "truth") == "overhead"  # the camera service makes the world
    onboard = getattr(args, "sensing", "mocap") == "onboard"  # no motion capture: the D435 rig, odometry
    if onboard and overhead_wanted:
        raise ValueError("--obstacles-from overhead is the indoor lab's camera; --sensing onboard is outdoors (the D435)")
    scenario = sc.make(args.scenario, args.seed, args.obstacles, sc.cruise_speed_for(rd.robot_params(args.variant)))
    duration = args.duration if args.duration is not None else scenario.default_duration_s
    if not (duration > 0 and math.isfinite(duration)):
        raise ValueError(f"duration must be positive, got {duration}")
    twin_params = with_overrides(params["twin"], {
        "scenario": args.scenario, "seed": args.seed, "variant": args.variant,
        "obstacles": -1 if args.obstacles is None else args.obstacles, "noise": params["twin"].noise and not args.no_noise,
        "publish_obstacles": args.perception == "truth" and not overhead_wanted})
    endpoint = args.endpoint or default_endpoint()
    ns = args.namespace or namespace()
    if endpoint_in_use(endpoint) and not args.join:
        # a stack left running (or someone else's) would get a second commander on its keys
        holder = endpoint_holder(endpoint)
        raise ValueError(f"{endpoint} is already served by another process{f' ({holder})' if holder else ''}; "
                         "stop it, choose another --endpoint, or pass --join to run beside it")
    planner = args.planner if args.planner != "auto" else ("graph" if scenario.obstacles else "scenario")
    firmware = getattr(args, "hardware", "twin") == "archer-firmware"
    if args.services == "auto":
        wanted = [s for s in STACK_SERVICES if not (s == "planner" and planner == "scenario")]
        if args.perception == "depth":
            if planner != "graph":
                raise ValueError("--perception depth feeds the graph planner; use --planner graph or auto")
            wanted.append("perception")  # the world from the twin's depth camera, not its ground truth
        if overhead_wanted:
            if planner != "graph" or args.perception != "truth":
                raise ValueError("--obstacles-from overhead feeds the graph planner instead of perception: "
                                 "use --planner graph or auto and --perception truth")
            wanted.append("camera_overhead")
        if firmware:  # outdoors no mocap service: there is no motion capture to read
            wanted = [*(s for s in FIRMWARE_SERVICES if not (onboard and s == "mocap")), *wanted]
    else:
        wanted = [s for s in args.services.split(",") if s and s != "none"]
        unknown = [s for s in wanted if s not in SERVICES]
        if unknown:
            raise ValueError(f"unknown services {unknown}; archer run knows {sorted(SERVICES)}")
    if getattr(args, "standby", False):  # a hot standby beside each of these that runs
        wanted += [s + STANDBY_SUFFIX for s in STANDBY_SERVICES if s in wanted]
    view = getattr(args, "view", False)
    if view and "view" not in wanted:
        wanted.append("view")
    missing = [s for s in wanted if process_of(s) not in SERVICES]
    lacking = missing_dependencies(wanted)
    if lacking:  # said before anything starts, not as a unit that never came up
        raise ValueError("; ".join(lacking))
    progress = _Progress(enabled=not args.quiet and duration >= PROGRESS_MIN_S)

    _take_twin_priority()
    stop_signal: list[int] = []  # the signal that ended the run early
    stop_requested = threading.Event()  # also read by the supervisor's waits (threads)

    def on_signal(sig: int) -> None:
        if not stop_signal:
            stop_signal.append(sig)
            exit_by_deadline(stop_signal_exit_code(sig), STOP_DEADLINE_S)
        stop_requested.set()

    async def main() -> dict:
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            # installed explicitly: a script's background job starts with SIGINT ignored
            loop.add_signal_handler(sig, on_signal, sig)
        twin_kwargs = {"ns": ns, "endpoint": endpoint, "params": {"twin": twin_params, "safety": params["safety"]}}
        if rig is not None and d435 is not None:
            twin = OnboardFirmwareTwinService(**twin_kwargs, board=rig.board, natnet_server=rig.natnet, mocap=rig.mocap,
                                              depth_camera=d435)
        elif rig is not None:
            twin = FirmwareTwinService(**twin_kwargs, board=rig.board, natnet_server=rig.natnet, mocap=rig.mocap)
        elif d435 is not None:
            twin = OnboardTwinService(**twin_kwargs, depth_camera=d435)
        elif overhead is not None:
            twin = OverheadTwinService(**twin_kwargs, stream=overhead.stream, rate_hz=overhead.rate_hz)
        else:
            twin = TwinService(**twin_kwargs)
        local = [twin]
        if planner == "scenario":
            local.append(ScenarioReferenceService(ns=ns, endpoint=endpoint, params={"twin": twin_params}))
        tasks: list[asyncio.Task] = []
        # Each service its own process under its systemd unit's policy (services/runtime/supervisor.py), a
        # router first unless one serves the endpoint already; the twin's physics starts once all
        # are up, as a robot is switched on under a running stack.
        units = [n for n in wanted if process_of(n) in SERVICES]
        units = (["router"] if units and not endpoint_in_use(endpoint) else []) + units
        sup = Supervisor(sim_specs(units, endpoint, ns, view_config.path if view_config is not None else services_config))
        wall0 = time.perf_counter()
        twin_started = time.monotonic()
        cpu0: tuple[dict[str, float], float] | None = None
        cpu_used: dict[str, float] = {}
        planner_counts: dict[str, int] = {}
        flip_errors: list[str] = []  # one per flip request sent ("" when the control service took it)
        flip_counts: dict[str, int] = {}
        probe = None
        camera_status: dict[str, Any] = {}
        planner_latency: dict[str, float] = {}
        estimator_counts: dict[str, int] = {}
        try:
            sup.start()
            if not await asyncio.to_thread(sup.wait_active, None, SERVICES_START_TIMEOUT_S, stop_requested):
                if stop_requested.is_set():
                    return {"stopped_by": signal.Signals(stop_signal[0]).name}
                raise RuntimeError(f"the services did not start: {sup.summary()}")
            tasks.append(asyncio.create_task(twin.run()))
            deadline = time.monotonic() + START_TIMEOUT_S
            while twin.state != "running":  # the twin serves the endpoint when no router does
                if tasks[0].done():
                    tasks[0].result()
                if time.monotonic() > deadline:
                    raise RuntimeError("the twin did not start")
                if stop_requested.is_set():
                    break
                await asyncio.sleep(0.02)
            tasks += [asyncio.create_task(s.run()) for s in local[1:]]
            if overhead is not None and twin.session is not None:
                probe = ObstacleProbe(twin.session, ns)
            wall0 = time.perf_counter()
            twin_started = time.monotonic()
            cpu0 = sup.cpu_seconds(), time.process_time()
            flips_due = list(scenario.flip_requests_s)  # sent as an operator would: control.flip_request
            while (twin.sim_ns / 1e9 < duration and twin.physics_wall_s < REALTIME_WALL_CAP * duration
                   and not stop_requested.is_set()):
                await asyncio.sleep(0.1)
                progress(min(twin.sim_ns / 1e9, duration), duration)
                if flips_due and twin.sim_ns / 1e9 >= flips_due[0]:
                    flips_due.pop(0)
                    flip_errors.append(await asyncio.to_thread(request_once, twin.session, ns, "control", "control.flip_request"))
                if tasks[0].done():
                    tasks[0].result()
                if twin.metrics.fell and not args.keep_going:
                    break
            if scenario.flip_requests_s and "control" in units:  # what became of the requests, as in lockstep
                status = await _final_status(twin.session, ns, "control")
                if status is not None:
                    flip_counts = {k: int(status.extra[k]) for k in ("flips", "flips_dropped", "flips_refused") if k in status.extra}
            if "camera_overhead" in units:  # what the camera made of the frames
                status = await _final_status(twin.session, ns, "camera_overhead")
                if status is not None:
                    camera_status = {"state": status.state, "last_error": status.last_error, **status.counters,
                                     **{k: round(v, 3) for k, v in status.extra.items()}}
            if d435 is not None and "estimator" in units:  # what the estimator made of the camera's odometry
                status = await _final_status(twin.session, ns, "estimator")
                if status is not None:
                    estimator_counts = {k[len("est."):]: int(v) for k, v in status.extra.items() if k.startswith("est.")}
            if "planner" in units:  # how it planned, as the lockstep runner reports it
                status = await _final_status(twin.session, ns, "planner")
                if status is not None:
                    planner_counts = {f"planner_{k}": int(status.extra[k]) for k in PLANNER_COUNTS if k in status.extra}
                    if overhead is not None:  # how the planner fared on the camera's world (what it refused, and why)
                        camera_status["planner_counters"] = dict(status.counters)
                        camera_status["planner_last_error"] = status.last_error
                        # a frame's receipt (its obstacles' stamp) to the planner's first tick on them
                        planner_latency = {k: v for k, v in status.extra.items() if k.startswith("world_to_plan_ms")}
        finally:
            run_ended = time.monotonic()  # what the stop itself does is no failure
            if cpu0 is not None:
                cpu_used = _cpu_cores(cpu0, (sup.cpu_seconds(), time.process_time()), time.perf_counter() - wall0)
            # the twin first: the run's physics ends here, not while the services stop
            for s in local:
                s.request_stop()
            await asyncio.gather(*tasks, return_exceptions=True)
            wall = time.perf_counter() - wall0
            exit_codes = await asyncio.to_thread(sup.stop)
        out = {"scenario": args.scenario, "seed": args.seed, "mode": "realtime", "variant": args.variant,
               "estimator": "kalman", "planner": planner, "controller": "lowlevel", "hardware": getattr(args, "hardware", "twin"),
               "wall_time_s": round(wall, 3)}
        out.update(twin.summary())
        out["services_started"] = sorted(exit_codes) + (["scenario_reference"] if planner == "scenario" else [])
        out["services_missing"] = missing
        out["service_exit_codes"] = exit_codes
        out["service_restarts"] = {n: u["restarts"] for n, u in sup.summary().items()}
        # why a unit went down, as systemd's journal would say (seconds since the twin started)
        out["service_failures"] = [
            {"t_s": round(e.t - twin_started, 3), "unit": e.unit, "what": e.what, "detail": e.detail}
            for e in sup.events if e.what not in ROUTINE_UNIT_EVENTS and e.t < run_ended
        ]
        out.update(planner_counts)
        if probe is not None and overhead is not None:
            probe.close()
            served = overhead.stream.finish()
            out["overhead"] = {**probe.report(served["stamps_ns"]), **planner_latency, "camera": camera_status,
                               "stream": served["summary"]}
        if d435 is not None:
            out["depth_camera"] = d435.finish()
            # the estimator's own counts, as lockstep reports them: touchdowns, anchors, what it fused and refused
            out["estimator_counters"] = estimator_counts
            out["visual_odometry"] = {k: v for k, v in estimator_counts.items() if k.startswith("vo_")}
        if scenario.flip_requests_s:
            out["flip"] = {**flip_counts, "requests_sent": len(flip_errors), "request_errors": [e for e in flip_errors if e]}
        out["endpoint"] = endpoint
        # cores each process group used while the twin ran ("sim": this process, the twin's);
        # a unit restarted meanwhile counts only its last process
        out["cpu_cores"] = cpu_used
        if stop_signal:
            out["stopped_by"] = signal.Signals(stop_signal[0]).name
        return out

    rig = FirmwareRig(args.config, args.variant) if firmware else None
    services_config = rig.config_path if rig is not None else args.config
    view_config = None
    overhead = None
    d435 = None
    try:
        if onboard:
            d435 = RealsenseRig(services_config, _toml, args.variant, endpoint, ns)
            services_config = d435.config_path
        if overhead_wanted:
            overhead = OverheadRig(services_config, _toml, scenario, args.seed)
            services_config = overhead.config_path
        if view:
            view_config = _ViewConfig(services_config, args.view_port, args.variant)
            print(f"archer sim: live view on ws://127.0.0.1:{view_config.port} (Foxglove: open connection)", file=sys.stderr)
        return asyncio.run(main())
    finally:
        if view_config is not None:
            view_config.close()
        if overhead is not None:
            overhead.close()
        if d435 is not None:
            d435.close()
        if rig is not None:
            rig.close()


class _ViewConfig:
    """The run's config file with the ``[view]`` section ``--view`` asks for (port, robot variant)."""

    def __init__(self, config: str | None, port: int | None, variant: str) -> None:
        params = load_params(config, ("view",))
        changes: dict[str, Any] = {"variant": variant}
        if port is not None:
            changes["port"] = port
        self.port = with_overrides(params["view"], changes).port  # validated before anything starts
        user = tomllib.loads(Path(config).read_text()) if config else {}
        user["view"] = {**user.get("view", {}), **changes}
        fd, self.path = tempfile.mkstemp(prefix="archer-view-", suffix=".toml")
        with os.fdopen(fd, "w") as f:
            f.write(_toml(user))

    def close(self) -> None:
        os.unlink(self.path)


async def _final_status(session: Any, ns: str, service: str) -> Any:
    """A service's status for the report, asked again where a query goes unanswered."""
    from services.runtime.peers import query_status

    for _ in range(FINAL_STATUS_TRIES):
        status = await asyncio.to_thread(query_status, session, ns, service)
        if status is not None:
            return status
    return None


def _cpu_cores(before: tuple[dict[str, float], float], after: tuple[dict[str, float], float], wall_s: float) -> dict[str, float]:
    """Cores used per unit (and by this process, ``sim``) between two CPU-time samples."""
    if wall_s <= 0:
        return {}
    units = {name: max(0.0, after[0][name] - before[0].get(name, 0.0)) / wall_s for name in after[0]}
    units["sim"] = (after[1] - before[1]) / wall_s
    units["total"] = sum(units.values())
    return {name: round(value, 3) for name, value in units.items()}


def run_sim(args: argparse.Namespace) -> int:
    """Exit code 0; 2 for what the user asked wrong; 1 when the run failed by itself."""
    try:
        if getattr(args, "view_port", None) is not None and not getattr(args, "view", False):
            raise ValueError("--view-port goes with --view")
        metrics = run_realtime(args) if args.mode == "realtime" else run_lockstep(args)
    except (ValueError, ConfigError) as exc:
        print(f"archer sim: {exc}", file=sys.stderr)
        return 2
    except RuntimeError as exc:  # SimulationError, services that did not start
        log.error("run failed", exc_info=exc)
        print(f"archer sim: {exc}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(metrics))
    else:
        width = max(len(k) for k in metrics)
        for key, value in metrics.items():
            print(f"{key:<{width}}  {value}")
    return EXIT_SIGINT if metrics.get("stopped_by") == signal.SIGINT.name else 0
