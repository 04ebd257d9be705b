"""What the IMU did not see: the state estimator's honest uncertainty between IMU samples and past
the newest one (thesis 5.5, line 2755: the estimate the 1 kHz controller is handed; ch. 8.1,
lines 3233-3327: a layer says how far its output can be trusted).

Part of :class:`~onboard.estimation.estimator.StateEstimator`. Over a gap the estimate is
predicted with the body rate and the CoM acceleration held; what the IMU did not see is taken as
an unknown constant acceleration (``gap_accel_std_m_s2``, ``gap_angular_accel_std_rad_s2``; none
for the CoM while the foot switch shows the robot in flight throughout), and the held
acceleration and the velocity uncertainty are both capped by the robot's top speed
(``max_speed_m_s``), so that a long gap ends in a large but finite covariance, never a velocity
the robot cannot reach.
"""

from __future__ import annotations

import math

from onboard.contracts.params import EstimatorParams

GAP_CORRELATION = 0.5  # position-velocity correlation of the covariance an IMU gap adds


class GapModel:
    """The covariance a gap of ``g`` seconds without IMU samples adds, and the cap on the held acceleration."""

    def __init__(self, p: EstimatorParams) -> None:
        self.accel_var = p.gap_accel_std_m_s2 ** 2
        self.alpha_var = p.gap_angular_accel_std_rad_s2 ** 2
        self.max_speed2 = p.max_speed_m_s ** 2

    def speed_limit(self, vx: float, vy: float, vz: float, ax: float, ay: float, az: float, dt: float) -> float:
        """The largest ``k`` in [0, 1] for which ``v + k a dt`` stays within the top speed: over an
        IMU gap the held acceleration must not predict a speed the robot cannot reach (the gap's
        velocity uncertainty is capped there too)."""
        dx, dy, dz = ax * dt, ay * dt, az * dt
        vmax2 = self.max_speed2
        if (vx + dx) ** 2 + (vy + dy) ** 2 + (vz + dz) ** 2 <= vmax2:
            return 1.0
        # |v + k d|^2 = vmax^2: the positive root (0 when already at the top speed)
        a = dx * dx + dy * dy + dz * dz
        b = vx * dx + vy * dy + vz * dz
        c = vx * vx + vy * vy + vz * vz - vmax2
        if c >= 0.0:
            return 0.0
        return (-b + math.sqrt(b * b - a * c)) / a

    def com_cov(self, g: float, stance: bool) -> tuple[float, float, float]:
        """Per-axis CoM covariance ``(pp, pv, vv)`` that ``g`` [s] without the accelerometer adds:
        an unknown constant acceleration, the velocity part capped by the robot's top speed.

        The position and velocity errors are correlated by half, not fully: a constant
        acceleration would correlate them fully, but it is a bound, not the truth, and a fully
        correlated term would let the first pose after the gap "measure" the velocity too."""
        if not stance or g <= 0.0:
            return 0.0, 0.0, 0.0
        vv = min(self.accel_var * g * g, self.max_speed2)
        pp = min(0.25 * self.accel_var * g * g * g * g, self.max_speed2 * g * g)
        return pp, GAP_CORRELATION * math.sqrt(pp * vv), vv

    def attitude_var(self, g: float) -> float:
        """Attitude variance [rad^2] an unknown constant angular acceleration adds over ``g`` [s]."""
        return 0.25 * self.alpha_var * g ** 4

    def rate_var(self, g: float) -> float:
        """Body rate variance [rad^2/s^2] it adds over ``g`` [s]."""
        return self.alpha_var * g * g
