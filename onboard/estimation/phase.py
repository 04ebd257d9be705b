"""Hop phase and event detection: touchdown, bottom, lift-off, apex.

The estimator's ``contact`` flag (already with hysteresis) decides stance and flight;
this detector adds minimum dwell times so that a bouncing contact switch cannot
produce a burst of hops, and derives the two events inside each phase:

- ``bottom``: in stance, the spring stops compressing (``foot_vel`` [m/s] changes
  from positive, compressing, to non-positive): the lowest point of the hop;
- ``apex``: in flight, the CoM's vertical velocity changes from up to down.

It also keeps what the low level needs to predict the next impact: the CoM height
at the last touchdown (an estimate of the ground under the robot, so steps and
ramps are tracked hop by hop) and the times of the last events. Times are the
caller's clock [ns]; heights are world z [m].
"""

from __future__ import annotations

import math

from onboard.contracts.messages import PhaseEvent, PhaseEventKind, StateEstimate

NS = 1_000_000_000


class PhaseDetector:
    """Feed every state estimate to :meth:`update`; it returns the events it saw."""

    def __init__(self, min_flight_s: float, min_stance_s: float, touchdown_height: float) -> None:
        """``touchdown_height``: CoM height [m] at touchdown assumed until one is seen."""
        self.set_dwell(min_flight_s, min_stance_s)
        self.phase = "flight"
        self.hop = 0
        self.touchdown_height = touchdown_height
        self.last_touchdown_ns = 0
        self.last_liftoff_ns = 0
        self.last_apex_height = math.nan  # CoM z [m] at the last apex
        self.last_touchdown_velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self.last_liftoff_velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._phase_start_ns: int | None = None
        self._seen_bottom = False
        self._seen_apex = False
        self._prev_foot_vel = 0.0
        self._prev_vz = 0.0

    def set_dwell(self, min_flight_s: float, min_stance_s: float) -> None:
        """The shortest flight and stance [s] a contact change must follow."""
        if min_flight_s < 0 or min_stance_s < 0:
            raise ValueError("dwell times must be non-negative")
        self._min_flight_ns = int(min_flight_s * NS)
        self._min_stance_ns = int(min_stance_s * NS)

    def reset(self, phase: str = "flight") -> None:
        self.phase = phase
        self._phase_start_ns = None

    def _event(self, kind: PhaseEventKind, now_ns: int, s: StateEstimate) -> PhaseEvent:
        return PhaseEvent(
            stamp_ns=now_ns, event=kind, hop=self.hop,
            position=list(s.position), velocity=list(s.velocity),
        )

    def update(self, now_ns: int, s: StateEstimate) -> PhaseEvent | None:
        """Advance on one estimate; return the event it marks, if any (at most one)."""
        if self._phase_start_ns is None:
            self._phase_start_ns = now_ns
            self.phase = "stance" if s.contact else "flight"
        in_phase_ns = now_ns - self._phase_start_ns
        event: PhaseEvent | None = None
        vz = s.velocity[2]
        if self.phase == "flight":
            if s.contact and in_phase_ns >= self._min_flight_ns:
                self.phase = "stance"
                self._phase_start_ns = now_ns
                self.hop += 1
                self.last_touchdown_ns = now_ns
                self.touchdown_height = s.position[2]
                self.last_touchdown_velocity = (s.velocity[0], s.velocity[1], s.velocity[2])
                self._seen_bottom = False
                event = self._event("touchdown", now_ns, s)
            elif not self._seen_apex and self._prev_vz > 0.0 >= vz:
                self._seen_apex = True
                self.last_apex_height = s.position[2]
                event = self._event("apex", now_ns, s)
        else:
            if not s.contact and in_phase_ns >= self._min_stance_ns:
                self.phase = "flight"
                self._phase_start_ns = now_ns
                self.last_liftoff_ns = now_ns
                self.last_liftoff_velocity = (s.velocity[0], s.velocity[1], s.velocity[2])
                self._seen_apex = False
                event = self._event("liftoff", now_ns, s)
            elif not self._seen_bottom and self._prev_foot_vel > 0.0 >= s.foot_vel:
                self._seen_bottom = True
                event = self._event("bottom", now_ns, s)
        self._prev_foot_vel = s.foot_vel
        self._prev_vz = vz
        return event
