"""Message schemas: every payload the stack exchanges, defined once.

Small messages are msgspec structs encoded as JSON so that any Zenoh client can
read them. Large arrays (depth images, occupancy grids) use the compact binary
layout in :mod:`onboard.contracts.binary_messages`.

Conventions (all messages):
- ``stamp_ns``: monotonic time in nanoseconds at which the content is valid
  (the capture time for sensor data), on the stack's clock (wall-monotonic on the
  robot, simulated time in the twin).
- ``seq``: per-publisher sequence number, incremented by one per message.
- ``version``: schema version; a receiver rejects versions it does not know.
- Frames: ``world`` is z-up, gravity along -z; ``body`` is the torso frame.
- Quaternions are ``[w, x, y, z]``, unit norm, rotating body to world.
- SI units everywhere; field comments give them.

Decoding is strict (:func:`decode`): unknown fields, wrong types, wrong array
lengths and non-finite floats all raise :class:`MessageError`.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal, TypeVar

import msgspec

SCHEMA_VERSION = 1

Vec2 = Annotated[list[float], msgspec.Meta(min_length=2, max_length=2)]
Vec3 = Annotated[list[float], msgspec.Meta(min_length=3, max_length=3)]
Quat = Annotated[list[float], msgspec.Meta(min_length=4, max_length=4)]


class MessageError(ValueError):
    """A payload that must not reach an algorithm."""


class Message(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    stamp_ns: int = 0  # monotonic time [ns] the content is valid at
    seq: int = 0  # per-publisher sequence number
    version: int = SCHEMA_VERSION  # schema version


# --- sensors (published by the hardware service or the twin) -----------------


class ImuSample(Message):
    quat: Quat  # orientation estimate of the IMU, body->world [w, x, y, z]
    gyro: Vec3  # body angular rate [rad/s], body frame
    accel: Vec3  # specific force [m/s^2], body frame (reads +g at rest)
    accel_sensed: bool = True  # False: no accelerometer behind this source (ARCHER's firmware); accel is 0, not a measurement


class JointSensors(Message):
    """Wheel and foot sensor frame."""

    wheel_pos: Vec3  # wheel angles [rad]
    wheel_vel: Vec3  # wheel speeds relative to the body [rad/s]
    wheel_torque: Vec3  # measured (current-derived) wheel torques [N m]
    foot_pos: float  # spring compression [m], 0 = fully extended, positive compressed
    foot_vel: float  # compression rate [m/s]
    foot_contact: bool  # contact switch / load cell over threshold
    foot_motor_pos: float = 0.0  # cable motor angle after the gearbox [rad]
    foot_sensed: bool = True  # False: no foot sensor behind this source (CAN-only hardware); foot_pos, foot_vel, foot_contact are 0, not measurements


class PoseMeasurement(Message):
    """Motion capture or tracking camera; ``stamp_ns`` is the capture time."""

    position: Vec3  # body origin in world [m]
    quat: Quat  # body->world [w, x, y, z]
    source: str = "mocap"


class VisualOdometryDelta(Message):
    """The CoM's displacement between two camera frames, from visual odometry
    (:mod:`onboard.perception.visual_odometry`); ``stamp_ns`` is the second frame's capture time."""

    from_stamp_ns: int  # the first frame's capture time [ns]
    displacement: Vec3  # CoM(stamp_ns) - CoM(from_stamp_ns) [m, world]
    cov: Annotated[list[float], msgspec.Meta(min_length=9, max_length=9)]  # its covariance, row-major 3x3 [m^2]
    inliers: int = 0  # features that agreed on the motion


# --- estimation ---------------------------------------------------------------

Phase = Literal["flight", "stance"]


class StateEstimate(Message):
    position: Vec3  # CoM in world [m]
    velocity: Vec3  # CoM velocity in world [m/s]
    quat: Quat  # body->world [w, x, y, z]
    omega: Vec3  # body angular rate [rad/s], body frame
    wheel_vel: Vec3  # wheel speeds [rad/s]
    foot_pos: float  # spring compression [m]
    foot_vel: float  # compression rate [m/s]
    contact: bool  # foot on the ground (with hysteresis)
    phase: Phase
    pos_vel_cov: list[float]  # 6x6 covariance of [position, velocity], row-major [m, m/s]^2
    att_cov: Vec3  # variance of the attitude error (rotation vector, body) [rad^2]
    valid: bool = True  # False while the filter has not converged or lost its inputs
    # attitude and body rate alone within their limits: the low level may hold the body upright
    # while the CoM estimate is not valid (an IMU gap grows the velocity's uncertainty first)
    attitude_valid: bool = True


PhaseEventKind = Literal["touchdown", "bottom", "liftoff", "apex"]


class PhaseEvent(Message):
    event: PhaseEventKind
    hop: int  # hop counter (incremented at touchdown)
    position: Vec3  # CoM at the event [m]
    velocity: Vec3  # CoM velocity at the event [m/s]


# --- commands -------------------------------------------------------------------


class TorqueCommand(Message):
    """Wheel and foot torques, to the hardware service or the twin."""

    wheel_torque: Vec3  # [N m], at the wheel motor shafts
    foot_torque: float  # [N m], at the foot cable motor output (after the gearbox)
    armed: bool  # False: the receiver applies zero torque and disables
    commander: str = ""  # instance id of the publishing control service (ServiceStatus.instance)


class AttitudeSetpoint(Message):
    """For a microcontroller that runs the attitude PD itself."""

    quat_des: Quat  # desired body->world [w, x, y, z]
    omega_des: Vec3  # desired body rate [rad/s]
    torque_ff: Vec3  # feed-forward wheel torque [N m]
    foot_torque: float  # [N m]
    armed: bool
    commander: str = ""  # instance id of the publishing control service (ServiceStatus.instance)


class MidLevelSetpoint(Message):
    """The geometric MPC's answer for the 1 kHz loop (thesis 5.3, "Quaternionic Feedback"):
    track ``quat_des`` and ``omega_des`` with the quaternion PD and add ``torque_ff``.
    Published only when the answer passed its checks (status, finiteness, bounds)."""

    quat_des: Quat  # desired body->world [w, x, y, z], q0 exp(xi) a lead time ahead
    omega_des: Vec3  # desired body rate [rad/s]
    torque_ff: Vec3  # feed-forward wheel motor torques [N m] (the plan's first input)
    qp_iterations: list[int]  # per SQP iteration
    solve_ms: float = 0.0  # wall time of the solve [ms] (0 in lockstep)
    # the plan's first stretch, so that the loop tracks the plan at the time it acts, however late
    # the answer arrives: knot times [s after stamp_ns] (a jump repeats a time), attitudes and
    # rates at them, and the wheel torques [N m] from each knot to the next
    plan_t: list[float] = []
    plan_quat: list[Quat] = []
    plan_omega: list[Vec3] = []
    plan_torque: list[Vec3] = []


# --- planning -------------------------------------------------------------------


class Polytope(msgspec.Struct, forbid_unknown_fields=True, omit_defaults=True):
    """Convex set ``{x : A x <= b}`` with its vertices (2D, world frame, metres).

    An obstacle may move: ``velocity`` [m/s] of the set (the planner cuts it in time), ``covariance``
    the 2x2 covariance of its position [m^2] row-major (empty: not estimated), ``name`` the
    operator's. All have defaults, so a publisher that knows none stays valid (a static world).
    """

    A: list[list[float]]
    b: list[float]
    vertices: list[list[float]]
    velocity: tuple[float, float] = (0.0, 0.0)
    covariance: list[float] = []
    name: str = ""  # what the operator called it (`archer obstacles init`), if anything


class PolytopeSet(Message):
    mode: Literal["free", "obstacles"]  # free-space cells or obstacles
    polytopes: list[Polytope]
    source: str = "perception"  # "perception" or "ground_truth"


class BezierSegment(msgspec.Struct, forbid_unknown_fields=True):
    t0: float  # start time [s] on the reference's time base (relative to t_ref_ns)
    duration: float  # [s]
    control_points: list[list[float]]  # position control points [m] (2D or 3D)


class ComReference(Message):
    """CoM reference trajectory the low level tracks (horizontal plane)."""

    t_ref_ns: int  # clock time at which segment time 0 is
    segments: list[BezierSegment]
    hold: bool = False  # True: no path; hop in place at ``segments[0]`` start
    yaw: float | None = None  # [rad] heading to turn the body (and its camera) to; None: keep the heading


class Waypoints(Message):
    points: list[Vec2]  # graph path positions [m]
    sets: list[Polytope]  # convex set each waypoint lies in


class Goal(Message):
    position: Vec2  # [m], world
    tolerance: float = 0.1  # [m]


# --- contracts and health ---------------------------------------------------------


class TrackingTube(Message):
    """What the low level achieves (its guarantee), measured online."""

    hops: int  # impacts in the window
    impact_err_p50: float  # CoM position error at impact [m]
    impact_err_p95: float
    impact_err_max: float
    attitude_err_p95: float  # attitude tracking error at impact [rad]


class ContractReport(Message):
    layer: str  # who checks: "planner" or "control"
    promised: float  # tube the planner plans with [m]
    achieved: float  # tube the low level reports (p95) [m]
    violated: bool
    violations: int  # running count
    detail: str = ""


class SafetyEvent(Message):
    trip: str  # which limit or check tripped
    value: float
    limit: float
    armed: bool  # arming state after the event
    count: int  # running count of this trip


class ServiceStatus(Message):
    service: str
    state: Literal["starting", "running", "degraded", "stopping", "error"]
    uptime_s: float
    rates_hz: dict[str, float]  # achieved rate per topic / loop
    counters: dict[str, int]  # rejections, overruns, ...
    last_error: str = ""
    contract: str = "ok"  # "ok", "violated", "unknown"
    extra: dict[str, float] = {}
    instance: str = ""  # random id of this process's run of the service (commands carry it)
    host: str = ""
    pid: int = 0
    started_unix_s: float = 0.0  # wall-clock start time, for people reading it


class ParamRequest(msgspec.Struct, forbid_unknown_fields=True):
    set: dict[str, float | int | bool | str] = {}


class ParamReply(msgspec.Struct, forbid_unknown_fields=True):
    params: dict[str, float | int | bool | str]
    error: str = ""


M = TypeVar("M", bound=msgspec.Struct)

_encoder = msgspec.json.Encoder()
_decoders: dict[type, msgspec.json.Decoder] = {}


def encode(msg: msgspec.Struct) -> bytes:
    return _encoder.encode(msg)


def _all_finite(obj: object) -> bool:
    if isinstance(obj, float):
        return math.isfinite(obj)
    if isinstance(obj, list):
        return all(_all_finite(v) for v in obj)
    if isinstance(obj, dict):
        return all(_all_finite(v) for v in obj.values())
    if isinstance(obj, msgspec.Struct):
        return all(_all_finite(getattr(obj, f)) for f in obj.__struct_fields__)
    return True


def decode(payload: bytes | bytearray | memoryview, msg_type: type[M]) -> M:
    """Strictly decode ``payload``; raise :class:`MessageError` on anything wrong."""
    dec = _decoders.get(msg_type)
    if dec is None:
        dec = _decoders[msg_type] = msgspec.json.Decoder(msg_type)
    try:
        msg = dec.decode(bytes(payload))
    except (msgspec.DecodeError, msgspec.ValidationError) as exc:
        raise MessageError(f"{msg_type.__name__}: {exc}") from None
    if isinstance(msg, Message) and msg.version != SCHEMA_VERSION:
        raise MessageError(f"{msg_type.__name__}: schema version {msg.version} != {SCHEMA_VERSION}")
    if not _all_finite(msg):
        raise MessageError(f"{msg_type.__name__}: non-finite value")
    return msg
