"""The identification routine's excitation (``[control] identify = true``): known inputs while hopping in place.

``archer identify`` fits the wheels' torque constant and drag from the commanded torques and the
measured speeds; hopping alone barely moves the yaw wheel, and its attitude torques in flight and the
stance spin-down (a torque proportional to the speed) cannot tell a torque constant from a drag.
So, while the routine runs:

- each wheel's command gets a dither of two sines (:func:`wheel_dither`), frequencies apart per wheel
  and above the attitude loop's bandwidth: it swings the wheel's speed by ~10 rad/s through zero and
  tilts the body by ~2 mrad at 0.2 N m;
- the heading swings by ``amplitude`` about the heading it armed with (:func:`heading_swing`):
  the yaw wheel takes the body's yaw momentum, tens of rad/s.

Pure functions of the time since arming (deterministic, no random state). Units: s, N m, rad.
"""

from __future__ import annotations

import math

# (Hz, Hz) per wheel: incommensurate, between the attitude loop (~5 Hz) and the drive's bandwidth
DITHER_HZ = ((5.3, 11.7), (6.1, 13.3), (7.9, 15.1))
TWO_PI = 2.0 * math.pi


def wheel_dither(t: float, amplitude: float) -> tuple[float, float, float]:
    """Torque added to each wheel's command at ``t`` [s] since arming: two sines of half the amplitude."""
    h = 0.5 * amplitude
    (a0, b0), (a1, b1), (a2, b2) = DITHER_HZ
    return (h * (math.sin(TWO_PI * a0 * t) + math.sin(TWO_PI * b0 * t)),
            h * (math.sin(TWO_PI * a1 * t) + math.sin(TWO_PI * b1 * t)),
            h * (math.sin(TWO_PI * a2 * t) + math.sin(TWO_PI * b2 * t)))


def heading_swing(t: float, amplitude: float, period_s: float) -> float:
    """The heading's offset [rad] from the armed heading at ``t`` [s] since arming."""
    return amplitude * math.sin(TWO_PI * t / period_s) if period_s > 0.0 else 0.0
