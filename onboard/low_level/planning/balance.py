"""The balance point: a disturbance observer on the hop-to-hop map (thesis 5.5's policy, made type 1).

The Zero Dynamics Policy chooses the impact attitude from the impact state's error,
``eta = S_eta (z - z_ref)``: a proportional law. A robot whose CoM lies a distance ``d`` off
its spine must land leaning by ``-d / L`` (``L``: CoM to foot pivot along the spine) for the foot
to come down under its CoM; the proportional law makes that lean only from a standing position
error ``d / (L k_p)``, about 14 ``d`` with the ZDP's ``k_p`` of ~0.21 rad/m and ``L`` ~0.36 m (and
the estimate, which places the CoM where the MJCF says, is ``d`` off besides).

The policy's own design linearizes the impact-to-impact map, per horizontal axis
``v' = a v + b eta`` (velocity at the next touchdown from this touchdown's velocity and impact
lean; ``a`` ~1.16, ``b`` ~3.85 m/s/rad for ARCHER). A CoM offset acts as a constant extra lean
``beta = d / L``: ``v' = a v + b (eta + beta)``. :class:`BalancePoint` observes
``beta = (v' - a v) / b - eta`` at every pair of touchdowns, whatever the robot is doing (standing,
walking a square, crossing a forest), and filters it per hop: the running mean over the first
``1 / gain`` hops after a reset (the first hops converge fast), then a fixed gain that follows a
change, each innovation clipped to ``innovation_max`` (a push or a stumble moves the estimate by a
bounded step). ``eta`` is the lean the body lands with (measured, not commanded): the observer
never sees its own correction, so it converges at its own rate whatever flies the robot (the ZDP,
the geometric MPC). The controller adds ``-beta`` to the policy's lean and moves the position the
policy sees by the CoM offset ``L beta``, so the robot stands with its true CoM, not the
estimate's, on the reference.

The map is the reduced model's. The twin's own, fitted on its touchdowns (square, seeds 0-2), is
``a`` 1.21, ``b`` 2.97: the difference reads as a lean of about -0.23 ``eta`` + 0.013 ``v`` while
the robot accelerates, which the filter averages out over a run but not within one leg of a square
(+-0.008 rad, ~3 mm of offset).

Anything that acts as a constant lean is learnt too: a floor slope, an attitude bias (IMU mount).
The hop map cannot tell those from a CoM offset, so their share of ``L beta`` moves where the robot
stands (~6 mm per degree); the lean itself is right.

``beta`` is held in the body's heading frame (the offset turns with the body), bounded by
``tilt_max`` and reset when the controller arms. Frames: world z up; heading frame x forward,
y left. Units: rad, m, m/s. Scalar floats only (runs in the 1 kHz loop).
"""

from __future__ import annotations

import math


class BalancePoint:
    """The observed lean disturbance and the CoM offset it implies (module docstring)."""

    def __init__(self, a_vel: float, b_vel: float, lever: float, gain: float, innovation_max: float,
                 tilt_max: float, speed_max: float, known_x: float = 0.0, known_y: float = 0.0) -> None:
        """``a_vel``, ``b_vel``: the hop map's velocity row (per axis); ``lever`` [m]: CoM to foot
        pivot along the spine at impact; ``gain``: share of each hop's innovation taken (0: off);
        ``speed_max`` [m/s]: faster touchdowns are outside the linearization and not observed;
        ``known_x``, ``known_y`` [m]: the CoM's offset from the spine that the robot description
        (an identified robot) gives and the estimate already places the CoM by, body frame: the
        observer starts from the lean it implies, and :meth:`offset` counts only the rest."""
        self.a_vel = a_vel
        self.b_vel = b_vel
        self.lever = lever
        self.known_x = known_x
        self.known_y = known_y
        self.gain = gain
        self.innovation_max = innovation_max
        self.tilt_max = tilt_max
        self.speed_max = speed_max
        self.beta_x = 0.0  # observed lean disturbance, heading frame [rad]
        self.beta_y = 0.0
        self.updates = 0  # hops observed
        self.clipped = 0  # of those, hops whose innovation was clipped (a push, a stumble, convergence)
        self._last: tuple[float, float, float, float] | None = None  # last touchdown's (vx, vy, eta_x, eta_y)
        self._observed = 0  # hops observed since the reset
        self._touchdowns = 0  # touchdowns since the reset
        self.reset()

    def configure(self, gain: float, innovation_max: float, tilt_max: float, speed_max: float) -> None:
        self.gain = gain
        self.innovation_max = innovation_max
        self.tilt_max = tilt_max
        self.speed_max = speed_max
        self.beta_x, self.beta_y = _clip(self.beta_x, self.beta_y, tilt_max)

    def reset(self) -> None:
        self.beta_x, self.beta_y = _clip(self.known_x / self.lever, self.known_y / self.lever, self.tilt_max)
        self._last = None
        # a known offset counts as the hops the fixed gain averages over; none: the running mean from the first hop
        self._observed = round(1.0 / self.gain) if self.gain > 0.0 and (self.known_x or self.known_y) else 0
        self._touchdowns = 0

    def lean(self, yaw: float) -> tuple[float, float]:
        """The lean that cancels the disturbance, world axes [rad] (added to the policy's ``eta``)."""
        c, s = math.cos(yaw), math.sin(yaw)
        return -(c * self.beta_x - s * self.beta_y), -(s * self.beta_x + c * self.beta_y)

    def offset(self, yaw: float) -> tuple[float, float]:
        """The CoM's horizontal offset from where the estimate puts it, world axes [m]."""
        c, s = math.cos(yaw), math.sin(yaw)
        hx, hy = self.lever * self.beta_x - self.known_x, self.lever * self.beta_y - self.known_y
        return c * hx - s * hy, s * hx + c * hy

    def on_touchdown(self, vx: float, vy: float, eta_x: float, eta_y: float, yaw: float, usable: bool) -> None:
        """One touchdown: its CoM velocity (world, m/s), the lean it lands with (the body z axis's
        horizontal part, world) and the heading. ``usable``: the CoM is trusted and the hop was an
        ordinary one (no flip); an unusable touchdown breaks the chain of pairs."""
        last = self._last
        ordinary = usable and self._touchdowns > 0 and math.hypot(vx, vy) <= self.speed_max
        self._touchdowns += 1  # the first after arming ends the drop from standing, not a hop
        self._last = (vx, vy, eta_x, eta_y) if ordinary else None
        if last is None or self._last is None or self.gain <= 0.0:
            return
        ox = (vx - self.a_vel * last[0]) / self.b_vel - last[2]
        oy = (vy - self.a_vel * last[1]) / self.b_vel - last[3]
        c, s = math.cos(yaw), math.sin(yaw)
        ix, iy = c * ox + s * oy - self.beta_x, -s * ox + c * oy - self.beta_y  # innovation, heading frame
        n = math.hypot(ix, iy)
        if n > self.innovation_max:
            ix, iy = _clip(ix, iy, self.innovation_max)
            self.clipped += 1
        g = max(self.gain, 1.0 / (self._observed + 1))  # the running mean until it has 1/gain hops
        self.beta_x, self.beta_y = _clip(self.beta_x + g * ix, self.beta_y + g * iy, self.tilt_max)
        self.updates += 1
        self._observed += 1


def _clip(x: float, y: float, limit: float) -> tuple[float, float]:
    n = math.hypot(x, y)
    if n > limit:
        s = limit / n if n > 0.0 else 0.0
        return x * s, y * s
    return x, y
