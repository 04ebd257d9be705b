"""The balance point: integral action on the zero dynamics (thesis 5.5's policy, made type 1).

The Zero Dynamics Policy chooses the impact attitude from the impact state's error,
``eta = S_eta (z - z_ref)``: a proportional law. A robot whose CoM lies a distance ``d`` off
its spine must land leaning by ``-d / L`` (``L``: CoM to foot pivot along the spine) for the foot
to come down under its CoM; the proportional law makes that lean only from a standing position
error ``d / (L k_p)``, about 14 ``d`` with the ZDP's ``k_p`` of ~0.21 rad/m and ``L`` ~0.34 m (and
the estimate, which places the CoM where the MJCF says, is ``d`` off besides).

:class:`BalancePoint` integrates each touchdown's position error into a lean ``b`` held in the
body's heading frame (the offset turns with the body), added to the policy's attitude:
``b += k_i k_p e`` with ``k_p`` the ZDP's own position gain, so ``k_i`` is the share of the
proportional action integrated per hop. At the fixed point the foot lands under the CoM and
``b = -d / L``, so ``-L b`` is the CoM's offset from the spine: the position the policy sees is
corrected by it, and the robot stands with its true CoM, not the estimate's, on the reference.
The lean is bounded by ``tilt_max`` (anti-windup) and reset when the controller arms.

Frames: world z up; ``b`` and the offset in the heading frame (x forward, y left, z up); world
values rotated by the heading ``yaw``. Units: rad, m. Scalar floats only (runs in the 1 kHz loop).
"""

from __future__ import annotations

import math


class BalancePoint:
    """The learnt lean at impact and the CoM offset it implies (module docstring)."""

    def __init__(self, k_pos: float, lever: float, ki: float, tilt_max: float) -> None:
        """``k_pos`` [rad/m]: the policy's impact tilt per position error (negative: lean back
        toward the reference); ``lever`` [m]: CoM to foot pivot along the spine at impact."""
        self.k_pos = k_pos
        self.lever = lever
        self.ki = ki
        self.tilt_max = tilt_max
        self.bx = 0.0  # learnt lean, heading frame [rad]
        self.by = 0.0
        self.updates = 0

    def configure(self, ki: float, tilt_max: float) -> None:
        self.ki = ki
        self.tilt_max = tilt_max
        self._clip()

    def reset(self) -> None:
        self.bx = self.by = 0.0

    def _clip(self) -> None:
        n = math.hypot(self.bx, self.by)
        if n > self.tilt_max:
            s = self.tilt_max / n if n > 0.0 else 0.0
            self.bx *= s
            self.by *= s

    def lean(self, yaw: float) -> tuple[float, float]:
        """The learnt lean in world axes [rad] (added to the policy's ``eta``)."""
        c, s = math.cos(yaw), math.sin(yaw)
        return c * self.bx - s * self.by, s * self.bx + c * self.by

    def offset(self, yaw: float) -> tuple[float, float]:
        """The CoM's horizontal offset from where the estimate puts it, world axes [m]."""
        ax, ay = self.lean(yaw)
        return -self.lever * ax, -self.lever * ay

    def update(self, ex: float, ey: float, yaw: float) -> None:
        """One touchdown's position error (world, m, already corrected by :meth:`offset`)."""
        if self.ki <= 0.0:
            return
        c, s = math.cos(yaw), math.sin(yaw)
        hx, hy = c * ex + s * ey, -s * ex + c * ey  # into the heading frame
        g = self.ki * self.k_pos
        self.bx += g * hx
        self.by += g * hy
        self._clip()
        self.updates += 1
