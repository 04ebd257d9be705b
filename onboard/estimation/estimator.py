"""State estimation: CoM position and velocity, attitude and rates, wheels, foot, contact.

Pure and synchronous (no clock read, no I/O): the ``estimator`` service and the
lockstep runner drive the same class with messages and their stamps.

Usage (lockstep or service)::

    est = StateEstimator(EstimatorParams(), robot_params("indoor"))
    est.update_imu(imu, t_arrival)        # ImuSample, 1 kHz: propagates attitude and CoM
    est.update_joints(joints, t_arrival)  # JointSensors, 1 kHz: wheels, foot, contact, leg kinematics
    est.update_pose(pose, t_arrival)      # PoseMeasurement, whenever one arrives (stamp = capture time)
    msg = est.estimate(now_ns)            # StateEstimate predicted to now_ns

``t_arrival`` is when the caller received the sample, on the clock its stamps use (the
service reads it when the message arrives; lockstep passes the tick's time): a sample
stamped more than ``input_future_tolerance_s`` after it, or ``input_max_age_s`` before
it, is refused. Each ``update_*`` returns True if the sample was used and False if it
was rejected; rejections are counted by reason (non-finite, future, past, out of order,
out of range, stale, gated outlier) in :meth:`StateEstimator.rejections` and
:attr:`StateEstimator.counters`. :meth:`StateEstimator.status` summarizes health:
``mode`` is ``"init"`` until the first pose is fused, ``"pose_outage"`` while no pose
has been fused for ``pose_timeout_s``, else ``"ok"``; with ``position_source = "odometry"``
(no motion capture) ``"init"`` until the first touchdown, then ``"odometry"``.

Honest covariance: every uncertainty grows with the time since its input was last
fused, and ``valid`` is the covariance's verdict (position, velocity, attitude and body
rate standard deviations under the ``valid_*`` limits), never a timer; ``attitude_valid``
is the verdict on the attitude and body rate alone (in an IMU gap the CoM velocity's
uncertainty crosses its limit well before the attitude's). Between IMU
samples, and past the newest one, the estimate is predicted with the rate and the CoM
acceleration held; what the IMU did not see is an unknown constant acceleration
(``gap_accel_std_m_s2``, ``gap_angular_accel_std_rad_s2``; none for the CoM while the
foot switch shows the robot in flight throughout), the velocity uncertainty capped by
``max_speed_m_s``. Without poses the CoM and attitude uncertainty grow with the process
noise and the gyro bias; leg kinematics are fused only while the IMU is current.

Model (thesis line 2751 and :mod:`onboard.estimation.com_filter`, :mod:`onboard.estimation.attitude_filter`):

- attitude and gyro bias: multiplicative EKF on the unit quaternion, corrected by the
  pose sensor's attitude (latency compensated) and by gravity when quasi-static;
- CoM (the whole robot's): projectile dynamics in flight; in stance the foot is pinned,
  the accelerometer drives the CoM (the sprung mass's share) and leg kinematics
  (rolling foot sphere, after the foot has settled) measure its velocity; the
  touchdown impact stops the foot (applied at the switch's closure, taken back if the
  debounce refuses it); the pose sensor's position is fused at its capture time on a
  delayed horizon; Mahalanobis gating rejects outliers; the covariance is published;
- each IMU interval is integrated once the same tick's joint frame (or the next
  sample, or ``estimate``) arrives, so the contact reading at the interval's end picks
  the dynamics: call ``update_joints`` after ``update_imu`` of the same tick;
- no accelerometer (``ImuSample.accel_sensed`` False: ARCHER's own firmware reports none):
  the specific force is a model, not a reading. In flight the body falls freely (the
  cable holds the spring's preload inside the body: 0); in stance, once the foot board
  has let the cable go, the spring pushes the sprung body along the leg,
  ``(k s + c s') / m_sprung`` from the foot's compression and rate. That model leaves out
  the leg's sideways constraint forces and what the cable still holds right after
  touchdown, so the stance process noise is ``accel_psd_stance_modelled`` instead of
  ``accel_psd_stance``, and gravity never corrects the attitude (a modelled force along the
  leg would say "upright" whatever the tilt): the pose sensor's attitude is the only
  correction, and without poses the attitude uncertainty grows with the gyro's;
- contact: the foot switch with hysteresis in time (consecutive samples to switch);
  without a foot sensor (``JointSensors.foot_sensed`` False) the specific force with
  hysteresis in level, and no leg kinematics;
- wheel speeds, foot compression and rate: the latest valid sensor values.

Frames: world z up; body = torso frame, origin at the point the pose sensor reports
(the torso origin), z up along the leg, foot compression along +z.
"""

from __future__ import annotations

import math
from typing import Protocol, cast

from scipy.stats import chi2

from onboard.geometry import quaternion as quat
from onboard.estimation.attitude_filter import AttitudeFilter
from onboard.estimation.com_filter import ComFilter, make_com_filter
from onboard.contracts.messages import ImuSample, JointSensors, PoseMeasurement, StateEstimate
from onboard.contracts.params import EstimatorParams

NS = 1_000_000_000
QUAT_NORM_TOL = 0.1  # a pose quaternion further than this from unit norm is malformed
FOOT_RANGE_MARGIN_M = 0.01  # [m] foot compression reading tolerated outside its travel
FOOT_EXTENDED_M = 0.001  # [m] below this compression the spring (~12 N) no longer holds the foot down
ATTITUDE_HISTORY_S = 0.25  # [s] oldest pose whose attitude can still be fused
GAP_CORRELATION = 0.5  # position-velocity correlation of the covariance an IMU gap adds


class RobotGeometry(Protocol):
    """What the estimator needs of the robot (``sim_twin.model.RobotParams`` has it)."""

    gravity: float  # [m/s^2]
    total_mass: float  # [kg]
    foot_mass: float  # unsprung mass [kg]
    com_offset_body: tuple[float, float, float]  # CoM from the torso origin, foot extended [m, body]
    leg_length: float  # torso origin to the foot's lowest point, foot extended [m]
    foot_radius: float  # contact sphere [m]
    foot_travel: float  # maximum compression [m]
    spring_stiffness: float  # leg spring [N/m]
    spring_damping: float  # [N s/m]


def _check(p: EstimatorParams) -> None:
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


class StateEstimator:
    """The estimator; see the module docstring for the interface and the model."""

    def __init__(self, params: EstimatorParams, robot: RobotGeometry) -> None:
        _check(params)
        self.params = params
        p = params
        self._g = robot.gravity
        mu = robot.foot_mass / robot.total_mass
        self._mu_foot = mu
        self._mu_sprung = 1.0 - mu
        c0 = tuple(float(v) for v in robot.com_offset_body)
        self._foot_travel = robot.foot_travel
        # the spring's push per metre of compression and per m/s of its rate, on the sprung body [m/s^2]
        m_sprung = robot.total_mass - robot.foot_mass
        self._spring_sf = (robot.spring_stiffness / m_sprung, robot.spring_damping / m_sprung)
        self._accel_sensed = True  # False once a sample says it carries no accelerometer
        self._foot_radius = robot.foot_radius
        # CoM relative to the foot sphere's centre at zero compression [m, body]; the foot
        # slides along body z, so compression s moves the sphere up by s and the CoM by mu s.
        self._r_cf0 = (c0[0], c0[1], c0[2] + robot.leg_length - robot.foot_radius)
        self._gate3 = float(chi2.ppf(p.gate_probability, 3))
        self._gate2 = float(chi2.ppf(p.gate_probability, 2))
        self.att = AttitudeFilter(
            gyro_noise_density=p.gyro_noise_density,
            gyro_bias_walk=p.gyro_bias_walk,
            init_att_std=p.init_att_std_rad,
            init_bias_std=p.init_bias_std_rad_s,
            history_len=int(ATTITUDE_HISTORY_S * p.imu_rate_hz),
        )
        self.com: ComFilter = make_com_filter(
            p.kf_backend,
            delay_s=p.pose_delay_s,
            compensate_latency=p.compensate_latency,
            accel_psd_flight=p.accel_psd_flight,
            accel_psd_stance=p.accel_psd_stance,
            init_pos_std=p.init_pos_std_m,
            init_vel_std=p.init_vel_std_m_s,
            gate_chi2=self._gate3,
            com_offset_body=c0,
            com_per_compression=(0.0, 0.0, mu),
            reacquire_s=p.pose_reacquire_s,
        )
        self._pose_pos_var = p.pose_pos_std_m ** 2
        self._pose_att_var = p.pose_att_std_rad ** 2
        self._leg_var = p.leg_vel_std_m_s ** 2
        self._impact_var = p.impact_vel_std_m_s ** 2
        self._liftoff_var = p.liftoff_vel_std_m_s ** 2
        self._tilt_var = p.tilt_std_rad ** 2
        self._static_hold_ns = int(p.static_hold_s * NS)
        self._accel_delay = p.accel_delay_s
        self._leg_settle_ns = int(p.leg_settle_s * NS)
        self._static_gyro2 = p.static_gyro_max_rad_s ** 2
        self._gyro_range2 = p.gyro_range_rad_s ** 2
        self._accel_range2 = p.accel_range_m_s2 ** 2
        self._valid_pos_var = p.valid_pos_std_m ** 2
        self._valid_vel_var = p.valid_vel_std_m_s ** 2
        self._valid_att_var = p.valid_att_std_rad ** 2
        self._valid_rate_var = p.valid_rate_std_rad_s ** 2
        self._period_ns = int(round(NS / p.imu_rate_hz))
        self._gap_accel_var = p.gap_accel_std_m_s2 ** 2
        self._gap_alpha_var = p.gap_angular_accel_std_rad_s2 ** 2
        self._max_speed2 = p.max_speed_m_s ** 2
        self._gyro_sample_var = p.gyro_noise_density ** 2 * p.imu_rate_hz  # one sample's white noise
        self._future_ns = int(p.input_future_tolerance_s * NS)
        self._max_age_ns = int(p.input_max_age_s * NS)
        self._counters: dict[str, int] = {}  # events: touchdowns, bounces
        self._rejections: dict[str, int] = {}  # refused inputs by reason
        self._rejected = 0  # their total (cheap to compare)
        # inputs
        self._t_imu = -1
        self._t_joints = -1
        self._t_pose = -1  # capture stamp of the newest accepted pose
        self._t_pose_fused = -1
        self._accel = (0.0, 0.0, 0.0)  # CoM acceleration at the newest sample [m/s^2, world]
        self._sf_prev = (0.0, 0.0, 0.0)  # specific force at the previous sample [m/s^2, world]
        self._pending: tuple[int, float, float, float, float] | None = None  # IMU interval not yet integrated
        self._rot = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)  # R at the newest sample, row-major
        self._static_since = -1
        self.wheel_vel = (0.0, 0.0, 0.0)
        self.foot_pos = 0.0
        self.foot_vel = 0.0
        # contact with hysteresis
        self.contact = False
        self._contact_run = 0
        self._switch = False  # the raw contact reading
        self._switch_on_ns = 0  # when the switch last closed
        self._impact: tuple[float, float, float] | None = None  # applied, not yet confirmed
        self._foot_sensed = True  # False: contact from the specific force (no foot sensor)
        self._free_foot = (0.0, 0.0)  # foot compression and rate at the last no-contact reading
        self._gap_contact = False  # a contact reading since the newest IMU interval was integrated
        self._imu_gap = (0, 0)  # the newest interval of more than two IMU periods [ns]
        # no pose (position_source "odometry"): the IMU's orientation for the attitude, an origin at touchdown
        self._odometry = p.position_source == "odometry"
        self._anchored = False
        self._imu_att_var = p.imu_att_std_rad ** 2
        self._imu_att_every = p.imu_att_every
        self._imu_att_run = 0
        self._anchor_var = p.anchor_std_m ** 2
        self._flat_ground = p.odometry_flat_ground

    # --- helpers ------------------------------------------------------------------

    def _reject(self, reason: str) -> bool:
        self._rejections[reason] = self._rejections.get(reason, 0) + 1
        self._rejected += 1
        return False

    def _stamp_refused(self, topic: str, t: int, arrival_ns: int | None) -> str:
        """The reason a stamp is refused against its arrival time ('' when it is not)."""
        if arrival_ns is None:
            return ""
        if t > arrival_ns + self._future_ns:
            return f"{topic}_future"
        if t < arrival_ns - self._max_age_ns:
            return f"{topic}_past"
        return ""

    def _speed_limit(self, vx: float, vy: float, vz: float, ax: float, ay: float, az: float, dt: float) -> float:
        """The largest ``k`` in [0, 1] for which ``v + k a dt`` stays within the top speed: over an
        IMU gap the held acceleration must not predict a speed the robot cannot reach (the gap's
        velocity uncertainty is capped there too)."""
        dx, dy, dz = ax * dt, ay * dt, az * dt
        vmax2 = self._max_speed2
        if (vx + dx) ** 2 + (vy + dy) ** 2 + (vz + dz) ** 2 <= vmax2:
            return 1.0
        # |v + k d|^2 = vmax^2: the positive root (0 when already at the top speed)
        a = dx * dx + dy * dy + dz * dz
        b = vx * dx + vy * dy + vz * dz
        c = vx * vx + vy * vy + vz * vz - vmax2
        if c >= 0.0:
            return 0.0
        return (-b + math.sqrt(b * b - a * c)) / a

    def _gap_cov(self, g: float, stance: bool) -> tuple[float, float, float]:
        """Per-axis CoM covariance ``(pp, pv, vv)`` that ``g`` [s] without the accelerometer adds:
        an unknown constant acceleration, the velocity part capped by the robot's top speed.

        The position and velocity errors are correlated by half, not fully: a constant
        acceleration would correlate them fully, but it is a bound, not the truth, and a fully
        correlated term would let the first pose after the gap "measure" the velocity too."""
        if not stance or g <= 0.0:
            return 0.0, 0.0, 0.0
        vv = min(self._gap_accel_var * g * g, self._max_speed2)
        pp = min(0.25 * self._gap_accel_var * g * g * g * g, self._max_speed2 * g * g)
        return pp, GAP_CORRELATION * math.sqrt(pp * vv), vv

    def _count(self, name: str) -> None:
        self._counters[name] = self._counters.get(name, 0) + 1

    def feed(self, topic: str, msg: object, arrival_ns: int | None = None) -> bool:
        """A sensor message by its topic (``imu``, ``joints``, ``pose``): the update it takes.
        Another topic is not a sensor of the estimator's: False, nothing counted."""
        if topic == "imu":
            return self.update_imu(cast(ImuSample, msg), arrival_ns)
        if topic == "joints":
            return self.update_joints(cast(JointSensors, msg), arrival_ns)
        if topic == "pose":
            return self.update_pose(cast(PoseMeasurement, msg), arrival_ns)
        return False

    # --- IMU --------------------------------------------------------------------------

    def update_imu(self, msg: ImuSample, arrival_ns: int | None = None) -> bool:
        """Propagate attitude and CoM to ``msg.stamp_ns``. Gyro [rad/s] and specific
        force [m/s^2] in the body frame."""
        t = msg.stamp_ns
        gyro, accel = msg.gyro, msg.accel
        # float(): callers building messages from numpy arrays pass numpy scalars,
        # whose arithmetic is several times slower than a float's
        gx, gy, gz = float(gyro[0]), float(gyro[1]), float(gyro[2])
        sensed = msg.accel_sensed
        if sensed:
            fx, fy, fz = float(accel[0]), float(accel[1]), float(accel[2])
        else:
            fx, fy, fz = 0.0, 0.0, self._modelled_specific_force()
        if sensed != self._accel_sensed:
            self._accel_sensed = sensed
            self.com.set_stance_psd(self.params.accel_psd_stance if sensed else self.params.accel_psd_stance_modelled)
        isf = math.isfinite
        if not (isf(gx) and isf(gy) and isf(gz) and isf(fx) and isf(fy) and isf(fz)):
            return self._reject("imu_nonfinite")
        refused = self._stamp_refused("imu", t, arrival_ns)  # first: a wrong clock, named as one
        if refused:
            return self._reject(refused)
        if t <= self._t_imu:
            return self._reject("imu_out_of_order")
        p = self.params
        wr = gx * gx + gy * gy + gz * gz
        fn2 = fx * fx + fy * fy + fz * fz
        if wr > self._gyro_range2 or fn2 > self._accel_range2:
            return self._reject("imu_out_of_range")
        att = self.att
        if not att.initialized:
            return self._start(msg)
        if self._pending is not None:
            self._step_com()
        dt = (t - self._t_imu) / NS
        gap = (t - self._t_imu - self._period_ns) / NS
        if t - self._t_imu > 2 * self._period_ns:
            self._imu_gap = (self._t_imu, t)
        self._t_imu = t
        att.propagate(t, gx, gy, gz, dt, 0.25 * self._gap_alpha_var * gap ** 4 if gap > 0.0 else 0.0)
        # gravity as the direction of up, only after a quasi-static spell
        wx, wy, wz = att.omega
        if sensed and abs(math.sqrt(fn2) - self._g) < p.static_accel_tol_m_s2 and wx * wx + wy * wy + wz * wz < self._static_gyro2:
            if self._static_since < 0:
                self._static_since = t
            elif t - self._static_since >= self._static_hold_ns:
                if not att.correct_gravity(fx, fy, fz, self._tilt_var, self._gate2):
                    self._reject("gravity_outliers")
        else:
            self._static_since = -1
        if self._odometry:
            self._imu_attitude(msg.quat, t)
        w, x, y, z = att.q
        r00 = 1.0 - 2.0 * (y * y + z * z)
        r01 = 2.0 * (x * y - w * z)
        r02 = 2.0 * (x * z + w * y)
        r10 = 2.0 * (x * y + w * z)
        r11 = 1.0 - 2.0 * (x * x + z * z)
        r12 = 2.0 * (y * z - w * x)
        r20 = 2.0 * (x * z - w * y)
        r21 = 2.0 * (y * z + w * x)
        r22 = 1.0 - 2.0 * (x * x + y * y)
        self._rot = (r00, r01, r02, r10, r11, r12, r20, r21, r22)
        # specific force in the world frame; the CoM step waits for this tick's contact reading
        sx = r00 * fx + r01 * fy + r02 * fz
        sy = r10 * fx + r11 * fy + r12 * fz
        sz = r20 * fx + r21 * fy + r22 * fz
        self._pending = (t, dt, sx, sy, sz)
        if not self._foot_sensed and sensed:
            # the spring's push is the only large specific force on a hopping robot's body
            f = math.sqrt(fn2)
            reading = f > p.accel_contact_on_m_s2 or (self._switch and f > p.accel_contact_off_m_s2)
            self._contact_reading(reading, t)
        return True

    def _imu_attitude(self, q: list[float], t: int) -> None:
        """Odometry: every ``imu_att_every``-th IMU orientation (its own AHRS) corrects the attitude."""
        self._imu_att_run += 1
        if self._imu_att_run < self._imu_att_every:
            return
        self._imu_att_run = 0
        qw, qx, qy, qz = float(q[0]), float(q[1]), float(q[2]), float(q[3])
        n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        if not math.isfinite(n) or abs(n - 1.0) > QUAT_NORM_TOL:
            self._reject("imu_bad_quat")
            return
        fused = self.att.correct_pose((qw / n, qx / n, qy / n, qz / n), t, self._imu_att_var, self._gate3)
        if fused:
            self._count("imu_att_fused")
        elif fused is not None:
            self._reject("imu_att_outliers")

    def _com_from_contact(self) -> tuple[float, float, float]:
        """The CoM from the foot's contact point [m, world]: the lever to the foot sphere's centre, then its radius."""
        r = self._rot
        bx, by, bz = self._r_cf0
        bz -= self._mu_sprung * self.foot_pos
        return (r[0] * bx + r[1] * by + r[2] * bz, r[3] * bx + r[4] * by + r[5] * bz,
                r[6] * bx + r[7] * by + r[8] * bz + self._foot_radius)

    def _anchor(self) -> None:
        """Odometry, at a confirmed touchdown. The first one's contact point is the origin (ground at
        z = 0). At each later one on flat ground (``odometry_flat_ground``) the foot is back on the
        ground's height: the CoM's height is set from the leg, which keeps the unobserved vertical
        drift to one hop's worth (its horizontal position stays the odometry's)."""
        lx, ly, lz = self._com_from_contact()
        if not self._anchored:
            self._anchored = True
            self.com.anchor(lx, ly, lz, self._anchor_var)
            self._count("odometry_anchored")
        elif self._flat_ground:
            self.com.shift_height(lz - self.com.position[2])
            self._count("ground_height_resets")

    def _modelled_specific_force(self) -> float:
        """The specific force along the leg [m/s^2, body z] with no accelerometer: the spring's
        push in stance (the raw switch, as the CoM step picks its dynamics), free fall in flight."""
        if not self._switch:
            return 0.0
        k, c = self._spring_sf
        return max(0.0, k * self.foot_pos + c * self.foot_vel)  # the spring only pushes

    def _step_com(self) -> None:
        """Integrate the CoM over the newest IMU interval.

        Deferred until the joint frame of the same tick (or the next IMU sample, or an
        estimate) so that the contact reading at the interval's end picks the model: at
        touchdown the accelerometer already feels the spring in that sample. Stance dynamics
        hold while the foot is on the ground and the spring pushes it there; at full extension
        the foot is about to be yanked off its stop, an internal impulse the accelerometer
        sees and the CoM does not. Projectile dynamics are exact once the foot is airborne.
        """
        pending = self._pending
        assert pending is not None  # every caller checks first
        t, dt, sx, sy, sz = pending
        self._pending = None
        gap = dt - self._period_ns / NS
        gap_cov = self._gap_cov(gap, self._gap_contact or self._switch) if gap > 0.0 else None
        self._gap_contact = self._switch
        px, py, pz = self._sf_prev
        self._sf_prev = (sx, sy, sz)
        g = self._g
        stance = self._switch and (self.foot_pos > FOOT_EXTENDED_M or not self._foot_sensed)
        if stance:
            # foot pinned: the CoM accelerates with the sprung mass's share of the body's. The
            # interval's mean from two samples each describing accel_delay_s before its stamp:
            # the trapezoid shifted by the delay.
            m = self._mu_sprung
            self._accel = (m * sx, m * sy, m * (sz - g))
            w1 = 0.5 + min(self._accel_delay / dt, 0.5)
            w0 = 1.0 - w1
            ax, ay, az = m * (w0 * px + w1 * sx), m * (w0 * py + w1 * sy), m * (w0 * pz + w1 * sz - g)
        else:
            self._accel = ax, ay, az = (0.0, 0.0, -g)  # projectile
        if gap > 0.0:  # two samples a gap apart: their mean is held only up to the top speed
            vx, vy, vz = self.com.velocity
            k = self._speed_limit(vx, vy, vz, ax, ay, az, dt)
            ax, ay, az = k * ax, k * ay, k * az
        self.com.push(t, dt, ax, ay, az, stance, self.foot_pos, gap_cov)

    def _start(self, msg: ImuSample) -> bool:
        """First IMU sample: the IMU's own attitude if it is a unit quaternion, else level."""
        q0 = cast(quat.Quat, tuple(float(v) for v in msg.quat))
        n = quat.norm(q0) if quat.is_finite(q0) else 0.0
        q_start = quat.normalize(q0) if abs(n - 1.0) < QUAT_NORM_TOL else quat.IDENTITY
        self.att.initialize(q_start, msg.stamp_ns, cast(quat.Vec3, tuple(float(v) for v in msg.gyro)))
        self.com.start(msg.stamp_ns)
        self._t_imu = msg.stamp_ns
        self._accel = (0.0, 0.0, -self._g)
        self._sf_prev = quat.rotate(q_start, tuple(float(v) for v in msg.accel))
        return True

    # --- joints -----------------------------------------------------------------------

    def update_joints(self, msg: JointSensors, arrival_ns: int | None = None) -> bool:
        """Wheel speeds, foot compression and rate, contact; leg kinematics in stance."""
        t = msg.stamp_ns
        wv = msg.wheel_vel
        s, sd = float(msg.foot_pos), float(msg.foot_vel)
        isf = math.isfinite
        if not (isf(wv[0]) and isf(wv[1]) and isf(wv[2]) and isf(s) and isf(sd)):
            return self._reject("joints_nonfinite")
        if t <= self._t_joints:
            return self._reject("joints_out_of_order")
        refused = self._stamp_refused("joints", t, arrival_ns)
        if refused:
            return self._reject(refused)
        if not -FOOT_RANGE_MARGIN_M <= s <= self._foot_travel + FOOT_RANGE_MARGIN_M:
            return self._reject("joints_out_of_range")
        self._t_joints = t
        self.wheel_vel = (float(wv[0]), float(wv[1]), float(wv[2]))
        if not msg.foot_sensed:
            # No foot sensor: the foot fields are zeros, not readings. Contact comes from the
            # specific force instead (in update_imu); no leg kinematics.
            self._foot_sensed = False
            if self._pending is not None:
                self._step_com()
            return True
        self._foot_sensed = True
        self.foot_pos = s
        self.foot_vel = sd
        self._gap_contact = self._gap_contact or msg.foot_contact
        self._contact_reading(msg.foot_contact, t)
        if (self.contact and msg.foot_contact and t - self._switch_on_ns >= self._leg_settle_ns and self.att.initialized
                and t - self._t_imu <= self._period_ns):
            # not while the foot still bounces off the ground after the impact, nor while
            # lift-off is being debounced: in both the foot is not pinned; nor in an IMU gap,
            # where attitude and rate are predictions and the CoM filter has no sample at t
            vx, vy, vz = self._leg_velocity(s, sd, rolling=True)
            # the attitude's own uncertainty turns the lever arm: (|w| |r| + |r'|)^2 var(theta)
            wx, wy, wz = self.att.omega
            bx, by, bz = self._r_cf0
            lever = (wx * wx + wy * wy + wz * wz) * (bx * bx + by * by + bz * bz) + (self._mu_sprung * sd) ** 2
            self.com.add_leg_velocity(vx, vy, vz, self._leg_var + lever * max(self.att.variances()))
        return True

    def _contact_reading(self, reading: bool, t: int) -> None:
        """One contact reading at ``t``: raw switch, impact map, debounced contact."""
        closed = reading and not self._switch
        if not reading:
            self._free_foot = (self.foot_pos, self.foot_vel)
            if self._switch and self.att.initialized:
                # lift-off: the stance velocity carries the leg kinematics' slow errors
                # (the ground gives as the load goes) into the flight
                self.com.add_impulse(0.0, 0.0, 0.0, self._liftoff_var, t)
        elif closed:
            self._switch_on_ns = t
        self._switch = reading
        if self._pending is not None:
            self._step_com()
        if closed and not self.contact and self.att.initialized:
            # the impact map applies at once, taken back if the debounce refuses the contact
            self._impact = self._touchdown_impulse()
        if reading == self.contact:
            self._contact_run = 0
            if self._impact is not None:  # the switch reopened before the contact was confirmed
                dvx, dvy, dvz = self._impact
                self.com.add_impulse(-dvx, -dvy, -dvz, 0.0, self._switch_on_ns)
                self._impact = None
                self._count("contact_bounces")
        else:
            self._contact_run += 1
            needed = self.params.contact_off_samples if self.contact else self.params.contact_on_samples
            if self._contact_run >= needed:
                self._contact_run = 0
                self.contact = reading
                if self.contact and self._impact is not None:
                    self._impact = None
                    self._count("touchdowns")
                if self.contact and self._odometry and self.att.initialized:
                    self._anchor()

    def _leg_velocity(self, s: float, sd: float, rolling: bool) -> tuple[float, float, float]:
        """CoM velocity [m/s, world] relative to the foot sphere's contact point
        (``rolling``) or to the sphere's centre, from attitude, body rate and the foot."""
        r = self._rot
        wx, wy, wz = self.att.omega
        k = self._mu_sprung
        bx, by, bz = self._r_cf0
        bz -= k * s
        # CoM - sphere centre in world, plus the sphere radius up to the contact point
        lx = r[0] * bx + r[1] * by + r[2] * bz
        ly = r[3] * bx + r[4] * by + r[5] * bz
        lz = r[6] * bx + r[7] * by + r[8] * bz
        if rolling:
            lz += self._foot_radius
        ox = r[0] * wx + r[1] * wy + r[2] * wz
        oy = r[3] * wx + r[4] * wy + r[5] * wz
        oz = r[6] * wx + r[7] * wy + r[8] * wz
        d = -k * sd  # d/dt of the body-z offset
        return (
            oy * lz - oz * ly + r[2] * d,
            oz * lx - ox * lz + r[5] * d,
            ox * ly - oy * lx + r[8] * d,
        )

    def _touchdown_impulse(self) -> tuple[float, float, float]:
        """Impact map: the ground stops the foot, the CoM loses the foot's share of momentum.
        Applies the velocity jump at the switch closure and returns it [m/s, world]."""
        # the foot's motion relative to the body just before it hit (now the spring is compressing)
        rx, ry, rz = self._leg_velocity(*self._free_foot, rolling=False)
        vx, vy, vz = self.com.velocity
        m = self._mu_foot
        # foot velocity = CoM velocity - (CoM relative to the foot)'
        dv = (-m * (vx - rx), -m * (vy - ry), -m * (vz - rz))
        self.com.add_impulse(dv[0], dv[1], dv[2], self._impact_var, self._switch_on_ns)
        return dv

    # --- pose -------------------------------------------------------------------------

    def update_pose(self, msg: PoseMeasurement, arrival_ns: int | None = None) -> bool:
        """Fuse a pose captured at ``msg.stamp_ns`` (torso origin [m, world], attitude).

        The position is gated against the state at the capture time first: a refused pose
        is not used at all (its attitude neither) and does not move the order check, so a
        stream of outliers cannot push the real poses out as out of order."""
        if self._odometry:
            return self._reject("pose_not_used")  # the odometry frame is not the pose sensor's
        t = msg.stamp_ns
        pos, q = msg.position, msg.quat
        px, py, pz = float(pos[0]), float(pos[1]), float(pos[2])
        qw, qx, qy, qz = float(q[0]), float(q[1]), float(q[2]), float(q[3])
        n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        if not (math.isfinite(px + py + pz) and math.isfinite(n)):  # a NaN or inf spreads to the sum
            return self._reject("pose_nonfinite")
        if abs(n - 1.0) > QUAT_NORM_TOL:
            return self._reject("pose_bad_quat")
        refused = self._stamp_refused("pose", t, arrival_ns)
        if refused:
            return self._reject(refused)
        if self._t_imu < 0:
            return self._reject("pose_before_imu")
        if t <= self._t_pose:
            return self._reject("pose_out_of_order")
        if t > self._t_imu + int(self.params.pose_future_tolerance_s * NS):
            return self._reject("pose_future")
        if self._imu_gap[0] < t < self._imu_gap[1]:
            # neither the attitude nor the CoM at that time is known well enough to compare
            return self._reject("pose_in_imu_gap")
        qm = (qw / n, qx / n, qy / n, qz / n)
        if self._pending is not None:
            self._step_com()
        r0, r1, r2 = quat.to_matrix(qm)
        rot = r0 + r1 + r2
        if not self.com.admits_pose(t, (px, py, pz), rot, self._pose_pos_var):
            return False  # counted by the CoM filter as an outlier
        if self.params.compensate_latency:
            fused = self.att.correct_pose(qm, t, self._pose_att_var, self._gate3)
        else:  # as if captured now
            fused = self.att.correct_pose(qm, self._t_imu, self._pose_att_var, self._gate3)
        if fused is None:
            return self._reject("pose_stale")
        self._t_pose = t
        if fused:
            self._t_pose_fused = t
        else:
            self._reject("att_outliers")
        self.com.add_pose(t, (px, py, pz), rot, self._pose_pos_var)
        return True

    # --- output -------------------------------------------------------------------------

    @property
    def has_imu(self) -> bool:
        """Whether any IMU sample arrived: before that there is no state to publish."""
        return self._t_imu >= 0

    def estimate(self, now_ns: int) -> StateEstimate:
        """The state at ``now_ns``, predicted from the newest IMU sample (its covariance grown
        by the time since); ``stamp_ns`` says the time it is valid at."""
        if self._pending is not None:
            self._step_com()
        t_imu = self._t_imu
        lag_ns = max(now_ns - t_imu, 0) if t_imu >= 0 else 0
        tau = lag_ns / NS
        com = self.com
        px, py, pz = com.position
        vx, vy, vz = com.velocity
        ax, ay, az = self._accel
        if tau > 0.0:
            k = self._speed_limit(vx, vy, vz, ax, ay, az, tau)
            ax, ay, az = k * ax, k * ay, k * az
        h = 0.5 * tau * tau
        att = self.att
        q = att.q
        wx, wy, wz = att.omega
        if tau > 0.0:
            px += vx * tau + ax * h
            py += vy * tau + ay * h
            pz += vz * tau + az * h
            vx += ax * tau
            vy += ay * tau
            vz += az * tau
            q = quat.mul(q, quat.exp((wx * tau, wy * tau, wz * tau)))
        ppp, ppv, pvv = com.output_p2(tau)
        av = att.body_variances()
        bias_var = max(att.bias_variances())
        rate_var = self._gyro_sample_var + bias_var
        if tau > 0.0:
            # the phase over the gap is known only while joint frames show the switch open throughout
            flight = not (self._gap_contact or self._switch) and now_ns - self._t_joints <= self._period_ns
            gpp, gpv, gvv = self._gap_cov(tau, not flight)
            ppp, ppv, pvv = ppp + gpp, ppv + gpv, pvv + gvv
            av = att.body_variances(q, att.predicted_variances(tau, 0.25 * self._gap_alpha_var * tau ** 4))
            rate_var += self._gap_alpha_var * tau * tau
        z = 0.0
        cov = [
            ppp, z, z, ppv, z, z,
            z, ppp, z, z, ppv, z,
            z, z, ppp, z, z, ppv,
            ppv, z, z, pvv, z, z,
            z, ppv, z, z, pvv, z,
            z, z, ppv, z, z, pvv,
        ]
        converged = max(self._t_pose_fused, com.last_fused_stamp) >= 0 or self._anchored
        attitude_valid = converged and max(av) <= self._valid_att_var and rate_var <= self._valid_rate_var
        # odometry: the position is the drifting frame's by definition; its covariance is published as it grows
        valid = attitude_valid and (self._odometry or ppp <= self._valid_pos_var) and pvv <= self._valid_vel_var
        return StateEstimate(
            stamp_ns=t_imu + lag_ns,
            position=[px, py, pz],
            velocity=[vx, vy, vz],
            quat=list(q),
            omega=[wx, wy, wz],
            wheel_vel=list(self.wheel_vel),
            foot_pos=self.foot_pos,
            foot_vel=self.foot_vel,
            contact=self.contact,
            phase="stance" if self.contact else "flight",
            pos_vel_cov=cov,
            att_cov=list(av),
            valid=valid,
            attitude_valid=attitude_valid,
        )

    def status(self) -> dict[str, float | str]:
        """Health figures: ``mode``, pose age [s], standard deviations, gyro bias [rad/s]."""
        t = self._t_imu
        fused = max(self._t_pose_fused, self.com.last_fused_stamp)
        if self._odometry:
            mode = "odometry" if self._anchored else "init"
            pose_age = math.inf
        elif fused < 0:
            mode = "init"
            pose_age = math.inf
        else:
            pose_age = (t - fused) / NS
            mode = "pose_outage" if pose_age > self.params.pose_timeout_s else "ok"
        ppp, _, pvv = self.com.output_p2()
        bx, by, bz = self.att.bias
        return {
            "mode": mode,
            "pose_age_s": pose_age,
            "pos_std_m": math.sqrt(ppp),
            "vel_std_m_s": math.sqrt(pvv),
            "att_std_rad": math.sqrt(max(self.att.variances())),
            "gyro_bias_rad_s": math.sqrt(bx * bx + by * by + bz * bz),
        }

    @property
    def rejected_total(self) -> int:
        """How many inputs were refused so far, all reasons together (cheap: for change detection)."""
        c = self.com.counters
        return self._rejected + c["pose_outliers"] + c["leg_outliers"]

    def rejections(self) -> dict[str, int]:
        """Refused inputs by reason: malformed, future or past stamps, out of order or range,
        gated outliers (pose, attitude, gravity, leg kinematics)."""
        out = dict(self._rejections)
        c = self.com.counters
        out["pose_outliers"] = c["pose_outliers"]
        out["leg_outliers"] = c["leg_outliers"]
        return out

    @property
    def counters(self) -> dict[str, int]:
        """Rejections by reason, gated outliers, fused measurements, touchdowns (a copy)."""
        out = dict(self._counters)
        out.update(self._rejections)
        out.update(self.com.counters)
        return out
