"""The one place for limits and tunable parameters.

The robot's physical parameters (masses, inertias, spring, travel) live in the MJCF
model ``sim_twin/models/archer.xml`` and nowhere else. What is here is what an
engineer tunes or what safety depends on. Each layer owns one frozen dataclass; a
config file (TOML, see :mod:`services.config`) overrides fields by section name,
and :func:`with_overrides` validates every override.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class SafetyLimits:
    """Limits every torque command passes through before it can reach a motor."""

    wheel_torque_max: float = 1.5  # [N m] per wheel, KV115 on 50.8 V, thesis lines 170-190
    foot_torque_max: float = 10.0  # [N m] foot cable motor after the 3:1 gearbox
    wheel_speed_max: float = 600.0  # [rad/s] beyond this the motor has no torque left
    tilt_max: float = math.radians(45.0)  # [rad] body z from vertical: a fall
    command_stale_s: float = 0.010  # [s] hardware/twin zero torque when no newer command
    estimate_stale_s: float = 0.005  # [s] control disarms on an older estimate
    reference_stale_s: float = 0.5  # [s] control falls back to hopping in place
    heartbeat_timeout_s: float = 0.100  # [s] Teensy / drive heartbeat consumer bound


@dataclass(frozen=True)
class MessagingParams:
    endpoint: str = "tcp/127.0.0.1:7447"  # the well-known local router endpoint
    status_period_s: float = 0.5  # how often a service refreshes its rate figures
    # Batches per link queue for the real_time and interactive_high priorities. An express
    # message takes a batch of its own, so Zenoh's default of 2 (and 1 ms wait) drops 1 kHz
    # samples whenever a receiver is ~3 ms late; 16 rides out a 16 ms stall, costs memory
    # only while a receiver lags, and latest-value readers skip what queued.
    link_queue_batches: int = 16


@dataclass(frozen=True)
class HardwareParams:
    """The ``hardware`` service and its drivers (ELMO drives over CAN, Teensy over serial).

    Joint order everywhere: wheel 0, wheel 1, wheel 2, foot. Per-joint tuples are
    drive settings (motor torque constant, current clamp) of the real robot; the
    emulators use the same values. Gear ratios come from the MJCF model.
    """

    backend: str = "can"  # "can": ELMO drives over CANopen; "teensy": framed serial
    rate_hz: float = 1000.0  # exchange rate with the drives / the Teensy [Hz]
    rt_priority: int = 70  # SCHED_FIFO priority of the exchange thread, below control (0: leave the scheduler alone)
    cpu: int = -1  # CPU the exchange thread is pinned to (-1: no pinning)
    # CAN (python-can arguments; the emulator prints them)
    can_interface: str = "socketcand"
    can_channel: str = "can0"
    can_host: str = "127.0.0.1"  # socketcand only
    can_port: int = 29536  # socketcand only
    can_bitrate: int = 1_000_000  # [bit/s]
    node_ids: tuple[int, ...] = (1, 2, 3, 4)  # CANopen node of each joint
    host_node_id: int = 127  # the host's heartbeat identifier 0x700 + id
    host_heartbeat_period_s: float = 0.025  # drives fault after SafetyLimits.heartbeat_timeout_s
    drive_heartbeat_period_s: float = 0.050  # drive heartbeat producer time (0x1017)
    position_every: int = 10  # position PDO on every n-th SYNC (bus budget)
    sdo_timeout_s: float = 0.5  # [s] per SDO response
    enable_timeout_s: float = 1.0  # [s] to reach OPERATION ENABLED
    torque_constant: tuple[float, ...] = (0.083, 0.083, 0.083, 0.083)  # [N m/A] KV115 wheels
    current_max: tuple[float, ...] = (12.0, 12.0, 12.0, 12.0)  # [A] drive current clamp
    joint_sign: tuple[int, ...] = (1, 1, 1, 1)  # motor direction vs joint direction
    # Teensy
    serial_port: str = ""  # e.g. /dev/ttyACM0 or the pty the emulator prints
    teensy_mode: str = "torque"  # "torque" or "attitude" (the Teensy runs the PD)
    reconnect_min_s: float = 0.05  # [s] first retry after the port vanished
    reconnect_max_s: float = 1.0  # [s] backoff ceiling
    link_timeout_s: float = 0.1  # [s] no sensor frame for this long: link lost
    recover_request: int = 0  # operator command: set a new value to clear latched faults and re-initialise


# Sections owned by each layer follow; each is registered in SECTIONS below.


@dataclass(frozen=True)
class EstimatorParams:
    """The state estimator (:mod:`onboard.estimator`) and its ``estimator`` service.

    Noise figures are the filter's model of its sensors (tune them to the hardware's
    datasheets or to the twin's sensor configuration); densities are per square root
    of a hertz so they do not depend on the sample rate.
    """

    rate_hz: float = 1000.0  # [Hz] state estimate publication rate
    robot: str = "indoor"  # MJCF variant the robot's parameters are read from (sim_twin/models)
    input_queue: int = 256  # sensor messages buffered between two ticks; the oldest dropped beyond
    # Pose sensor (motion capture / tracking camera), fused with its latency compensated.
    pose_delay_s: float = 0.025  # [s] fusion horizon: covers the pose sensor's latency
    compensate_latency: bool = True  # False: fuse each pose as if it were current
    pose_pos_std_m: float = 0.002  # [m] position noise per axis
    pose_att_std_rad: float = 0.01  # [rad] attitude noise per axis
    pose_timeout_s: float = 0.1  # [s] no pose for this long: status reports an outage
    pose_future_tolerance_s: float = 0.002  # [s] pose stamped later than the last IMU sample
    # Mahalanobis gating of pose and leg-kinematics measurements.
    gate_probability: float = 0.9995  # chi-square acceptance probability
    gate_reset_after: int = 20  # consecutive gated poses: re-initialize on the next one
    # CoM process model: white acceleration noise around projectile / stance dynamics.
    accel_psd_flight: float = 0.003  # [(m/s^2)^2/Hz] flight: what projectile dynamics leave out (drag)
    accel_psd_stance: float = 2.0  # [(m/s^2)^2/Hz] stance (accelerometer-driven)
    leg_vel_std_m_s: float = 0.03  # [m/s] stance CoM velocity from leg kinematics
    leg_settle_s: float = 0.006  # [s] after touchdown the foot bounces off the ground this long
    accel_delay_s: float = 0.0005  # [s] accelerometer samples describe this long before their
    # stamp (the twin's MuJoCo accelerometer reads the state one 0.5 ms physics step back;
    # on hardware: the IMU's filter group delay), at most half a sample
    impact_vel_std_m_s: float = 0.1  # [m/s] CoM velocity uncertainty added at touchdown
    liftoff_vel_std_m_s: float = 0.02  # [m/s] ... and at lift-off (stance model errors carried into flight)
    # Attitude: gyro propagation with bias, pose and gravity corrections.
    gyro_noise_density: float = 0.003  # [rad/s/sqrt(Hz)]
    gyro_bias_walk: float = 1e-4  # [rad/s^2/sqrt(Hz)] bias random walk
    tilt_std_rad: float = 0.03  # [rad] accelerometer gravity direction, when quasi-static
    static_accel_tol_m_s2: float = 0.3  # [m/s^2] | |accel| - g | below this: quasi-static
    static_gyro_max_rad_s: float = 0.2  # [rad/s] body rate below this: quasi-static
    static_hold_s: float = 0.2  # [s] quasi-static this long before gravity is trusted
    # Initial uncertainty (before the first pose).
    init_pos_std_m: float = 10.0
    init_vel_std_m_s: float = 2.0
    init_att_std_rad: float = 1.0
    init_bias_std_rad_s: float = 0.02
    # Contact and phase: switch debounce (hysteresis in time).
    contact_on_samples: int = 2  # consecutive contact readings to enter stance
    contact_off_samples: int = 3  # consecutive no-contact readings to enter flight
    accel_contact_on_m_s2: float = 15.0  # [m/s^2] no foot sensor: specific force reading contact
    accel_contact_off_m_s2: float = 4.0  # [m/s^2] ... and no longer contact
    # Input sanity and validity.
    gyro_range_rad_s: float = 35.0  # [rad/s] beyond the gyro's range: rejected
    accel_range_m_s2: float = 160.0  # [m/s^2] beyond the accelerometer's range: rejected
    imu_timeout_s: float = 0.005  # [s] IMU older than this: estimate not valid
    max_extrapolation_s: float = 0.005  # [s] estimate() predicts at most this far past the IMU
    valid_pos_std_m: float = 0.05  # [m] position std above this: estimate not valid
    valid_att_std_rad: float = 0.05  # [rad] attitude std above this: estimate not valid
    kf_backend: str = "lean"  # CoM filter arithmetic: "lean" (floats) or "filterpy" (reference)


@dataclass(frozen=True)
class ControlParams:
    """The hard-rate low level (:mod:`onboard.low_level`) and its ``control`` service.

    Attitude gains act on the body torque per body axis; the attitude error is a
    rotation vector (see :mod:`onboard.attitude_control`).
    """

    rate_hz: float = 1000.0  # control loop rate [Hz]
    auto_arm: bool = True  # arm on the first valid estimate (else wait for an arm request)
    robot: str = "indoor"  # MJCF variant the parameters are read from (sim_twin/models)
    rt_priority: int = 80  # SCHED_FIFO priority of the loop process (0: leave the scheduler alone)
    cpu: int = -1  # CPU the loop process is pinned to (-1: no pinning)
    tube_period_s: float = 0.5  # publish the measured tube this often [s]
    arm_request: int = 0  # operator command: set a new value to arm (after a latched disarm)
    disarm_request: int = 0  # operator command: set a new value to disarm
    # flight: quaternion PD (thesis 2201-2216)
    kp_tilt: float = 40.0  # [N m/rad] roll and pitch
    kd_tilt: float = 3.0  # [N m s/rad]
    kp_yaw: float = 2.0  # [N m/rad]
    kd_yaw: float = 0.25  # [N m s/rad]
    attitude_log: bool = False  # error map: False = 2 Im(q_d^-1 q) (thesis default), True = Log
    # ground: flywheel spin-down u = -gamma * wheel speed (thesis 2723-2731)
    spin_down_gamma: float = 0.03  # [N m s/rad]
    # foot: hop-height regulator (preload in flight, release at touchdown)
    hop_height: float = 0.12  # CoM rise from touchdown to apex [m] (higher: fewer hops per metre, less wheel momentum)
    hop_gain: float = 0.5  # fraction of the hop-energy error corrected per hop
    loss_adapt: float = 0.2  # per-hop gain of the energy-loss estimate
    preload_max: float = 0.05  # [m] spring compression the cable may hold
    spool_kp: float = 10.0  # spool position gain [N m/rad]
    spool_kd: float = 0.2  # spool damping [N m s/rad]
    release_slack: float = 0.015  # at release unwind to this much cable [m] past the extended foot
    # phases
    min_flight_s: float = 0.05  # ignore a touchdown earlier than this after lift-off [s]
    min_stance_s: float = 0.02  # ignore a lift-off earlier than this after touchdown [s]
    # Zero Dynamics Policy (thesis 2377-2777)
    policy: str = "zdp"  # "zdp" (eq. 5.44, clipped), "lqr" (plain gain, unclipped), "raibert", "mlp"
    zdp_q_pos: float = 1.0  # LQR state weight on position error [1/m^2]
    zdp_q_vel: float = 0.5  # on velocity error [s^2/m^2]
    zdp_q_tilt: float = 2.0  # on the impact attitude [1/rad^2]
    zdp_r: float = 2.0  # on the attitude command [1/rad^2]
    raibert_kp: float = 0.25  # eq. 5.48 gains: tilt per position error [rad/m]
    raibert_kd: float = 0.30  # tilt per velocity error [rad s/m]
    tilt_cmd_max: float = 0.12  # clip on the commanded impact tilt [rad]
    pos_err_max: float = 0.30  # clip on the position error the policy sees [m]
    vel_err_max: float = 0.60  # clip on the velocity error the policy sees [m/s]
    mlp_weights: str = "zdp_mlp.npz"  # file under onboard/data/ for policy = "mlp"
    # tracking certificate
    tube_window: int = 100  # impacts in the published tube statistics
    # supervisor
    estimate_fault_disarm_s: float = 0.05  # a bad estimate for this long disarms (latched) [s]
    arm_tilt_max: float = 0.35  # refuse to arm beyond this tilt [rad]


@dataclass(frozen=True)
class TwinParams:
    """The digital twin's sensors (:mod:`sim_twin.sensors`) and pacing.

    Every sensor has seeded white noise, a constant bias drawn once per run (std given),
    a delivery latency and a dropout probability. Noise densities are per square root of
    a hertz (the per-sample std is density * sqrt(rate)), as in :class:`EstimatorParams`.
    """

    noise: bool = True  # False: every sensor reads the true state (no noise, bias, dropouts)
    control_rate_hz: float = 1000.0  # [Hz] sensor frames out, torque commands in
    # IMU (orientation from the IMU's own filter, gyro, accelerometer), body frame at the IMU site
    imu_rate_hz: float = 1000.0
    imu_latency_s: float = 0.0
    imu_dropout: float = 0.0  # probability a sample is lost
    gyro_noise_density: float = 0.001  # [rad/s/sqrt(Hz)]
    gyro_bias_std: float = 0.005  # [rad/s]
    accel_noise_density: float = 0.003  # [m/s^2/sqrt(Hz)]
    accel_bias_std: float = 0.05  # [m/s^2]
    imu_att_std: float = 0.005  # [rad] per axis, the IMU's orientation output
    # Wheel encoders, foot deflection and contact (one joint frame per control tick)
    joints_latency_s: float = 0.0
    joints_dropout: float = 0.0
    encoder_counts_per_rev: int = 16384  # wheel and spool encoders: angles are quantized
    wheel_vel_std: float = 0.2  # [rad/s] speed from the drive
    wheel_torque_std: float = 0.02  # [N m] current-derived torque
    foot_pos_std: float = 0.0003  # [m]
    foot_vel_std: float = 0.01  # [m/s]
    contact_threshold_n: float = 10.0  # [N] foot load above which the contact switch reads true
    # Pose sensor (motion capture / tracking camera): body origin and orientation in world
    pose_rate_hz: float = 100.0
    pose_latency_s: float = 0.010  # [s] delivered this long after capture (stamp = capture time)
    pose_dropout: float = 0.0
    pose_pos_std: float = 0.001  # [m] per axis
    pose_att_std: float = 0.005  # [rad] per axis
    pose_source: str = "mocap"
    # Depth camera by ray casting (site "depth_camera" of the MJCF)
    depth_rate_hz: float = 5.0
    depth_latency_s: float = 0.030
    depth_dropout: float = 0.0
    depth_width: int = 64  # [px]
    depth_height: int = 48  # [px]
    depth_hfov_deg: float = 87.0  # [deg] horizontal field of view (D435 depth)
    depth_max_range_m: float = 6.0  # [m] no return beyond (reads 0)
    depth_noise_per_m2: float = 0.005  # [1/m] depth std = this * depth^2
    # Real-time twin service (``archer run twin``): what it simulates and what it tells the stack
    scenario: str = "hop-in-place"  # sim_twin.scenarios name
    seed: int = 0  # seeds the scenario and the sensor noise
    variant: str = "indoor"  # MJCF variant (sim_twin/models)
    obstacles: int = -1  # forest: number of obstacles (-1: the scenario's default)
    publish_world: bool = True  # publish the scenario's goal and ground-truth obstacle polytopes
    world_period_s: float = 1.0  # [s] goal and polytopes are re-published this often (late joiners)


@dataclass(frozen=True)
class PlannerParams:
    """High-level planner (thesis ch. 6-7, :mod:`onboard.graph_planner`) and its ``planner`` service.

    Planning model: the CoM double integrator in the horizontal plane, state
    ``[x, y, vx, vy]`` (world frame). Limits are per axis (infinity norm).
    """

    v_max: float = 0.35  # [m/s] planned CoM speed bound per axis (the twin's hopper cruises at 0.25)
    a_max: float = 0.5  # [m/s^2] planned CoM acceleration (virtual input) bound per axis
    segment_s: float = 2.0  # [s] duration of one graph edge (a whole number of mpc_dt)
    nodes: int = 5000  # graph nodes over a given planning region; at most this many in an automatic one
    node_density: float = 110.0  # [1/m^2] nodes per square metre of an automatic planning region
    sampling: str = "uniform"  # "uniform" (random positions and velocities) or "grid"
    grid_velocities: int = 3  # "grid": velocity values per axis (odd keeps 0)
    rest_grid: float = 0.15  # [m] extra graph nodes at rest on a lattice of this spacing (0: none): narrow gaps
    time_weight: float = 0.15  # [m/s] search cost per second of path on top of its length (0: length only)
    seed: int = 0  # node sampling seed
    tube: float = 0.1  # [m] promised low-level tracking tube (CoM position); obstacles grow by it
    tube_growth: float = 1.1  # on a broken promise, plan with the achieved tube times this
    robot_radius: float = 0.0  # [m] robot footprint radius; 0: read from the MJCF
    bounds_padding: float = 0.5  # [m] planning region around start, goal and obstacles (plus twice the margin)
    region_tube: float = 0.2  # [m] the region leaves room for a tube this large: no new graph while the tube grows to it
    bounds_quantum: float = 1.0  # [m] region corners snap to this grid (graph cache hits)
    goal_speed_tol: float = 0.05  # [m/s] graph nodes this slow near the goal may end a path
    start_speed_tol: float = 0.1  # [m/s] velocity part of "the node contains the state"
    replan_hz: float = 10.0  # [Hz] cut and search when the world or the goal changed
    refine_hz: float = 100.0  # [Hz] MPC refinement (one SQP iteration per tick)
    mpc_horizon: int = 50  # MPC knots (thesis: 50)
    mpc_dt: float = 0.1  # [s] MPC knot spacing (thesis: 0.1 s)
    mpc_trust: float = 0.5  # [m] trust region of each MPC knot around the graph path (L1)
    halfspaces: int = 4  # separating halfspaces per MPC segment (nearest obstacles)
    halfspace_reach: float = 2.0  # [m] obstacles farther than this from a segment are ignored
    replan_deviation: float = 0.3  # [m] replan when the CoM is this far from where the path puts it
    tube_max: float = 0.5  # [m] the tube the planner grows to at most after broken promises
    contract_min_hops: int = 5  # impacts in the low level's tube window before it is judged
    state_stale_s: float = 0.1  # [s] an older state estimate is not planned from
    nice: int = 10  # the planner process lowers its CPU priority by this much: it must never starve the 1 kHz loops


@dataclass(frozen=True)
class PerceptionParams:
    """Depth image -> occupancy grid -> convex sets (:mod:`onboard.perception`), ``perception`` service.

    Thesis 3100-3116 (Algorithm 4, convex free cells or convex obstacles) and 3336 (the
    outdoor pipeline: depth at apex, segmentation, vertical binning, Algorithm 4).
    Lengths [m], angles [deg], times [s]; cell counts in grid cells.
    """

    # service
    rate_hz: float = 5.0  # polytope publication rate (issue: 4-20 Hz; the published node ran at 5)
    mode: str = "obstacles"  # "free": convex free cells; "obstacles": convex obstacles
    # point cloud
    pixel_stride: int = 1  # use every n-th pixel in both directions
    max_range_m: float = 6.0  # farther returns are dropped (depth noise grows with range^2)
    # geometric segmentation: RANSAC ground plane, height and slope thresholds
    ransac_iterations: int = 64
    ransac_inlier_m: float = 0.03  # plane distance of a RANSAC inlier
    ground_min_points: int = 30  # fewer inliers: fall back to the plane z = 0
    ground_tilt_max_deg: float = 25.0  # a ground-plane candidate tilted more is rejected
    plane_keep_fraction: float = 0.9  # keep the last plane while it has this share of a new fit's inliers
    ground_tol_m: float = 0.04  # points this close to the ground plane are ground...
    ground_tol_per_m: float = 0.012  # ...plus this per metre of range (depth noise grows with range)
    slope_max_deg: float = 25.0  # ground points whose surface is steeper are obstacles
    obstacle_height_max_m: float = 1.0  # points higher above the ground are ignored (overhangs)
    depth_jump_m: float = 0.10  # neighbours farther apart than this (per pixel) give no surface normal
    normal_step_px: int = 2  # surface normals from neighbours this many pixels away (noise vs detail)
    seed: int = 0  # RANSAC and K-means randomness
    # occupancy grid: world frame, square, follows the robot by whole cells
    grid_cells: int = 200  # the published pipeline: 200 x 200 cells of 5 cm
    resolution_m: float = 0.05
    min_points_per_cell: int = 2  # obstacle points a cell needs in one view to count as hit
    hit_evidence: float = 1.0  # added per view to a hit cell
    miss_evidence: float = 0.5  # removed per view from a cell seen as ground
    evidence_max: float = 3.0  # saturation, both signs
    occupied_threshold: float = 0.9  # evidence at or above: occupied
    free_threshold: float = 0.4  # evidence at or below minus this: free
    decay_half_life_s: float = 10.0  # evidence of cells not seen in a view fades to unknown
    carve_range_m: float = 4.0  # ground seen along a ray up to this range is free
    footprint_radius_m: float = 0.15  # the robot stands here: free
    recenter_distance_m: float = 2.0  # re-centre the grid when the robot is this far off centre
    # convex free cells (Algorithm 4)
    cluster_cells: int = 2500  # free cells per K-means cluster (sets k)
    clusters_min: int = 2
    clusters_max: int = 24
    ellipse_sigmas: float = 3.0  # thesis: three standard deviations
    kmeans_max_points: int = 4000  # K-means runs on blocks of cells, about this many
    coverage_rounds: int = 3  # refits of the free cells the polygons missed
    coverage_target: float = 0.95  # no more coverage rounds once reached
    residual_min_cells: int = 12  # missed pieces smaller than this are left alone
    repair_rounds: int = 2  # connectivity repairs between groups of polygons
    repair_radius_cells: float = 6.0  # circle metric of repair and must-cover fits
    # convex obstacles
    obstacle_method: str = "hull"  # "hull" or "rect" (minimum-area rectangle, as the thesis)
    obstacle_solidity_min: float = 0.6  # cells / hull area below which a blob is split
    obstacle_split_min_cells: int = 8
    obstacle_split_depth: int = 6  # halvings per blob at most
    obstacles_max: int = 400


@dataclass(frozen=True)
class RecorderParams:
    """The flight recorder (``recorder`` service): every topic to rotating MCAP files."""

    directory: str = ""  # "" = $STATE_DIRECTORY/recordings under systemd, else ./recordings
    chunk_s: float = 10.0  # finalize the file and start the next after this long [s]
    chunk_bytes: int = 64 * 1024 * 1024  # ... or once this many message bytes are written
    flush_s: float = 1.0  # close an MCAP chunk this often, so a crash loses at most this [s]
    compression: str = "zstd"  # "zstd", "lz4" or "none"
    keep_bytes: int = 8 * 1024 * 1024 * 1024  # delete the oldest finished files beyond this
    status_period_s: float = 5.0  # record every live service's status this often [s] (a query costs them CPU)


@dataclass(frozen=True)
class MocapParams:
    """The ``mocap`` service: a motion capture system's pose through ``motioncapture``.

    ``stamp_ns`` of a published pose is the capture time on the stack's monotonic
    clock: the receive time minus ``latency_s`` (the motioncapture 1.1 bindings report
    no per-frame latency or timestamp, so the lab measures it once and sets it here).
    """

    system: str = "optitrack"  # motioncapture backend: optitrack, vicon, qualisys, vrpn
    host: str = "127.0.0.1"  # the mocap server (the lab's address belongs in the robot's config)
    port: int = 0  # the server's command port (0: the system's default, e.g. NatNet 1510)
    rigid_body: str = "archer"  # the robot's rigid body name in the mocap software
    rigid_body_id: int = 1  # NatNet streaming id (the emulator's; the service matches by name)
    latency_s: float = 0.005  # [s] capture to receive: exposure, processing, network
    rate_hz: float = 120.0  # [Hz] the system's frame rate (emulator's stream rate)
    quat_norm_tolerance: float = 1e-3  # |norm - 1| beyond which a pose is refused
    connect_timeout_s: float = 2.0  # [s] a NatNet server must answer NAT_CONNECT within this
    reconnect_s: float = 1.0  # [s] wait before connecting again after a failure


SECTIONS: dict[str, type] = {
    "perception": PerceptionParams,
    "planner": PlannerParams,
    "control": ControlParams,
    "safety": SafetyLimits,
    "messaging": MessagingParams,
    "hardware": HardwareParams,
    "estimator": EstimatorParams,
    "twin": TwinParams,
    "recorder": RecorderParams,
    "mocap": MocapParams,
}


def with_overrides(obj: Any, overrides: dict[str, Any]) -> Any:
    """A copy of the dataclass ``obj`` with ``overrides`` applied, type-checked."""
    fields = {f.name: f for f in dataclasses.fields(obj)}
    clean: dict[str, Any] = {}
    for name, value in overrides.items():
        if name not in fields:
            raise ValueError(f"{type(obj).__name__} has no parameter {name!r}")
        current = getattr(obj, name)
        if isinstance(current, bool):
            if not isinstance(value, bool):
                raise ValueError(f"{name}: expected a bool, got {value!r}")
        elif isinstance(current, (int, float)):
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(f"{name}: expected a number, got {value!r}")
            if not math.isfinite(float(value)):
                raise ValueError(f"{name}: not finite")
            value = type(current)(value) if isinstance(current, float) else value
        elif isinstance(current, str):
            if not isinstance(value, str):
                raise ValueError(f"{name}: expected a string, got {value!r}")
        elif isinstance(current, tuple):
            value = tuple(value)
        clean[name] = value
    return dataclasses.replace(obj, **clean)


def as_dict(obj: Any) -> dict[str, Any]:
    return dataclasses.asdict(obj)
