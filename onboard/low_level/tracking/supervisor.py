"""The low level's safety supervisor: every limit and every fallback in one place.

Checks, in the order a tick meets them:

- the state estimate: non-finite, flagged invalid, or older than
  ``SafetyLimits.estimate_stale_s`` -> this tick's command is the safe one (zero
  torque, disarmed flag); a fault lasting ``ControlParams.estimate_fault_disarm_s``
  disarms (latched). Its CoM not valid while its attitude is (``attitude_valid``):
  :attr:`Supervisor.attitude_only` -- the low level holds the body upright and hops in
  place without position feedback (trip ``estimate_attitude_only``), for at most
  ``ControlParams.attitude_only_max_s``, then disarms (latched, ``estimate_lost``);
  arming needs the whole estimate valid;
- tilt beyond ``SafetyLimits.tilt_max`` -> a fall: disarm (latched); not while
  :attr:`Supervisor.tilt_exempt` (set by the low level over a planned flip's turn only);
- the reference: older than ``reference_stale_s``, empty or non-finite -> refused,
  the low level hops in place (this is the fallback when the planner dies);
- the command: wheel torques clamped to ``wheel_torque_max``, a wheel at or over
  ``wheel_speed_max`` gets no torque that would spin it faster, the foot torque
  clamped to ``foot_torque_max``; a non-finite command becomes zero torque.

Arming: :meth:`Supervisor.request_arm` arms at the next valid, upright estimate
(tilt under ``ControlParams.arm_tilt_max``); :meth:`Supervisor.disarm` disarms.
A latched disarm needs a new arm request.

Every trip is counted (:attr:`Supervisor.counts`) and queued as a
:class:`~onboard.contracts.messages.SafetyEvent` (:meth:`Supervisor.drain_events`) for the
caller to log and publish; continuous conditions (a clamp held for many ticks)
are one trip when they start, not one per tick. Pure: the caller passes the time.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from onboard.geometry import quaternion as qt
from onboard.contracts.messages import BezierSegment, ComReference, SafetyEvent, StateEstimate
from onboard.contracts.params import ControlParams, SafetyLimits

NS = 1_000_000_000

Vec3 = tuple[float, float, float]
_ESTIMATE_FAULTS = ("estimate_nonfinite", "estimate_invalid", "estimate_stale", "estimate_attitude_only")


_isfinite = math.isfinite


# Both checks run every tick: all(map(...)) tests in C, a generator resumes per value.
def estimate_is_finite(s: StateEstimate) -> bool:
    return all(map(_isfinite, (*s.position, *s.velocity, *s.quat, *s.omega, *s.wheel_vel, s.foot_pos, s.foot_vel)))


def reference_is_usable(ref: ComReference) -> bool:
    if not ref.segments:
        return False
    for seg in ref.segments:
        if not (_isfinite(seg.t0) and _isfinite(seg.duration) and seg.duration > 0.0):
            return False
        pts = seg.control_points
        if not pts:
            return False
        for p in pts:
            if len(p) < 2 or not all(map(_isfinite, p)):
                return False
    return True


class Supervisor:
    """See the module docstring."""

    def __init__(self, limits: SafetyLimits, params: ControlParams) -> None:
        self.armed = False
        self.arm_requested = params.auto_arm
        self.disarm_reason = "not armed"
        self.counts: dict[str, int] = {}
        self._events: list[SafetyEvent] = []
        self._active: set[str] = set()  # continuous conditions currently tripped
        # the reference checked last and its verdict: the same message comes back every
        # tick until a new one arrives, and a 50-segment check costs ~35 us
        self._checked_ref: ComReference | None = None
        self._checked_segments: list[BezierSegment] | None = None
        self._checked_ref_usable = False
        self._fault_since_ns: int | None = None
        self.attitude_only = False  # this tick: only the estimate's attitude and rate may be used
        self.tilt_exempt = False  # the low level turns the body over on purpose (a flip's planned turn)
        self._attitude_only_since_ns: int | None = None
        self.retune(limits, params)

    def retune(self, limits: SafetyLimits, params: ControlParams) -> None:
        """New limits and arming parameters; arming state, counts and trips carry on."""
        self.limits = limits
        self.params = params
        self._estimate_stale_ns = int(limits.estimate_stale_s * NS)
        self._reference_stale_ns = int(limits.reference_stale_s * NS)
        self._fault_disarm_ns = int(params.estimate_fault_disarm_s * NS)
        self._attitude_only_max_ns = int(params.attitude_only_max_s * NS)

    # --- events -------------------------------------------------------------------

    def _trip(self, now_ns: int, trip: str, value: float, limit: float) -> None:
        n = self.counts.get(trip, 0) + 1
        self.counts[trip] = n
        self._events.append(
            SafetyEvent(stamp_ns=now_ns, trip=trip, value=float(value) if math.isfinite(value) else -1.0,
                        limit=float(limit), armed=self.armed, count=n)
        )

    def _edge(self, now_ns: int, trip: str, active: bool, value: float, limit: float) -> None:
        """A continuous condition: one trip when it becomes active."""
        if active:
            if trip not in self._active:
                self._active.add(trip)
                self._trip(now_ns, trip, value, limit)
        else:
            self._active.discard(trip)

    def drain_events(self) -> list[SafetyEvent]:
        """The events since the last call (oldest first)."""
        if not self._events:
            return []
        out, self._events = self._events, []
        return out

    # --- arming -------------------------------------------------------------------

    def request_arm(self) -> None:
        self.arm_requested = True

    def disarm(self, now_ns: int, reason: str, value: float = 0.0, limit: float = 0.0) -> None:
        """Disarm (latched until the next arm request) and record why."""
        was = self.armed
        self.armed = False
        self.arm_requested = False
        self.disarm_reason = reason
        if was:
            self._trip(now_ns, reason, value, limit)

    # --- checks -------------------------------------------------------------------

    def check_estimate(self, now_ns: int, s: StateEstimate) -> bool:
        """True when the estimate may drive the motors this tick (and we are armed)."""
        fault = ""
        value, limit = 0.0, 0.0
        attitude_only = False
        if not estimate_is_finite(s):
            fault = "estimate_nonfinite"
        elif not (s.valid or s.attitude_valid and self.armed):
            fault = "estimate_invalid"
        elif now_ns - s.stamp_ns > self._estimate_stale_ns:
            fault, value, limit = "estimate_stale", (now_ns - s.stamp_ns) / NS, self.limits.estimate_stale_s
        else:
            attitude_only = not s.valid
        self.attitude_only = attitude_only
        if attitude_only:
            self._edge(now_ns, "estimate_attitude_only", True, 0.0, 0.0)
            if self._attitude_only_since_ns is None:
                self._attitude_only_since_ns = now_ns
            elif now_ns - self._attitude_only_since_ns >= self._attitude_only_max_ns:
                self.disarm(now_ns, "estimate_lost", (now_ns - self._attitude_only_since_ns) / NS,
                            self.params.attitude_only_max_s)
                self.attitude_only = False
                return False
        elif not fault:  # only a whole valid estimate ends it: a flickering one must not
            self._attitude_only_since_ns = None
        if fault:
            if self.armed:
                self._edge(now_ns, fault, True, value, limit)
                if self._fault_since_ns is None:
                    self._fault_since_ns = now_ns
                elif now_ns - self._fault_since_ns >= self._fault_disarm_ns:
                    self.disarm(now_ns, "estimate_lost", (now_ns - self._fault_since_ns) / NS,
                                self.params.estimate_fault_disarm_s)
            return False
        if self._active:
            for name in _ESTIMATE_FAULTS:
                if not (attitude_only and name == "estimate_attitude_only"):
                    self._active.discard(name)
        self._fault_since_ns = None

        tilt = qt.tilt(s.quat)
        if self.armed:
            if tilt > self.limits.tilt_max and not self.tilt_exempt:
                self.disarm(now_ns, "tilt", tilt, self.limits.tilt_max)
                return False
            return True
        if self.arm_requested and tilt <= self.params.arm_tilt_max:
            self.armed = True
            self.disarm_reason = ""
            self._trip(now_ns, "arm", tilt, self.params.arm_tilt_max)
            return True
        return False

    def check_reference(self, now_ns: int, ref: ComReference | None) -> ComReference | None:
        """The reference if usable; None (hop in place) if absent, stale or malformed."""
        if ref is None:
            return None
        if ref is not self._checked_ref:
            # a planner that keeps its refined path republishes it in a new message around the same
            # segments (a copy with a new stamp): those were checked already
            if ref.segments is not self._checked_segments:
                self._checked_ref_usable = reference_is_usable(ref)
            self._checked_ref, self._checked_segments = ref, ref.segments
        if not self._checked_ref_usable:
            self._edge(now_ns, "reference_invalid", True, 0.0, 0.0)
            return None
        age = now_ns - ref.stamp_ns
        stale = age > self._reference_stale_ns
        if stale or self._active:  # nothing to record or clear on a healthy tick
            self._active.discard("reference_invalid")
            self._edge(now_ns, "reference_stale", stale, age / NS, self.limits.reference_stale_s)
        return None if stale else ref

    def limit_command(
        self, now_ns: int, wheel: Sequence[float], foot: float, wheel_vel: Sequence[float]
    ) -> tuple[Vec3, float]:
        """Clamp a command to the limits (see the module docstring)."""
        tmax = self.limits.wheel_torque_max
        smax = self.limits.wheel_speed_max
        out = [0.0, 0.0, 0.0]
        clamped = False
        overspeed = False
        worst_t, worst_s = 0.0, 0.0
        if not all(map(_isfinite, (*wheel, foot))):
            # a bug upstream must never reach a motor
            self._trip(now_ns, "command_nonfinite", math.nan, 0.0)
            return (0.0, 0.0, 0.0), 0.0
        for i in range(3):
            t = wheel[i]
            if t > tmax or t < -tmax:
                clamped = True
                worst_t = max(worst_t, abs(t))
                t = tmax if t > 0 else -tmax
            w = wheel_vel[i]
            if (w >= smax and t > 0.0) or (w <= -smax and t < 0.0):
                overspeed = True
                worst_s = max(worst_s, abs(w))
                t = 0.0
            out[i] = t
        fmax = self.limits.foot_torque_max
        foot_clamped = foot > fmax or foot < -fmax
        if clamped or overspeed or foot_clamped or self._active:  # nothing to record or clear on a clean tick
            self._edge(now_ns, "wheel_torque", clamped, worst_t, tmax)
            self._edge(now_ns, "wheel_speed", overspeed, worst_s, smax)
            self._edge(now_ns, "foot_torque", foot_clamped, abs(foot), fmax)
        if foot_clamped:
            foot = fmax if foot > 0 else -fmax
        return (out[0], out[1], out[2]), foot
