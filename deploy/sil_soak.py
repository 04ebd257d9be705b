"""Chaos soak: the real-time stack for minutes on the twin, with a schedule of faults injected.

    python -m deploy.sil_soak --schedule deploy/soak/default.toml --out /tmp/soak
    archer soak --duration 90 --fault stall@30:target=control/child,duration=0.2 --out /tmp/soak

Runs ``archer sim --mode realtime`` (the twin in place of the hardware, every service its own
process under :mod:`services.runtime.supervisor`) on a free loopback endpoint and its own namespace,
with the flight recorder. An operator thread re-sends a tour of goals every second (so that a
restarted planner picks the current one up). At the schedule's times (seconds after the stack
first armed, or after the twin started when no ``control`` runs; :mod:`deploy.soak_schedule`) it injects each fault (:mod:`deploy.soak_faults`): kill -9
of a service or its loop child, SIGSTOP stalls, a router restart, a CPU hog, floods of malformed
or badly stamped messages.

What the stack does is observed from outside, as an operator would: ``safety`` events,
``torque_cmd`` (armed or not), ``reference`` and touchdown ``phase`` events, liveliness tokens,
status queries (polled every ``STATUS_HOT_S`` around a fault, else every ``STATUS_COLD_S``; the
twin's every ``TWIN_STATUS_S``: its status costs its loop a percentile of 65k ticks), the exit
of a killed process; afterwards the flight recording gives messages lost per topic. When the
twin's physics reports a fall, the soak puts the robot back (``twin.seed``, see
:mod:`services.twin`), rebuilds the estimator and asks control to arm once the
estimate has settled, so that one fault's fall does not spoil the rest of the run (``--no-put-back``:
leave it lying).

Output: one JSON line per fault on stdout (the fields are defined in :mod:`deploy.soak_analysis`),
then one line of totals; everything in ``OUT/summary.json``, with the sim's own metrics, the
recorder's whole-run counts and the status polls in ``OUT/status.jsonl``. Every process the soak
starts (the sim, hogs, flooders) is stopped whatever happens and dies with the soak.
This is a measurement for reports, not a test: CI runs only a short one (tests/test_soak.py).
"""

from __future__ import annotations

import argparse
import json
import os
import select
import signal
import subprocess
import sys
import threading
import time
import tomllib
from array import array
from pathlib import Path
from typing import Any

import zenoh

from deploy import soak_faults as sf
from deploy.soak_analysis import COMMANDER, TWIN, Injection, Streams, analyze, falls_by_window, settle_windows, window_losses
from deploy.soak_schedule import ROUTER, Fault, Schedule, ScheduleError, check_schedule, load_schedule, parse_kill, parse_shorthand
from onboard.contracts import messages as m
from onboard.contracts.topics import TOPICS, liveliness_key, topic_for_key
from services.runtime.peers import query_params, query_status
from services.runtime.realtime import die_with_parent
from services.recorder import envelope, file_metadata, read_recording, recording_files
from services.runtime.zenoh_session import endpoint_in_use, free_endpoint, open_session

NS_DEFAULT = "archer/soak"
CONFIG_DIR = Path(__file__).resolve().parent / "config"
SIL_CONFIG = CONFIG_DIR / "sil.toml"
DEFAULT_SCHEDULE = Path(__file__).resolve().parent / "soak" / "default.toml"
SERVICES = "estimator,control,planner,recorder"
DURATION_S = 600.0
GOAL_RESEND_S = 1.0
STATUS_HOT_S = 0.5  # status polls from BASELINE_S before a fault until HOT_AFTER_S after its action
BASELINE_S = 1.5  # (the last poll before the fault is the counters' baseline)
HOT_AFTER_S = 5.0
STATUS_COLD_S = 10.0
TWIN_STATUS_S = 2.0
SIM_START_TIMEOUT_S = 180.0  # the planner compiles its kernels on a cold cache
HELPER_START_TIMEOUT_S = 60.0  # a hog or flood not started by then is killed
HELPER_GRACE_S = 15.0  # a hog or flood past its duration by this much is killed (a session's close on a starved host takes seconds)
KILL_WATCH_S = 5.0  # how long a killed process's exit and reaping are watched
PUT_BACK_SETTLE_S = 1.5  # after the put back (and again after the estimator rebuild) before arming
SIM_STOP_TIMEOUT_S = 30.0
FAULT_MIN_WATCH_S = 2.0  # a fault is watched this long at least before the next is carried out (a starved soak ran late)
OBSERVE_END_S = 1.0  # observation ends this long before the run does (then the stack is stopped)
CONTROL_LOOP_RUNNING_S = 0.2  # commands this recent: a control loop is there to take over after a put back


def commanded_armed(payload: bytes) -> tuple[bool, int] | None:
    """A torque command's armed flag and stamp, or None for a payload the stack itself refuses.

    Decoded whole, as the twin decodes it: a malformed flood on ``torque_cmd`` (a field missing,
    an unknown one) must not read as the commander disarming."""
    try:
        cmd = m.decode(payload, m.TorqueCommand)
    except m.MessageError:
        return None
    return cmd.armed, cmd.stamp_ns


class Observer:
    """Subscribes what shows how the stack is doing; sends the operator's goals."""

    def __init__(self, session: zenoh.Session, ns: str, goals: list[tuple[float, float]], period_s: float) -> None:
        self.session, self.ns, self.goals, self.period_s = session, ns, goals, period_s
        self.streams = Streams(torque_rx=array("q"), torque_armed=bytearray(), torque_sent=array("q"))
        self._live: set[str] = set()
        self._live_lock = threading.Lock()  # written by a Zenoh thread, read by the soak's
        self._stop = threading.Event()
        self._subs = [
            session.declare_subscriber(TOPICS["safety"].key(ns), self._on_safety),
            session.declare_subscriber(TOPICS["torque_cmd"].key(ns), self._on_torque),
            session.declare_subscriber(TOPICS["reference"].key(ns), lambda s: self.streams.reference_rx.append(time.monotonic_ns())),
            session.declare_subscriber(TOPICS["phase"].key(ns), self._on_phase),
            session.liveliness().declare_subscriber(liveliness_key(ns, "*"), self._on_token, history=True),
        ]
        self._pub = session.declare_publisher(TOPICS["goal"].key(ns), reliability=zenoh.Reliability.RELIABLE)
        self._thread = threading.Thread(target=self._send_goals, name="operator", daemon=True)
        self.t0 = time.monotonic()

    def _on_safety(self, sample: zenoh.Sample) -> None:
        try:
            ev = m.decode(sample.payload.to_bytes(), m.SafetyEvent)
        except m.MessageError:
            return  # a flood on the topic: not the stack's event
        self.streams.safety.append((ev.stamp_ns, ev.trip))

    def _on_torque(self, sample: zenoh.Sample) -> None:
        rx = time.monotonic_ns()
        command = commanded_armed(sample.payload.to_bytes())
        if command is None:
            return
        armed, sent_ns = command
        self.streams.torque_rx.append(rx)  # type: ignore[attr-defined]
        self.streams.torque_armed.append(1 if armed else 0)  # type: ignore[attr-defined]
        self.streams.torque_sent.append(sent_ns)  # type: ignore[attr-defined]

    def _on_phase(self, sample: zenoh.Sample) -> None:
        rx = time.monotonic_ns()
        try:
            ev = m.decode(sample.payload.to_bytes(), m.PhaseEvent)
        except m.MessageError:
            return
        if ev.event == "touchdown":
            self.streams.touchdowns.append(rx)

    def _on_token(self, sample: zenoh.Sample) -> None:
        service = str(sample.key_expr).removeprefix(liveliness_key(self.ns, ""))
        alive = sample.kind == zenoh.SampleKind.PUT
        with self._live_lock:
            (self._live.add if alive else self._live.discard)(service)
            self.streams.liveliness.append((time.monotonic_ns(), service, alive))

    @property
    def live(self) -> frozenset[str]:
        """The services whose liveliness token is declared now."""
        with self._live_lock:
            return frozenset(self._live)

    def start(self) -> None:
        self.t0 = time.monotonic()
        self._thread.start()

    def current_goal(self) -> tuple[float, float]:
        k = int((time.monotonic() - self.t0) / self.period_s)
        return self.goals[k % len(self.goals)]

    def _send_goals(self) -> None:
        seq = 0
        while not self._stop.wait(GOAL_RESEND_S):
            seq += 1
            x, y = self.current_goal()
            self._pub.put(m.encode(m.Goal(stamp_ns=time.monotonic_ns(), seq=seq, position=[x, y], tolerance=0.15)))

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()
        for s in self._subs:
            s.undeclare()
        self._pub.undeclare()


class StatusPoller:
    """Polls the live services' status into the streams (and ``status.jsonl``) on its own thread:
    a stalled service makes a query wait for its timeout."""

    def __init__(self, session: zenoh.Session, ns: str, observer: Observer, log_path: Path) -> None:
        self.session, self.ns, self.observer = session, ns, observer
        self.hot_until = 0.0  # time.monotonic() until which polls are frequent
        self.twin_falls = 0.0
        self._next_all = 0.0
        self._log = open(log_path, "w")
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="status-poller", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def poll(self, services: list[str]) -> None:
        for name in services:
            # stamped when asked: a reply that comes after a fault, to a query sent before it, may
            # hold a trip from before the fault (an estimate late on a loaded host) and is its baseline
            t = time.monotonic_ns()
            st = query_status(self.session, self.ns, name)
            if st is None:
                continue
            values = {f"counters.{k}": float(v) for k, v in st.counters.items()}
            values.update({k: float(v) for k, v in st.extra.items()})
            self.observer.streams.statuses.append((t, name, values))
            if name == TWIN:
                self.twin_falls = values.get("falls", self.twin_falls)
            self._log.write(json.dumps({"t_ns": t, "service": name, "state": st.state, "values": values}) + "\n")

    def heat(self, until: float) -> None:
        """Poll every ``STATUS_HOT_S`` from now until ``until`` (``time.monotonic()``)."""
        self.hot_until = until
        self._next_all = min(self._next_all, time.monotonic())

    def _run(self) -> None:
        next_twin = 0.0
        while not self._stop.wait(0.05):
            now = time.monotonic()
            if now >= next_twin:
                next_twin = now + TWIN_STATUS_S
                self.poll([TWIN] if TWIN in self.observer.live else [])
            if now >= self._next_all:
                self._next_all = now + (STATUS_HOT_S if now < self.hot_until else STATUS_COLD_S)
                self.poll(sorted(self.observer.live - {TWIN}))

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()
        self._log.close()


def fault_start_ns(t0_ns: int, at_s: float, previous_end_ns: int | None) -> int:
    """When a fault due ``at_s`` after ``t0_ns`` is carried out: when due, or ``FAULT_MIN_WATCH_S`` after
    the previous one's action ended, whichever is later (a starved soak carried a fault out late, and the
    next one, due meanwhile, left it no time to show and recover)."""
    due = t0_ns + int(at_s * 1e9)
    return due if previous_end_ns is None else max(due, previous_end_ns + int(FAULT_MIN_WATCH_S * 1e9))


def _sil_config(base: Path, rec_dir: Path) -> str:
    """``base`` with the recording going to ``rec_dir`` in 30 s files, as TOML."""
    tables = tomllib.loads(base.read_text())
    tables.setdefault("recorder", {}).update(directory=str(rec_dir), chunk_s=30.0)
    return "".join(
        f"[{name}]\n" + "".join(f"{key} = {json.dumps(value)}\n" for key, value in table.items()) + "\n"
        for name, table in tables.items()
    )


class Soak:
    """One run: the sim, the observers, the faults, and the cleanup of every process."""

    def __init__(self, args: argparse.Namespace, schedule: Schedule, services: list[str], duration_s: float) -> None:
        self.args, self.schedule, self.services, self.duration_s = args, schedule, services, duration_s
        self.out = Path(args.out).resolve()
        self.endpoint = free_endpoint()
        self.ns = args.namespace
        self.helpers: list[subprocess.Popen] = []
        self.stopped: list[tuple[int, bool]] = []  # (pid, whole unit) under SIGSTOP right now
        self.injections: list[Injection] = []
        self.put_backs: list[int] = []
        self.falls_handled = 0.0

    # --- the run ---

    def run(self) -> dict[str, Any]:
        self.out.mkdir(parents=True, exist_ok=True)
        rec_dir = self.out / "rec"
        config = self.out / "sil.toml"
        config.write_text(_sil_config(Path(self.args.config), rec_dir))
        wall_minus_mono = time.time_ns() - time.monotonic_ns()  # the recorder stamps receipt on the wall clock
        cmd = [sys.executable, "-m", "services.cli.main", "sim", "--mode", "realtime", "--scenario", self.args.scenario,
               "--planner", "graph", "--services", ",".join(self.services),
               "--duration", str(self.duration_s + SIM_START_TIMEOUT_S),  # the soak stops it; its clock starts at arming
               "--keep-going", "--json", "--quiet", "--config", str(config), "--endpoint", self.endpoint, "--namespace", self.ns]
        parent = os.getpid()
        stdout, stderr = open(self.out / "sim.stdout", "wb"), open(self.out / "sim.stderr", "wb")
        # started before any thread of ours exists: preexec_fn is safe here
        sim = subprocess.Popen(cmd, stdout=stdout, stderr=stderr, preexec_fn=lambda: die_with_parent(parent))
        session = observer = poller = None
        t_end = 0
        try:
            deadline = time.monotonic() + SIM_START_TIMEOUT_S
            while not endpoint_in_use(self.endpoint):
                self._check_sim(sim, deadline)
                time.sleep(0.1)
            # every helper set up now, each waiting for its word: one started at the fault before took
            # 3-12 s to import and connect beside the real-time stack, longer than the gap to its fault;
            # started at arming, 11 s were not enough on a loaded 2-core host (the flood went in 16 s late)
            faults = list(self.schedule.faults)
            helpers = [self._start_helper(fault) for fault in faults]
            session = open_session(self.endpoint, "peer")  # a peer, as the services: a router restart does not blind it
            goals = [tuple(float(v) for v in g.split(",")) for g in self.args.goals.split(";")]
            observer = Observer(session, self.ns, goals, self.args.goal_period)  # type: ignore[arg-type]
            while TWIN not in observer.live:  # the physics starts with the twin
                self._check_sim(sim, deadline)
                time.sleep(0.05)
            if COMMANDER in self.services:  # without a commander nothing arms: the clock starts with the twin
                self._wait_armed(sim, observer, deadline)
            t0 = time.monotonic_ns()
            observer.start()
            poller = StatusPoller(session, self.ns, observer, self.out / "status.jsonl")
            poller.start()
            run_end = t0 + int(self.duration_s * 1e9)
            for k, fault in enumerate(faults):
                helper = helpers[k]
                start = fault_start_ns(t0, fault.at_s, self.injections[-1].end_ns if self.injections else None)
                self._wait_until(start - int(BASELINE_S * 1e9), sim, session, poller, observer)
                poller.heat(time.monotonic() + BASELINE_S + fault.duration_s + HOT_AFTER_S)
                self._wait_until(start, sim, session, poller, observer)
                window_end = t0 + int(faults[k + 1].at_s * 1e9) if k + 1 < len(faults) else run_end - int(OBSERVE_END_S * 1e9)
                inj = self._inject(fault, sim.pid, session, window_end, helper)
                self.injections.append(inj)
                self._print_progress(inj, t0)
            self._wait_until(run_end - int(OBSERVE_END_S * 1e9), sim, session, poller, observer)
            t_end = time.monotonic_ns()
            time.sleep(OBSERVE_END_S)
            sim.send_signal(signal.SIGTERM)  # the sim stops and prints its metrics
            try:
                sim.wait(SIM_STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                pass
        finally:
            t_end = t_end or time.monotonic_ns()
            self._cleanup(sim, session, observer, poller, stdout, stderr)
        settle_windows(self.injections, t_end)
        return self._summarize(observer.streams, t0, rec_dir, wall_minus_mono)

    def _wait_armed(self, sim: subprocess.Popen, observer: Observer, deadline: float) -> None:
        """Until the stack's first armed command: the schedule's clock starts there, since a fault
        injected before the robot is up tests nothing, and a loaded machine takes seconds to start
        the services."""
        seen = 0
        while 1 not in observer.streams.torque_armed[seen:]:
            seen = len(observer.streams.torque_armed)
            self._check_sim(sim, deadline)
            time.sleep(0.05)

    def _check_sim(self, sim: subprocess.Popen, deadline: float) -> None:
        if sim.poll() is not None:
            raise RuntimeError(f"the sim exited with {sim.returncode}: see {self.out / 'sim.stderr'}")
        if time.monotonic() > deadline:
            raise RuntimeError(f"the stack did not start in {SIM_START_TIMEOUT_S:g} s: see {self.out / 'sim.stderr'}")

    def _wait_until(self, t_ns: int, sim: subprocess.Popen, session: zenoh.Session, poller: StatusPoller,
                    observer: Observer) -> None:
        """Sleep until ``t_ns``, putting a fallen robot back meanwhile."""
        while (left := t_ns - time.monotonic_ns()) > 0:
            if sim.poll() is not None:
                raise RuntimeError(f"the sim exited with {sim.returncode} during the soak: see {self.out / 'sim.stderr'}")
            if not self.args.no_put_back and poller.twin_falls > self.falls_handled and self._can_take_over(observer):
                self.falls_handled = poller.twin_falls
                self._put_back(session)
            time.sleep(min(left / 1e9, 0.05))

    def _can_take_over(self, observer: Observer) -> bool:
        """A robot put back falls again unless an estimator and a control loop run."""
        rx = observer.streams.torque_rx
        return ("estimator" in observer.live or "estimator" not in self.services) and bool(rx) and \
            time.monotonic_ns() - rx[-1] < CONTROL_LOOP_RUNNING_S * 1e9

    # --- faults ---

    def _start_helper(self, f: Fault) -> subprocess.Popen | None:
        """The helper process of a load or message fault, started now and waiting for its word."""
        if f.kind == "cpu_hog" and f.cpu < (os.cpu_count() or 1):
            argv = sf.helper_argv("hog", "--cpu", str(f.cpu), "--duration", str(f.duration_s))
        elif f.kind in ("malformed_flood", "bad_stamps"):
            argv = sf.helper_argv("flood", "--endpoint", self.endpoint, "--namespace", self.ns, "--topics", ",".join(f.topics),
                                  "--kind", "malformed" if f.kind == "malformed_flood" else "stamps",
                                  "--rate", str(f.rate_hz), "--offset", str(f.offset_s), "--duration", str(f.duration_s))
        else:
            return None
        proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.PIPE)
        self.helpers.append(proc)
        return proc

    def _inject(self, f: Fault, sim_pid: int, session: zenoh.Session, window_end: int,
                helper: subprocess.Popen | None = None) -> Injection:
        if f.kind == "noop":  # nothing done: what shows in its window is a false detection
            now = time.monotonic_ns()
            return Injection(f, now, now, window_end)
        if f.kind in ("kill", "router_restart"):
            pid = sf.target_pid(sim_pid, ROUTER if f.kind == "router_restart" else f.target)
            start = time.monotonic_ns()
            if pid is None:
                return Injection(f, start, start, window_end, error=f"no process for {f.service!r} found")
            watch = sf.ExitWatch(pid)
            watch_thread = watch.start(KILL_WATCH_S)
            os.kill(pid, signal.SIGKILL)
            start = time.monotonic_ns()
            inj = Injection(f, start, start, window_end, pid=pid)
            self._watch_exit(inj, watch, watch_thread)
            return inj
        if f.kind == "stall":
            pid = sf.target_pid(sim_pid, f.target)
            start = time.monotonic_ns()
            if pid is None:
                return Injection(f, start, start, window_end, error=f"no process for {f.target!r} found")
            whole_unit = "/" not in f.target
            sf.signal_unit(pid, signal.SIGSTOP, whole_unit)
            start = time.monotonic_ns()
            self.stopped.append((pid, whole_unit))
            try:
                time.sleep(f.duration_s)
            finally:
                sf.signal_unit(pid, signal.SIGCONT, whole_unit)
                self.stopped.remove((pid, whole_unit))
            return Injection(f, start, time.monotonic_ns(), window_end, pid=pid)
        if helper is None:  # a hog on a core this host lacks
            now = time.monotonic_ns()
            return Injection(f, now, now, window_end, error=f"cpu {f.cpu} does not exist here")
        return self._run_helper(f, helper, window_end)

    def _watch_exit(self, inj: Injection, watch: sf.ExitWatch, thread: threading.Thread) -> None:
        thread.join(KILL_WATCH_S + 1.0)
        inj.exited_ns, inj.reaped_ns = watch.exited_ns, watch.reaped_ns

    def _run_helper(self, f: Fault, proc: subprocess.Popen, window_end: int) -> Injection:
        start = time.monotonic_ns()
        try:
            # started with the schedule; one not set up yet is waited for, and the fault (and
            # its deadline) begins at the word it is given, not when it was due
            ready = select.select([proc.stdout], [], [], HELPER_START_TIMEOUT_S)[0] and proc.stdout.readline()
            if ready and ready.decode(errors="replace").strip() == sf.READY_LINE:
                start = time.monotonic_ns()
                assert proc.stdin is not None
                proc.stdin.write(f"{sf.GO_LINE}\n".encode())
                proc.stdin.flush()
                out, err = proc.communicate(timeout=f.duration_s + HELPER_GRACE_S)
            else:
                proc.kill()
                out, err = proc.communicate()
                out = (ready or b"") + out
        except subprocess.TimeoutExpired:
            proc.kill()
            out, err = proc.communicate()
        finally:  # also when the soak itself is being stopped
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            self.helpers.remove(proc)
        inj = Injection(f, start, time.monotonic_ns(), window_end, pid=proc.pid)
        lines = [ln for ln in out.decode(errors="replace").strip().splitlines() if ln.strip() != sf.READY_LINE]
        try:
            inj.helper = json.loads(lines[-1]) if lines else None
        except json.JSONDecodeError:
            inj.helper = None
        if proc.returncode != 0:
            inj.error = f"helper exited with {proc.returncode}: {err.decode(errors='replace')[-500:]}"
        return inj

    def _put_back(self, session: zenoh.Session) -> None:
        """The twin reports a fall: put the robot back, rebuild the estimate, arm."""
        t = time.monotonic_ns()
        twin = query_params(session, self.ns, TWIN)
        if twin is None or "twin.seed" not in twin.params:
            return
        reply = query_params(session, self.ns, TWIN, {"twin.seed": twin.params["twin.seed"]})
        if reply is None or reply.error:
            return
        self.put_backs.append(t)
        for inj in self.injections:
            if inj.start_ns <= t < inj.window_end_ns and inj.put_back_ns is None:
                inj.put_back_ns = t
        time.sleep(PUT_BACK_SETTLE_S)
        est = query_params(session, self.ns, "estimator")
        if est is not None and "estimator.rate_hz" in est.params:  # re-converge from the next pose
            query_params(session, self.ns, "estimator", {"estimator.rate_hz": est.params["estimator.rate_hz"]})
            time.sleep(PUT_BACK_SETTLE_S)
        ctl = query_params(session, self.ns, "control")
        if ctl is not None and "control.arm_request" in ctl.params:
            query_params(session, self.ns, "control", {"control.arm_request": int(ctl.params["control.arm_request"]) + 1})

    def _print_progress(self, inj: Injection, t0: int) -> None:
        where = f"{inj.fault.kind}@{inj.fault.at_s:g}"
        print(f"soak: injected {where} at {(inj.start_ns - t0) / 1e9:.2f} s{' (' + inj.error + ')' if inj.error else ''}",
              file=sys.stderr, flush=True)

    # --- the end ---

    def _cleanup(self, sim: subprocess.Popen, session: zenoh.Session | None, observer: Observer | None,
                 poller: StatusPoller | None, *files: Any) -> None:
        for pid, whole_unit in list(self.stopped):
            sf.signal_unit(pid, signal.SIGCONT, whole_unit)
        for proc in list(self.helpers):
            proc.kill()
            proc.wait()
        if poller is not None:
            poller.stop()
        if observer is not None:
            observer.stop()
        if sim.poll() is None:
            sim.send_signal(signal.SIGTERM)
            try:
                sim.wait(SIM_STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                sim.kill()
                sim.wait()
        # Units that outlived their sim (a sim killed hard leaves its supervisor's children): they
        # carry this run's endpoint, which no one else uses.
        for pid in _processes_with(self.endpoint.encode()):
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        if session is not None:
            session.close()
        for f in files:
            f.close()

    def _summarize(self, streams: Streams, t0: int, rec_dir: Path, wall_minus_mono: int) -> dict[str, Any]:
        lines = (self.out / "sim.stdout").read_text().strip().splitlines()
        try:
            metrics = json.loads(lines[-1]) if lines else {}
        except json.JSONDecodeError:
            metrics = {"unparsed": lines[-1][-2000:]}
        files = recording_files([rec_dir]) if rec_dir.is_dir() else []
        windows = [(inj.start_ns, inj.window_end_ns) for inj in self.injections]
        losses = window_losses(_recorded_seqs(files, self.ns, wall_minus_mono), windows) if files else [None] * len(windows)
        faults = [analyze(streams, inj, t0, loss) for inj, loss in zip(self.injections, losses)]
        falls = falls_by_window(streams, self.injections, t0)
        finished = [p for p in files if p.suffix == ".mcap"]
        summary = {
            "run": {"duration_s": self.duration_s, "services": self.services, "endpoint": self.endpoint, "namespace": self.ns,
                    "schedule": [f.describe() for f in self.schedule.faults], "put_backs_s": [round((t - t0) / 1e9, 3) for t in self.put_backs]},
            "faults": faults,
            "totals": _totals(faults, falls),
            "metrics": metrics,
            "recorder": file_metadata(finished[-1]) if finished else {},
            "recording_files": len(files),
        }
        if files and not self.args.no_plot:
            plot = subprocess.run([sys.executable, "-m", "services.cli.main", "plot", str(rec_dir), "--out", str(self.out / "plots")],
                                  capture_output=True, text=True)
            summary["plot"] = json.loads(plot.stdout.strip().splitlines()[-1]) if plot.returncode == 0 else plot.stderr[-2000:]
        return summary


def _processes_with(needle: bytes) -> list[int]:
    """Pids of the processes whose command line contains ``needle``."""
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit() and int(entry.name) != os.getpid():
            try:
                if needle in (entry / "cmdline").read_bytes():
                    out.append(int(entry.name))
            except OSError:
                pass
    return out


def _recorded_seqs(files: list[Path], ns: str, wall_minus_mono: int):
    """``(receipt on the monotonic clock, topic, seq)`` of every recorded message."""
    for rec in read_recording(files):
        topic = topic_for_key(ns, rec.key)
        if topic is None:
            continue  # service statuses
        _, seq = envelope(topic, rec.data)
        yield rec.log_ns - wall_minus_mono, topic.name, seq


def _totals(faults: list[dict[str, Any]], falls: list[dict[str, Any]]) -> dict[str, Any]:
    """The run's figures and its verdict: ``passed`` only when every fault was carried out and
    detected, the robot never fell (by its physics), and a lost commander always reached zero
    torque."""
    real = [f for f in faults if f["kind"] != "noop"]
    noops = [f for f in faults if f["kind"] == "noop"]
    zero = [f["zero_torque_ms"] for f in real if f.get("zero_torque_ms") is not None]
    recovery = [f["recovery_s"] for f in real if f.get("recovery_s") is not None]
    name = lambda f: f"{f['kind']}@{f['at']:g}"  # noqa: E731
    totals = {
        "faults": len(real),
        "detected": sum(1 for f in real if f["detected"]),
        "undetected": [name(f) for f in real if f["injected"] and not f["detected"]],
        "not_injected": [name(f) for f in real if not f["injected"]],
        "noop_faults": len(noops),
        "false_detections": [name(f) for f in noops if f["detected"]],
        "false_detection_rate": round(sum(f["detected"] for f in noops) / len(noops), 3) if noops else None,
        "falls": len(falls),  # every fall of the run, by the physics
        "fall_times": falls,
        "falls_outside_faults": sum(1 for fall in falls if fall["fault"] is None),
        "fell_on": [name(f) for f in real if f.get("fell")],
        "zero_torque_missing": [name(f) for f in real if f.get("zero_torque_missing")],
        "not_recovered": [name(f) for f in real if not f["recovered"]],
        "zero_torque_ms_max": max(zero) if zero else None,
        "recovery_s_max": max(recovery) if recovery else None,
        "lost": {t: n for t, n in _sum_lost(real).items() if n},
    }
    totals["passed"] = not (totals["undetected"] or totals["not_injected"] or falls or totals["zero_torque_missing"])
    return totals


def _sum_lost(faults: list[dict[str, Any]]) -> dict[str, int]:
    out: dict[str, int] = {}
    for f in faults:
        for topic, n in f.get("lost", {}).items():
            out[topic] = out.get(topic, 0) + n
    return out


# --- the command line ---


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--schedule", default=None, help=f"fault schedule, TOML or JSON (default: {DEFAULT_SCHEDULE.name} unless faults are given below)")
    ap.add_argument("--kill", action="append", default=[], metavar="SERVICE@T", help="kill -9 SERVICE (SERVICE/child: its loop process) T s after the stack first armed")
    ap.add_argument("--fault", action="append", default=[], metavar="KIND@T[:k=v,...]", help="any fault, e.g. stall@40:target=control/child,duration=0.2 (see deploy/soak_schedule.py)")
    ap.add_argument("--duration", type=float, default=None, help=f"[s] wall time (default: the schedule's, else {DURATION_S:g})")
    ap.add_argument("--scenario", default=None, help="twin scenario (default: the schedule's, else hop-in-place)")
    ap.add_argument("--goals", default="1.5,0;1.5,1.5;0,1.5;0,0", help="tour of goals 'x,y;x,y;...' [m]")
    ap.add_argument("--goal-period", type=float, default=75.0, help="[s] per goal")
    ap.add_argument("--services", default=None, help=f"units besides the router (default: the schedule's, else {SERVICES})")
    ap.add_argument("--out", default="soak", help="output directory")
    ap.add_argument("--namespace", default=NS_DEFAULT)
    ap.add_argument("--config", default=str(SIL_CONFIG), help="the SIL profile the run starts from")
    ap.add_argument("--no-put-back", action="store_true", help="leave a fallen robot lying")
    ap.add_argument("--no-plot", action="store_true", help="skip the plots of the recording")


def build_schedule(args: argparse.Namespace) -> tuple[Schedule, list[str], float]:
    """The schedule of the file and the shorthand, checked against the run it will get."""
    extra = [parse_kill(k) for k in args.kill] + [parse_shorthand(f) for f in args.fault]
    path = args.schedule or (None if extra else DEFAULT_SCHEDULE)
    schedule = load_schedule(path) if path else Schedule(())
    schedule = schedule.merged(extra)
    settings = schedule.settings
    unknown = set(settings) - {"duration_s", "services", "scenario"}
    if unknown:
        raise ScheduleError(f"[soak]: unknown keys {sorted(unknown)} (duration_s, services, scenario)")
    duration = float(args.duration if args.duration is not None else settings.get("duration_s", DURATION_S))
    services = [s for s in str(args.services or settings.get("services", SERVICES)).split(",") if s]
    args.scenario = args.scenario or settings.get("scenario", "hop-in-place")
    check_schedule(schedule, duration, services)
    return schedule, services, duration


def run(args: argparse.Namespace) -> int:
    try:
        schedule, services, duration = build_schedule(args)
    except ScheduleError as exc:
        print(f"archer soak: {exc}", file=sys.stderr)
        return 2
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # unwind through the cleanup
    soak = Soak(args, schedule, services, duration)
    try:
        summary = soak.run()
    except RuntimeError as exc:
        print(f"archer soak: {exc}", file=sys.stderr)
        return 1
    (soak.out / "summary.json").write_text(json.dumps(summary, indent=2))
    for fault in summary["faults"]:
        print(json.dumps(fault), flush=True)
    print(json.dumps({"totals": summary["totals"], "summary": str(soak.out / "summary.json")}), flush=True)
    return 0 if summary["totals"]["passed"] else 1  # a fault not carried out or not detected, a fall, torque never cut


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_arguments(ap)
    return run(ap.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
