"""The ``estimator`` service: the state estimate at 1 kHz (issue 5).

Subscribes: ``imu`` and ``joints`` (1 kHz), ``pose`` (motion capture / tracking camera,
stamped with its capture time), ``visual_odometry`` (the camera service's displacement between
two apex frames, stamped with their capture times; fused with ``position_source = "odometry"``
and ``visual_odometry``). Every message is kept: samples wait in Zenoh's own ring
buffers (``input_queue`` each, the oldest dropped beyond, counted as
``input_ring_full.<topic>``) until the loop thread drains them at its next tick, decodes
them (malformed payloads are rejected and counted as for any subscription) and feeds
them to the estimator in sensor-time order, with the drain time as their arrival; the
estimator refuses stamps too far from their arrival (the future, or the distant past).
No Python callback thread competes with the loop for the GIL (a 5 kHz flood of
malformed input delayed the loop by tens of milliseconds when one did). Latest-value
slots would not do here: the filter integrates every IMU interval.

Computes: :class:`onboard.estimation.estimator.StateEstimator` (robot parameters from the MJCF
variant ``EstimatorParams.robot``). Every ``1 / rate_hz`` a
:class:`services.runtime.realtime.DeadlineLoop` thread drains the queue into the estimator and
publishes ``state`` (StateEstimate with its covariance) for the stack clock's now.

Scheduling: the loop thread runs at ``EstimatorParams.rt_priority`` (SCHED_FIFO, when
permitted) between the twin / hardware exchange and the control loop: it is the control
loop's input, and a CPU hog at normal priority must not delay it (the log says what was
applied).

Status: the estimator's mode (``degraded`` while it has no pose, ``running`` otherwise),
pose age, standard deviations, gyro bias, loop timing and every estimator counter
(``est.<reason>`` in its figures); the refused inputs (future / past stamps, gated pose
outliers, out of order...) are also status counters, ``est.<reason>``. A parameter change rebuilds the estimator (it re-converges from
the next pose).
"""

from __future__ import annotations

import asyncio
import threading
from typing import Any, ClassVar

from onboard.estimation.estimator import StateEstimator
from onboard.contracts.params import EstimatorParams, restart_changes
from robot_description import identified
from services.runtime.realtime import DeadlineLoop, make_realtime_from
from services.runtime.service import Service, fence

INPUTS = ("imu", "joints", "pose", "visual_odometry")


class EstimatorService(Service):
    name: ClassVar[str] = "estimator"
    params_sections: ClassVar[tuple[str, ...]] = ("estimator",)
    subscribes: ClassVar[tuple[str, ...]] = INPUTS + ("state",)  # state: a standby watches the primary's estimates

    async def setup(self) -> None:
        p: EstimatorParams = self.params["estimator"]
        if not p.rate_hz > 0:
            raise ValueError(f"estimator rate must be positive, got {p.rate_hz}")
        self._lock = threading.Lock()  # the loop vs. a parameter change or a status query
        self._build(p)
        # inputs wait in Zenoh's ring buffers and the loop thread drains them (Service.polled)
        self._inputs = {topic: self.polled(topic, max(1, p.input_queue)) for topic in INPUTS}
        self._state_pub = self.publisher("state")
        # a hot standby (Service.role): the primary's estimates, by receipt time only (never decoded)
        self._fence_pid = self.fence_pid()
        self._fence_ns = int(p.standby_fence_s * 1e9) if self._fence_pid else 0
        self._primary_rx = self.rate("rx.state") if self.role == "standby" else None
        if self._primary_rx is not None:
            self.latest_sampled("state")
        self._fenced = 0  # 1: a hung primary was killed, -1: the fence found no such process
        self._realtime_pending = False  # a standby's loop: real-time scheduling when it takes over
        self._imu_rx = self.rate("rx.imu")  # ticked as the loop drains the IMU ring
        self._ticks = self.rate("loop")
        self._loop = DeadlineLoop(1.0 / p.rate_hz, self._tick, name="estimator-loop",
                                  on_start=lambda: self._schedule_loop(p))

    def _schedule_loop(self, p: EstimatorParams) -> None:
        """On the loop thread: scheduling is per thread. A standby's loop stays at normal priority until it
        takes over (two real-time estimators and control loops on a small machine starve everything else)."""
        if self.role == "standby":
            self._realtime_pending = True
            return
        applied = make_realtime_from(p.rt_priority, p.cpu)
        self.log.info("estimator loop scheduling", extra={"fields": applied})

    def _build(self, p: EstimatorParams) -> None:
        self.est = StateEstimator(p, identified.robot_params(p.robot, p.identified))
        self._rejected_seen = 0  # the estimator's rejections already added to the status counters
        self._rejections_seen: dict[str, int] = {}

    def _tick(self, _deadline_s: float) -> None:
        batch: list[Any] = []
        topic_of: dict[int, str] = {}
        for topic, polled in self._inputs.items():
            start = len(batch)
            if polled.drain(batch) >= polled.capacity:
                self.count(f"input_ring_full.{topic}")  # older samples may have been dropped
            for i in range(start, len(batch)):
                topic_of[i] = topic
        arrival_ns = self.clock.now_ns()
        # sensor time order across the topics (IMU and joint frames of one tick interleaved as
        # they were sampled); a stamp from the future or the past is refused by the estimator
        order = sorted(range(len(batch)), key=lambda i: batch[i].stamp_ns)
        with self._lock:
            feed = self.est.feed
            for i in order:
                feed(topic_of[i], batch[i], arrival_ns)
            if self.est.rejected_total != self._rejected_seen:
                self._count_rejections()
            if not self.est.has_imu:  # nothing to stamp an estimate with yet
                self.count("ticks_without_imu")
                return
            state = self.est.estimate(self.clock.now_ns())
        self._ticks.tick()
        if self._realtime_pending and self.role != "standby":  # just promoted
            self._realtime_pending = False
            self._schedule_loop(self.params["estimator"])
        if self.role == "standby":  # warm, silent (role is set on the event loop; read once per tick)
            self._watch_primary_estimates(state.valid)
            return
        self._state_pub.put(state)

    def _watch_primary_estimates(self, own_valid: bool) -> None:
        """A standby: the primary's estimates stopped while its token stays (a hang) and ours are valid:
        kill it (same host only), so that its token goes and we take over."""
        rx = self._primary_rx
        if not self._fence_ns or self._fenced or rx is None or rx.last_ns == 0 or not own_valid:
            return
        now = self.clock.now_ns()
        # our own inputs flow (so our Zenoh threads are not the ones starved) and the primary's estimates do not
        if now - self._imu_rx.last_ns < self._fence_ns // 4 and now - rx.last_ns > self._fence_ns:
            self._fenced = 1 if fence(self._fence_pid, self.name) else -1
            self.count("fenced" if self._fenced > 0 else "fence_failed")
            self.log.warning("primary estimates stopped with its token declared: fenced (kill -9)",
                             extra={"fields": {"pid": self._fence_pid, "killed": self._fenced > 0,
                                               "silent_ms": (now - rx.last_ns) / 1e6}})

    def _count_rejections(self) -> None:
        """Carry the estimator's new rejections into the status counters (under the lock)."""
        seen = self._rejections_seen
        for reason, n in self.est.rejections().items():
            new = n - seen.get(reason, 0)
            if new > 0:
                self.count(f"est.{reason}", new)
                seen[reason] = n
        self._rejected_seen = self.est.rejected_total

    async def main(self) -> None:
        self._loop.start()
        try:
            while not self.stopping.is_set():
                try:
                    await asyncio.wait_for(self.stopping.wait(), 0.5)
                except asyncio.TimeoutError:
                    pass
                if self._loop.error is not None:
                    self.state = "error"
                    self.fail(f"estimator loop crashed: {self._loop.error!r}")
                    return
                if self.state != "error":
                    with self._lock:  # the loop thread updates the estimator meanwhile
                        mode = self.est.status()["mode"]
                    self.state = "running" if mode != "init" else "degraded"
        finally:
            await asyncio.to_thread(self._loop.stop, 2.0)

    def accept_params(self, updated: dict[str, Any]) -> None:
        new = updated.get("estimator")
        fixed = restart_changes("estimator", self.params["estimator"], new) if new is not None else []
        if fixed:
            raise ValueError(f"{fixed} are taken when the estimator starts: restart it to change them")

    def on_params_changed(self, section: str) -> None:
        with self._lock:
            self._build(self.params["estimator"])
        self.log.info("estimator rebuilt with new parameters")

    def progress(self) -> bool:
        return self._loop.progressing()

    def status_extra(self) -> dict[str, float]:
        with self._lock:
            st = self.est.status()
            counters = self.est.counters
        out = {k: float(v) for k, v in st.items() if k != "mode"}
        if out["pose_age_s"] == float("inf"):  # JSON has no infinity: no pose yet reads -1
            out["pose_age_s"] = -1.0
        out["pose_outage"] = float(st["mode"] == "pose_outage")
        out.update({f"est.{k}": float(v) for k, v in counters.items()})
        loop = self._loop.recorder.stats()
        out["loop_tick_us_p99"] = loop.tick_us_p99
        out["loop_period_jitter_us_p99"] = loop.period_jitter_us_p99
        out["loop_overruns"] = float(loop.overruns)
        return out
