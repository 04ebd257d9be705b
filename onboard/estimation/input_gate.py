"""What the state estimator refuses, and the counts it keeps (thesis 5.5, line 2755: the filter
fuses only measurements it can trust; ch. 8.1, lines 3233-3327: bad input is counted, never fused).

Part of :class:`~onboard.estimation.estimator.StateEstimator`, and shared with its position
sources (:mod:`onboard.estimation.position_sources`): parameters the filters cannot work with are
refused at construction with a clear error (:func:`check_params`); at run time an input is
refused, and counted by reason, when its stamp lies more than ``input_future_tolerance_s``
after its arrival or ``input_max_age_s`` before it (a visual odometry displacement: ``vo_history_s``,
the odometry it is compared with; :meth:`InputGate.stamp_refused`), and
for the reasons each update names (non-finite, out of order, out of range, gated outlier).
Events that are not refusals (touchdowns, bounces, anchors) are counted beside them. The
Mahalanobis gates themselves live in the filters (:mod:`onboard.estimation.com_filter`,
:mod:`onboard.estimation.attitude_filter`), which count their own outliers.
"""

from __future__ import annotations

from onboard.contracts.params import EstimatorParams

NS = 1_000_000_000
QUAT_NORM_TOL = 0.1  # a pose quaternion further than this from unit norm is malformed
ATTITUDE_HISTORY_S = 0.25  # [s] oldest pose whose attitude can still be fused


def check_params(p: EstimatorParams) -> None:
    """Refuse parameters the filter cannot work with (a clear error, not a silent NaN)."""
    positive = ("rate_hz", "pose_pos_std_m", "pose_att_std_rad", "leg_vel_std_m_s", "gyro_noise_density",
                "tilt_std_rad", "init_pos_std_m", "init_vel_std_m_s", "init_att_std_rad", "init_bias_std_rad_s",
                "accel_psd_flight", "accel_psd_stance", "valid_pos_std_m", "valid_vel_std_m_s", "valid_att_std_rad",
                "valid_rate_std_rad_s", "imu_rate_hz", "max_speed_m_s", "input_max_age_s")
    non_negative = ("pose_delay_s", "accel_delay_s", "leg_settle_s", "impact_vel_std_m_s", "liftoff_vel_std_m_s",
                    "gyro_bias_walk", "static_hold_s", "pose_future_tolerance_s", "gap_accel_std_m_s2",
                    "gap_angular_accel_std_rad_s2", "input_future_tolerance_s")
    for name in positive:
        if not getattr(p, name) > 0.0:
            raise ValueError(f"estimator.{name} must be positive, got {getattr(p, name)}")
    for name in non_negative:
        if not getattr(p, name) >= 0.0:
            raise ValueError(f"estimator.{name} must be >= 0, got {getattr(p, name)}")
    if not 0.0 < p.gate_probability < 1.0:
        raise ValueError(f"estimator.gate_probability must be in (0, 1), got {p.gate_probability}")
    if p.pose_delay_s > ATTITUDE_HISTORY_S:
        raise ValueError(f"estimator.pose_delay_s beyond the {ATTITUDE_HISTORY_S} s attitude history")
    if p.contact_on_samples < 1 or p.contact_off_samples < 1:
        raise ValueError("estimator contact debounce counts must be at least 1")


class InputGate:
    """Refused inputs by reason and counted events, and the window a stamp must fall in."""

    def __init__(self, p: EstimatorParams) -> None:
        self._future_ns = int(p.input_future_tolerance_s * NS)
        self._max_age_ns = int(p.input_max_age_s * NS)
        self.counters: dict[str, int] = {}  # events: touchdowns, bounces
        self.rejections: dict[str, int] = {}  # refused inputs by reason
        self.rejected = 0  # their total (cheap to compare)

    def reject(self, reason: str) -> bool:
        """Count a refused input under ``reason``; False (what an update that refuses returns)."""
        self.rejections[reason] = self.rejections.get(reason, 0) + 1
        self.rejected += 1
        return False

    def count(self, name: str) -> None:
        self.counters[name] = self.counters.get(name, 0) + 1

    def stamp_refused(self, topic: str, t: int, arrival_ns: int | None, max_age_ns: int = -1) -> str:
        """The reason a stamp is refused against its arrival time ('' when it is not); ``max_age_ns``:
        the topic's own bound on age, where it has one (else ``input_max_age_s``)."""
        if arrival_ns is None:
            return ""
        if t > arrival_ns + self._future_ns:
            return f"{topic}_future"
        if t < arrival_ns - (max_age_ns if max_age_ns >= 0 else self._max_age_ns):
            return f"{topic}_past"
        return ""
