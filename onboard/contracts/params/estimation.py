"""Parameters of the estimation layer (``onboard.estimation``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Literal

from msgspec import Meta


from onboard.contracts.params.base import Cpu, LOOP_HZ_MAX, Name, RtPriority, _Section, above, within


@dataclass(frozen=True)
class EstimatorParams(_Section, section="estimator"):
    """The state estimator (:mod:`onboard.estimation.estimator`) and its ``estimator`` service.

    Noise figures are the filter's model of its sensors (tune them to the hardware's
    datasheets or to the twin's sensor configuration); densities are per square root
    of a hertz so they do not depend on the sample rate.
    """

    rate_hz: Annotated[float, within(1.0, LOOP_HZ_MAX)] = 1000.0  # [Hz] state estimate publication rate
    # the control loop's input: scheduled above the twin / hardware exchange (70), below control (80)
    rt_priority: RtPriority = 75  # SCHED_FIFO priority of the estimator's loop thread (0: leave the scheduler alone)
    cpu: Cpu = -1  # CPU the loop thread is pinned to (-1: no pinning)
    robot: Name = "indoor"  # MJCF variant the robot's parameters are read from (robot_description/models)
    # archer identify's file (robot_description/identified.py): the CoM where the robot's own was measured; "": the MJCF's
    identified: str = ""
    input_queue: Annotated[int, within(1, 65536)] = 256  # sensor messages of each input topic buffered between two ticks (Zenoh ring buffer); the oldest dropped beyond
    # Pose sensor (motion capture / tracking camera), fused with its latency compensated.
    pose_delay_s: Annotated[float, within(0.0, 0.25)] = 0.025  # [s] fusion horizon: covers the pose sensor's latency (0.25 s attitude history)
    compensate_latency: bool = True  # False: fuse each pose as if it were current
    pose_pos_std_m: Annotated[float, above(0.0, 1.0)] = 0.002  # [m] position noise per axis
    pose_att_std_rad: Annotated[float, above(0.0, 1.0)] = 0.01  # [rad] attitude noise per axis
    pose_timeout_s: Annotated[float, above(0.0, 10.0)] = 0.1  # [s] no pose for this long: status reports an outage
    pose_future_tolerance_s: Annotated[float, within(0.0, 0.1)] = 0.002  # [s] pose stamped later than the last IMU sample
    # Mahalanobis gating of pose and leg-kinematics measurements. No reset after a run of
    # refusals: the covariance grows while nothing is fused, and the gate alone decides.
    gate_probability: Annotated[float, Meta(gt=0.0, lt=1.0)] = 0.9995  # chi-square acceptance probability
    pose_reacquire_s: Annotated[float, above(0.0, 10.0)] = 0.1  # [s] every pose gated this long: the state is lost, take the poses back (its covariance inflated)
    # CoM process model: white acceleration noise around projectile / stance dynamics.
    accel_psd_flight: Annotated[float, above(0.0, 1e3)] = 0.003  # [(m/s^2)^2/Hz] flight: what projectile dynamics leave out (drag)
    accel_psd_stance: Annotated[float, above(0.0, 1e3)] = 2.0  # [(m/s^2)^2/Hz] stance (accelerometer-driven)
    # stance without an accelerometer (ImuSample.accel_sensed False, e.g. ARCHER's own firmware): the
    # specific force is modelled as the spring's push along the leg; what that leaves out (the leg's
    # sideways constraint forces, cable tension left after the release, spring model error) is this.
    # Measured on the twin behind the emulated boards (hop in place, 14 stances): the model's error
    # integrated over each stance is an equivalent 0.05 along the leg and 0.004 sideways; twice the
    # accelerometer's figure leaves room for tilted stances and keeps the estimate valid through the
    # pose horizon (4 x 0.025 s of stance adds 0.32 m/s of velocity std, under valid_vel_std_m_s)
    accel_psd_stance_modelled: Annotated[float, above(0.0, 1e3)] = 4.0  # [(m/s^2)^2/Hz]
    leg_vel_std_m_s: Annotated[float, above(0.0, 10.0)] = 0.03  # [m/s] stance CoM velocity from leg kinematics
    leg_settle_s: Annotated[float, within(0.0, 0.1)] = 0.006  # [s] after touchdown the foot bounces off the ground this long
    accel_delay_s: Annotated[float, within(0.0, 0.005)] = 0.0005  # [s] accelerometer samples describe this long before their
    # stamp (the twin's MuJoCo accelerometer reads the state one 0.5 ms physics step back;
    # on hardware: the IMU's filter group delay), at most half a sample
    impact_vel_std_m_s: Annotated[float, within(0.0, 10.0)] = 0.1  # [m/s] CoM velocity uncertainty added at touchdown
    liftoff_vel_std_m_s: Annotated[float, within(0.0, 10.0)] = 0.02  # [m/s] ... and at lift-off (stance model errors carried into flight)
    # Attitude: gyro propagation with bias, pose and gravity corrections.
    gyro_noise_density: Annotated[float, above(0.0, 1.0)] = 0.003  # [rad/s/sqrt(Hz)]
    gyro_bias_walk: Annotated[float, within(0.0, 1.0)] = 1e-4  # [rad/s^2/sqrt(Hz)] bias random walk
    tilt_std_rad: Annotated[float, above(0.0, 1.0)] = 0.03  # [rad] accelerometer gravity direction, when quasi-static
    static_accel_tol_m_s2: Annotated[float, within(0.0, 10.0)] = 0.3  # [m/s^2] | |accel| - g | below this: quasi-static
    static_gyro_max_rad_s: Annotated[float, within(0.0, 10.0)] = 0.2  # [rad/s] body rate below this: quasi-static
    static_hold_s: Annotated[float, within(0.0, 60.0)] = 0.2  # [s] quasi-static this long before gravity is trusted
    # Initial uncertainty (before the first pose).
    init_pos_std_m: Annotated[float, above(0.0, 1e3)] = 10.0
    init_vel_std_m_s: Annotated[float, above(0.0, 100.0)] = 2.0
    init_att_std_rad: Annotated[float, above(0.0, math.pi)] = 1.0
    init_bias_std_rad_s: Annotated[float, above(0.0, 1.0)] = 0.02
    # Contact and phase: switch debounce (hysteresis in time).
    contact_on_samples: Annotated[int, within(1, 1000)] = 2  # consecutive contact readings to enter stance
    contact_off_samples: Annotated[int, within(1, 1000)] = 3  # consecutive no-contact readings to enter flight
    accel_contact_on_m_s2: Annotated[float, above(0.0, 160.0)] = 15.0  # [m/s^2] no foot sensor: specific force reading contact
    accel_contact_off_m_s2: Annotated[float, above(0.0, 160.0)] = 4.0  # [m/s^2] ... and no longer contact
    # IMU gaps: an interval longer than one IMU period, or an estimate past the newest sample,
    # carries what the IMU did not see. Measured on the twin (hop-in-place, hold-last-value
    # prediction over 5-200 ms, 99th percentile / 2.6): the stance CoM acceleration changes by
    # 15-26 m/s^2; in flight projectile dynamics stay exact. The wheels' peak torque over the
    # body's inertia bounds the angular acceleration (1.5 N m / 0.105 kg m^2 = 14 rad/s^2).
    imu_rate_hz: Annotated[float, within(1.0, LOOP_HZ_MAX)] = 1000.0  # [Hz] nominal IMU rate: a longer interval is a gap
    gap_accel_std_m_s2: Annotated[float, above(0.0, 1e3)] = 25.0  # [m/s^2] unseen CoM acceleration in an IMU gap (stance or unknown phase)
    gap_angular_accel_std_rad_s2: Annotated[float, above(0.0, 1e3)] = 10.0  # [rad/s^2] unseen body angular acceleration in an IMU gap
    max_speed_m_s: Annotated[float, above(0.0, 100.0)] = 4.0  # [m/s] the CoM's speed never exceeds this: caps the velocity uncertainty
    # Input sanity: stamps against the arrival time the caller passes (see StateEstimator).
    gyro_range_rad_s: Annotated[float, above(0.0, 1e3)] = 35.0  # [rad/s] beyond the gyro's range: rejected
    accel_range_m_s2: Annotated[float, above(0.0, 1e4)] = 160.0  # [m/s^2] beyond the accelerometer's range: rejected
    input_future_tolerance_s: Annotated[float, within(0.0, 1.0)] = 0.005  # [s] a sample stamped later than its arrival plus this: refused
    input_max_age_s: Annotated[float, above(0.0, 60.0)] = 0.5  # [s] a sample stamped earlier than its arrival minus this: refused
    # Validity: from the covariance (the standard deviations it implies), not from timers.
    valid_pos_std_m: Annotated[float, above(0.0, 10.0)] = 0.05  # [m] position std above this: estimate not valid
    valid_vel_std_m_s: Annotated[float, above(0.0, 100.0)] = 0.5  # [m/s] velocity std above this: estimate not valid
    valid_att_std_rad: Annotated[float, above(0.0, math.pi)] = 0.05  # [rad] attitude std above this: estimate not valid
    valid_rate_std_rad_s: Annotated[float, above(0.0, 100.0)] = 0.5  # [rad/s] body rate std above this: estimate not valid
    kf_backend: Literal["lean", "filterpy"] = "lean"  # CoM filter arithmetic: "lean" (floats) or "filterpy" (reference)
    # No motion capture (outdoors, thesis 8.2): "odometry" never waits for a pose. The frame is the
    # odometry frame, its origin the foot's first touchdown point; from there the CoM follows the IMU
    # and leg kinematics (the foot pinned in stance), and its position drifts: the published position
    # covariance grows honestly and validity no longer asks for a small one (obstacles are seen
    # relative to the robot, in the same frame). The attitude takes the IMU's own (AHRS) orientation
    # instead of the pose's.
    position_source: Literal["pose", "odometry"] = "pose"
    imu_att_std_rad: Annotated[float, above(0.0, 1.0)] = 0.02  # [rad] the IMU's own orientation per axis (odometry)
    imu_att_every: Annotated[int, within(1, 1000)] = 10  # fuse every n-th IMU orientation (odometry)
    anchor_std_m: Annotated[float, above(0.0, 1.0)] = 0.01  # [m] the odometry origin at the first touchdown
    odometry_flat_ground: bool = True  # every touchdown is at the first one's ground height (no steps or ramps)
    # hot standby (services/estimator.py): a primary on this host whose estimates stopped this long while ours are
    # valid and our inputs flow (a hang: its token outlives it by the link's lease) is killed, so that the standby
    # takes over [s]; 0: never. Above the worst stall of a loaded machine (a false fence costs a takeover and a
    # restart), so over ControlParams.estimate_fault_disarm_s: control disarms first (a hang still drops the robot)
    standby_fence_s: Annotated[float, within(0.0, 1.0)] = 0.25
    # Visual odometry (position_source = "odometry"): the D435's apex frames, frame to frame
    # (onboard.perception.visual_odometry), give the CoM's horizontal displacement between two apexes;
    # the odometry fuses it with its own displacement over the same stamps by inverse variance. On by
    # measurement (eb5acf8): forest and sidewalk, seeds 0-19, outdoor, onboard sensing: drift per metre p50
    # 0.0108 -> 0.0045 and 0.0112 -> 0.0047, success 15 -> 20 and 14 -> 20 of 20 (the misses were the drift)
    visual_odometry: bool = True
    vo_features: Annotated[int, within(50, 10_000)] = 1000  # ORB keypoints per frame
    vo_min_inliers: Annotated[int, within(6, 10_000)] = 25  # PnP inliers below this: the pair is refused
    vo_reprojection_px: Annotated[float, above(0.0, 20.0)] = 2.0  # [px] RANSAC inlier threshold
    vo_ransac_iterations: Annotated[int, within(10, 10_000)] = 300
    vo_ratio: Annotated[float, Meta(gt=0.0, le=1.0)] = 0.8  # Lowe's ratio test on the two nearest descriptors
    vo_min_depth_m: Annotated[float, within(0.0, 10.0)] = 0.3  # [m] 3D points from the first frame's depth in this range
    vo_max_depth_m: Annotated[float, above(0.0, 20.0)] = 4.0
    vo_min_spread: Annotated[float, within(0.0, 1.0)] = 0.05  # inliers' bounding box below this share of the image: bad geometry
    vo_max_rotation_error_rad: Annotated[float, above(0.0, 3.2)] = 0.1  # the frames' rotation vs the attitude's
    vo_max_speed_m_s: Annotated[float, above(0.0, 50.0)] = 3.0  # a displacement faster than this between two frames is refused
    vo_max_interval_s: Annotated[float, above(0.0, 10.0)] = 1.0  # [s] frames further apart are not a pair
    vo_max_std_m: Annotated[float, above(0.0, 10.0)] = 0.05  # [m] a displacement less certain than this is refused
    # The residuals' covariance times this. Measured in lockstep (archer sim --sensing onboard with visual_odometry:
    # the report's visual_odometry.nees_xy_mean, each pair's error against the true CoM displacement normalized by
    # its covariance, 2 when honest): unscaled 4.3-7.3 over forest and sidewalk seeds 0-1 (30 s), 1.7-2.5 with 3
    vo_cov_scale: Annotated[float, above(0.0, 1e6)] = 3.0
    vo_history_s: Annotated[float, above(0.0, 10.0)] = 1.5  # [s] odometry positions kept to meet a late displacement's stamps
    # [m] per axis: the leg odometry's own error in the CoM's displacement from one apex to the next. Measured the
    # same way (visual_odometry.estimate_error_axis_std_m with the VO not fused): 1.6-2.2 mm. The filter's own
    # position covariance grows by ~7.6 mm a hop (final_pos_std_m 0.127 m after 276 hops, sidewalk seed 0): ~4x
    # that (it is isotropic and holds the unobserved vertical too), so the fusion uses the measured figure
    vo_leg_std_m: Annotated[float, above(0.0, 1.0)] = 0.002
