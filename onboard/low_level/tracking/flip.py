"""The flip (thesis Fig. 5.13): one full turn of the body about a horizontal axis within one
flight, landing upright and hopping on.

In flight the angular momentum about the CoM is conserved, so the wheels turn the body only by
spinning the other way: the body accelerates at ``alpha = tau / I`` while the wheels take up
the momentum, and the body is back at rest, upright, once the wheels are. The turn is planned
bang-bang in angle over a turn time ``T``: ``+alpha`` for ``T / 2``, ``-alpha`` for ``T / 2``,
``alpha = 4 * 2 pi / T^2``; the body rate peaks at ``alpha T / 2`` and the wheels at that
momentum over their spin inertia.

Sequence (:class:`FlipManoeuvre`, driven by :class:`onboard.low_level.controller.LowLevelController`):

1. ``pumping``: the hop regulator aims at ``ControlParams.flip_hop_height``; at each lift-off
   the predicted flight decides: a turn that fits (its torque within ``flip_torque_share`` of
   the wheels' limit, its wheel speed within the speed limit) starts; after ``flip_pump_hops``
   lift-offs without one the request is dropped (counted);
2. ``turning``: the quaternion PD tracks ``q_d(t) = q_0 exp(theta(t) a)`` and
   ``omega_d = theta'(t) a`` with the feed-forward ``I a theta''(t)``, ``a`` the body axis at
   ``flip_axis_deg`` in the body's xy plane, ``q_0`` upright at the held heading. The turn ends
   ``flip_settle_s`` before the predicted touchdown; the supervisor's tilt bound is lifted over
   it and over nothing else;
3. ``landing``: the usual flight attitude until the touchdown, which completes the flip.

A request the robot cannot carry out at all (even the highest allowed hop leaves no time for
the turn, as on the 1.5 N m robot) is refused at once, with its reason. Pure: the caller passes
the time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from onboard.low_level.tracking import attitude_control as ac
from onboard.geometry import quaternion as qt
from onboard.contracts.params import ControlParams

NS = 1_000_000_000
TURN = 2.0 * math.pi
BANG_BANG = 4.0 * TURN  # alpha T^2 of a bang-bang turn by TURN

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class FlipLimits:
    """What bounds a turn: the wheels and the body (from the robot model and the limits)."""

    inertia: tuple[Vec3, Vec3, Vec3]  # body inertia about the CoM, body frame [kg m^2]
    wheel_axes: tuple[Vec3, Vec3, Vec3]  # spin axes, body frame
    wheel_inertia: float  # spin inertia of one wheel [kg m^2]
    wheel_torque_max: float  # per wheel [N m]
    wheel_speed_max: float  # per wheel [rad/s]
    gravity: float  # [m/s^2]


@dataclass(frozen=True)
class TurnPlan:
    """One planned turn: bang-bang in angle about the body axis ``axis`` from ``q0``."""

    t0_ns: int
    duration_s: float
    axis: Vec3  # body frame, unit
    q0: qt.Quat
    alpha: float  # [rad/s^2]
    torque_per_alpha: Vec3  # body torque per unit angular acceleration, I a [N m s^2]

    def at(self, now_ns: int) -> tuple[qt.Quat, Vec3, Vec3]:
        """``(q_d, omega_d, body torque feed-forward)`` at ``now_ns`` (held at the end)."""
        t = min(max((now_ns - self.t0_ns) / NS, 0.0), self.duration_s)
        half = 0.5 * self.duration_s
        a = self.alpha
        if t < half:
            theta, rate, acc = 0.5 * a * t * t, a * t, a
        elif t < self.duration_s:
            r = self.duration_s - t
            theta, rate, acc = TURN - 0.5 * a * r * r, a * r, -a
        else:
            theta, rate, acc = TURN, 0.0, 0.0
        ax, ay, az = self.axis
        q = qt.mul(self.q0, qt.exp((theta * ax, theta * ay, theta * az)))
        tx, ty, tz = self.torque_per_alpha
        return q, (rate * ax, rate * ay, rate * az), (acc * tx, acc * ty, acc * tz)


class FlipManoeuvre:
    """The flip's sequence; see the module docstring."""

    def __init__(self, limits: FlipLimits, params: ControlParams) -> None:
        self.configure(limits, params)
        self.state = "idle"  # idle | pumping | turning | landing
        self.plan: TurnPlan | None = None
        self._pumped = 0
        self.flips = 0  # completed (touched down after a turn)
        self.dropped = 0  # no lift-off left time for the turn within the pump hops
        self.refused = 0  # infeasible on this robot even at the highest hop
        self.last_refusal = ""

    def configure(self, limits: FlipLimits, params: ControlParams) -> None:
        """New limits and ``flip_*`` settings; a flip under way keeps its plan."""
        self.limits = limits
        phi = math.radians(params.flip_axis_deg)
        self.axis: Vec3 = (math.cos(phi), math.sin(phi), 0.0)
        (i0, i1, i2) = self.limits.inertia
        ax, ay, az = self.axis
        self._i_axis: Vec3 = (i0[0] * ax + i0[1] * ay + i0[2] * az, i1[0] * ax + i1[1] * ay + i1[2] * az,
                              i2[0] * ax + i2[1] * ay + i2[2] * az)
        # each wheel's torque per unit angular acceleration of the body about the axis; it is also
        # each wheel's momentum per unit body rate (the wheels take what the body gains)
        per_alpha = ac.WheelAllocation.from_axes(self.limits.wheel_axes).wheel_torques(self._i_axis)
        self._wheel_per_alpha = max(abs(w) for w in per_alpha)
        self.settle_s = params.flip_settle_s
        self.torque_share = params.flip_torque_share
        self.pump_hops = params.flip_pump_hops
        self.hop_height = params.flip_hop_height

    # --- feasibility -----------------------------------------------------------------

    def turn_time_min(self) -> float:
        """The shortest turn [s] within the torque share and the wheel speed limit."""
        lim = self.limits
        alpha_max = self.torque_share * lim.wheel_torque_max / self._wheel_per_alpha
        t_torque = math.sqrt(BANG_BANG / alpha_max)
        # the body rate peaks at alpha T / 2 = 2 TURN / T, the busiest wheel at that times its share / I_w
        t_speed = 2.0 * TURN * self._wheel_per_alpha / (lim.wheel_inertia * lim.wheel_speed_max)
        return max(t_torque, t_speed)

    def flight_time_max(self) -> float:
        """The flight [s] of the flip's hop (ballistic, from touchdown height back to it)."""
        return 2.0 * math.sqrt(2.0 * self.hop_height / self.limits.gravity)

    def infeasible_reason(self) -> str:
        """Why no hop allowed gives the turn time (empty: it may)."""
        need, have = self.turn_time_min() + self.settle_s, self.flight_time_max()
        if need > have:
            return (f"the turn needs {need:.2f} s of flight at {self.torque_share:.0%} of the wheels' torque, "
                    f"the {self.hop_height:.2f} m hop gives {have:.2f} s")
        return ""

    # --- the sequence ----------------------------------------------------------------

    def request(self) -> bool:
        """Ask for one flip; False (counted, reason in :attr:`last_refusal`) if it cannot be done."""
        if self.state != "idle":
            return True  # one at a time: the flip under way answers it
        reason = self.infeasible_reason()
        if reason:
            self.refuse(reason)
            return False
        self.state = "pumping"
        self._pumped = 0
        return True

    def refuse(self, reason: str) -> None:
        """A request not taken: counted, and why kept for the status and the log."""
        self.refused += 1
        self.last_refusal = reason

    @property
    def raising_hop(self) -> bool:
        """The hop regulator should aim at :attr:`hop_height`."""
        return self.state in ("pumping", "turning")

    def on_liftoff(self, now_ns: int, flight_s: float, yaw: float) -> None:
        """At a lift-off with ``flight_s`` [s] predicted to touchdown: start the turn if it fits."""
        if self.state != "pumping":
            return
        duration = flight_s - self.settle_s
        if math.isfinite(duration) and duration >= self.turn_time_min():
            alpha = BANG_BANG / (duration * duration)
            self.plan = TurnPlan(now_ns, duration, self.axis, qt.from_axis_yaw((0.0, 0.0, 1.0), yaw), alpha, self._i_axis)
            self.state = "turning"
            return
        self._pumped += 1
        if self._pumped >= self.pump_hops:
            self.state = "idle"
            self.dropped += 1

    def target(self, now_ns: int) -> tuple[qt.Quat, Vec3, Vec3] | None:
        """The turn's setpoint while it lasts; None otherwise (the turn's end starts the landing)."""
        plan = self.plan
        if self.state != "turning" or plan is None:
            return None
        if now_ns - plan.t0_ns > plan.duration_s * NS:
            self.state = "landing"
            return None
        return plan.at(now_ns)

    def tilt_exempt(self, now_ns: int) -> bool:
        """The supervisor may let the body turn over: only within the planned turn."""
        plan = self.plan
        return self.state == "turning" and plan is not None and 0 <= now_ns - plan.t0_ns <= plan.duration_s * NS

    def on_touchdown(self) -> None:
        """A touchdown ends a flip in flight: done after its turn; cut short mid-turn (the supervisor
        then judges the tilt); a flip still pumping carries on."""
        if self.state in ("landing", "turning"):
            if self.state == "landing":
                self.flips += 1
            self.state = "idle"
            self.plan = None

    def cancel(self) -> None:
        """Disarmed or re-armed: nothing carries over."""
        self.state = "idle"
        self.plan = None

    def counters(self) -> dict[str, int]:
        return {"flips": self.flips, "flips_dropped": self.dropped, "flips_refused": self.refused}
