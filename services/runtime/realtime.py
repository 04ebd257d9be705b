"""Hard-rate loops: absolute deadlines, statistics, real-time scheduling.

As openpilot's ``common/realtime.py``: deadlines advance by whole periods
(``next += period``) so lateness never becomes drift, and a late tick is counted
as an overrun instead of silently stretching the period. Waiting sleeps until
``SPIN_S`` before the deadline, then spins, because the kernel's sleep granularity
(tens of microseconds, worse under load) would otherwise be the jitter. The loop
thread's timer slack is cut to 1 us so that the spin stays short: spinning is CPU
that the other services of a small computer need.
"""

from __future__ import annotations

import ctypes
import gc
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

log = logging.getLogger("archer.realtime")

SPIN_S = 60e-6  # spin this long before each deadline instead of sleeping (timer slack is 1 us)
LOOP_TIMER_SLACK_NS = 1000  # the default 50 us slack would make every sleep overshoot the spin window
STATS_CAPACITY = 1 << 16  # ring of recent ticks kept for percentiles (65 s at 1 kHz)
STATUS_WINDOW = 5000  # ticks a status report summarises: a full-ring percentile costs ms
RT_SWITCH_INTERVAL_S = 0.0005  # CPython GIL hand-over interval while a hard loop runs


def make_realtime(priority: int | None = None, cpu: int | None = None, reset_on_fork: bool = False) -> dict[str, str]:
    """Best effort: SCHED_FIFO at ``priority`` and affinity to ``cpu`` for the calling thread.

    Threads it starts later inherit the class (a loop process's Zenoh threads must, or
    they deliver its inputs at normal priority); with ``reset_on_fork`` neither they nor
    processes it starts do (a supervisor's services). Returns what was applied or why
    not; a laptop or an unprivileged container refuses, which is logged and skipped,
    never fatal.
    """
    applied: dict[str, str] = {}
    if cpu is not None:
        try:
            os.sched_setaffinity(0, {cpu})
            applied["cpu"] = str(cpu)
        except (OSError, AttributeError) as exc:
            applied["cpu"] = f"refused: {exc}"
            log.warning("cpu affinity refused", extra={"fields": {"cpu": cpu, "error": str(exc)}})
    if priority is not None:
        try:
            policy = os.SCHED_FIFO | (os.SCHED_RESET_ON_FORK if reset_on_fork else 0)
            os.sched_setscheduler(0, policy, os.sched_param(priority))
            applied["priority"] = f"SCHED_FIFO {priority}"
        except (OSError, AttributeError) as exc:
            applied["priority"] = f"refused: {exc}"
            log.warning("real-time priority refused", extra={"fields": {"priority": priority, "error": str(exc)}})
    return applied


def make_realtime_from(rt_priority: int, cpu: int) -> dict[str, str]:
    """:func:`make_realtime` with the parameter sections' convention (``ControlParams``,
    ``HardwareParams``): priority 0 and cpu -1 leave the scheduler alone."""
    return make_realtime(rt_priority or None, cpu if cpu >= 0 else None)


PR_SET_PDEATHSIG = 1  # linux/prctl.h
PR_SET_TIMERSLACK = 29


def _prctl(option: int, value: int) -> bool:
    """prctl(2) on the calling thread; False where it is unavailable or refused."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(option, value, 0, 0, 0) == 0:
            return True
        log.warning("prctl refused", extra={"fields": {"option": option, "errno": ctypes.get_errno()}})
    except (OSError, AttributeError) as exc:
        log.warning("prctl unavailable", extra={"fields": {"error": str(exc)}})
    return False


def die_with_parent(parent_pid: int, sig: int = signal.SIGKILL) -> None:
    """Have the kernel send ``sig`` to this process when its parent dies.

    A hard-rate loop in a child process must not outlive the service that owns it
    (a killed control service would otherwise leave its loop publishing torque), nor
    a service the supervisor that started it (SIGTERM: it stops cleanly). The kernel
    signals when the parent *thread* that started us exits: a supervisor starts its
    units from the one thread that lives as long as it supervises. Where prctl is
    unavailable a loop child still stops when its pipe breaks.
    """
    if parent_pid <= 0:
        return
    _prctl(PR_SET_PDEATHSIG, sig)
    if os.getppid() != parent_pid:  # the parent died before prctl took effect
        os._exit(1)


def freeze_heap() -> None:
    """Take what the process has allocated so far out of the garbage collector's sight.

    A full (generation 2) collection walks every container object of the process and holds
    the GIL meanwhile: with NumPy, MuJoCo, Zenoh and the message types loaded, 14-57 ms on
    this machine (``gc.callbacks`` timing in ``archer sim --mode realtime``), the hard-rate
    loop and every other thread of the process stopped: an IMU gap of tens of ticks. What a
    service builds before its loop starts lives as long as the service; frozen, it is never
    walked again, and collections see only what was allocated since.
    """
    gc.collect()
    gc.freeze()


@dataclass
class LoopStats:
    ticks: int  # every tick of the run
    overruns: int  # of every tick
    window: int  # the most recent ticks the percentiles cover (the ring, or fewer when asked)
    period_jitter_us_p50: float
    period_jitter_us_p99: float
    period_jitter_us_max: float
    tick_us_p50: float
    tick_us_p99: float
    tick_us_max: float  # the maxima cover every tick of the run

    def as_dict(self) -> dict[str, float]:
        return {k: (round(v, 2) if isinstance(v, float) else v) for k, v in self.__dict__.items()}


class LoopRecorder:
    """Fixed-size rings of wake-up lateness and compute time: no allocation per tick."""

    def __init__(self, capacity: int = STATS_CAPACITY) -> None:
        self._late = np.zeros(capacity)
        self._compute = np.zeros(capacity)
        self._n = 0
        self.overruns = 0
        self._late_max = 0.0  # over every tick, not only the ring's
        self._compute_max = 0.0

    def record(self, late_s: float, compute_s: float, overrun: bool) -> None:
        i = self._n % len(self._late)
        self._late[i] = late_s
        self._compute[i] = compute_s
        self._n += 1
        late = abs(late_s)
        if late > self._late_max:
            self._late_max = late
        if compute_s > self._compute_max:
            self._compute_max = compute_s
        if overrun:
            self.overruns += 1

    @property
    def ticks(self) -> int:
        return self._n

    def stats(self, last: int | None = None) -> LoopStats:
        """Percentiles over the ring, or over the ``last`` ticks only (cheap enough for a status);
        maxima and overruns over every tick."""
        n = min(self._n, len(self._late))
        if last is not None:
            n = min(n, last)
        if n == 0:
            return LoopStats(self._n, self.overruns, 0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        idx = (self._n - n + np.arange(n)) % len(self._late)
        late = np.abs(self._late[idx]) * 1e6
        compute = self._compute[idx] * 1e6
        return LoopStats(
            ticks=self._n,
            overruns=self.overruns,
            window=n,
            period_jitter_us_p50=float(np.percentile(late, 50)),
            period_jitter_us_p99=float(np.percentile(late, 99)),
            period_jitter_us_max=self._late_max * 1e6,
            tick_us_p50=float(np.percentile(compute, 50)),
            tick_us_p99=float(np.percentile(compute, 99)),
            tick_us_max=self._compute_max * 1e6,
        )


def wait_until(deadline_s: float, clock: Callable[[], float] = time.perf_counter) -> float:
    """Sleep, then spin, until ``deadline_s``; returns the wake-up time."""
    remaining = deadline_s - clock()
    if remaining > SPIN_S:
        time.sleep(remaining - SPIN_S)
    now = clock()
    while now < deadline_s:
        now = clock()
    return now


class DeadlineLoop:
    """Calls ``tick(deadline_s)`` every ``period_s`` on its own thread until stopped.

    ``tick`` must not block on the network, allocate much or log; it reads
    latest-value slots and publishes. A tick that ends after the next deadline is an
    overrun: the loop skips the missed deadlines instead of bursting to catch up.
    """

    def __init__(
        self, period_s: float, tick: Callable[[float], None], name: str = "deadline-loop",
        on_start: Callable[[], None] | None = None,
    ) -> None:
        """``on_start`` runs first on the loop's own thread (scheduling policy is per thread)."""
        if period_s <= 0:
            raise ValueError("period must be positive")
        self.period_s = period_s
        self._tick = tick
        self._on_start = on_start
        self._stop = threading.Event()
        self.recorder = LoopRecorder()
        self.error: BaseException | None = None
        self._progress_ticks = 0
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout_s: float = 1.0) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout_s)

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    def progressing(self) -> bool:
        """Whether the loop ticked since the last call and has not crashed (gates watchdogs)."""
        ticks = self.recorder.ticks
        advanced = ticks > self._progress_ticks
        self._progress_ticks = ticks
        return advanced and self.error is None

    def run_here(self) -> None:
        """Run the loop on the calling thread (for a dedicated process)."""
        self._run()

    def _run(self) -> None:
        if self._on_start is not None:
            self._on_start()
        freeze_heap()
        _prctl(PR_SET_TIMERSLACK, LOOP_TIMER_SLACK_NS)  # per thread: sleeps end within the spin window
        previous = sys.getswitchinterval()
        sys.setswitchinterval(RT_SWITCH_INTERVAL_S)  # other threads must not hold the GIL for 5 ms
        period = self.period_s
        clock = time.perf_counter
        deadline = clock() + period
        try:
            while not self._stop.is_set():
                woke = wait_until(deadline, clock)
                self._tick(deadline)
                done = clock()
                next_deadline = deadline + period
                overrun = done > next_deadline
                self.recorder.record(woke - deadline, done - woke, overrun)
                if overrun:  # skip the deadlines already missed; keep the phase
                    missed = int((done - deadline) / period)
                    next_deadline = deadline + (missed + 1) * period
                deadline = next_deadline
        except BaseException as exc:  # surfaced through .error; the owner disarms
            self.error = exc
            log.exception("deadline loop crashed")
        finally:
            sys.setswitchinterval(previous)
