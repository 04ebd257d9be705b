"""The geometric MPC's process: the mid level beside the 1 kHz loop (``control.mid_level =
"geometric_mpc"``, thesis 5.3).

Subscribes (latest value): ``state``, ``reference``.
Computes: :class:`onboard.low_level.planning.gmpc_mid_level.GmpcMidLevel` every ``1 / gmpc.rate_hz`` on a
:class:`services.runtime.realtime.DeadlineLoop` (absolute deadlines; a solve that runs past
the next deadline is an overrun, counted, and the missed deadlines are skipped).
Publishes: ``mid_level`` (MidLevelSetpoint) for each answer that passed its checks; a
refused answer is counted and logged by the control service from the reports, and nothing
is published, so the loop falls back to the ZDP once its last setpoint is stale.

Why a process of its own: a solve takes milliseconds of Python and C++ holding the GIL; in the
loop's process it would delay the 1 kHz ticks by as much (ARCHITECTURE.md, Timing). It runs
at a real-time priority below the loop's, the estimator's and the hardware's (``gmpc.rt_priority``). The control service starts and stops it
with the loop and reads its reports (solves, refusals and why, solve times) over a pipe.
"""

from __future__ import annotations

import dataclasses
import signal
import time
from collections import Counter, deque
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from onboard.contracts import messages as msgs
from onboard.contracts.params import ControlParams, GeometricMpcParams, SafetyLimits
from onboard.contracts.topics import TOPICS
from robot_description.controller import build_gmpc_mid_level
from services.runtime.child_process import ChildProcess
from services.runtime.clock import WallClock
from services.runtime.realtime import DeadlineLoop, die_with_parent, make_realtime_from
from services.runtime.service import LatestSlot, TypedPublisher, check_publisher
from services.runtime.zenoh_session import open_session

READS = ("state", "reference")
PUBLISHER = "control"  # the control service owns the process and its topic
REPORT_PERIOD_S = 0.5  # [s] between reports to the control service
SOLVE_WINDOW = 1000  # solve times kept for the reported percentiles
START_TIMEOUT_S = 60.0  # [s] Pinocchio model, QP setup (a cold numba cache: its kernels compile, ~15 s on a loaded machine), Zenoh


@dataclasses.dataclass(frozen=True)
class MidLevelConfig:
    """What the process needs (picklable)."""

    ns: str
    endpoint: str
    zenoh_config: str | None
    control: ControlParams
    gmpc: GeometricMpcParams
    safety: SafetyLimits
    parent_pid: int = 0


class MidLevelLoop:
    """The solve loop with its own Zenoh session; runs in the mid-level process."""

    def __init__(self, cfg: MidLevelConfig) -> None:
        self.cfg = cfg
        self.clock = WallClock()
        self.mid = build_gmpc_mid_level(cfg.control.robot, cfg.gmpc, cfg.control, cfg.safety)
        self.session = open_session(cfg.endpoint, "peer", cfg.zenoh_config)
        self.slots: dict[str, LatestSlot] = {}
        self.undecodable = 0
        for name in READS:
            self.slots[name] = self._subscribe(name)
        self.pub = TypedPublisher(self.session, check_publisher(PUBLISHER, "mid_level"), cfg.ns, self.clock)
        self.published = 0
        self.refusals: Counter[str] = Counter()
        self.solve_s: deque[float] = deque(maxlen=SOLVE_WINDOW)
        self.loop = DeadlineLoop(1.0 / cfg.gmpc.rate_hz, self.tick, name="gmpc-loop")

    def _subscribe(self, name: str) -> LatestSlot:
        slot: LatestSlot = LatestSlot()
        topic = TOPICS[name]

        def on_sample(sample: Any) -> None:  # Zenoh thread: decode, drop in the slot
            try:
                msg = msgs.decode(sample.payload.to_bytes(), topic.msg_type)
            except msgs.MessageError:
                self.undecodable += 1
                return
            slot.put(msg, self.clock.now_ns())

        self.session.declare_subscriber(topic.key(self.cfg.ns), on_sample)
        return slot

    def tick(self, _deadline_s: float) -> None:
        st = self.slots["state"].get()
        if st is None:
            return
        ref = self.slots["reference"].get()
        t0 = time.perf_counter()
        try:
            sp = self.mid.step(self.clock.now_ns(), st[0], ref[0] if ref is not None else None)
            why = self.mid.last_status
        except Exception as exc:  # a solver's or the model's failure on this input: refused, the loop goes on
            self.mid.rejected += 1
            sp, why = None, f"{type(exc).__name__}: {exc}"[:200]
        dt = time.perf_counter() - t0
        self.solve_s.append(dt)
        if sp is None:
            self.refusals[why] += 1
            return
        sp.solve_ms = dt * 1e3
        self.pub.put(sp)
        self.published += 1

    def report(self) -> dict[str, Any]:
        times = np.asarray(self.solve_s) * 1e3
        return {
            "solves": self.mid.solves,
            "published": self.published,
            "refused": self.mid.rejected,
            "refusals": dict(self.refusals),
            "undecodable": self.undecodable,
            "solve_ms_p50": float(np.percentile(times, 50)) if times.size else 0.0,
            "solve_ms_p99": float(np.percentile(times, 99)) if times.size else 0.0,
            "loop": self.loop.recorder.stats().as_dict(),
        }


def mid_level_process_main(cfg: MidLevelConfig, conn: Connection) -> None:
    """Build, report ready, solve until told to stop (or the pipe breaks)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent stops it over the pipe
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    die_with_parent(cfg.parent_pid)
    try:
        applied = make_realtime_from(cfg.gmpc.rt_priority, cfg.gmpc.cpu)  # before any thread: they inherit it
        loop = MidLevelLoop(cfg)
    except Exception as exc:  # reported to the parent, which fails the service
        conn.send({"error": repr(exc)})
        return
    conn.send({"ready": True, "realtime": applied})
    loop.loop.start()
    try:
        while True:
            if conn.poll(REPORT_PERIOD_S):
                if conn.recv() == "stop":
                    break
            if loop.loop.error is not None:
                conn.send({"error": repr(loop.loop.error), **loop.report()})
                break
            conn.send(loop.report())
    except (EOFError, OSError):
        pass
    loop.loop.stop()
    try:
        conn.send({"final": True, **loop.report()})
    except (BrokenPipeError, OSError):
        pass
    loop.session.close()


class MidLevelProcess(ChildProcess):
    """Starts and talks to the mid-level process (used by the control service)."""

    def __init__(self, cfg: MidLevelConfig) -> None:
        super().__init__(mid_level_process_main, cfg, "archer-gmpc")

    def start(self, timeout_s: float = START_TIMEOUT_S) -> None:
        super().start(timeout_s)
