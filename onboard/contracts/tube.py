"""The tracking certificate the low level measures and publishes (thesis 1441-1460).

The low level promises the planner a tube: at each impact the CoM is within some
distance of the reference sample ``z_k`` (Corollary 5.8), and the attitude within
some angle of the policy's command. :class:`TubeMonitor` keeps the last ``window``
impacts in fixed rings and summarizes them as a
:class:`~onboard.contracts.messages.TrackingTube` (percentiles of the achieved errors), so
the planner can compare the promise it plans with to what is delivered (thesis
3233-3300). Recording is allocation-free; summarizing sorts (call it at the
publishing rate, not per tick).
"""

from __future__ import annotations

import math

from onboard.contracts.messages import TrackingTube


def _percentile(sorted_vals: list[float], p: float) -> float:
    """Linear-interpolated percentile ``p`` in [0, 100] of a sorted, non-empty list."""
    if len(sorted_vals) == 1:
        return sorted_vals[0]
    x = p / 100.0 * (len(sorted_vals) - 1)
    i = int(math.floor(x))
    j = min(i + 1, len(sorted_vals) - 1)
    return sorted_vals[i] + (x - i) * (sorted_vals[j] - sorted_vals[i])


class TubeMonitor:
    def __init__(self, window: int) -> None:
        if window < 1:
            raise ValueError("tube window must hold at least one impact")
        self.window = window
        self._pos = [0.0] * window
        self._att = [0.0] * window
        self._n = 0
        self.impacts = 0  # all impacts recorded since start
        self.max_pos_err = 0.0  # over all impacts [m]

    def record_impact(self, pos_err: float, att_err: float) -> None:
        """One impact: CoM position error to the reference [m], attitude error [rad]."""
        i = self._n % self.window
        self._pos[i] = pos_err
        self._att[i] = att_err
        self._n += 1
        self.impacts += 1
        if pos_err > self.max_pos_err:
            self.max_pos_err = pos_err

    def reset(self) -> None:
        self._n = 0

    def tube(self, stamp_ns: int = 0) -> TrackingTube:
        n = min(self._n, self.window)
        if n == 0:
            return TrackingTube(stamp_ns=stamp_ns, hops=0, impact_err_p50=0.0, impact_err_p95=0.0,
                                impact_err_max=0.0, attitude_err_p95=0.0)
        pos = sorted(self._pos[:n])
        att = sorted(self._att[:n])
        return TrackingTube(
            stamp_ns=stamp_ns,
            hops=n,
            impact_err_p50=_percentile(pos, 50.0),
            impact_err_p95=_percentile(pos, 95.0),
            impact_err_max=pos[-1],
            attitude_err_p95=_percentile(att, 95.0),
        )
