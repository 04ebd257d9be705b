"""The ``control`` service: the 1 kHz low level (issue 4).

Subscribes (latest value): ``state`` (StateEstimate), ``reference`` (ComReference),
``joints`` (JointSensors: the foot's cable spool angle), ``mid_level`` (MidLevelSetpoint).
Computes: :class:`onboard.low_level.controller.LowLevelController` every 1 ms; with
``control.mid_level = "geometric_mpc"`` the geometric MPC runs beside it in a process of its own
(:mod:`services.mid_level`, ``gmpc.rate_hz``) and the loop tracks its setpoints (torque output
only: with ``output = "attitude"`` the board's PD tracks the ZDP's attitude as before).
Publishes: ``torque_cmd`` every tick (disarmed zeros until a valid estimate arms it),
or with ``control.output = "attitude"`` (hardware that runs the attitude PD and the foot's
hop cycle itself: ARCHER's firmware) ``attitude_cmd`` instead
(:meth:`LowLevelController.step_attitude`; disarmed until a valid estimate arms it);
``phase`` and ``safety`` events as they happen, ``tube`` every
``ControlParams.tube_period_s``.

Timing: the loop runs in a child process of its own (:class:`ControlLoop`), on a
:class:`services.runtime.realtime.DeadlineLoop` with absolute deadlines, real-time priority and
a pinned CPU when the kernel allows (logged and skipped when not). The child has no
asyncio loop and no other Python thread that competes for the GIL at 1 kHz except the
Zenoh callbacks that drop decoded messages into latest-value slots; the parent process
(this :class:`ControlService`) keeps the asyncio duties: liveliness, status, parameters,
logging every safety trip. Every ``STATS_PERIOD_S`` the child reports its loop
statistics (period jitter, compute time, overruns) and the safety trips to the parent
over a pipe, so the tick never logs.

Parameters: a change of a control gain or a safety limit goes to the loop over the
pipe and the controller takes it between two ticks (:meth:`LowLevelController.retune`);
the loop process, its Zenoh session and the torque stream carry on. A change of a field
in :data:`onboard.contracts.params.NEEDS_RESTART` needs a new loop process: refused while the
controller is armed or about to arm, applied by a restart when disarmed (the new loop
starts disarmed; the service's watchdog is fed through the restart). A new value of
``control.flip_request`` asks the loop for one flip (:mod:`onboard.low_level.tracking.flip`), taken between two
ticks; a refusal is logged with its reason, and the status counts ``flips``, ``flips_dropped``
and ``flips_refused``.

:func:`robot_description.controller.build_controller` builds the controller from the
MJCF (the robot's parameters and the reduced hopper model) and the policy weights file.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import os
import signal
import threading
import time
from multiprocessing.connection import Connection
from typing import Any, ClassVar

from onboard.contracts import messages as msgs
from onboard.contracts.params import ControlParams, GeometricMpcParams, SafetyLimits, restart_changes
from onboard.contracts.topics import TOPICS
from robot_description.controller import build_controller
from services.runtime.child_process import STOP_TIMEOUT_S, ChildProcess
from services.runtime.clock import WallClock
from services.runtime.realtime import STATUS_WINDOW, DeadlineLoop, die_with_parent, make_realtime_from
from services.runtime.service import LatestSlot, Service, TypedPublisher, check_publisher, fence
from services.runtime.zenoh_session import open_session
from services.mid_level import MidLevelConfig, MidLevelProcess

LOOP_READS = ("state", "reference", "joints", "mid_level")  # what the loop process subscribes to (latest values)
SHADOW_READS = ("torque_cmd", "attitude_cmd")  # a standby's loop watches the primary's commands (its shadow figures)
SHADOW_FRESH_NS = 5_000_000  # a primary command this recent is compared with the standby's own [ns]

STATS_PERIOD_S = 0.5  # child -> parent report period [s]
START_TIMEOUT_S = 30.0  # building the controller (linearization) and opening Zenoh [s]

log = logging.getLogger("archer.control")


# --- the loop process -----------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class LoopConfig:
    """Everything the loop process needs (picklable: it crosses the process boundary)."""

    ns: str
    endpoint: str
    zenoh_config: str | None
    control: ControlParams
    safety: SafetyLimits
    duration_s: float = 0.0  # > 0: stop by itself after this long (the bench)
    parent_pid: int = 0  # the loop process dies with this process (0: no check)
    commander: str = ""  # the service's instance id, carried by every command (onboard/contracts/commander.py)
    hold_disarmed: bool = False  # start disarmed whatever auto_arm says (a restart for new parameters)
    standby: bool = False  # compute on the same inputs, publish nothing until the parent says "promote"
    fence_pid: int = 0  # a standby: the primary's pid on this host, killed when its armed commands stop (0: none)


class ControlLoop:
    """The 1 kHz loop with its own Zenoh session; runs in the loop process."""

    def __init__(self, cfg: LoopConfig) -> None:
        self.cfg = cfg
        self.clock = WallClock()
        self.ctrl = build_controller(cfg.control.robot, cfg.control, cfg.safety)
        self.session = open_session(cfg.endpoint, "peer", cfg.zenoh_config)
        self.rejected: dict[str, int] = {}
        self.received: dict[str, int] = {}
        self.slots = {name: self._latest(name) for name in LOOP_READS}
        self.attitude_mode = cfg.control.output == "attitude"
        self.command_topic = "attitude_cmd" if self.attitude_mode else "torque_cmd"
        self.pubs = {name: TypedPublisher(self.session, check_publisher(ControlService.name, name), cfg.ns, self.clock)
                     for name in (self.command_topic, "phase", "safety", "tube")}
        self._tube_every = max(1, int(cfg.control.tube_period_s * cfg.control.rate_hz))
        self._ticks = 0
        self._unsent_trips: list[msgs.SafetyEvent] = []
        self._trip_lock = threading.Lock()
        self.safe_ticks = 0  # ticks without a usable estimate or disarmed
        # new gains and limits: set by the pipe thread, taken by the tick between two ticks
        self.retune_to: tuple[int, ControlParams, SafetyLimits] | None = None
        self._retuned: tuple[int, ControlParams, SafetyLimits] | None = None
        self.params_seq = 0  # the parent's number of the parameters in effect
        self.params_error = ""
        self.arm_requests = 0  # arm requests taken from the parent
        self.flip_requests = 0  # flip requests from the parent (the pipe thread counts, the tick takes them)
        self._flips_taken = 0
        if cfg.hold_disarmed:
            self.ctrl.disarm(self.clock.now_ns(), "parameter_restart")
        # hot standby: the controller runs on the same inputs (its phase, arming and filters warm); its
        # commands are compared with the primary's and not sent until promoted (set by the pipe thread)
        self.publishing = not cfg.standby
        self.promote_ns = 0  # when the promotion request arrived (stack clock)
        self.primary = self._latest(self.command_topic) if cfg.standby else None
        self.shadow_diff_max = 0.0  # largest |own - primary| torque [N m] / attitude component since the last report
        self.shadow_compared = 0
        self.takeover: dict[str, float] = {}  # the first published tick after a promotion
        self._fence_ns = int(cfg.control.standby_fence_s * 1e9) if cfg.fence_pid else 0
        self.fenced = 0  # 1: the hung primary was killed, -1: the fence found no such process
        self.realtime_applied: dict[str, str] = {}  # a standby's scheduling, applied when it takes over
        self.loop = DeadlineLoop(1.0 / cfg.control.rate_hz, self.tick, name="control-loop")

    def _latest(self, name: str) -> LatestSlot:
        topic = TOPICS[name]
        slot: LatestSlot = LatestSlot()
        clock = self.clock
        self.rejected[name] = 0
        self.received[name] = 0

        def on_sample(sample: Any) -> None:  # Zenoh thread: decode, drop in the slot
            try:
                msg = msgs.decode(sample.payload.to_bytes(), topic.msg_type)
            except msgs.MessageError:
                self.rejected[name] += 1
                return
            self.received[name] += 1
            slot.put(msg, clock.now_ns())

        self.session.declare_subscriber(topic.key(self.cfg.ns), on_sample)
        return slot

    def _retune(self, request: tuple[int, ControlParams, SafetyLimits]) -> None:
        self._retuned = request
        seq, control, safety = request
        try:
            self.ctrl.retune(control, safety)
        except ValueError as exc:  # a field only a restart applies: the parent never sends one
            self.params_error = str(exc)
            return
        self._tube_every = max(1, int(control.tube_period_s * control.rate_hz))
        self.params_seq = seq

    def tick(self, _deadline_s: float) -> None:
        request = self.retune_to
        if request is not self._retuned:
            self._retune(request)  # type: ignore[arg-type]
        now = self.clock.now_ns()
        ctrl = self.ctrl
        if self.flip_requests != self._flips_taken:  # taken between two ticks, as a retune is
            self._flips_taken += 1
            ctrl.request_flip()
        st = self.slots["state"].get()
        cmd: msgs.TorqueCommand | msgs.AttitudeSetpoint
        if st is None:
            if self.attitude_mode:
                cmd = ctrl.safe_setpoint(now)
            else:
                cmd = msgs.TorqueCommand(stamp_ns=now, wheel_torque=[0.0, 0.0, 0.0], foot_torque=0.0, armed=False)
        else:
            ref = self.slots["reference"].get()
            if self.attitude_mode:  # the foot board runs the foot: no joints needed
                cmd = ctrl.step_attitude(now, st[0], ref[0] if ref is not None else None)
            else:
                jn = self.slots["joints"].get()
                mid = self.slots["mid_level"].get()
                cmd = ctrl.step(now, st[0], ref[0] if ref is not None else None, jn[0] if jn is not None else None,
                                mid[0] if mid is not None else None)
        if not cmd.armed:
            self.safe_ticks += 1
        cmd.commander = self.cfg.commander
        if not self.publishing and self.promote_ns:  # promoted (by the pipe thread): this tick publishes
            self.publishing = True
            self.realtime_applied = make_realtime_from(self.cfg.control.rt_priority, self.cfg.control.cpu)
        if not self.publishing:
            self._shadow(now, cmd)
        else:
            if self.primary is not None and not self.takeover:
                self._took_over(now, cmd)
            self.pubs[self.command_topic].put(cmd)
        for ev in ctrl.drain_phase_events():
            if self.publishing:
                self.pubs["phase"].put(ev)
        trips = ctrl.drain_safety_events()
        if trips:
            for ev in trips:
                if self.publishing:
                    self.pubs["safety"].put(ev)
            with self._trip_lock:
                self._unsent_trips.extend(trips)
        self._ticks += 1
        if self._ticks % self._tube_every == 0 and self.publishing:
            self.pubs["tube"].put(ctrl.tube(now))
        if self.cfg.duration_s > 0 and self._ticks >= self.cfg.duration_s * self.cfg.control.rate_hz:
            self.loop.stop(timeout_s=0)

    def _shadow(self, now: int, cmd: msgs.TorqueCommand | msgs.AttitudeSetpoint) -> None:
        """A standby's tick: how far its command is from the primary's latest (the warmth of its state)."""
        got = self.primary.get() if self.primary is not None else None
        if got is None:
            return
        age = now - got[1]
        st = self.slots["state"].get()  # our own input flows: our Zenoh threads are not the ones starved
        if (self._fence_ns and not self.fenced and age > self._fence_ns and got[0].armed and cmd.armed and st is not None
                and now - st[1] < self._fence_ns // 4):
            # the primary was armed and went quiet with its token declared (a hang): we are armed and
            # ready, and its token would outlive it by seconds; kill it, and its token goes at once
            self.fenced = 1 if fence(self.cfg.fence_pid, ControlService.name) else -1
        if age > SHADOW_FRESH_NS:
            return
        self.shadow_compared += 1
        self.shadow_diff_max = max(self.shadow_diff_max, command_step(got[0], cmd))

    def _took_over(self, now: int, cmd: msgs.TorqueCommand | msgs.AttitudeSetpoint) -> None:
        """The first command a promoted standby publishes: the gap since the primary's last command and
        the step from it (what the motors see at the takeover)."""
        got = self.primary.get() if self.primary is not None else None
        self.takeover = {
            "gap_ms": (now - got[1]) / 1e6 if got is not None else -1.0,
            "promote_to_publish_ms": (now - self.promote_ns) / 1e6,
            "step": command_step(got[0], cmd) if got is not None else -1.0,
            "armed": float(cmd.armed),
            "primary_armed": float(got[0].armed) if got is not None else -1.0,
        }

    def report(self, final: bool = False) -> dict[str, Any]:
        """Loop statistics and what happened since the last report (for the parent).

        Periodic reports summarise the last ``STATUS_WINDOW`` ticks (a full-ring
        percentile would stall this process for milliseconds); the final one all of them.
        """
        with self._trip_lock:
            trips, self._unsent_trips = self._unsent_trips, []
        tube = self.ctrl.tube(0)
        shadow_diff_max, self.shadow_diff_max = self.shadow_diff_max, 0.0
        return {
            "loop": self.loop.recorder.stats(None if final else STATUS_WINDOW).as_dict(),
            "armed": self.ctrl.armed,
            "arm_requested": self.ctrl.supervisor.arm_requested,
            "arm_requests": self.arm_requests,
            "disarm_reason": self.ctrl.supervisor.disarm_reason,
            "params_seq": self.params_seq,
            "params_error": self.params_error,
            "control": self.ctrl.p,  # what the controller runs with, read back from it
            "safety": self.ctrl.safety,
            "hops": self.ctrl.phase.hop,
            "flip": self.ctrl.flip.counters(),
            "flip_refusal": self.ctrl.flip.last_refusal,
            "mid_level_ticks": self.ctrl.mid_level_ticks,
            "mid_level_fallback_ticks": self.ctrl.mid_level_fallback_ticks,
            "safe_ticks": self.safe_ticks,
            "tube_p95_m": tube.impact_err_p95,
            "momentum": self.ctrl.momentum.counters(),
            "trip_counts": dict(self.ctrl.supervisor.counts),
            "trips": [msgs.encode(t) for t in trips],
            "rejected": dict(self.rejected),
            "received": dict(self.received),
            "publishing": self.publishing,
            "shadow_diff_max": shadow_diff_max,
            "shadow_compared": self.shadow_compared,
            "takeover": dict(self.takeover),
            "fenced": self.fenced,
        }

    def close(self) -> None:
        self.session.close()


def loop_process_main(cfg: LoopConfig, conn: Connection) -> None:
    """Entry point of the loop process: build, report ready, loop until told to stop.

    Ignores SIGINT and SIGTERM (a terminal or systemd signals the whole group): the
    parent stops the loop over the pipe, and the loop stops by itself when the pipe
    breaks (parent gone)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    die_with_parent(cfg.parent_pid)
    try:
        # a standby's loop stays at normal priority until it takes over: two real-time control loops (and two
        # estimators) on a small machine starve everything else, a restarting service included
        applied = {"standby": "normal priority until promoted"} if cfg.standby else make_realtime_from(cfg.control.rt_priority, cfg.control.cpu)
        loop = ControlLoop(cfg)
    except Exception as exc:  # reported to the parent, which fails the service
        conn.send({"error": repr(exc)})
        return
    send_lock = threading.Lock()
    done = threading.Event()

    def send(obj: Any) -> bool:
        try:
            with send_lock:
                conn.send(obj)
            return True
        except (BrokenPipeError, OSError):
            return False

    send({"ready": True, "realtime": applied})

    def serve() -> None:  # parent requests; blocks in poll (no GIL held while waiting)
        while not done.is_set():
            try:
                if not conn.poll(STATS_PERIOD_S):
                    if not send(loop.report()):
                        break
                    continue
                req = conn.recv()
            except (EOFError, OSError):
                break
            if req == "stop":
                break
            if isinstance(req, tuple) and req[0] == "params":
                loop.retune_to = req[1:]
            elif req == "arm":
                loop.arm_requests += 1
                loop.ctrl.request_arm()
            elif req == "disarm":
                loop.ctrl.disarm(loop.clock.now_ns())
            elif req == "flip":
                loop.flip_requests += 1
            elif req == "promote":
                loop.promote_ns = loop.clock.now_ns()
        loop.loop.stop(timeout_s=0)  # parent gone or asked: end the loop

    server = threading.Thread(target=serve, name="control-pipe", daemon=True)
    server.start()
    loop.loop.run_here()
    done.set()
    final = loop.report(final=True)
    final["final"] = True
    if loop.loop.error is not None:
        final["error"] = repr(loop.loop.error)
    send(final)
    loop.close()


def command_step(a: msgs.TorqueCommand | msgs.AttitudeSetpoint, b: msgs.TorqueCommand | msgs.AttitudeSetpoint) -> float:
    """The largest change of one command component from ``a`` to ``b``: torques [N m], or an attitude
    setpoint's quaternion, rate [rad/s] and torques: what a switch of commander puts on the motors."""
    if isinstance(a, msgs.TorqueCommand) and isinstance(b, msgs.TorqueCommand):
        pairs = [*zip(a.wheel_torque, b.wheel_torque), (a.foot_torque, b.foot_torque)]
    elif isinstance(a, msgs.AttitudeSetpoint) and isinstance(b, msgs.AttitudeSetpoint):
        pairs = [*zip(a.quat_des, b.quat_des), *zip(a.omega_des, b.omega_des), *zip(a.torque_ff, b.torque_ff),
                 (a.foot_torque, b.foot_torque)]
    else:
        return float("inf")
    return max(abs(x - y) for x, y in pairs)


class LoopProcess(ChildProcess):
    """Starts and talks to the loop process (used by the service and the bench)."""

    def __init__(self, cfg: LoopConfig) -> None:
        super().__init__(loop_process_main, cfg, "archer-control-loop")
        self.arm_requests = 0  # sent; the loop reports how many it took

    def start(self, timeout_s: float = START_TIMEOUT_S) -> None:
        super().start(timeout_s)

    def send(self, request: str | tuple[Any, ...]) -> None:
        """``"stop"``, ``"arm"``, ``"disarm"``, ``"flip"`` or ``("params", seq, control, safety)``."""
        if request == "arm":
            self.arm_requests += 1
        super().send(request)


# --- the service ------------------------------------------------------------------------------------


class ControlService(Service):
    name: ClassVar[str] = "control"
    params_sections: ClassVar[tuple[str, ...]] = ("control", "safety", "gmpc")
    subscribes: ClassVar[tuple[str, ...]] = LOOP_READS + SHADOW_READS  # read by the loop process
    # parameter state, read by the parameter queryable from the moment run() declares it
    _loop_proc: LoopProcess | None = None
    _restart_pending = False  # a restart for new parameters is accepted and not done yet
    _restart_deadline: float | None = None  # monotonic bound of the restart under way
    _restarted_from: LoopProcess | None = None  # the loop that restart replaces
    _mid_proc: MidLevelProcess | None = None  # the geometric MPC's process (control.mid_level)
    _mid_restart = False  # new gmpc parameters: the MPC process restarts with them

    async def setup(self) -> None:
        self._restart = asyncio.Event()
        self._trips_logged = 0
        self._progress_ticks = 0
        self._params_seq = 0  # numbers the gains and limits sent to the loop
        self._mid_refused_logged = 0
        self._flips_refused_logged = 0
        self._fence_logged = False
        await self._start_loop()

    def _loop_config(self, hold_disarmed: bool) -> LoopConfig:
        self._sent = (self.params["control"], self.params["safety"])  # what the loop runs with
        return LoopConfig(ns=self.ns, endpoint=self.endpoint, zenoh_config=self._zenoh_config_file,
                          control=self.params["control"], safety=self.params["safety"], parent_pid=os.getpid(),
                          commander=self.instance, hold_disarmed=hold_disarmed,
                          standby=self.role == "standby" and not self.promoted.is_set(),
                          fence_pid=self.fence_pid() if not self.promoted.is_set() else 0)

    async def _start_mid_level(self) -> None:
        """The geometric MPC's process, when ``control.mid_level`` asks for it."""
        control: ControlParams = self.params["control"]
        if control.mid_level != "geometric_mpc":
            return
        gmpc: GeometricMpcParams = self.params["gmpc"]
        proc = MidLevelProcess(MidLevelConfig(ns=self.ns, endpoint=self.endpoint, zenoh_config=self._zenoh_config_file,
                                              control=control, gmpc=gmpc, safety=self.params["safety"], parent_pid=os.getpid()))
        await asyncio.to_thread(proc.start)
        self._mid_proc = proc
        self.log.info("geometric MPC started", extra={"fields": {"pid": proc.proc.pid, "rate_hz": gmpc.rate_hz,
                                                                 "backend": gmpc.backend, "realtime": proc.realtime}})

    async def _stop_mid_level(self) -> None:
        proc, self._mid_proc = self._mid_proc, None
        if proc is not None:
            self._absorb_mid(await asyncio.to_thread(proc.stop))

    def _absorb_mid(self, rep: dict[str, Any]) -> None:
        """Log refused MPC answers (counted by reason) as they are reported."""
        refused = int(rep.get("refused", 0))
        if refused > self._mid_refused_logged:
            self.count("mid_level.refused", refused - self._mid_refused_logged)
            self.log.warning("geometric MPC answers refused (the loop falls back to the ZDP while stale)",
                             extra={"fields": {"new": refused - self._mid_refused_logged, "by_reason": rep.get("refusals", {})}})
            self._mid_refused_logged = refused
        if "error" in rep:
            self.fail(f"geometric MPC: {rep['error']}")

    async def _start_loop(self, hold_disarmed: bool = False) -> None:
        if self.role == "primary":  # a standby's MPC would publish: it starts on the takeover
            await self._start_mid_level()
        proc = LoopProcess(self._loop_config(hold_disarmed))
        await asyncio.to_thread(proc.start)
        # the loop's exit (kill -9, a crash) withdraws our token at once, so that the standby takes over
        # within milliseconds, not at the next poll of main()
        asyncio.get_running_loop().add_reader(proc.proc.sentinel, self._on_loop_exit, proc)
        self._progress_ticks = 0  # a new loop counts its ticks from zero
        with self._params_lock:
            self._loop_proc = proc
            self._restart_pending = False
            self._sync_loop()  # what changed while it started
        self.log.info("control loop started", extra={"fields": {"pid": proc.proc.pid, "realtime": proc.realtime}})

    def _on_loop_exit(self, proc: LoopProcess) -> None:
        """On the event loop: a loop process ended that nobody asked to stop (main() fails the service)."""
        self._unwatch(proc)
        if proc is self._loop_proc and not self.stopping.is_set():
            self.withdraw()
            self.log.error("control loop process exited; token withdrawn", extra={"fields": {"exitcode": proc.proc.exitcode}})

    def _unwatch(self, proc: LoopProcess) -> None:
        """Before a loop process is stopped on purpose (a restart, the service's stop)."""
        if self._aio_loop is not None:
            self._aio_loop.remove_reader(proc.proc.sentinel)

    def on_promoted(self) -> None:
        proc = self._loop_proc
        if proc is not None:
            proc.send("promote")
        if self.params["control"].mid_level == "geometric_mpc":
            self._tasks.append(asyncio.ensure_future(self._start_mid_level()))

    async def _restart_loop(self, proc: LoopProcess) -> None:
        """Stop the disarmed loop and start one with the new parameters, disarmed. A
        restart asked for is progress until the new loop reports ticks (or the restart
        overruns its bound): the watchdog stays fed through it."""
        self._restart_deadline = time.monotonic() + STOP_TIMEOUT_S + START_TIMEOUT_S + STATS_PERIOD_S
        self._restarted_from = proc
        changed = restart_changes("control", self._sent[0], self.params["control"])
        self.log.info("restarting the control loop for new parameters", extra={"fields": {"changed": changed}})
        self._unwatch(proc)
        final = await asyncio.to_thread(proc.stop)
        if final:
            self._absorb(final)
        await self._stop_mid_level()
        await self._start_loop(hold_disarmed=True)

    async def main(self) -> None:
        while not self.stopping.is_set():
            # woken by a restart, or by the stop itself: a stopped stack must be gone within 3 s
            wakes = [asyncio.ensure_future(self._restart.wait()), asyncio.ensure_future(self.stopping.wait())]
            await asyncio.wait(wakes, timeout=STATS_PERIOD_S, return_when=asyncio.FIRST_COMPLETED)
            for wake in wakes:
                wake.cancel()
            if self.stopping.is_set():
                break
            proc = self._loop_proc
            if proc is None:
                continue
            for rep in proc.poll():
                self._absorb(rep)
            mid = self._mid_proc
            if mid is not None:
                for rep in mid.poll():
                    self._absorb_mid(rep)
                if self._mid_restart:
                    self._mid_restart = False
                    await self._stop_mid_level()
                    await self._start_mid_level()
                elif not mid.alive:
                    self.state = "error"
                    raise RuntimeError(f"geometric MPC process exited with code {mid.proc.exitcode}")
            if self._restart.is_set():
                self._restart.clear()
                await self._restart_loop(proc)
            elif not proc.alive:
                # A failure, not a stop: the process exits non-zero so that systemd
                # (Restart=on-failure) or the supervisor starts control again.
                self.state = "error"
                raise RuntimeError(f"control loop process exited with code {proc.proc.exitcode}")

    def _absorb(self, rep: dict[str, Any]) -> None:
        """Log every safety trip the loop reported; keep the figures for the status."""
        if "error" in rep:
            self.fail(rep["error"])
        for raw in rep.get("trips", []):
            ev = msgs.decode(raw, msgs.SafetyEvent)
            self._trips_logged += 1
            self.count(f"trip.{ev.trip}")
            self.log.warning("safety trip", extra={"fields": {"trip": ev.trip, "value": ev.value, "limit": ev.limit,
                                                              "armed": ev.armed, "count": ev.count}})
        if rep.get("fenced") and not self._fence_logged:
            self._fence_logged = True
            self.count("fenced" if rep["fenced"] > 0 else "fence_failed")
            self.log.warning("primary's armed commands stopped with its token declared: fenced (kill -9)",
                             extra={"fields": {"pid": self.fence_pid(), "killed": rep["fenced"] > 0}})
        refused = rep.get("flip", {}).get("flips_refused", 0)
        if refused > self._flips_refused_logged:
            self._flips_refused_logged = refused
            self.log.warning("flip refused", extra={"fields": {"reason": rep.get("flip_refusal", "")}})
        self.state = "running" if rep.get("armed") else "degraded"

    async def teardown(self) -> None:
        await self._stop_mid_level()
        if self._loop_proc is not None:
            self._unwatch(self._loop_proc)
            final = await asyncio.to_thread(self._loop_proc.stop)
            for rep in ([final] if final else []):
                self._absorb(rep)
            self._loop_proc = None

    def accept_params(self, updated: dict[str, Any]) -> None:
        """A restart-needing change only while the loop is known disarmed and not about
        to arm; no arm request while a restart is on its way."""
        control = updated.get("control")
        if control is None:
            return
        current = self.params["control"]
        restart = restart_changes("control", current, control)
        if restart and not self._restart_pending:
            why = self._arming_state()
            if why:
                raise ValueError(f"{', '.join(restart)}: needs a restart of the control loop, refused while {why}; "
                                 "disarm first (control.disarm_request)")
        if control.arm_request != current.arm_request and (restart or self._restart_pending):
            raise ValueError("control.arm_request: refused while the control loop restarts for new parameters")

    def _arming_state(self) -> str:
        """Why the loop may be armed now or arm by itself ("" when it cannot).

        A disarmed loop with no arm request pending arms only on a new arm request, and
        those all pass through here: the loop counts the ones it took."""
        proc = self._loop_proc
        if proc is None:
            return "the control loop starts"
        rep = proc.last
        if "armed" not in rep:
            return "the control loop has not reported its state yet"
        if rep.get("arm_requests") != proc.arm_requests:
            return "an arm request is on its way to the loop"
        if rep["armed"]:
            return "armed"
        if rep.get("arm_requested"):
            return "arming (the loop arms on the next valid upright estimate)"
        return ""

    def on_params_changed(self, section: str) -> None:
        if section == "gmpc":  # the MPC process takes its parameters when it starts
            self._mid_restart = self._mid_proc is not None
            return
        self._sync_loop()

    def _sync_loop(self) -> None:
        """Bring the loop to ``self.params`` (under the parameter lock): gains and limits go
        over the pipe for the next tick, operator arm/disarm as requests, restart-needing
        fields by a restart (accepted only when disarmed: :meth:`accept_params`)."""
        if self._loop_proc is None or self._restart_pending:
            return  # the loop (re)starts from self.params
        control, safety = self.params["control"], self.params["safety"]
        sent_control, sent_safety = self._sent
        if restart_changes("control", sent_control, control):
            self._restart_pending = True
            self.call_in_loop(self._restart.set)
            return
        if control.arm_request != sent_control.arm_request:
            self.request_arm()
        if control.disarm_request != sent_control.disarm_request:
            self.request_disarm()
        if control.flip_request != sent_control.flip_request:
            self._loop_proc.send("flip")
        gains = dataclasses.replace(control, arm_request=sent_control.arm_request, disarm_request=sent_control.disarm_request,
                                    flip_request=sent_control.flip_request)
        if gains != sent_control or safety != sent_safety:
            self._params_seq += 1
            self._loop_proc.send(("params", self._params_seq, control, safety))
        self._sent = (control, safety)

    def request_arm(self) -> None:
        if self._loop_proc is not None:
            self._loop_proc.send("arm")

    def request_disarm(self) -> None:
        if self._loop_proc is not None:
            self._loop_proc.send("disarm")

    def progress(self) -> bool:
        """The loop process is alive and its tick count advanced since the last check, or
        a restart for new parameters is under way and within its time bound."""
        proc = self._loop_proc
        advanced = False
        if proc is not None and proc.alive:
            ticks = proc.last.get("loop", {}).get("ticks", 0)
            advanced = ticks > self._progress_ticks
            self._progress_ticks = ticks
        if self._restart_deadline is not None:
            if not advanced or proc is self._restarted_from:
                return time.monotonic() < self._restart_deadline
            self._restart_deadline = None  # the new loop ticks
        return advanced

    def status_extra(self) -> dict[str, float]:
        rep = self._loop_proc.last if self._loop_proc is not None else {}
        out: dict[str, float] = {}
        for k, v in rep.get("loop", {}).items():
            out[f"loop_{k}"] = float(v)
        out["armed"] = float(bool(rep.get("armed", False)))
        out["hops"] = float(rep.get("hops", 0))
        out["safe_ticks"] = float(rep.get("safe_ticks", 0))
        out["tube_p95_m"] = float(rep.get("tube_p95_m", 0.0))
        for name, v in rep.get("momentum", {}).items():  # the wheels' momentum governor (low_level/planning/momentum.py)
            out[f"momentum_{name}"] = float(v)
        for name, n in rep.get("rejected", {}).items():
            out[f"rejected_{name}"] = float(n)
        out["safety_trips_logged"] = float(self._trips_logged)
        for name, n in rep.get("flip", {}).items():
            out[name] = float(n)
        out["mid_level_ticks"] = float(rep.get("mid_level_ticks", 0))
        out["mid_level_fallback_ticks"] = float(rep.get("mid_level_fallback_ticks", 0))
        mid = self._mid_proc.last if self._mid_proc is not None else {}
        for key in ("solves", "published", "refused", "solve_ms_p50", "solve_ms_p99"):
            if key in mid:
                out[f"gmpc_{key}"] = float(mid[key])
        out["shadow_diff_max"] = float(rep.get("shadow_diff_max", 0.0))  # standby: |own - primary| command
        out["shadow_compared"] = float(rep.get("shadow_compared", 0))
        out["fenced"] = float(rep.get("fenced", 0))
        for k, v in rep.get("takeover", {}).items():
            out[f"takeover_{k}"] = float(v)
        out["params_seq_sent"] = float(self._params_seq)
        out["params_seq_applied"] = float(rep.get("params_seq", 0))
        return out
