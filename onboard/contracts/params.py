"""The one place for limits and tunable parameters.

The robot's physical parameters (masses, inertias, spring, travel) live in the MJCF
model ``robot_description/models/archer.xml`` and nowhere else. What is here is what an
engineer tunes or what safety depends on. Each layer owns one frozen dataclass; a
config file (TOML, see :mod:`services.runtime.config`) overrides fields by section name,
and :func:`with_overrides` validates every override.

Every field declares its type and its range in its annotation
(``Annotated[float, within(0.0, 500.0)]``); a section refuses, when it is built, any
field of the wrong type (an int field refuses 1.5 and True, a float field takes an
int) or out of its range, naming the field as ``section.name``. Live changes of a
running control loop are applied between two ticks except for :data:`NEEDS_RESTART`.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import typing
from dataclasses import dataclass
from typing import Annotated, Any, Literal

import msgspec
from msgspec import Meta


class ParamError(ValueError):
    """A parameter of the wrong type, out of its range or unknown; names ``section.name``."""


def within(lo: float, hi: float) -> Meta:
    """The closed range [lo, hi]."""
    return Meta(ge=lo, le=hi)


def above(lo: float, hi: float) -> Meta:
    """(lo, hi]: ``lo`` itself excluded (a period, a rate, a standard deviation)."""
    return Meta(gt=lo, le=hi)


# Ceilings read off the robot description (tests/test_params.py holds them to the MJCF of every
# variant). The controller further caps torques at the loaded variant's own peak.
WHEEL_TORQUE_PEAK = 15.0  # [N m] largest wheel drive peak of any variant (sim15nm; the real KV115 drive: 1.6)
FOOT_TORQUE_PEAK = 10.0  # [N m] the foot cable drive's peak at the gearbox output
WHEEL_NO_LOAD_SPEED = 3200.0  # [rad/s] fastest no-load wheel of any variant (sim15nm; the real KV115 on 50.8 V: 611.8)
CAN_NODES = 127  # CANopen node ids 1..127: per-node tuples are never longer (an emulated bus may carry more drives than joints)
LOOP_HZ_MAX = 2000.0  # [Hz] what a Python hard-rate loop keeps on the onboard computer

Probability = Annotated[float, within(0.0, 1.0)]
Dropout = Annotated[float, Meta(ge=0.0, lt=1.0)]  # a sensor that loses every sample is no sensor
RtPriority = Annotated[int, within(0, 99)]  # SCHED_FIFO 1..99; 0: leave the scheduler alone
Cpu = Annotated[int, within(-1, 1023)]  # a CPU index; -1: no pinning
Port = Annotated[int, within(1, 65535)]
Seed = Annotated[int, within(0, 2**32 - 1)]  # numpy's seed range
Request = Annotated[int, within(0, 2**53)]  # an operator command counter: a new value is the command
Name = Annotated[str, Meta(min_length=1)]
NodeId = Annotated[int, within(1, CAN_NODES)]
PER_NODE = Meta(min_length=1, max_length=CAN_NODES)  # a tuple with one entry per drive


@functools.cache
def _field_types(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls, include_extras=True)


def _section_name(cls: type) -> str:
    return next((name for name, c in SECTIONS.items() if c is cls), cls.__name__)


def _error_text(field: str, value: Any, exc: msgspec.ValidationError) -> str:
    """``section.name[i]: expected `int`, got `null``` from msgspec's ``... - at `$[i]```."""
    text, _, path = str(exc).partition(" - at `$")
    return f"{field}{path.rstrip('`')}: {text[:1].lower()}{text[1:]} (value {value!r})"


class _Section:
    """Validates and normalizes (int -> float, list -> tuple) every field when built."""

    def __post_init__(self) -> None:
        types = _field_types(type(self))
        errors = []
        for f in dataclasses.fields(self):  # type: ignore[arg-type]
            value = getattr(self, f.name)
            try:
                clean = msgspec.convert(value, type=types[f.name], strict=True)
            except msgspec.ValidationError as exc:
                errors.append(_error_text(f"{_section_name(type(self))}.{f.name}", value, exc))
                continue
            if clean is not value:
                object.__setattr__(self, f.name, clean)
        if not errors:
            errors = self._relations()
        if errors:
            raise ParamError("; ".join(errors))

    def _relations(self) -> list[str]:
        """Errors of constraints between fields (none unless a section says so)."""
        return []


@dataclass(frozen=True)
class SafetyLimits(_Section):
    """Limits every torque command passes through before it can reach a motor."""

    wheel_torque_max: Annotated[float, above(0.0, WHEEL_TORQUE_PEAK)] = 1.5  # [N m] per wheel, KV115 on 50.8 V, thesis lines 170-190
    foot_torque_max: Annotated[float, above(0.0, FOOT_TORQUE_PEAK)] = 10.0  # [N m] foot cable motor after the 3:1 gearbox
    wheel_speed_max: Annotated[float, above(0.0, WHEEL_NO_LOAD_SPEED)] = 600.0  # [rad/s] beyond this the motor has no torque left
    tilt_max: Annotated[float, above(0.0, math.pi / 2)] = math.radians(45.0)  # [rad] body z from vertical: a fall
    command_stale_s: Annotated[float, above(0.0, 0.1)] = 0.010  # [s] hardware/twin zero torque when no newer command
    estimate_stale_s: Annotated[float, above(0.0, 0.1)] = 0.005  # [s] control disarms on an older estimate
    reference_stale_s: Annotated[float, above(0.0, 10.0)] = 0.5  # [s] control falls back to hopping in place
    heartbeat_timeout_s: Annotated[float, above(0.0, 1.0)] = 0.100  # [s] Teensy / drive heartbeat consumer bound


@dataclass(frozen=True)
class MessagingParams(_Section):
    endpoint: Name = "tcp/127.0.0.1:7447"  # the well-known local router endpoint
    status_period_s: Annotated[float, above(0.0, 60.0)] = 0.5  # how often a service refreshes its rate figures
    # Batches per link queue for the real_time and interactive_high priorities. An express
    # message takes a batch of its own, so Zenoh's default of 2 (and 1 ms wait) drops 1 kHz
    # samples whenever a receiver is ~3 ms late; 16 rides out a 16 ms stall, costs memory
    # only while a receiver lags, and latest-value readers skip what queued.
    link_queue_batches: Annotated[int, within(1, 1024)] = 16


@dataclass(frozen=True)
class HardwareParams(_Section):
    """The ``hardware`` service and its drivers (ELMO drives over CAN, Teensy over serial).

    Joint order everywhere: wheel 0, wheel 1, wheel 2, foot. Per-joint tuples are
    drive settings (motor torque constant, current clamp) of the real robot; the
    emulators use the same values. Gear ratios come from the MJCF model.
    """

    backend: Literal["can", "teensy", "archer-firmware"] = "can"  # "can": ELMO drives over CANopen; "teensy": framed serial; "archer-firmware": ARCHER's flywheel board over UDP ([archer_firmware])
    rate_hz: Annotated[float, within(1.0, LOOP_HZ_MAX)] = 1000.0  # exchange rate with the drives / the Teensy [Hz]
    rt_priority: RtPriority = 70  # SCHED_FIFO priority of the exchange thread, below control (0: leave the scheduler alone)
    cpu: Cpu = -1  # CPU the exchange thread is pinned to (-1: no pinning)
    # CAN (python-can arguments; the emulator prints them)
    can_interface: Name = "socketcand"
    can_channel: Name = "can0"
    can_host: str = "127.0.0.1"  # socketcand only
    can_port: Port = 29536  # socketcand only
    can_bitrate: Annotated[int, within(10_000, 1_000_000)] = 1_000_000  # [bit/s] classic CAN tops out at 1 Mbit/s
    node_ids: Annotated[tuple[NodeId, ...], PER_NODE] = (1, 2, 3, 4)  # CANopen node of each joint
    host_node_id: NodeId = 127  # the host's heartbeat identifier 0x700 + id
    host_heartbeat_period_s: Annotated[float, above(0.0, 1.0)] = 0.025  # drives fault after SafetyLimits.heartbeat_timeout_s
    drive_heartbeat_period_s: Annotated[float, above(0.0, 1.0)] = 0.050  # drive heartbeat producer time (0x1017)
    position_every: Annotated[int, within(1, 1000)] = 10  # position PDO on every n-th SYNC (bus budget)
    sdo_timeout_s: Annotated[float, above(0.0, 10.0)] = 0.5  # [s] per SDO response
    enable_timeout_s: Annotated[float, above(0.0, 60.0)] = 1.0  # [s] to reach OPERATION ENABLED
    torque_constant: Annotated[tuple[Annotated[float, above(0.0, 1.0)], ...], PER_NODE] = (0.083, 0.083, 0.083, 0.083)  # [N m/A] KV115 wheels
    current_max: Annotated[tuple[Annotated[float, above(0.0, 100.0)], ...], PER_NODE] = (12.0, 12.0, 12.0, 12.0)  # [A] drive current clamp
    joint_sign: Annotated[tuple[Literal[1, -1], ...], PER_NODE] = (1, 1, 1, 1)  # motor direction vs joint direction
    # Teensy
    serial_port: str = ""  # e.g. /dev/ttyACM0 or the pty the emulator prints
    teensy_mode: Literal["torque", "attitude"] = "torque"  # "torque" or "attitude" (the Teensy runs the PD)
    reconnect_min_s: Annotated[float, above(0.0, 10.0)] = 0.05  # [s] first retry after the port vanished
    reconnect_max_s: Annotated[float, above(0.0, 60.0)] = 1.0  # [s] backoff ceiling
    link_timeout_s: Annotated[float, above(0.0, 10.0)] = 0.1  # [s] no sensor frame for this long: link lost
    recover_request: Request = 0  # operator command: set a new value to clear latched faults and re-initialise

    def _relations(self) -> list[str]:
        if self.reconnect_min_s > self.reconnect_max_s:
            return [f"hardware.reconnect_min_s: above reconnect_max_s ({self.reconnect_min_s} > {self.reconnect_max_s})"]
        return []


@dataclass(frozen=True)
class ArcherFirmwareParams(_Section):
    """ARCHER's own flywheel-board firmware over UDP (``docs/archer_firmware_protocol.md``).

    Read by the computer-side driver (``drivers/archer_firmware``) and by its emulator,
    which also takes the firmware's configuration from here: the attitude PD gains, the
    current clamp and the foot board's hop cycle. Addresses default to loopback; the
    robot's (board 10.0.0.7, computer 10.0.0.6) belong in its deployment config only.
    """

    board_host: Name = "127.0.0.1"  # the flywheel Teensy
    board_port: Port = 4333  # the firmware's UDP port
    computer_host: Name = "127.0.0.1"  # the address the computer binds (the firmware answers there)
    computer_port: Port = 4333
    # computer side
    link_timeout_s: Annotated[float, above(0.0, 10.0)] = 0.100  # [s] no reply this long while commanding: fault (latched)
    reply_late_s: Annotated[float, above(0.0, 1.0)] = 0.002  # [s] a reply arriving later than this after its request is late
    reply_missing_s: Annotated[float, above(0.0, 10.0)] = 0.050  # [s] a request unanswered this long counts as missing
    # The board answers only what it receives and has no motors-off packet: while disarmed the computer
    # sends the reset command every tick (motors off, and the board answers with its state, which the
    # estimator needs to arm on). False: silence while disarmed (no state until armed; the watchdog stops the motors).
    poll_disarmed: bool = True
    # the firmware (what the emulator runs; the real board has them in its own configuration)
    rate_hz: Annotated[float, within(1.0, LOOP_HZ_MAX)] = 1000.0  # [Hz] the board's control loop
    watchdog_s: Annotated[float, above(0.0, 10.0)] = 0.100  # [s] no valid packet this long: motors off
    kp_tilt: Annotated[float, within(0.0, 500.0)] = 60.0  # [N m] per unit of quaternion error vector, roll and pitch
    kp_yaw: Annotated[float, within(0.0, 500.0)] = 4.0  # [N m] per unit of quaternion error vector, yaw
    kd_tilt: Annotated[float, within(0.0, 50.0)] = 3.0  # [N m s/rad] roll and pitch
    kd_yaw: Annotated[float, within(0.0, 50.0)] = 0.25  # [N m s/rad] yaw
    torque_constant: Annotated[float, above(0.0, 10.0)] = 0.083  # [N m/A] wheel motors
    current_max: Annotated[float, above(0.0, 100.0)] = 12.0  # [A] wheel current clamp
    # the foot board's hop cycle (spool position control, as the foot Teensy runs it)
    foot_preload_m: Annotated[float, within(0.0, 0.2)] = 0.03  # [m] spring compression wound in during flight, released at touchdown
    foot_spool_kp: Annotated[float, within(0.0, 1000.0)] = 10.0  # [N m/rad]
    foot_spool_kd: Annotated[float, within(0.0, 100.0)] = 0.2  # [N m s/rad]
    foot_release_slack_m: Annotated[float, within(0.0, 0.2)] = 0.015  # [m] at touchdown unwind this much cable past the extended foot
    # hop height from the contact switch: a fixed preload gains more per hop than the impact loses
    # (measured on the twin: apex 0.51 -> 0.86 m in 5 s, then the spring bottoms out; 0.015 m: the
    # hop dies), so the board scales the preload by the flight time it measured (apex rise g T^2 / 8)
    foot_hop_height_m: Annotated[float, within(0.0, 0.5)] = 0.12  # [m] apex rise the preload is regulated to (0: fixed preload)
    foot_hop_gain: Annotated[float, within(0.0, 1.0)] = 0.5  # fraction of the hop-height error corrected per hop
    foot_min_flight_s: Annotated[float, within(0.0, 1.0)] = 0.05  # [s] a shorter flight is the foot bouncing at touchdown, not a hop


# Sections owned by each layer follow; each is registered in SECTIONS below.


@dataclass(frozen=True)
class EstimatorParams(_Section):
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


@dataclass(frozen=True)
class ControlParams(_Section):
    """The hard-rate low level (:mod:`onboard.low_level.controller`) and its ``control`` service.

    Attitude gains act on the body torque per body axis; the attitude error is a
    rotation vector (see :mod:`onboard.low_level.tracking.attitude_control`). Gain ceilings: with the
    body's ~0.054 kg m^2 about a horizontal axis, kp 500 N m/rad is a 15 Hz loop
    (far past what 1.6 N m wheels deliver) and kd 50 N m s/rad half the 1 kHz
    discrete damping limit 2 I / dt.
    """

    rate_hz: Annotated[float, within(100.0, LOOP_HZ_MAX)] = 1000.0  # control loop rate [Hz]
    auto_arm: bool = True  # arm on the first valid estimate (else wait for an arm request)
    robot: Name = "indoor"  # MJCF variant the parameters are read from (robot_description/models)
    rt_priority: RtPriority = 80  # SCHED_FIFO priority of the loop process (0: leave the scheduler alone)
    cpu: Cpu = -1  # CPU the loop process is pinned to (-1: no pinning)
    tube_period_s: Annotated[float, above(0.0, 60.0)] = 0.5  # publish the measured tube this often [s]
    # "torque": wheel and foot torques (torque_cmd); "attitude": the hardware runs the attitude PD and
    # the foot's hop cycle itself, the loop publishes attitude setpoints (attitude_cmd) and no foot command
    output: Literal["torque", "attitude"] = "torque"
    arm_request: Request = 0  # operator command: set a new value to arm (after a latched disarm)
    disarm_request: Request = 0  # operator command: set a new value to disarm
    # flight: quaternion PD (thesis 2201-2216)
    kp_tilt: Annotated[float, within(0.0, 500.0)] = 40.0  # [N m/rad] roll and pitch
    kd_tilt: Annotated[float, within(0.0, 50.0)] = 3.0  # [N m s/rad]
    kp_yaw: Annotated[float, within(0.0, 500.0)] = 2.0  # [N m/rad]
    kd_yaw: Annotated[float, within(0.0, 50.0)] = 0.25  # [N m s/rad]
    attitude_log: bool = False  # error map: False = 2 Im(q_d^-1 q) (thesis default), True = Log
    # ground: flywheel spin-down u = -gamma * wheel speed (thesis 2723-2731)
    spin_down_gamma: Annotated[float, within(0.0, 1.0)] = 0.03  # [N m s/rad]
    yaw_rate_max: Annotated[float, within(0.0, 10.0)] = 1.0  # [rad/s] the heading follows the reference's yaw (the planner points the camera) at most this fast
    # foot: hop-height regulator (preload in flight, release at touchdown)
    hop_height: Annotated[float, above(0.0, 0.5)] = 0.12  # CoM rise from touchdown to apex [m] (higher: fewer hops per metre, less wheel momentum)
    hop_gain: Annotated[float, within(0.0, 1.0)] = 0.5  # fraction of the hop-energy error corrected per hop
    loss_adapt: Annotated[float, within(0.0, 1.0)] = 0.2  # per-hop gain of the energy-loss estimate
    preload_max: Annotated[float, within(0.0, 0.1)] = 0.05  # [m] spring compression the cable may hold (the spring travels 0.1 m)
    spool_kp: Annotated[float, within(0.0, 1000.0)] = 10.0  # spool position gain [N m/rad]
    spool_kd: Annotated[float, within(0.0, 50.0)] = 0.2  # spool damping [N m s/rad]
    release_slack: Annotated[float, within(0.0, 0.1)] = 0.015  # at release unwind to this much cable [m] past the extended foot
    # phases
    min_flight_s: Annotated[float, within(0.0, 1.0)] = 0.05  # ignore a touchdown earlier than this after lift-off [s]
    min_stance_s: Annotated[float, within(0.0, 1.0)] = 0.02  # ignore a lift-off earlier than this after touchdown [s]
    # Zero Dynamics Policy (thesis 2377-2777)
    policy: Literal["zdp", "lqr", "raibert", "mlp"] = "zdp"  # "zdp" (eq. 5.44, clipped), "lqr" (plain gain, unclipped), "raibert", "mlp"
    zdp_q_pos: Annotated[float, within(0.0, 1e4)] = 1.0  # LQR state weight on position error [1/m^2]
    zdp_q_vel: Annotated[float, within(0.0, 1e4)] = 0.5  # on velocity error [s^2/m^2]
    zdp_q_tilt: Annotated[float, within(0.0, 1e4)] = 2.0  # on the impact attitude [1/rad^2]
    zdp_r: Annotated[float, above(0.0, 1e4)] = 2.0  # on the attitude command [1/rad^2] (positive: the LQR needs R > 0)
    raibert_kp: Annotated[float, within(0.0, 10.0)] = 0.25  # eq. 5.48 gains: tilt per position error [rad/m]
    raibert_kd: Annotated[float, within(0.0, 10.0)] = 0.30  # tilt per velocity error [rad s/m]
    tilt_cmd_max: Annotated[float, within(0.0, 0.5)] = 0.12  # clip on the commanded impact tilt [rad]
    pos_err_max: Annotated[float, within(0.0, 10.0)] = 0.30  # clip on the position error the policy sees [m]
    vel_err_max: Annotated[float, within(0.0, 10.0)] = 0.60  # clip on the velocity error the policy sees [m/s]
    mlp_weights: Name = "zdp_mlp.npz"  # file under onboard/data/ for policy = "mlp"
    # tracking certificate
    tube_window: Annotated[int, within(1, 100_000)] = 100  # impacts in the published tube statistics
    # supervisor
    estimate_fault_disarm_s: Annotated[float, within(0.0, 1.0)] = 0.05  # a bad estimate for this long disarms (latched) [s]
    # the CoM estimate not valid while its attitude is: the low level holds the body upright and
    # hops in place (no position feedback) for at most this long, then disarms (latched) [s]
    attitude_only_max_s: Annotated[float, within(0.0, 5.0)] = 0.5
    arm_tilt_max: Annotated[float, within(0.0, math.pi / 2)] = 0.35  # refuse to arm beyond this tilt [rad]
    # mid level: "zdp" (the impact attitude of the policy above) or "geometric_mpc" (thesis 5.3: the
    # loop tracks the MPC's attitude, rate and feed-forward with the quaternion PD in both phases,
    # and falls back to the ZDP while no fresh, checked MPC answer is at hand)
    mid_level: Literal["zdp", "geometric_mpc"] = "zdp"
    mid_level_stale_s: Annotated[float, above(0.0, 1.0)] = 0.05  # [s] an MPC setpoint older than this is not tracked
    # the flip (thesis Fig. 5.13, onboard.low_level.tracking.flip): one full turn about a horizontal body axis in one flight
    flip_request: Request = 0  # operator command: set a new value to flip once (refused where the wheels cannot)
    flip_hop_height: Annotated[float, above(0.0, 0.5)] = 0.40  # [m] apex rise the hops are raised to for the turn's flight
    flip_axis_deg: Annotated[float, within(-180.0, 180.0)] = 45.0  # turn axis in the body's xy plane from body x [deg] (45: wheels x and y share it)
    flip_settle_s: Annotated[float, within(0.0, 0.5)] = 0.06  # [s] the turn ends this long before the predicted touchdown
    flip_torque_share: Annotated[float, above(0.0, 1.0)] = 0.7  # share of a wheel's torque limit the turn's feed-forward may take
    flip_pump_hops: Annotated[int, within(1, 50)] = 10  # hops to raise the flight before the request is dropped


@dataclass(frozen=True)
class GeometricMpcParams(_Section):
    """The geometric MPC (:mod:`onboard.low_level.planning.geometric_mpc`, thesis section 5.3, Table 5.3).

    Weights are the diagonal of ``Q`` (also the terminal ``V``, as in the thesis) and ``R``;
    the vertical position and velocity are left to the hop-height regulator.
    """

    rate_hz: Annotated[float, above(0.0, 1000.0)] = 100.0  # solves per second (thesis: 100 Hz)
    # SCHED_FIFO priority of the MPC's process: below the control loop (80), the estimator (75) and the
    # hardware exchange (70); at normal priority on a loaded 2-core machine a 6 ms solve took 20 ms (p50)
    rt_priority: RtPriority = 60
    cpu: Cpu = -1  # CPU the MPC's process is pinned to (-1: no pinning)
    # [s] of the plan sent with each answer: the loop follows the plan at the time it acts, so an
    # answer that arrives late (a loaded machine: solves of 20 ms) still acts where it was meant to
    setpoint_plan_s: Annotated[float, above(0.0, 1.0)] = 0.1
    horizon: Annotated[int, within(2, 200)] = 20  # knots, jumps included (thesis: 20)
    sqp_iterations: Annotated[int, within(1, 10)] = 2  # thesis: 2
    flight_step_s: Annotated[float, above(0.0, 0.2)] = 0.04  # [s] flight knot
    stance_step_s: Annotated[float, above(0.0, 0.2)] = 0.01  # [s] stance knot (finer: the spring is stiff)
    min_step_s: Annotated[float, above(0.0, 0.05)] = 0.002  # [s] a mode remainder shorter than this joins the knot before
    # position and velocity: the thesis's Table 5.3 has 10 and 1; on the twin (sim15nm square, seed 0, 12 s)
    # 30 and 10 tracked to 0.033 m RMS against 0.33 m (it hopped, but drifted behind the reference)
    weight_position: Annotated[float, within(0.0, 1e6)] = 30.0  # horizontal position [1/m^2]
    weight_height: Annotated[float, within(0.0, 1e6)] = 0.0  # vertical position [1/m^2]
    weight_orientation: Annotated[float, within(0.0, 1e6)] = 10.0  # xi, the Lie-algebra attitude [1/rad^2] (thesis: 10)
    weight_velocity: Annotated[float, within(0.0, 1e6)] = 10.0  # horizontal velocity [s^2/m^2]
    weight_vertical_velocity: Annotated[float, within(0.0, 1e6)] = 0.0  # [s^2/m^2]
    weight_omega: Annotated[float, within(0.0, 1e6)] = 0.01  # body rate [s^2/rad^2] (thesis: 0.01)
    weight_wheel_speed: Annotated[float, within(0.0, 1e6)] = 1e-4  # keeps the wheels from spinning up [s^2/rad^2]
    weight_input: Annotated[float, above(0.0, 1e6)] = 0.001  # wheel torque [1/(N m)^2] (thesis: 0.001)
    weight_floor: Annotated[float, above(0.0, 1.0)] = 1e-8  # on unweighted states: keeps P positive definite
    # [rad] bound on the planned tilt (body z from vertical, linearized about the present attitude,
    # never tighter than the present tilt); 0: none (the thesis's problem has none)
    tilt_max_plan: Annotated[float, within(0.0, 1.5)] = 0.0
    # PIQP by default: on this QP (stiff stance rows, 420 equalities) OSQP needed 400-1300 ADMM
    # iterations and ~50 ms a solve against PIQP's 8 iterations and ~2.5 ms (measured, shared 2-core machine)
    backend: Literal["osqp", "piqp"] = "piqp"
    eps: Annotated[float, above(0.0, 1.0)] = 1e-5  # QP tolerance (absolute and relative)
    max_qp_iter: Annotated[int, within(1, 100_000)] = 4000  # per QP: bounds the solve time
    osqp_check_termination: Annotated[int, within(1, 1000)] = 10  # OSQP checks convergence this often
    residual_tol: Annotated[float, above(0.0, 1.0)] = 1e-3  # largest dynamics residual an answer may keep [state units]


@dataclass(frozen=True)
class TwinParams(_Section):
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


@dataclass(frozen=True)
class PlannerParams(_Section):
    """High-level planner (thesis ch. 6-7, :mod:`onboard.high_level.planning.graph_planner`) and its ``planner`` service.

    Planning model: the CoM double integrator in the horizontal plane, state
    ``[x, y, vx, vy]`` (world frame). Limits are per axis (infinity norm).
    """

    v_max: Annotated[float, above(0.0, 5.0)] = 0.35  # [m/s] planned CoM speed bound in every direction (an octagon: onboard.high_level.planning.bezier_graph.speed_limits); the twin's hopper cruises at 0.25
    a_max: Annotated[float, above(0.0, 20.0)] = 0.5  # [m/s^2] planned CoM acceleration (virtual input) bound per axis
    segment_s: Annotated[float, above(0.0, 60.0)] = 2.0  # [s] duration of one graph edge (a whole number of mpc_dt)
    nodes: Annotated[int, within(1, 1_000_000)] = 5000  # graph nodes over a given planning region; at most this many in an automatic one
    node_density: Annotated[float, above(0.0, 1e4)] = 110.0  # [1/m^2] nodes per square metre of an automatic planning region
    sampling: Literal["uniform", "grid"] = "uniform"  # "uniform" (random positions and velocities) or "grid"
    grid_velocities: Annotated[int, within(1, 15)] = 3  # "grid": velocity values per axis (odd keeps 0)
    rest_grid: Annotated[float, within(0.0, 10.0)] = 0.15  # [m] extra graph nodes at rest on a lattice of this spacing (0: none): narrow gaps
    time_weight: Annotated[float, within(0.0, 10.0)] = 0.15  # [m/s] search cost per second of path on top of its length (0: length only)
    # densification (onboard.high_level.planning.densify): when the search finds no path, nodes at rest are added
    # where it failed, finer level by level, before the planner declares that there is none
    densify_budget_s: Annotated[float, within(0.0, 60.0)] = 0.3  # [s] per plan call (0: never densify); below the reference's 0.5 s staleness
    densify_grid: Annotated[float, above(0.0, 10.0)] = 0.3  # [m] first lattice spacing for a graph without a rest lattice (else half of rest_grid)
    densify_min_grid: Annotated[float, above(0.0, 10.0)] = 0.02  # [m] finest lattice spacing: below it the goal is unreachable "at the finest resolution"
    densify_max_nodes: Annotated[int, within(1, 1_000_000)] = 40_000  # nodes densification may add to one graph (memory, cut time)
    densify_round_nodes: Annotated[int, within(1, 1_000_000)] = 500  # nodes added per round at most (one round, ~0.1-0.3 s on a shared 2-core machine, is what may overrun the budget)
    densify_max_rounds: Annotated[int, within(1, 10_000)] = 4  # rounds per plan call at most when the caller has no clock (lockstep): the same on any machine
    seed: Seed = 0  # node sampling seed
    tube: Annotated[float, within(0.0, 5.0)] = 0.1  # [m] promised low-level tracking tube (CoM position); obstacles grow by it
    tube_growth: Annotated[float, within(1.0, 10.0)] = 1.1  # on a broken promise, plan with the achieved tube times this
    robot_radius: Annotated[float, within(0.0, 2.0)] = 0.0  # [m] robot footprint radius; 0: read from the MJCF
    robot: Name = "indoor"  # MJCF variant: its footprint (unless robot_radius) and the speed it sustains cap v_max
    bounds_padding: Annotated[float, within(0.0, 100.0)] = 0.5  # [m] planning region around start, goal and obstacles (plus twice the margin)
    region_tube: Annotated[float, within(0.0, 5.0)] = 0.2  # [m] the region leaves room for a tube this large: no new graph while the tube grows to it
    bounds_quantum: Annotated[float, above(0.0, 100.0)] = 1.0  # [m] region corners snap to this grid (graph cache hits)
    goal_speed_tol: Annotated[float, within(0.0, 5.0)] = 0.05  # [m/s] graph nodes this slow near the goal may end a path
    start_speed_tol: Annotated[float, within(0.0, 5.0)] = 0.1  # [m/s] velocity part of "the node contains the state"
    replan_hz: Annotated[float, above(0.0, 1000.0)] = 10.0  # [Hz] cut and search when the world or the goal changed
    refine_hz: Annotated[float, above(0.0, 1000.0)] = 100.0  # [Hz] MPC refinement (one SQP iteration per tick)
    mpc_horizon: Annotated[int, within(2, 1000)] = 50  # MPC knots (thesis: 50)
    mpc_dt: Annotated[float, above(0.0, 10.0)] = 0.1  # [s] MPC knot spacing (thesis: 0.1 s)
    mpc_trust: Annotated[float, above(0.0, 100.0)] = 0.5  # [m] trust region of each MPC knot around the graph path (L1)
    halfspaces: Annotated[int, within(0, 64)] = 4  # separating halfspaces per MPC segment (nearest obstacles)
    halfspace_reach: Annotated[float, above(0.0, 100.0)] = 2.0  # [m] obstacles farther than this from a segment are ignored
    replan_deviation: Annotated[float, above(0.0, 100.0)] = 0.3  # [m] replan when the CoM is this far from where the path puts it
    tube_max: Annotated[float, within(0.0, 10.0)] = 0.5  # [m] the tube the planner grows to at most after broken promises
    contract_min_hops: Annotated[int, within(1, 100_000)] = 5  # impacts in the low level's tube window before it is judged
    state_stale_s: Annotated[float, above(0.0, 10.0)] = 0.1  # [s] an older state estimate is not planned from
    # seen before stepped on (onboard.high_level.planning.seen_space): with a perceived world the robot is committed
    # only to the first commit_s of a reference, and only over ground the camera saw free
    require_seen: bool = True  # false only where no camera watches and no world is given (nothing would ever be seen)
    commit_s: Annotated[float, within(0.0, 10.0)] = 1.0  # [s] beyond a replan (0.1 s) and a stop from cruise (~2 hops)
    commit_step_s: Annotated[float, above(0.0, 1.0)] = 0.05  # [s] reference samples checked along it (one cell at cruise speed)
    heading_lookahead_s: Annotated[float, above(0.0, 60.0)] = 1.0  # [s] the camera points at where the reference is this far ahead (or a multiple, when that is near)
    heading_min_m: Annotated[float, within(0.0, 10.0)] = 0.15  # [m] nearer than this the heading is left alone (no turning on the spot at the goal)
    # free mode (plans inside perceived free cells only): when no path in them reaches the goal, the
    # path ends at rest near a frontier of the seen space (onboard.high_level.planning.seen_space), the one best by path cost
    # plus frontier_weight times its straight-line distance to the goal; replans move it as the map grows
    frontier_reach: Annotated[float, within(0.0, 10.0)] = 0.3  # [m] a node at rest within the margin plus this of a frontier cell may end such a path
    frontier_min: Annotated[float, within(0.0, 100.0)] = 1.0  # [m] frontier cells nearer the robot are ignored: beside or behind it the camera cannot see them, so standing by them would never resolve them
    frontier_weight: Annotated[float, within(1.0, 100.0)] = 2.0  # [-] cost per metre from a frontier to the goal: at least 1 (the search's heuristic stays admissible), above a known path's cost per metre (1 + time_weight / cruise speed ~ 1.6) so progress toward the goal is worth its path
    frontier_approach_weight: Annotated[float, within(0.0, 1000.0)] = 4.0  # [-] only when the cells reach no frontier (a wall's gap whose cells overlap too thinly for the margin): any node at rest may end the path, at this cost per metre it falls short of that reach over free ground, so the robot goes as near one as they let it, where the cells fitted around it join up (0: it holds)
    frontier_hysteresis: Annotated[float, within(0.0, 100.0)] = 2.0  # [m of cost] the frontier the robot is heading for (nodes within rest_grid of it) is this much cheaper than others: each new view shifts the costs, and two about as good had it turning back and forth between them (maze seed 1 at 0: 50 s; forest 9, 14 and maze 5 at 1: short of the goal when the time ran out, all three reached at 2)
    nice: Annotated[int, within(0, 19)] = 10  # the planner process lowers its CPU priority by this much: it must never starve the 1 kHz loops


@dataclass(frozen=True)
class PerceptionParams(_Section):
    """Depth image -> occupancy grid -> convex sets (:mod:`onboard.perception`), ``perception`` service.

    Thesis 3100-3116 (Algorithm 4, convex free cells or convex obstacles) and 3336 (the
    outdoor pipeline: depth at apex, segmentation, vertical binning, Algorithm 4).
    Lengths [m], angles [deg], times [s]; cell counts in grid cells.
    """

    # service
    rate_hz: Annotated[float, above(0.0, 100.0)] = 5.0  # polytope publication rate (issue: 4-20 Hz; the published node ran at 5)
    mode: Literal["free", "obstacles"] = "obstacles"  # "free": convex free cells; "obstacles": convex obstacles
    # point cloud
    pixel_stride: Annotated[int, within(1, 64)] = 1  # use every n-th pixel in both directions
    max_range_m: Annotated[float, above(0.0, 100.0)] = 6.0  # farther returns are dropped (depth noise grows with range^2)
    # geometric segmentation: RANSAC ground plane, height and slope thresholds
    ransac_iterations: Annotated[int, within(1, 10_000)] = 64
    ransac_inlier_m: Annotated[float, above(0.0, 1.0)] = 0.03  # plane distance of a RANSAC inlier
    ground_min_points: Annotated[int, within(3, 1_000_000)] = 30  # fewer inliers: fall back to the plane z = 0
    ground_tilt_max_deg: Annotated[float, within(0.0, 90.0)] = 25.0  # a ground-plane candidate tilted more is rejected
    plane_keep_fraction: Probability = 0.9  # keep the last plane while it has this share of a new fit's inliers
    ground_tol_m: Annotated[float, within(0.0, 1.0)] = 0.04  # points this close to the ground plane are ground...
    ground_tol_per_m: Annotated[float, within(0.0, 1.0)] = 0.012  # ...plus this per metre of range (depth noise grows with range)
    slope_max_deg: Annotated[float, within(0.0, 90.0)] = 25.0  # ground points whose surface is steeper are obstacles
    obstacle_height_max_m: Annotated[float, above(0.0, 100.0)] = 1.0  # points higher above the ground are ignored (overhangs)
    depth_jump_m: Annotated[float, above(0.0, 10.0)] = 0.10  # neighbours farther apart than this (per pixel) give no surface normal
    normal_step_px: Annotated[int, within(1, 64)] = 2  # surface normals from neighbours this many pixels away (noise vs detail)
    seed: Seed = 0  # RANSAC and K-means randomness
    # occupancy grid: world frame, square, follows the robot by whole cells
    grid_cells: Annotated[int, within(2, 4096)] = 200  # the published pipeline: 200 x 200 cells of 5 cm
    resolution_m: Annotated[float, above(0.0, 10.0)] = 0.05
    min_points_per_cell: Annotated[int, within(1, 100_000)] = 2  # obstacle points a cell needs in one view to count as hit
    hit_evidence: Annotated[float, within(0.0, 100.0)] = 1.0  # added per view to a hit cell
    miss_evidence: Annotated[float, within(0.0, 100.0)] = 0.5  # removed per view from a cell seen as ground
    evidence_max: Annotated[float, above(0.0, 1000.0)] = 3.0  # saturation, both signs
    occupied_threshold: Annotated[float, within(0.0, 1000.0)] = 0.9  # evidence at or above: occupied
    free_threshold: Annotated[float, within(0.0, 1000.0)] = 0.4  # evidence at or below minus this: free
    decay_half_life_s: Annotated[float, above(0.0, 86_400.0)] = 10.0  # evidence of cells not seen in a view fades to unknown
    carve_range_m: Annotated[float, within(0.0, 100.0)] = 4.0  # ground seen along a ray up to this range is free
    footprint_radius_m: Annotated[float, within(0.0, 10.0)] = 0.15  # the robot stands here: free
    # free mode only: the ground around where the robot stands or stood is free, out to this radius, where in
    # sight of it past nothing seen occupied. The camera never sees it: ground within ~0.35 m ahead (its near
    # blind zone) and beside the robot. Twice the planner's margin (robot radius 0.13 + tube 0.1): the
    # corridor between the unseen ground beside the robot, from it to what the camera saw ahead, must be
    # wider than the margin on both sides for a plan to leave through it
    stand_radius_m: Annotated[float, within(0.0, 10.0)] = 0.5
    recenter_distance_m: Annotated[float, above(0.0, 1000.0)] = 2.0  # re-centre the grid when the robot is this far off centre
    # convex free cells (Algorithm 4)
    cluster_cells: Annotated[int, within(1, 10_000_000)] = 2500  # free cells per K-means cluster (sets k)
    clusters_min: Annotated[int, within(1, 1000)] = 2
    clusters_max: Annotated[int, within(1, 1000)] = 24
    ellipse_sigmas: Annotated[float, above(0.0, 10.0)] = 3.0  # thesis: three standard deviations
    kmeans_max_points: Annotated[int, within(1, 10_000_000)] = 4000  # K-means runs on blocks of cells, about this many
    coverage_rounds: Annotated[int, within(0, 100)] = 3  # refits of the free cells the polygons missed
    coverage_target: Probability = 0.95  # no more coverage rounds once reached
    residual_min_cells: Annotated[int, within(1, 10_000_000)] = 12  # missed pieces smaller than this are left alone
    repair_rounds: Annotated[int, within(0, 100)] = 2  # connectivity repairs between groups of polygons
    repair_radius_cells: Annotated[float, above(0.0, 1000.0)] = 6.0  # circle metric of repair and must-cover fits
    # free mode: the robot gets cells of its own, fitted around it, so that plans can leave it: one in a circle
    # (it stands as deep in it as its clearance allows) and, seen through the gap between its blind sides,
    # corridors along ellipses of start_fit_aspect in start_fit_directions directions over a half turn
    start_fit_radius_m: Annotated[float, within(0.0, 100.0)] = 2.0  # [m] the circle's radius and the ellipses' long half axis (0: no own cells)
    start_fit_directions: Annotated[int, within(0, 64)] = 4  # ellipses, their long axes evenly spread over 180 deg
    start_fit_aspect: Annotated[float, within(1.0, 100.0)] = 4.0  # long over short half axis: faces near the robot's sides run along the axis
    # convex obstacles
    obstacle_method: Literal["hull", "rect"] = "hull"  # "hull" or "rect" (minimum-area rectangle, as the thesis)
    obstacle_solidity_min: Probability = 0.6  # cells / hull area below which a blob is split
    obstacle_split_min_cells: Annotated[int, within(1, 10_000_000)] = 8
    obstacle_split_depth: Annotated[int, within(0, 64)] = 6  # halvings per blob at most
    obstacles_max: Annotated[int, within(1, 100_000)] = 400

    def _relations(self) -> list[str]:
        if self.clusters_min > self.clusters_max:
            return [f"perception.clusters_min: above clusters_max ({self.clusters_min} > {self.clusters_max})"]
        return []


@dataclass(frozen=True)
class RecorderParams(_Section):
    """The flight recorder (``recorder`` service): every topic to rotating MCAP files."""

    directory: str = ""  # "" = $STATE_DIRECTORY/recordings under systemd, else ./recordings
    chunk_s: Annotated[float, above(0.0, 86_400.0)] = 10.0  # finalize the file and start the next after this long [s]
    chunk_bytes: Annotated[int, within(1, 2**40)] = 64 * 1024 * 1024  # ... or once this many message bytes are written
    flush_s: Annotated[float, within(0.0, 3600.0)] = 1.0  # close an MCAP chunk this often, so a crash loses at most this [s]
    compression: Literal["zstd", "lz4", "none"] = "zstd"  # "zstd", "lz4" or "none"
    keep_bytes: Annotated[int, within(0, 2**50)] = 8 * 1024 * 1024 * 1024  # delete the oldest finished files beyond this
    status_period_s: Annotated[float, above(0.0, 3600.0)] = 5.0  # record every live service's status this often [s] (a query costs them CPU)
    scene: bool = True  # also write the Foxglove scene channels (services/scene.py, drawn as [view] says) beside the raw topics


@dataclass(frozen=True)
class ViewParams(_Section):
    """The live viewer bridge (``view`` service): the stack's topics to a Foxglove WebSocket server."""

    host: Name = "127.0.0.1"  # bind address; the default serves this machine only (reach it over an SSH tunnel)
    port: Annotated[int, within(0, 65535)] = 8765  # Foxglove's default port; 0: any free port (logged)
    variant: Literal["indoor", "outdoor", "sim15nm"] = "indoor"  # robot model drawn (robot_description variant)
    max_rate_hz: Annotated[float, above(0.0, 1000.0)] = 30.0  # [Hz] at most this per channel: fast topics send their latest
    event_queue: Annotated[int, within(1, 100_000)] = 256  # slow and event topics: messages kept between two sends
    obstacle_height_m: Annotated[float, above(0.0, 10.0)] = 0.5  # [m] obstacles drawn as prisms this tall
    reference_samples: Annotated[int, within(2, 10_000)] = 200  # points drawn along the reference curve
    message_backlog: Annotated[int, within(1, 1_000_000)] = 256  # per client: the SDK drops the oldest beyond it
    lockstep_wait_s: Annotated[float, within(0.0, 3600.0)] = 60.0  # [s] `archer sim --view` in lockstep waits this long for a viewer


@dataclass(frozen=True)
class MocapParams(_Section):
    """The ``mocap`` service: a motion capture system's pose through ``motioncapture``.

    ``stamp_ns`` of a published pose is the capture time on the stack's monotonic
    clock: the receive time minus ``latency_s`` (the motioncapture 1.1 bindings report
    no per-frame latency or timestamp, so the lab measures it once and sets it here).
    """

    system: Literal["optitrack", "vicon", "qualisys", "vrpn"] = "optitrack"  # motioncapture backend
    host: Name = "127.0.0.1"  # the mocap server (the lab's address belongs in the robot's config)
    port: Annotated[int, within(0, 65535)] = 0  # the server's command port (0: the system's default, e.g. NatNet 1510)
    rigid_body: Name = "archer"  # the robot's rigid body name in the mocap software
    rigid_body_id: Annotated[int, within(0, 65535)] = 1  # NatNet streaming id (the emulator's; the service matches by name)
    latency_s: Annotated[float, within(0.0, 1.0)] = 0.005  # [s] capture to receive: exposure, processing, network
    rate_hz: Annotated[float, within(1.0, 1000.0)] = 120.0  # [Hz] the system's frame rate (emulator's stream rate)
    quat_norm_tolerance: Annotated[float, above(0.0, 0.5)] = 1e-3  # |norm - 1| beyond which a pose is refused
    connect_timeout_s: Annotated[float, above(0.0, 60.0)] = 2.0  # [s] a NatNet server must answer NAT_CONNECT within this
    reconnect_s: Annotated[float, above(0.0, 60.0)] = 1.0  # [s] wait before connecting again after a failure


SECTIONS: dict[str, type] = {
    "perception": PerceptionParams,
    "planner": PlannerParams,
    "control": ControlParams,
    "gmpc": GeometricMpcParams,
    "safety": SafetyLimits,
    "messaging": MessagingParams,
    "hardware": HardwareParams,
    "archer_firmware": ArcherFirmwareParams,
    "estimator": EstimatorParams,
    "twin": TwinParams,
    "recorder": RecorderParams,
    "mocap": MocapParams,
    "view": ViewParams,
}

# Fields a running control loop cannot take between two ticks: they shape the loop process
# (rate, scheduling), the robot model, or the policy design (linearized about the hop, or
# loaded from a file), or they size the tube statistics. The control service applies a change
# of one by restarting its loop, which it refuses while the controller is armed. Every other
# control and safety field is applied between two ticks. The estimator's loop thread takes
# its rate and scheduling when it starts: a change of those needs a restart of the service
# (refused live); every other estimator field rebuilds the filter.
NEEDS_RESTART: dict[str, frozenset[str]] = {
    "control": frozenset({"rate_hz", "robot", "rt_priority", "cpu", "output", "mid_level", "policy", "mlp_weights", "hop_height",
                          "zdp_q_pos", "zdp_q_vel", "zdp_q_tilt", "zdp_r", "tube_window"}),
    "estimator": frozenset({"rate_hz", "rt_priority", "cpu", "input_queue"}),
}


def restart_changes(section: str, before: Any, after: Any) -> list[str]:
    """The ``section.name`` of every restart-needing field that differs between two objects."""
    return [f"{section}.{name}" for name in sorted(NEEDS_RESTART.get(section, ()))
            if getattr(before, name) != getattr(after, name)]


def with_overrides(obj: Any, overrides: dict[str, Any]) -> Any:
    """A copy of the dataclass ``obj`` with ``overrides`` applied, all or nothing.

    Raises :class:`ParamError` (a ``ValueError``) naming every unknown, wrongly typed or
    out-of-range field as ``section.name``.
    """
    known = {f.name for f in dataclasses.fields(obj)}
    unknown = [name for name in overrides if name not in known]
    if unknown:
        section = _section_name(type(obj))
        raise ParamError("; ".join(f"{section} has no parameter {name!r}" for name in unknown))
    return dataclasses.replace(obj, **overrides)


def as_dict(obj: Any) -> dict[str, Any]:
    return dataclasses.asdict(obj)
