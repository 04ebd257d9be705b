"""Where the state estimator's position and absolute attitude come from (thesis 5.5, line 2755:
"a Kalman filter with projectile dynamics is used to filter the position estimates from
optitrack"; ``EstimatorParams.position_source`` picks one).

Part of :class:`~onboard.estimation.estimator.StateEstimator`, which steps the CoM filter up to
the present before either source touches it:

- :class:`MocapPoses` (``"mocap"``): a pose sensor's position and attitude, fused at their capture
  time. A pose is checked first (finite, unit quaternion, stamp, order, not in the future of the
  IMU, not inside an IMU gap), then gated against the CoM filter's state at its capture time: a
  refused pose is not used at all (its attitude neither) and does not move the order check, so
  a stream of outliers cannot push the real poses out as out of order.
- :class:`Odometry` (``"odometry"``: no motion capture): the IMU's own orientation (its AHRS)
  corrects the attitude every ``imu_att_every`` samples; the first confirmed touchdown's contact
  point is the origin (ground at z = 0), and on flat ground every later one resets the CoM's
  height from the leg, keeping the unobserved vertical drift to one hop's worth. With
  ``visual_odometry`` the D435's frame-to-frame displacement between two apex stamps
  (:mod:`onboard.perception.visual_odometry`) is fused with the odometry's own displacement
  between the same stamps by inverse variance, and the frame moved by the difference: the
  measurement arrives late (the VO's compute), so the odometry keeps its own positions for
  ``vo_history_s`` and compares at the frames' stamps, not at the arrival.
"""

from __future__ import annotations

import math
from collections import deque

from onboard.contracts.messages import PoseMeasurement, VisualOdometryDelta
from onboard.contracts.params import EstimatorParams
from onboard.estimation.attitude_filter import AttitudeFilter
from onboard.estimation.com_filter import ComFilter
from onboard.estimation.input_gate import NS, QUAT_NORM_TOL, InputGate
from onboard.geometry import quaternion as quat
from onboard.geometry.quaternion import Quat, Vec3


class MocapPoses:
    """The pose sensor's measurements: their checks, and their fusion into attitude and CoM filters."""

    def __init__(self, p: EstimatorParams, gate: InputGate, gate3: float) -> None:
        self._gate = gate
        self._gate3 = gate3
        self._pos_var = p.pose_pos_std_m ** 2
        self._att_var = p.pose_att_std_rad ** 2
        self._future_ns = int(p.pose_future_tolerance_s * NS)
        self._compensate_latency = p.compensate_latency
        self.t_pose = -1  # capture stamp of the newest accepted pose
        self.t_fused = -1  # capture stamp of the newest pose whose attitude was fused

    def accept(self, msg: PoseMeasurement, arrival_ns: int | None, t_imu: int,
               imu_gap: tuple[int, int]) -> tuple[int, Vec3, Quat] | None:
        """The pose's capture stamp, torso origin [m, world] and unit attitude, or None when it is
        refused before the filters see it (counted by reason)."""
        t = msg.stamp_ns
        pos, q = msg.position, msg.quat
        px, py, pz = float(pos[0]), float(pos[1]), float(pos[2])
        qw, qx, qy, qz = float(q[0]), float(q[1]), float(q[2]), float(q[3])
        n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        finite = math.isfinite(px + py + pz) and math.isfinite(n)  # a NaN or inf spreads to the sum
        reason = self._refusal(t, finite, n, arrival_ns, t_imu, imu_gap)
        if reason:
            self._gate.reject(reason)
            return None
        return t, (px, py, pz), (qw / n, qx / n, qy / n, qz / n)

    def _refusal(self, t: int, finite: bool, n: float, arrival_ns: int | None, t_imu: int,
                 imu_gap: tuple[int, int]) -> str:
        """Why a pose stamped ``t`` (its quaternion of norm ``n``) is refused, in the order the
        reasons are checked ('' when it is not)."""
        if not finite:
            return "pose_nonfinite"
        if abs(n - 1.0) > QUAT_NORM_TOL:
            return "pose_bad_quat"
        refused = self._gate.stamp_refused("pose", t, arrival_ns)
        if refused:
            return refused
        if t_imu < 0:
            return "pose_before_imu"
        if t <= self.t_pose:
            return "pose_out_of_order"
        if t > t_imu + self._future_ns:
            return "pose_future"
        if imu_gap[0] < t < imu_gap[1]:
            # neither the attitude nor the CoM at that time is known well enough to compare
            return "pose_in_imu_gap"
        return ""

    def fuse(self, pose: tuple[int, Vec3, Quat], t_imu: int, att: AttitudeFilter, com: ComFilter) -> bool:
        """Fuse an accepted pose (the CoM filter stepped up to ``t_imu``, the newest IMU sample):
        its position gated against the CoM at the capture time, then its attitude; whether it was used."""
        t, pos, qm = pose
        r0, r1, r2 = quat.to_matrix(qm)
        rot = r0 + r1 + r2
        if not com.admits_pose(t, pos, rot, self._pos_var):
            return False  # counted by the CoM filter as an outlier
        if self._compensate_latency:
            fused = att.correct_pose(qm, t, self._att_var, self._gate3)
        else:  # as if captured now
            fused = att.correct_pose(qm, t_imu, self._att_var, self._gate3)
        if fused is None:
            return self._gate.reject("pose_stale")
        self.t_pose = t
        if fused:
            self.t_fused = t
        else:
            self._gate.reject("att_outliers")
        com.add_pose(t, pos, rot, self._pos_var)
        return True


class Odometry:
    """No pose sensor: the IMU's orientation for the attitude, an origin at the first touchdown."""

    def __init__(self, p: EstimatorParams, gate: InputGate, gate3: float, gate2: float) -> None:
        self._gate = gate
        self._gate3 = gate3
        self.anchored = False
        self._imu_att_var = p.imu_att_std_rad ** 2
        self._imu_att_every = p.imu_att_every
        self._imu_att_run = 0
        self._anchor_var = p.anchor_std_m ** 2
        self._flat_ground = p.odometry_flat_ground
        # visual odometry: the odometry's own horizontal positions (without the VO's corrections) by stamp
        self.visual = p.visual_odometry
        self._history: deque[tuple[int, float, float]] = deque()
        self._history_ns = int(p.vo_history_s * NS)
        self._shift_x = 0.0  # the VO's corrections so far [m, world]
        self._shift_y = 0.0
        self._leg_disp_var = p.vo_leg_std_m ** 2
        self._gate2 = gate2

    def imu_attitude(self, att: AttitudeFilter, q: list[float], t: int) -> None:
        """Every ``imu_att_every``-th IMU orientation (its own AHRS) corrects the attitude."""
        self._imu_att_run += 1
        if self._imu_att_run < self._imu_att_every:
            return
        self._imu_att_run = 0
        qw, qx, qy, qz = float(q[0]), float(q[1]), float(q[2]), float(q[3])
        n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        if not math.isfinite(n) or abs(n - 1.0) > QUAT_NORM_TOL:
            self._gate.reject("imu_bad_quat")
            return
        fused = att.correct_pose((qw / n, qx / n, qy / n, qz / n), t, self._imu_att_var, self._gate3)
        if fused:
            self._gate.count("imu_att_fused")
        elif fused is not None:
            self._gate.reject("imu_att_outliers")

    def anchor(self, com: ComFilter, from_contact: Vec3) -> None:
        """At a confirmed touchdown, with the CoM ``from_contact`` [m, world] above the contact point.
        The first one's contact point is the origin (ground at z = 0). At each later one on flat
        ground (``odometry_flat_ground``) the foot is back on the ground's height: the CoM's height
        is set from the leg (its horizontal position stays the odometry's)."""
        lx, ly, lz = from_contact
        if not self.anchored:
            self.anchored = True
            com.anchor(lx, ly, lz, self._anchor_var)
            self._history.clear()  # the frame's origin moved: positions before it are not comparable
            self._gate.count("odometry_anchored")
        elif self._flat_ground:
            com.shift_height(lz - com.position[2])
            self._gate.count("ground_height_resets")

    def record(self, t: int, com: ComFilter) -> None:
        """The CoM's horizontal position at ``t`` (an IMU sample), less the VO's corrections so far:
        what a later displacement is compared against."""
        if not self.anchored:
            return
        px, py, _ = com.position
        history = self._history
        history.append((t, px - self._shift_x, py - self._shift_y))
        oldest = t - self._history_ns
        while history[0][0] < oldest:
            history.popleft()

    def _position_at(self, t: int) -> tuple[float, float] | None:
        """The odometry's own horizontal position at ``t`` [m], interpolated between the kept samples;
        None outside them."""
        history = self._history
        if not history or t < history[0][0] or t > history[-1][0]:
            return None
        later = history[-1]
        for i in range(len(history) - 1, -1, -1):  # the stamps asked for are recent: from the newest back
            e = history[i]
            if e[0] <= t:
                if later[0] == e[0]:
                    return e[1], e[2]
                w = (t - e[0]) / (later[0] - e[0])
                return e[1] + w * (later[1] - e[1]), e[2] + w * (later[2] - e[2])
            later = e
        return None

    def fuse_displacement(self, msg: VisualOdometryDelta, com: ComFilter) -> bool:
        """Fuse the VO's horizontal displacement of the CoM between ``msg.from_stamp_ns`` and
        ``msg.stamp_ns`` with the odometry's own between the same stamps, by inverse variance
        (the odometry's: ``vo_leg_std_m`` per axis; the VO's: its covariance), gated against their
        sum; the frame moves by the fused minus the odometry's. Whether it was used."""
        if not self.visual:
            return self._gate.reject("vo_disabled")
        if not self.anchored:
            return self._gate.reject("vo_before_anchor")
        d, c = msg.displacement, msg.cov
        dx, dy = float(d[0]), float(d[1])
        cxx, cxy, cyy = float(c[0]), 0.5 * (float(c[1]) + float(c[3])), float(c[4])
        if not (math.isfinite(dx + dy) and math.isfinite(cxx + cxy + cyy)):
            return self._gate.reject("vo_nonfinite")
        if cxx <= 0.0 or cyy <= 0.0 or cxx * cyy - cxy * cxy <= 0.0:
            return self._gate.reject("vo_bad_cov")
        if msg.stamp_ns <= msg.from_stamp_ns:
            return self._gate.reject("vo_bad_interval")
        p0 = self._position_at(msg.from_stamp_ns)
        p1 = self._position_at(msg.stamp_ns)
        if p0 is None or p1 is None:
            return self._gate.reject("vo_stamps_not_kept")
        ox, oy = p1[0] - p0[0], p1[1] - p0[1]
        v = self._leg_disp_var
        # innovation covariance S = C_vo + v I; the fused displacement is the odometry's plus v S^-1 e
        a, b, dd = cxx + v, cxy, cyy + v
        det = a * dd - b * b
        ex, ey = dx - ox, dy - oy
        if (dd * ex * ex - 2.0 * b * ex * ey + a * ey * ey) / det > self._gate2:
            return self._gate.reject("vo_outliers")
        kx = v * (dd * ex - b * ey) / det
        ky = v * (a * ey - b * ex) / det
        com.shift_horizontal(kx, ky)
        self._shift_x += kx
        self._shift_y += ky
        self._gate.count("vo_fused")
        return True
