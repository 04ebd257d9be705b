"""A process supervisor that runs services as systemd would, for software in the loop.

``archer sim --mode realtime`` starts every service of the stack as its own process
(``archer run NAME``) through :class:`Supervisor`, with the policy of the service's
unit in ``deploy/systemd/`` (so a run on a workstation exercises what the robot
does):

- ``Type=notify``: a unit is *active* once its process sent ``READY=1`` over the
  notify socket (``$NOTIFY_SOCKET``, the protocol of :mod:`services.runtime.sd_notify`);
  units listed in ``After=`` start only when those are active, as systemd orders
  them. The sender is identified by ``SCM_CREDENTIALS``; ``NotifyAccess=all``
  accepts any process of the unit's process group, ``main`` only the main one.
- ``WatchdogSec=``: no ``WATCHDOG=1`` for that long kills the unit with SIGABRT.
- ``TimeoutStartSec=``: no ``READY=1`` for that long is a failure.
- ``Restart=on-failure`` (``RestartSec=``): an exit code other than 0, a signal
  other than SIGHUP/SIGINT/SIGTERM/SIGPIPE, a watchdog or start timeout restarts
  the unit, at most ``StartLimitBurst=`` starts per ``StartLimitIntervalSec=``.
- Stopping or after the main process died, the rest of its process group (as a
  cgroup) gets SIGTERM, then SIGKILL after ``TimeoutStopSec=``; units stop in the
  reverse order of starting.
- ``Nice=``, ``CPUSchedulingPolicy=fifo`` with ``CPUSchedulingPriority=``: the CPU
  priority of the unit's processes (the hard-rate loops and their inputs above the
  planner, perception and the recorder).

Every transition is an :class:`Event` (``events``); :meth:`Supervisor.summary`
counts restarts per unit.
"""

from __future__ import annotations

import ctypes
import logging
import os
import select
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

from onboard.contracts.topics import STANDBY_SERVICES, STANDBY_SUFFIX
from services.runtime.realtime import make_realtime

STDERR_FD = 2
log = logging.getLogger("archer.supervisor")

UNIT_DIR = Path(__file__).resolve().parents[2] / "deploy" / "systemd"
POLL_S = 0.05  # supervision tick for exits and timeouts (notifications wake it at once)
CLEAN_SIGNALS = frozenset({signal.SIGHUP, signal.SIGINT, signal.SIGTERM, signal.SIGPIPE})
WATCHDOG_SIGNAL = signal.SIGABRT  # systemd's default WatchdogSignal=
SUPERVISOR_RT_PRIORITY = 20  # SCHED_FIFO of the supervision thread: above normal tasks, below control loops
KILL_GRACE_S = 1.0  # after SIGKILL, a group still there holds only zombies
PR_SET_CHILD_SUBREAPER = 36  # prctl(2)
SUPERVISOR_PID_ENV = "ARCHER_SUPERVISOR_PID"  # a unit's process dies with this process (services/cli/run.py)
_UCRED = struct.Struct("3i")  # pid, uid, gid
_TIME_UNITS = {"us": 1e-6, "ms": 1e-3, "s": 1.0, "sec": 1.0, "m": 60.0, "min": 60.0, "h": 3600.0}

# systemd's defaults for what a unit does not say
DEFAULT_RESTART_S = 0.1
DEFAULT_START_TIMEOUT_S = 90.0
DEFAULT_STOP_TIMEOUT_S = 90.0
DEFAULT_START_LIMIT_BURST = 5
DEFAULT_START_LIMIT_INTERVAL_S = 10.0


# --- unit files ---------------------------------------------------------------------------------


def parse_unit(text: str) -> dict[str, dict[str, list[str]]]:
    """``{section: {key: [values in order]}}`` of a systemd unit (keys may repeat)."""
    sections: dict[str, dict[str, list[str]]] = {}
    current: dict[str, list[str]] | None = None
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line[0] in "#;":
            continue
        if line.startswith("[") and line.endswith("]"):
            current = sections.setdefault(line[1:-1], {})
            continue
        if current is None or "=" not in line:
            raise ValueError(f"not a unit file line: {raw!r}")
        key, value = line.split("=", 1)
        current.setdefault(key.strip(), []).append(value.strip())
    return sections


def parse_timespan(value: str) -> float | None:
    """systemd time span (``500ms``, ``2s``, ``1min 30s``, ``infinity``) in seconds; None: infinity."""
    value = value.strip()
    if value in ("infinity", ""):
        return None
    total, number = 0.0, ""
    i = 0
    while i < len(value):
        ch = value[i]
        if ch.isdigit() or ch == ".":
            number += ch
            i += 1
            continue
        if ch == " ":
            i += 1
            continue
        j = i
        while j < len(value) and value[j].isalpha():
            j += 1
        unit = value[i:j]
        if unit not in _TIME_UNITS or not number:
            raise ValueError(f"bad time span {value!r}")
        total += float(number) * _TIME_UNITS[unit]
        number, i = "", j
    if number:
        total += float(number)  # a bare number is seconds
    return total


@dataclass(frozen=True)
class UnitSpec:
    """What the supervisor needs of one unit: its command and its policy."""

    name: str  # the service ("control" for archer-control.service)
    argv: tuple[str, ...]
    after: tuple[str, ...] = ()  # services that must be active first
    notify: bool = True  # Type=notify (else active once spawned)
    notify_access: str = "main"  # "main" or "all"
    watchdog_s: float | None = None
    restart: str = "on-failure"  # "no", "on-failure", "always"
    restart_s: float = DEFAULT_RESTART_S
    start_timeout_s: float | None = DEFAULT_START_TIMEOUT_S
    stop_timeout_s: float | None = DEFAULT_STOP_TIMEOUT_S
    start_limit_burst: int = DEFAULT_START_LIMIT_BURST
    start_limit_interval_s: float = DEFAULT_START_LIMIT_INTERVAL_S
    nice: int = 0  # Nice=: CPU priority of the whole process (-20 highest .. 19 lowest)
    fifo_priority: int = 0  # CPUSchedulingPolicy=fifo with CPUSchedulingPriority= (0: normal scheduling)
    env: dict[str, str] = field(default_factory=dict)


def unit_path(service: str, unit_dir: Path = UNIT_DIR) -> Path:
    return unit_dir / f"archer-{service}.service"


def spec_from_unit(service: str, argv: list[str], unit_dir: Path = UNIT_DIR, **overrides) -> UnitSpec:
    """The policy of ``archer-<service>.service`` around ``argv`` (a unit that does not exist
    gets systemd's defaults with ``Restart=on-failure``)."""
    path = unit_path(service, unit_dir)
    if not path.is_file():
        return UnitSpec(name=service, argv=tuple(argv), **overrides)
    unit = parse_unit(path.read_text())
    u, s = unit.get("Unit", {}), unit.get("Service", {})

    def last(section: dict[str, list[str]], key: str, default: str = "") -> str:
        return section.get(key, [default])[-1]

    after = tuple(
        name.removeprefix("archer-").removesuffix(".service")
        for value in u.get("After", [])
        for name in value.split()
        if name.startswith("archer-") and name.endswith(".service")
    )
    fields = dict(
        name=service,
        argv=tuple(argv),
        after=after,
        notify=last(s, "Type", "simple") == "notify",
        notify_access=last(s, "NotifyAccess", "main"),
        watchdog_s=parse_timespan(last(s, "WatchdogSec", "infinity")) or None,
        restart=last(s, "Restart", "no"),
        restart_s=parse_timespan(last(s, "RestartSec", "100ms")) or 0.0,
        start_timeout_s=parse_timespan(last(s, "TimeoutStartSec", "90s")),
        stop_timeout_s=parse_timespan(last(s, "TimeoutStopSec", "90s")),
        start_limit_burst=int(last(u, "StartLimitBurst", str(DEFAULT_START_LIMIT_BURST))),
        start_limit_interval_s=parse_timespan(last(u, "StartLimitIntervalSec", "10s")) or 0.0,
        nice=int(last(s, "Nice", "0")),
        fifo_priority=int(last(s, "CPUSchedulingPriority", "0")) if last(s, "CPUSchedulingPolicy") == "fifo" else 0,
    )
    fields.update(overrides)
    return UnitSpec(**fields)


def service_argv(service: str, endpoint: str, ns: str, config: str | None = None, log_level: str = "WARNING") -> list[str]:
    """``archer run SERVICE`` with this interpreter, on the sim's endpoint and namespace."""
    argv = [sys.executable, "-m", "services.cli.main", "run", service, "--endpoint", endpoint, "--namespace", ns, "--log-level", log_level]
    if config:
        argv += ["--config", config]
    return argv


def process_of(unit: str) -> str:
    """What ``archer run`` starts for a unit: a hot standby unit (``control_standby``) runs a second
    instance of its service, which stands by while the first one lives (services/runtime/service.py)."""
    base = unit.removesuffix(STANDBY_SUFFIX)
    return base if base != unit and base in STANDBY_SERVICES else unit


def sim_specs(services: list[str], endpoint: str, ns: str, config: str | None = None, log_level: str = "WARNING") -> list[UnitSpec]:
    """Specs for ``archer sim --mode realtime``: the units' policy, the sim's endpoint."""
    specs = [spec_from_unit(s, service_argv(process_of(s), endpoint, ns, config, log_level)) for s in services]
    names = set(services)
    # After= on units outside the run (the router the sim itself serves, the hardware the
    # twin replaces) orders nothing here.
    return [UnitSpec(**{**spec.__dict__, "after": tuple(a for a in spec.after if a in names)}) for spec in specs]


# --- supervision ----------------------------------------------------------------------------------


@dataclass
class Event:
    t: float  # time.monotonic()
    unit: str
    what: str  # "start", "ready", "exit", "watchdog", "start-timeout", "restart-scheduled", "start-limit-hit", "stop", "nice-refused", "priority-refused"
    detail: str = ""


@dataclass
class _Unit:
    spec: UnitSpec
    # inactive (not started yet), activating, active, deactivating (killed for a broken
    # promise), stop-sigterm (main gone, group stopping), auto-restart, failed, dead
    state: str = "inactive"
    proc: subprocess.Popen | None = None
    started_at: float = 0.0
    last_ping: float = 0.0
    restart_at: float = 0.0
    starts: list[float] = field(default_factory=list)
    restarts: int = 0
    status: str = ""
    watchdog_pings: int = 0
    exit_codes: list[int] = field(default_factory=list)
    log_file: IO[bytes] | None = None
    failed: bool = False  # how the last main process ended
    group: int | None = None  # process group still being stopped
    kill_at: float = 0.0  # SIGKILL the group after this
    sigkilled: bool = False
    pidfd: int | None = None  # readable when the main process exits (Linux >= 5.3)


class Supervisor:
    """Starts, watches and restarts units; see the module docstring."""

    def __init__(self, specs: list[UnitSpec], log_dir: str | Path | None = None, env: dict[str, str] | None = None) -> None:
        names = [s.name for s in specs]
        if len(set(names)) != len(names):
            raise ValueError("duplicate unit")
        self._units = {s.name: _Unit(s) for s in specs}
        self._order: list[str] = []  # the order units first became active
        self._log_dir = Path(log_dir) if log_dir else None
        self._env = dict(os.environ if env is None else env)
        self._tmp = tempfile.TemporaryDirectory(prefix="archer-supervisor-")
        self.notify_path = os.path.join(self._tmp.name, "notify")
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
        self._sock.bind(self.notify_path)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_PASSCRED, 1)
        self._sock.setblocking(False)
        self._lock = threading.RLock()
        self._stopping = False
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, name="supervisor", daemon=True)
        self.events: list[Event] = []
        self.error: BaseException | None = None

    # --- public API ---

    def start(self) -> None:
        if self._log_dir:
            self._log_dir.mkdir(parents=True, exist_ok=True)
        _become_subreaper()
        self._thread.start()

    def wait_active(self, names: list[str] | None = None, timeout_s: float = 60.0, cancel: threading.Event | None = None) -> bool:
        """Block until ``names`` (default: all) are active; False on timeout, failure or ``cancel``."""
        wanted = names or list(self._units)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and not (cancel is not None and cancel.is_set()):
            states = [self.state(n) for n in wanted]
            if all(s == "active" for s in states):
                return True
            if "failed" in states or self.error is not None:
                return False
            time.sleep(0.02)
        return False

    def stop(self) -> dict[str, int | None]:
        """Stop every unit (reverse start order); returns the last exit code per unit."""
        with self._lock:
            self._stopping = True
        if self._thread.is_alive():
            self._done.wait()
            self._thread.join()
        else:
            self._stop_all()
        self._sock.close()
        self._tmp.cleanup()
        return {n: (u.exit_codes[-1] if u.exit_codes else None) for n, u in self._units.items()}

    def state(self, name: str) -> str:
        return self._units[name].state

    def pid(self, name: str) -> int | None:
        proc = self._units[name].proc
        return proc.pid if proc is not None and proc.poll() is None else None

    def restarts(self, name: str) -> int:
        return self._units[name].restarts

    def cpu_seconds(self) -> dict[str, float]:
        """CPU time [s] (user + system) used so far by the live processes of each unit's
        process group: its main process and what it started (a control loop child)."""
        groups = {u.proc.pid: n for n, u in self._units.items() if u.proc is not None}
        out = {n: 0.0 for n in self._units}
        for pgid, seconds in process_group_cpu_seconds(set(groups)).items():
            out[groups[pgid]] += seconds
        return out

    def summary(self) -> dict[str, dict[str, object]]:
        return {
            n: {"state": u.state, "restarts": u.restarts, "exit_codes": list(u.exit_codes), "watchdog_pings": u.watchdog_pings, "status": u.status}
            for n, u in self._units.items()
        }

    # --- the loop ---

    def _event(self, unit: str, what: str, detail: str = "") -> None:
        self.events.append(Event(time.monotonic(), unit, what, detail))
        log.info("unit %s: %s %s", unit, what, detail, extra={"fields": {"unit": unit, "event": what, "detail": detail}})

    def _run(self) -> None:
        # As PID 1 is, this thread must run the moment a main process dies: what it left
        # behind (a control loop) is still publishing. Logged and skipped where refused.
        make_realtime(priority=SUPERVISOR_RT_PRIORITY, reset_on_fork=True)  # not for the services it starts
        try:
            while True:
                with self._lock:
                    if self._stopping:
                        break
                # a main process's exit wakes us at once through its pidfd (its children must
                # not keep publishing for a polling period: think of a control loop)
                pidfds = [u.pidfd for u in self._units.values() if u.pidfd is not None]
                ready, _, _ = select.select([self._sock, *pidfds], [], [], POLL_S)
                now = time.monotonic()
                if self._sock in ready:
                    self._read_notifications(now)
                self._reap(now)
                self._check_timeouts(now)
                self._start_due(now)
        except BaseException as exc:  # surfaced through .error; units still get stopped
            self.error = exc
            log.exception("supervisor crashed")
        finally:
            self._stop_all()
            self._done.set()

    def _spawn(self, unit: _Unit, now: float) -> None:
        spec = unit.spec
        env = dict(self._env)
        env.update(spec.env)
        env["NOTIFY_SOCKET"] = self.notify_path
        env[SUPERVISOR_PID_ENV] = str(os.getpid())
        env.pop("WATCHDOG_PID", None)
        if spec.watchdog_s:
            env["WATCHDOG_USEC"] = str(int(spec.watchdog_s * 1e6))
        else:
            env.pop("WATCHDOG_USEC", None)
        out: IO[bytes] | int | None = None
        if self._log_dir:
            if unit.log_file is None:
                unit.log_file = open(self._log_dir / f"{spec.name}.log", "ab")
            out = unit.log_file
        # without a log file a unit's stdout joins our stderr: our stdout is the caller's report
        # (`archer sim --json`), and a library in a unit may print (the NatNet client does)
        unit.proc = subprocess.Popen(
            list(spec.argv), env=env, stdin=subprocess.DEVNULL, stdout=out if out is not None else STDERR_FD, stderr=out,
            start_new_session=True
        )
        unit.pidfd = _pidfd(unit.proc.pid)
        self._apply_scheduling(unit)
        unit.state = "activating" if spec.notify else "active"
        unit.started_at = unit.last_ping = now
        unit.starts.append(now)
        self._event(spec.name, "start", f"pid {unit.proc.pid}")
        if not spec.notify:
            self._became_active(unit)

    def _apply_scheduling(self, unit: _Unit) -> None:
        assert unit.proc is not None
        for what, detail in apply_unit_scheduling(unit.spec, unit.proc.pid):
            self._event(unit.spec.name, what, detail)

    def _became_active(self, unit: _Unit) -> None:
        if unit.spec.name not in self._order:
            self._order.append(unit.spec.name)

    def _start_due(self, now: float) -> None:
        for unit in self._units.values():
            if unit.state == "inactive":
                deps = [self._units[a].state for a in unit.spec.after if a in self._units]
                if all(d in ("active", "failed") for d in deps):
                    self._spawn(unit, now)
            elif unit.state == "auto-restart" and now >= unit.restart_at:
                window = [t for t in unit.starts if now - t < unit.spec.start_limit_interval_s]
                if len(window) >= unit.spec.start_limit_burst:
                    unit.state = "failed"
                    self._event(unit.spec.name, "start-limit-hit", f"{len(window)} starts in {unit.spec.start_limit_interval_s:g} s")
                    continue
                unit.restarts += 1
                self._spawn(unit, now)

    def _unit_of_pid(self, pid: int) -> _Unit | None:
        for unit in self._units.values():
            proc = unit.proc
            if proc is None:
                continue
            if proc.pid == pid:
                return unit
            if unit.spec.notify_access == "all":
                try:
                    if os.getpgid(pid) == proc.pid:  # the unit's process group (start_new_session)
                        return unit
                except ProcessLookupError:
                    pass
        return None

    def _read_notifications(self, now: float) -> None:
        cmsg_size = socket.CMSG_SPACE(_UCRED.size)
        while True:
            try:
                data, ancdata, _, _ = self._sock.recvmsg(4096, cmsg_size)
            except BlockingIOError:
                return
            pid = None
            for level, kind, payload in ancdata:
                if level == socket.SOL_SOCKET and kind == socket.SCM_CREDENTIALS:
                    pid = _UCRED.unpack(payload[: _UCRED.size])[0]
            unit = self._unit_of_pid(pid) if pid is not None else None
            if unit is None:
                continue  # not from a process we supervise (or not allowed to notify)
            fields = dict(line.split("=", 1) for line in data.decode(errors="replace").splitlines() if "=" in line)
            if fields.get("READY") == "1" and unit.state == "activating":
                unit.state = "active"
                unit.last_ping = now
                self._became_active(unit)
                self._event(unit.spec.name, "ready", f"after {now - unit.started_at:.2f} s")
            if fields.get("WATCHDOG") == "1":
                unit.last_ping = now
                unit.watchdog_pings += 1
            if fields.get("WATCHDOG") == "trigger":
                self._fail(unit, "watchdog", "WATCHDOG=trigger", WATCHDOG_SIGNAL)
            if "STATUS" in fields:
                unit.status = fields["STATUS"]

    def _check_timeouts(self, now: float) -> None:
        for unit in self._units.values():
            spec = unit.spec
            if unit.state == "activating" and spec.start_timeout_s and now - unit.started_at > spec.start_timeout_s:
                self._fail(unit, "start-timeout", f"no READY in {spec.start_timeout_s:g} s", signal.SIGTERM)
            elif unit.state == "active" and spec.watchdog_s and now - unit.last_ping > spec.watchdog_s:
                self._fail(unit, "watchdog", f"no WATCHDOG=1 in {spec.watchdog_s:g} s", WATCHDOG_SIGNAL)

    def _fail(self, unit: _Unit, what: str, detail: str, sig: int) -> None:
        """Kill a unit that broke its promise; its exit is then handled as a failure."""
        self._event(unit.spec.name, what, detail)
        unit.state = "deactivating"
        unit.status = f"{what}: {detail}"
        if unit.proc is not None and unit.proc.poll() is None:
            unit.proc.send_signal(sig)

    def _reap(self, now: float) -> None:
        """Handle main processes that exited, then units whose process group emptied."""
        for unit in self._units.values():
            proc = unit.proc
            if proc is not None and proc.poll() is not None:
                self._main_exited(unit, proc, now)
            if unit.state == "stop-sigterm" and unit.group is not None:
                if not _group_alive(unit.group):
                    unit.group = None
                    self._settle(unit, now)
                elif now > unit.kill_at + KILL_GRACE_S:
                    unit.group = None  # only zombies someone else must reap can be left
                    self._settle(unit, now)
                elif now > unit.kill_at and not unit.sigkilled:
                    _signal_group(unit.group, signal.SIGKILL)
                    unit.sigkilled = True

    def _main_exited(self, unit: _Unit, proc: subprocess.Popen, now: float) -> None:
        code = proc.returncode
        unit.exit_codes.append(code)
        unit.proc = None
        _close_pidfd(unit)
        killed_by = -code if code < 0 else 0
        unit.failed = code > 0 or (killed_by and killed_by not in CLEAN_SIGNALS) or unit.state == "deactivating"
        self._event(unit.spec.name, "exit", f"code {code}" if code >= 0 else f"signal {signal.Signals(killed_by).name}")
        # As systemd with a cgroup: what the main process left behind is stopped before
        # the unit counts as down (a control loop child must not outlive its parent).
        unit.state, unit.group, unit.sigkilled = "stop-sigterm", proc.pid, False
        unit.kill_at = now + (unit.spec.stop_timeout_s if unit.spec.stop_timeout_s is not None else DEFAULT_STOP_TIMEOUT_S)
        _signal_group(proc.pid, signal.SIGTERM)

    def _settle(self, unit: _Unit, now: float) -> None:
        """The unit is down: restart it or leave it failed/dead."""
        spec = unit.spec
        if spec.restart == "always" or (spec.restart == "on-failure" and unit.failed):
            unit.state = "auto-restart"
            unit.restart_at = now + spec.restart_s
            self._event(spec.name, "restart-scheduled", f"in {spec.restart_s:g} s")
        else:
            unit.state = "failed" if unit.failed else "dead"

    def _stop_all(self) -> None:
        """SIGTERM each main process in reverse start order (KillMode=mixed), then its group."""
        order = self._order[::-1] + [n for n in self._units if n not in self._order]
        for name in order:
            unit = self._units[name]
            timeout = unit.spec.stop_timeout_s if unit.spec.stop_timeout_s is not None else DEFAULT_STOP_TIMEOUT_S
            proc = unit.proc
            if proc is not None:
                self._event(name, "stop")
                proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(timeout)
                except subprocess.TimeoutExpired:
                    _signal_group(proc.pid, signal.SIGKILL)
                    proc.wait()
                unit.exit_codes.append(proc.returncode)
                unit.group, unit.proc = proc.pid, None
                _close_pidfd(unit)
            if unit.group is not None:
                _stop_group(unit.group, timeout)
                unit.group = None
            unit.state = "dead"
        for unit in self._units.values():
            if unit.log_file is not None:
                unit.log_file.close()
                unit.log_file = None


def apply_unit_scheduling(spec: UnitSpec, pid: int) -> list[tuple[str, str]]:
    """A unit's ``Nice=`` and SCHED_FIFO for process ``pid`` (0: the caller), as systemd
    applies them: nice 0 where the unit sets none, so that a supervisor's own value is
    not inherited. Linux keeps both per thread; applied while the process is still
    starting its interpreter (one thread), every thread it starts later inherits them.
    Raising priority needs CAP_SYS_NICE (systemd has it); what is refused is returned
    as ``(event, detail)`` pairs and the process runs as it is."""
    refused = []
    try:
        if os.getpriority(os.PRIO_PROCESS, pid) != spec.nice:
            os.setpriority(os.PRIO_PROCESS, pid, spec.nice)
    except OSError as exc:
        refused.append(("nice-refused", f"Nice={spec.nice}: {exc}"))
    if spec.fifo_priority:
        try:
            os.sched_setscheduler(pid, os.SCHED_FIFO, os.sched_param(spec.fifo_priority))
        except OSError as exc:
            refused.append(("priority-refused", f"CPUSchedulingPriority={spec.fifo_priority}: {exc}"))
    return refused


def process_group_cpu_seconds(pgids: set[int]) -> dict[int, float]:
    """User + system CPU seconds of the live processes of each group in ``pgids`` (/proc)."""
    out = {g: 0.0 for g in pgids}
    tick = os.sysconf("SC_CLK_TCK")
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        pgid = int(fields[2])
        if pgid in out:
            out[pgid] += (int(fields[11]) + int(fields[12])) / tick  # utime, stime
    return out


def _pidfd(pid: int) -> int | None:
    try:
        return os.pidfd_open(pid)
    except (OSError, AttributeError):
        return None  # an old kernel: exits are found by polling every POLL_S


def _close_pidfd(unit: _Unit) -> None:
    if unit.pidfd is not None:
        os.close(unit.pidfd)
        unit.pidfd = None


def _signal_group(pgid: int, sig: int) -> None:
    try:
        os.killpg(pgid, sig)
    except (ProcessLookupError, PermissionError):
        pass


def _group_alive(pgid: int) -> bool:
    """Whether a process of group ``pgid`` is left; reaps those that are our children."""
    while True:
        try:
            if os.waitid(os.P_PGID, pgid, os.WEXITED | os.WNOHANG) is None:
                break
        except ChildProcessError:
            break
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _stop_group(pgid: int, timeout_s: float) -> None:
    """SIGTERM a process group, SIGKILL it after ``timeout_s``; returns once it is gone."""
    _signal_group(pgid, signal.SIGTERM)
    deadline = time.monotonic() + timeout_s
    while _group_alive(pgid):
        now = time.monotonic()
        if now > deadline + KILL_GRACE_S:
            return  # zombies of another parent
        if now > deadline:
            _signal_group(pgid, signal.SIGKILL)
        time.sleep(0.01)


def _become_subreaper() -> bool:
    """Orphans of supervised processes become our children (as under systemd), so that
    they can be reaped: a container's PID 1 often reaps nothing."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False
