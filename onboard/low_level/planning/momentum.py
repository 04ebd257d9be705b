"""The wheels' momentum governor: the speed the ZDP steers to, capped while the wheels run fast.

The wheels shed momentum only in stance (the spin-down), at most their torque limit times the
stance time; every flight spins them up again to turn the body back from the lean the stance gave
it. How much a hop leaves in the wheels grows steeply with the robot's speed. On the nominal twin
the setpoint's cruise keeps them under ~200 rad/s, but a robot that is not the model (the
``datasheet`` profile's setpoint seed 34: torso pitch inertia +40 %, a heavier foot, weaker
motors) gains ~60 rad/s every hop at 0.35-0.45 m/s, reaches the motors' speed limit in 4 s and
falls; the same robot steered at 0.18 m/s stays under 140 rad/s (issue 26).

So the sustained speed is a property of the robot as built, and the wheels measure it. At every
touchdown (the hop's peak, before the spin-down) each wheel's speed is projected ``lookahead_hops``
on if it grew over the last hop (the growth is steep: 115, 210, 380, 547 rad/s on four hops of the
datasheet square's seed 37, too fast for a cap on the speed alone), and the fastest sets the cap:
none below ``wheel_speed_lo``, from there falling linearly from the robot's nominal sustained speed
to ``speed_min`` at ``wheel_speed_hi``. The cap falls at once and rises by ``cap_rise`` a hop, so a
robot that slowed does not run back up to the speed that spun its wheels (setpoint seed 47 did: it
slowed from 0.32 to 0.15 m/s, was let go, and fell two hops later). The controller clips the
reference's velocity to the cap and the position error the policy sees to ``lead_s`` of travel at
it, so the robot lags the reference (the tube measures the lag) instead of running its wheels into
their limit. Scalar floats only (runs in the 1 kHz loop).
"""

from __future__ import annotations

import math


class MomentumGovernor:
    """See the module docstring."""

    def __init__(self, speed_free: float, wheel_speed_lo: float, wheel_speed_hi: float, speed_min: float, lead_s: float,
                 lookahead_hops: float, cap_rise: float) -> None:
        """``speed_free`` [m/s]: the cap where it starts (the robot's nominal sustained speed);
        ``wheel_speed_lo`` < ``wheel_speed_hi`` [rad/s]: where the cap starts and where it reaches
        ``speed_min`` [m/s]; ``lead_s`` [s]: the position error the policy sees is clipped to this
        long at the capped speed. ``wheel_speed_lo`` 0: off; ``wheel_speed_hi`` at or under it: the cap
        drops to ``speed_min`` at once."""
        self.speed_free = speed_free
        self.configure(wheel_speed_lo, wheel_speed_hi, speed_min, lead_s, lookahead_hops, cap_rise)
        self.cap = math.inf  # [m/s] the speed the ZDP may steer to now
        self.wheel_speed = 0.0  # [rad/s] the fastest wheel at the last touchdown, projected (module docstring)
        self._last = (0.0, 0.0, 0.0)  # each wheel's speed at the last touchdown [rad/s]
        self._first = True  # no touchdown since the reset: nothing to measure a growth from
        self._exempt = False  # a flip's momentum still in the wheels: not the hopping's to govern
        self.governed_hops = 0  # touchdowns that set a cap

    def configure(self, wheel_speed_lo: float, wheel_speed_hi: float, speed_min: float, lead_s: float, lookahead_hops: float,
                  cap_rise: float) -> None:
        self.wheel_speed_lo = wheel_speed_lo
        self.wheel_speed_hi = wheel_speed_hi
        self.speed_min = min(speed_min, self.speed_free)
        self.lead_s = lead_s
        self.lookahead_hops = lookahead_hops
        self.cap_rise = cap_rise

    def reset(self) -> None:
        self.cap = math.inf
        self.wheel_speed = 0.0
        self._last = (0.0, 0.0, 0.0)
        self._first = True
        self._exempt = False

    def on_touchdown(self, w0: float, w1: float, w2: float, ordinary: bool = True) -> None:
        """The wheels' speeds [rad/s] at a touchdown: the cap for the next flights. Not ``ordinary``
        (a flip's): the wheels hold the turn's momentum, which the stances shed; no cap until a
        touchdown finds them under the low bound again."""
        if not ordinary or self._exempt:
            self._exempt = not ordinary or max(abs(w0), abs(w1), abs(w2)) > self.wheel_speed_lo
            if self._exempt:
                self.cap = math.inf
                self._last = (w0, w1, w2)
                self._first = True
                return
        l0, l1, l2 = self._last
        self._last = (w0, w1, w2)
        k = 0.0 if self._first else self.lookahead_hops
        self._first = False
        w = max(_projected(w0, l0, k), _projected(w1, l1, k), _projected(w2, l2, k))
        self.wheel_speed = w
        lo = self.wheel_speed_lo
        if lo <= 0.0:
            self.cap = math.inf
            return
        if w > lo:
            span = self.wheel_speed_hi - lo
            s = min(1.0, (w - lo) / span) if span > 0.0 else 1.0
            wanted = self.speed_free + s * (self.speed_min - self.speed_free)
        else:
            wanted = math.inf
        # down at once, up by cap_rise a hop: the speed it slowed at is near what this robot sustains
        raised = self.cap + self.cap_rise
        self.cap = wanted if wanted <= raised else (raised if raised < self.speed_free else math.inf)
        if self.cap != math.inf:
            self.governed_hops += 1

    def counters(self) -> dict[str, float]:
        """For the service's status: the cap [m/s] (0: none), the projected wheel speed it came from
        [rad/s] and the touchdowns that set one."""
        return {"speed_cap_m_s": self.cap if self.cap != math.inf else 0.0, "wheel_speed_rad_s": self.wheel_speed,
                "governed_hops": float(self.governed_hops)}

    def target(self, ex: float, ey: float, rvx: float, rvy: float) -> tuple[float, float, float, float]:
        """The impact error to the reference ``(ex, ey)`` [m] and the reference velocity [m/s],
        clipped to what the cap allows (unchanged without one)."""
        cap = self.cap
        if cap == math.inf:
            return ex, ey, rvx, rvy
        lead = cap * self.lead_s
        n = math.hypot(ex, ey)
        if n > lead:
            ex, ey = ex * lead / n, ey * lead / n
        v = math.hypot(rvx, rvy)
        if v > cap:
            rvx, rvy = rvx * cap / v, rvy * cap / v
        return ex, ey, rvx, rvy


def _projected(w: float, last: float, hops: float) -> float:
    """A wheel's speed magnitude ``hops`` touchdowns on, if it keeps growing as it did over the last hop."""
    growth = abs(w) - abs(last)
    return abs(w) + hops * growth if growth > 0.0 else abs(w)
