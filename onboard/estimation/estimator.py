"""State estimation: CoM position and velocity, attitude and rates, wheels, foot, contact.

Pure and synchronous (no clock read, no I/O): the ``estimator`` service and the
lockstep runner drive the same class with messages and their stamps.

Usage (lockstep or service)::

    est = StateEstimator(EstimatorParams(), robot_params("indoor"))
    est.update_imu(imu, t_arrival)        # ImuSample, 1 kHz: propagates attitude and CoM
    est.update_joints(joints, t_arrival)  # JointSensors, 1 kHz: wheels, foot, contact, leg kinematics
    est.update_pose(pose, t_arrival)      # PoseMeasurement, whenever one arrives (stamp = capture time)
    est.update_visual_odometry(vo, t)     # VisualOdometryDelta (odometry): the CoM's displacement between two frames
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
from typing import cast

from scipy.stats import chi2

from onboard.geometry import quaternion as quat
from onboard.estimation.attitude_filter import AttitudeFilter
from onboard.estimation.com_filter import ComFilter, make_com_filter
from onboard.estimation.contact import FootContact
from onboard.estimation.imu_gaps import GapModel
from onboard.estimation.input_gate import ATTITUDE_HISTORY_S, NS, QUAT_NORM_TOL, InputGate, check_params
from onboard.estimation.leg_model import FOOT_EXTENDED_M, LegModel, RobotGeometry
from onboard.estimation.position_sources import MocapPoses, Odometry
from onboard.contracts.messages import ImuSample, JointSensors, PoseMeasurement, StateEstimate, VisualOdometryDelta
from onboard.contracts.params import EstimatorParams


class StateEstimator:
    """The estimator; see the module docstring for the interface and the model."""

    def __init__(self, params: EstimatorParams, robot: RobotGeometry) -> None:
        check_params(params)
        self.params = params
        p = params
        self._g = robot.gravity
        self.leg = LegModel(robot)
        self._mu_sprung = self.leg.mu_sprung
        self._accel_sensed = True  # False once a sample says it carries no accelerometer
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
            com_offset_body=self.leg.com_offset,
            com_per_compression=(0.0, 0.0, self.leg.mu_foot),
            reacquire_s=p.pose_reacquire_s,
        )
        self._leg_var = p.leg_vel_std_m_s ** 2
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
        self._gaps = GapModel(p)
        self._gyro_sample_var = p.gyro_noise_density ** 2 * p.imu_rate_hz  # one sample's white noise
        self._gate = InputGate(p)  # refusals by reason, events
        # inputs
        self._t_imu = -1
        self._t_joints = -1
        self._accel = (0.0, 0.0, 0.0)  # CoM acceleration at the newest sample [m/s^2, world]
        self._sf_prev = (0.0, 0.0, 0.0)  # specific force at the previous sample [m/s^2, world]
        self._pending: tuple[int, float, float, float, float] | None = None  # IMU interval not yet integrated
        self._rot = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)  # R at the newest sample, row-major
        self._static_since = -1
        self.wheel_vel = (0.0, 0.0, 0.0)
        self.foot_pos = 0.0
        self.foot_vel = 0.0
        self._contact = FootContact(p, self.leg, self.com, self._gate)  # with hysteresis
        self._foot_sensed = True  # False: contact from the specific force (no foot sensor)
        self._gap_contact = False  # a contact reading since the newest IMU interval was integrated
        self._imu_gap = (0, 0)  # the newest interval of more than two IMU periods [ns]
        # where position and absolute attitude come from (onboard.estimation.position_sources)
        self._odometry = p.position_source == "odometry"
        self.mocap = MocapPoses(p, self._gate, self._gate3)
        self.odometry = Odometry(p, self._gate, self._gate3, self._gate2)
        self._vo_record = self._odometry and p.visual_odometry  # keep the odometry's positions for late VO
        # a displacement is as late as the camera's chain (frame pairs, drawing, matching): it may be as old
        # as the odometry kept to compare it with, not only input_max_age_s
        self._vo_max_age_ns = int(p.vo_history_s * NS)

    # --- input ------------------------------------------------------------------

    def feed(self, topic: str, msg: object, arrival_ns: int | None = None) -> bool:
        """A sensor message by its topic (``imu``, ``joints``, ``pose``): the update it takes.
        Another topic is not a sensor of the estimator's: False, nothing counted."""
        if topic == "imu":
            return self.update_imu(cast(ImuSample, msg), arrival_ns)
        if topic == "joints":
            return self.update_joints(cast(JointSensors, msg), arrival_ns)
        if topic == "pose":
            return self.update_pose(cast(PoseMeasurement, msg), arrival_ns)
        if topic == "visual_odometry":
            return self.update_visual_odometry(cast(VisualOdometryDelta, msg), arrival_ns)
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
            return self._gate.reject("imu_nonfinite")
        refused = self._gate.stamp_refused("imu", t, arrival_ns)  # first: a wrong clock, named as one
        if refused:
            return self._gate.reject(refused)
        if t <= self._t_imu:
            return self._gate.reject("imu_out_of_order")
        p = self.params
        wr = gx * gx + gy * gy + gz * gz
        fn2 = fx * fx + fy * fy + fz * fz
        if wr > self._gyro_range2 or fn2 > self._accel_range2:
            return self._gate.reject("imu_out_of_range")
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
        att.propagate(t, gx, gy, gz, dt, self._gaps.attitude_var(gap) if gap > 0.0 else 0.0)
        # gravity as the direction of up, only after a quasi-static spell
        wx, wy, wz = att.omega
        if sensed and abs(math.sqrt(fn2) - self._g) < p.static_accel_tol_m_s2 and wx * wx + wy * wy + wz * wz < self._static_gyro2:
            if self._static_since < 0:
                self._static_since = t
            elif t - self._static_since >= self._static_hold_ns:
                if not att.correct_gravity(fx, fy, fz, self._tilt_var, self._gate2):
                    self._gate.reject("gravity_outliers")
        else:
            self._static_since = -1
        if self._odometry:
            self.odometry.imu_attitude(att, msg.quat, t)
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
            reading = f > p.accel_contact_on_m_s2 or (self._contact.switch and f > p.accel_contact_off_m_s2)
            self._contact_reading(reading, t)
        return True

    def _modelled_specific_force(self) -> float:
        """The specific force along the leg [m/s^2, body z] with no accelerometer: the spring's
        push in stance (the raw switch, as the CoM step picks its dynamics), free fall in flight."""
        if not self._contact.switch:
            return 0.0
        return self.leg.spring_specific_force(self.foot_pos, self.foot_vel)

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
        gap_cov = self._gaps.com_cov(gap, self._gap_contact or self._contact.switch) if gap > 0.0 else None
        self._gap_contact = self._contact.switch
        px, py, pz = self._sf_prev
        self._sf_prev = (sx, sy, sz)
        g = self._g
        stance = self._contact.switch and (self.foot_pos > FOOT_EXTENDED_M or not self._foot_sensed)
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
            k = self._gaps.speed_limit(vx, vy, vz, ax, ay, az, dt)
            ax, ay, az = k * ax, k * ay, k * az
        self.com.push(t, dt, ax, ay, az, stance, self.foot_pos, gap_cov)
        if self._vo_record:
            self.odometry.record(t, self.com)

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
            return self._gate.reject("joints_nonfinite")
        if t <= self._t_joints:
            return self._gate.reject("joints_out_of_order")
        refused = self._gate.stamp_refused("joints", t, arrival_ns)
        if refused:
            return self._gate.reject(refused)
        if not self.leg.in_range(s):
            return self._gate.reject("joints_out_of_range")
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
        if (self._contact.contact and msg.foot_contact and t - self._contact.switch_on_ns >= self._leg_settle_ns and self.att.initialized
                and t - self._t_imu <= self._period_ns):
            # not while the foot still bounces off the ground after the impact, nor while
            # lift-off is being debounced: in both the foot is not pinned; nor in an IMU gap,
            # where attitude and rate are predictions and the CoM filter has no sample at t
            omega = self.att.omega
            vx, vy, vz = self.leg.velocity(self._rot, omega, s, sd, True)
            # the attitude's own uncertainty turns the lever arm
            lever = self.leg.lever_rate2(omega, sd)
            self.com.add_leg_velocity(vx, vy, vz, self._leg_var + lever * max(self.att.variances()))
        return True

    def _contact_reading(self, reading: bool, t: int) -> None:
        """One contact reading at ``t``: raw switch, the CoM step it ends, impact map, debounced contact."""
        closed = self._contact.switch_reading(reading, t, self.foot_pos, self.foot_vel, self.att.initialized)
        if self._pending is not None:
            self._step_com()
        if self._contact.debounce(reading, closed, self._rot, self.att) and self._odometry and self.att.initialized:
            self.odometry.anchor(self.com, self.leg.com_from_contact(self._rot, self.foot_pos))

    # --- pose -------------------------------------------------------------------------

    def update_pose(self, msg: PoseMeasurement, arrival_ns: int | None = None) -> bool:
        """Fuse a pose captured at ``msg.stamp_ns`` (torso origin [m, world], attitude).

        The position is gated against the state at the capture time first: a refused pose
        is not used at all (its attitude neither) and does not move the order check, so a
        stream of outliers cannot push the real poses out as out of order."""
        if self._odometry:
            return self._gate.reject("pose_not_used")  # the odometry frame is not the pose sensor's
        pose = self.mocap.accept(msg, arrival_ns, self._t_imu, self._imu_gap)
        if pose is None:
            return False  # refused, counted by reason
        if self._pending is not None:
            self._step_com()
        return self.mocap.fuse(pose, self._t_imu, self.att, self.com)

    # --- visual odometry --------------------------------------------------------------

    def update_visual_odometry(self, msg: VisualOdometryDelta, arrival_ns: int | None = None) -> bool:
        """Fuse the CoM's displacement between two camera frames (``position_source = "odometry"``
        with ``visual_odometry``): compared with the odometry's own between the frames' stamps,
        whenever it arrives within ``vo_history_s`` of them."""
        if not self._odometry:
            return self._gate.reject("vo_not_odometry")  # the pose sensor's frame is absolute
        refused = self._gate.stamp_refused("vo", msg.stamp_ns, arrival_ns, self._vo_max_age_ns)
        if refused:
            return self._gate.reject(refused)
        if self._pending is not None:
            self._step_com()
        return self.odometry.fuse_displacement(msg, self.com)

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
            k = self._gaps.speed_limit(vx, vy, vz, ax, ay, az, tau)
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
            flight = not (self._gap_contact or self._contact.switch) and now_ns - self._t_joints <= self._period_ns
            gpp, gpv, gvv = self._gaps.com_cov(tau, not flight)
            ppp, ppv, pvv = ppp + gpp, ppv + gpv, pvv + gvv
            av = att.body_variances(q, att.predicted_variances(tau, self._gaps.attitude_var(tau)))
            rate_var += self._gaps.rate_var(tau)
        z = 0.0
        cov = [
            ppp, z, z, ppv, z, z,
            z, ppp, z, z, ppv, z,
            z, z, ppp, z, z, ppv,
            ppv, z, z, pvv, z, z,
            z, ppv, z, z, pvv, z,
            z, z, ppv, z, z, pvv,
        ]
        converged = max(self.mocap.t_fused, com.last_fused_stamp) >= 0 or self.odometry.anchored
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
            contact=self._contact.contact,
            phase="stance" if self._contact.contact else "flight",
            pos_vel_cov=cov,
            att_cov=list(av),
            valid=valid,
            attitude_valid=attitude_valid,
        )

    def status(self) -> dict[str, float | str]:
        """Health figures: ``mode``, pose age [s], standard deviations, gyro bias [rad/s]."""
        t = self._t_imu
        fused = max(self.mocap.t_fused, self.com.last_fused_stamp)
        if self._odometry:
            mode = "odometry" if self.odometry.anchored else "init"
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
        return self._gate.rejected + c["pose_outliers"] + c["leg_outliers"]

    def rejections(self) -> dict[str, int]:
        """Refused inputs by reason: malformed, future or past stamps, out of order or range,
        gated outliers (pose, attitude, gravity, leg kinematics)."""
        out = dict(self._gate.rejections)
        c = self.com.counters
        out["pose_outliers"] = c["pose_outliers"]
        out["leg_outliers"] = c["leg_outliers"]
        return out

    @property
    def counters(self) -> dict[str, int]:
        """Rejections by reason, gated outliers, fused measurements, touchdowns (a copy)."""
        out = dict(self._gate.counters)
        out.update(self._gate.rejections)
        out.update(self.com.counters)
        return out
