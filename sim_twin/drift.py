"""How far a no-motion-capture estimate wanders from the twin's truth (``--sensing onboard``), in
lockstep and in real time alike."""

from __future__ import annotations

import math

import mujoco

from onboard.contracts import messages as m
from onboard.geometry import quaternion as quat
from sim_twin import stack as st


class EstimateDrift:
    """How far the estimate's position wanders from the truth, per metre the robot travels, and
    how far its attitude does: heading (no absolute yaw without motion capture) and tilt (what
    places a camera's ground at range: 1 deg is 3.5 cm of height 2 m ahead)."""

    def __init__(self, truth: st.TruthEstimator) -> None:
        self.truth = truth
        self.distance_m = 0.0
        self.last_xy: tuple[float, float] | None = None
        self.max_drift_m = 0.0
        self.final_drift_m = 0.0
        self.final_drift_z_m = 0.0
        self.final_pos_std_m = 0.0
        self.final_heading_err_deg = 0.0
        self.max_heading_err_deg = 0.0
        self.final_tilt_err_deg = 0.0
        self.max_tilt_err_deg = 0.0

    def update(self, now_ns: int, data: mujoco.MjData, state: m.StateEstimate) -> None:
        truth = self.truth.estimate(now_ns, data)
        true = truth.position
        xy = (true[0], true[1])
        if self.last_xy is not None:
            self.distance_m += math.dist(xy, self.last_xy)
        self.last_xy = xy
        est = state.position
        self.final_drift_m = math.dist((est[0], est[1]), xy)
        self.final_drift_z_m = est[2] - true[2]
        self.final_pos_std_m = math.sqrt(max(state.pos_vel_cov[0], 0.0))
        self.max_drift_m = max(self.max_drift_m, self.final_drift_m)
        error = quat.mul(state.quat, quat.conj(truth.quat))  # estimated world <- true world
        self.final_heading_err_deg = abs(math.degrees(quat.yaw_of(error)))
        self.final_tilt_err_deg = math.degrees(quat.tilt(error))
        self.max_heading_err_deg = max(self.max_heading_err_deg, self.final_heading_err_deg)
        self.max_tilt_err_deg = max(self.max_tilt_err_deg, self.final_tilt_err_deg)

    def summary(self) -> dict:
        d = self.distance_m
        return {"distance_travelled_m": round(d, 3), "final_drift_m": round(self.final_drift_m, 4),
                "final_drift_z_m": round(self.final_drift_z_m, 4), "max_drift_m": round(self.max_drift_m, 4),
                "drift_per_m": round(self.final_drift_m / d, 5) if d > 0.1 else None,
                "final_pos_std_m": round(self.final_pos_std_m, 4),
                "final_heading_err_deg": round(self.final_heading_err_deg, 3), "max_heading_err_deg": round(self.max_heading_err_deg, 3),
                "final_tilt_err_deg": round(self.final_tilt_err_deg, 3), "max_tilt_err_deg": round(self.max_tilt_err_deg, 3)}
