"""The Zero Dynamics Policy as the 1 kHz loop evaluates it (thesis eq. 5.48), apart from the
design in :mod:`onboard.low_level.planning.zdp` (numpy and scipy, run once) so that the optional compiled build
(setup.py) can take it: scalar floats only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def clip_norm(x: float, y: float, limit: float) -> tuple[float, float]:
    """Scale the 2-vector ``(x, y)`` down to length ``limit`` if it is longer."""
    n = math.hypot(x, y)
    if n > limit > 0.0:
        s = limit / n
        return x * s, y * s
    return x, y


@dataclass(frozen=True)
class LinearPolicy:
    """``eta = S_eta (z - z_ref)`` with clipped signals: the Raibert form, eq. 5.48.

    Per horizontal axis ``eta_x = k_p (x - x_ref) + k_d (vx - vx_ref)`` (and the
    cross terms, zero for the symmetric hopper). The position and velocity errors
    are clipped to ``pos_err_max`` [m], ``vel_err_max`` [m/s] (by vector norm, so
    directions are kept) and the commanded tilt ``|eta|`` to ``sin(tilt_max)``; a
    limit of 0 disables that clip (the plain LQR/Raibert gain of Fig. 5.22).
    """

    s_eta: tuple[tuple[float, float, float, float], tuple[float, float, float, float]]
    pos_err_max: float
    vel_err_max: float
    tilt_max: float

    def __call__(self, ex: float, ey: float, evx: float, evy: float) -> tuple[float, float]:
        """Errors of the predicted impact state to the reference -> ``(a_x, a_y)``."""
        ex, ey = clip_norm(ex, ey, self.pos_err_max)
        evx, evy = clip_norm(evx, evy, self.vel_err_max)
        r0, r1 = self.s_eta
        ax = r0[0] * ex + r0[1] * ey + r0[2] * evx + r0[3] * evy
        ay = r1[0] * ex + r1[1] * ey + r1[2] * evx + r1[3] * evy
        lim = math.sin(self.tilt_max) if self.tilt_max > 0.0 else 0.999
        return clip_norm(ax, ay, lim)

    def __reduce__(self) -> tuple[type, tuple[object, ...]]:
        """Pickled by its fields (a campaign's workers get policies): the compiled build's frozen
        dataclass cannot be restored field by field."""
        return LinearPolicy, (self.s_eta, self.pos_err_max, self.vel_err_max, self.tilt_max)

    @classmethod
    def from_matrix(cls, s_eta: np.ndarray, pos_err_max: float, vel_err_max: float, tilt_max: float) -> LinearPolicy:
        rows = tuple(tuple(float(c) for c in row) for row in np.asarray(s_eta))
        return cls(rows, pos_err_max, vel_err_max, tilt_max)  # type: ignore[arg-type]
