"""Parameters of the digital twin (``sim_twin``): the scenario, noise and what the twin publishes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from msgspec import Meta


from onboard.contracts.params.base import Dropout, LOOP_HZ_MAX, Name, Seed, _Section, above, within


@dataclass(frozen=True)
class TwinParams(_Section, section="twin"):
    """The digital twin's sensors (:mod:`sim_twin.sensors`) and pacing.

    Every sensor has seeded white noise, a constant bias drawn once per run (std given),
    a delivery latency and a dropout probability. Noise densities are per square root of
    a hertz (the per-sample std is density * sqrt(rate)), as in :class:`EstimatorParams`.
    """

    noise: bool = True  # False: every sensor reads the true state (no noise, bias, dropouts)
    control_rate_hz: Annotated[float, within(1.0, LOOP_HZ_MAX)] = 1000.0  # [Hz] sensor frames out, torque commands in
    # IMU (orientation from the IMU's own filter, gyro, accelerometer), body frame at the IMU site
    imu_rate_hz: Annotated[float, within(1.0, LOOP_HZ_MAX)] = 1000.0
    imu_latency_s: Annotated[float, within(0.0, 1.0)] = 0.0
    imu_dropout: Dropout = 0.0  # probability a sample is lost
    gyro_noise_density: Annotated[float, within(0.0, 1.0)] = 0.001  # [rad/s/sqrt(Hz)]
    gyro_bias_std: Annotated[float, within(0.0, 1.0)] = 0.005  # [rad/s]
    accel_noise_density: Annotated[float, within(0.0, 10.0)] = 0.003  # [m/s^2/sqrt(Hz)]
    accel_bias_std: Annotated[float, within(0.0, 10.0)] = 0.05  # [m/s^2]
    imu_att_std: Annotated[float, within(0.0, 1.0)] = 0.005  # [rad] per axis, the IMU's orientation output
    # Wheel encoders, foot deflection and contact (one joint frame per control tick)
    joints_latency_s: Annotated[float, within(0.0, 1.0)] = 0.0
    joints_dropout: Dropout = 0.0
    encoder_counts_per_rev: Annotated[int, within(1, 2**24)] = 16384  # wheel and spool encoders: angles are quantized
    wheel_vel_std: Annotated[float, within(0.0, 100.0)] = 0.2  # [rad/s] speed from the drive
    wheel_torque_std: Annotated[float, within(0.0, 10.0)] = 0.02  # [N m] current-derived torque
    foot_pos_std: Annotated[float, within(0.0, 0.1)] = 0.0003  # [m]
    foot_vel_std: Annotated[float, within(0.0, 10.0)] = 0.01  # [m/s]
    contact_threshold_n: Annotated[float, within(0.0, 1000.0)] = 10.0  # [N] foot load above which the contact switch reads true
    # Pose sensor (motion capture / tracking camera): body origin and orientation in world
    pose_rate_hz: Annotated[float, above(0.0, LOOP_HZ_MAX)] = 100.0
    pose_latency_s: Annotated[float, within(0.0, 1.0)] = 0.010  # [s] delivered this long after capture (stamp = capture time)
    pose_dropout: Dropout = 0.0
    pose_pos_std: Annotated[float, within(0.0, 1.0)] = 0.001  # [m] per axis
    pose_att_std: Annotated[float, within(0.0, 1.0)] = 0.005  # [rad] per axis
    pose_source: Name = "mocap"
    # Depth camera by ray casting (site "depth_camera" of the MJCF)
    depth_rate_hz: Annotated[float, above(0.0, 100.0)] = 5.0
    depth_latency_s: Annotated[float, within(0.0, 1.0)] = 0.030
    depth_dropout: Dropout = 0.0
    depth_width: Annotated[int, within(1, 1280)] = 64  # [px]
    depth_height: Annotated[int, within(1, 720)] = 48  # [px]
    depth_hfov_deg: Annotated[float, Meta(gt=0.0, lt=180.0)] = 87.0  # [deg] horizontal field of view (D435 depth)
    depth_max_range_m: Annotated[float, above(0.0, 100.0)] = 6.0  # [m] no return beyond (reads 0)
    depth_noise_per_m2: Annotated[float, within(0.0, 1.0)] = 0.005  # [1/m] depth std = this * depth^2
    # Real-time twin service (``archer run twin``): what it simulates and what it tells the stack
    scenario: Name = "hop-in-place"  # sim_twin.scenarios name
    seed: Seed = 0  # seeds the scenario and the sensor noise
    variant: Name = "indoor"  # MJCF variant (robot_description/models)
    obstacles: Annotated[int, within(-1, 10_000)] = -1  # forest: number of obstacles (-1: the scenario's default)
    publish_world: bool = True  # publish the scenario's goal and ground-truth obstacle polytopes
    publish_obstacles: bool = True  # ...and, of the world, its obstacles (false: the perception service makes them from the depth camera)
    world_period_s: Annotated[float, above(0.0, 60.0)] = 1.0  # [s] goal and polytopes are re-published this often (late joiners)
    # the twin's physics drawn with ``seed`` around the MJCF, the stack nominal (sim_twin.model_error): "nominal",
    # a profile of sim_twin/model_errors/, a TOML file or name=value;... (the real-time twin adds no actuator delay:
    # its commands already cross the network)
    model_error: Name = "nominal"
    # Visual odometry in lockstep (estimator.visual_odometry with --sensing onboard): the D435's frame at each apex,
    # at the camera service's published size (its mode over the decimation), reaches the estimator as a displacement
    # this long after its capture (the camera's transfer, ~10 ms, plus the VO's compute, 10-20 ms at 424 x 240 here)
    vo_latency_s: Annotated[float, within(0.0, 1.0)] = 0.04
