"""Identification: the robot's parameters that matter, fitted from a recording of its own sensors.

The routine is hopping in place (``archer run control``, or ``archer sim --scenario hop-in-place``
on the twin): every topic it needs is already recorded. Two linear least-squares fits, each value
with a 1-sigma uncertainty from the fit's covariance (residual variance x (A^T A)^-1, inflated by
the residuals' lag-1 correlation) and, where a nominal value enters the model, that value's own
stated uncertainty added in quadrature:

- **wheels** (per wheel, all phases): the spin axis's angular momentum balance of a symmetric rotor
  ``J (dw/dt + a.domega/dt) = k tau - b w - c sign(w)`` (``w`` the wheel's speed relative to the
  body, ``a`` its axis, ``omega`` the body rate from the gyro, ``tau`` the *commanded* torque,
  ``J`` the MJCF's spin inertia), integrated over windows of ``window_s`` so that no speed is
  differentiated: ``J (Delta w + a.Delta omega) = k int tau - b Delta theta - c int sign(w)``.
  Gives the torque constant ``k`` (relative to the nominal 1), the viscous drag ``b``
  [N m s/rad] and the Coulomb friction ``c`` [N m]. All three scale with ``J``: its relative
  uncertainty (``wheel_inertia_sigma``, what the spin-down test states) is added. A delay ``d``
  of the drives (beyond the stack's own tick) enters to first order as ``-k d Delta tau``: fitted
  too, it gives ``actuator_delay``.
- **balance point** (touchdowns): the robot stands where its foot lands under its CoM; at each
  touchdown the horizontal world offset of the true CoM from the foot's sphere centre,
  ``R (c_nom + d - p_foot)``, is a neutral-point term ``a v`` (Raibert; ``v`` the CoM's horizontal
  velocity). Linear in the CoM's offset from the spine ``d = (d_x, d_y)`` [m, body frame] and
  ``a``. Without motion capture the attitude is the IMU's: a mount error ``e`` reads as ``L e``
  of CoM offset (``imu_mount_sigma``, what the mount calibration states, added as ``L`` x it);
  with it (``pose`` recorded) the estimate's attitude is the markers'. The touchdown model's own
  error (``com_model_sigma``, measured on single-factor twins) is added too.

Pure: numpy only, no I/O; the command (``services/cli/identify.py``) reads the recording.
Frames: body = torso frame; world z up. SI units.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from robot_description.params import RobotParams

NS = 1e9
REQUIRED_TOPICS = ("joints", "imu", "torque_cmd", "state", "phase")


class IdentificationError(ValueError):
    """A recording the fit cannot use (missing topics, too few samples, non-finite values)."""


@dataclass(frozen=True)
class Estimate:
    value: float
    sigma: float  # 1-sigma [same unit]
    unit: str = ""


@dataclass(frozen=True)
class IdentifyOptions:
    window_s: float = 0.1  # wheel fit: integration window [s] (longer: less speed noise per unit of signal)
    settle_s: float = 3.0  # data before this time (from the first state) is skipped: the robot still lands
    torque_margin: float = 0.95  # wheel windows with a command beyond this share of the limit are skipped (clamped)
    wheel_torque_max: float = 1.5  # [N m] the safety clamp the command went through (SafetyLimits)
    wheel_inertia_sigma: float = 0.03  # relative 1-sigma of the MJCF's wheel spin inertia (spin-down test)
    imu_mount_sigma: float = 0.0035  # [rad] 1-sigma of the IMU mount per axis (level-plate calibration)
    # [m] the balance-point model's own error, added to the CoM offset's: single-factor twins (seed 0,
    # 3 mm offset) read 0.13-0.19 mm off the truth, 0.33 mm with 2 ms of pose latency
    com_model_sigma: float = 0.0003
    sprung_mass_sigma: float = 0.01  # relative 1-sigma of the MJCF's sprung mass (weighed)
    cable_slack_min: float = 0.002  # [m] spring fit: the cable this slack at least (its stretch and the spool's play)
    min_stance_samples: int = 500
    min_windows: int = 30  # per wheel
    min_touchdowns: int = 10


@dataclass
class Identified:
    """Name -> estimates (one per wheel for wheel parameters), and what the fit used."""

    params: dict[str, list[Estimate]] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)  # samples per fit (windows per wheel, touchdowns)

    def value(self, name: str, i: int = 0) -> float:
        return self.params[name][i].value

    def sigma(self, name: str, i: int = 0) -> float:
        return self.params[name][i].sigma


# --- the recording as arrays ----------------------------------------------------------------------


@dataclass(frozen=True)
class Series:
    """The recording's samples the fits read, as arrays on one clock [s]."""

    t_joints: np.ndarray  # (n,)
    wheel_pos: np.ndarray  # (n, 3) [rad]
    wheel_vel: np.ndarray  # (n, 3) [rad/s]
    t_imu: np.ndarray  # (m,)
    gyro: np.ndarray  # (m, 3) body rate [rad/s]
    t_cmd: np.ndarray  # (p,)
    wheel_torque: np.ndarray  # (p, 3) commanded [N m]; 0 when disarmed
    t_state: np.ndarray  # (q,)
    quat: np.ndarray  # (q, 4) body -> world [w, x, y, z]
    velocity: np.ndarray  # (q, 3) CoM velocity [m/s]
    t_touchdown: np.ndarray  # (r,)
    has_pose: bool = False  # motion capture recorded: the estimate's attitude is the markers', not the IMU mount's
    # the spring fit's (None: not recorded, or no foot sensor): at the joints' stamps
    foot_pos: np.ndarray | None = None  # (n,) compression [m]
    foot_vel: np.ndarray | None = None  # (n,) compression rate [m/s]
    cable_slack: np.ndarray | None = None  # (n,) foot_pos - r * spool angle [m]: > 0, the cable is slack
    foot_contact: np.ndarray | None = None  # (n,) bool
    accel: np.ndarray | None = None  # (m, 3) specific force at the IMU, body frame [m/s^2], at t_imu


def series_from_messages(by_topic: dict[str, Sequence], spool_radius: float = 0.015) -> Series:
    """Arrays from decoded messages by topic name (each message's own ``stamp_ns``)."""
    missing = [t for t in REQUIRED_TOPICS if not by_topic.get(t) and t != "phase"]
    if missing:
        raise IdentificationError(f"recording lacks topics {', '.join(missing)} (needs {', '.join(REQUIRED_TOPICS)})")

    def stamps(msgs: Sequence) -> np.ndarray:
        return np.array([msg.stamp_ns for msg in msgs], dtype=np.int64)

    joints, imu, cmds, states = by_topic["joints"], by_topic["imu"], by_topic["torque_cmd"], by_topic["state"]
    touchdowns = [ev for ev in by_topic.get("phase", ()) if ev.event == "touchdown"]
    out = Series(
        t_joints=_seconds(stamps(joints)),
        wheel_pos=np.array([j.wheel_pos for j in joints], dtype=float),
        wheel_vel=np.array([j.wheel_vel for j in joints], dtype=float),
        t_imu=_seconds(stamps(imu)),
        gyro=np.array([s.gyro for s in imu], dtype=float),
        t_cmd=_seconds(stamps(cmds)),
        wheel_torque=np.array([c.wheel_torque if c.armed else (0.0, 0.0, 0.0) for c in cmds], dtype=float),
        t_state=_seconds(stamps(states)),
        quat=np.array([s.quat for s in states], dtype=float),
        velocity=np.array([s.velocity for s in states], dtype=float),
        t_touchdown=_seconds(stamps(touchdowns)),
        has_pose=bool(by_topic.get("pose")),
    )
    sensed = [j for j in joints if j.foot_sensed]
    if len(sensed) == len(joints) and all(s.accel_sensed for s in imu):
        out = dataclasses.replace(
            out, foot_pos=np.array([j.foot_pos for j in joints]), foot_vel=np.array([j.foot_vel for j in joints]),
            cable_slack=np.array([j.foot_pos for j in joints]) - spool_radius * np.array([j.foot_motor_pos for j in joints]),
            foot_contact=np.array([j.foot_contact for j in joints]), accel=np.array([s.accel for s in imu], dtype=float))
    for name in ("wheel_pos", "wheel_vel", "gyro", "wheel_torque", "quat", "velocity", "foot_pos", "foot_vel", "accel"):
        if getattr(out, name) is not None and not np.all(np.isfinite(getattr(out, name))):
            raise IdentificationError(f"recording: non-finite {name} samples")
    return out


def _seconds(ns: np.ndarray) -> np.ndarray:
    return ns.astype(float) / NS


# --- least squares --------------------------------------------------------------------------------


def least_squares(a: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """OLS ``a x = y``: (x, covariance of x, residuals). Covariance ``s^2 (A^T A)^-1`` with ``s^2``
    the residual variance, times ``(1 + rho) / (1 - rho)`` for a positive lag-1 correlation ``rho``
    of the residuals (in the rows' order: neighbouring windows, successive hops)."""
    n, p = a.shape
    if n <= p:
        raise IdentificationError(f"{n} equations for {p} unknowns")
    scale = np.linalg.norm(a, axis=0)
    if np.any(scale == 0.0):
        raise IdentificationError("a regressor is identically zero (no excitation)")
    an = a / scale
    x_n, *_ = np.linalg.lstsq(an, y, rcond=None)
    r = y - an @ x_n
    s2 = float(r @ r) / (n - p)
    rho = float(r[1:] @ r[:-1]) / float(r @ r) if float(r @ r) > 0.0 else 0.0
    inflate = (1.0 + rho) / (1.0 - rho) if 0.0 < rho < 1.0 else 1.0
    cov_n = s2 * inflate * np.linalg.inv(an.T @ an)
    return x_n / scale, cov_n / np.outer(scale, scale), r


# --- wheels ---------------------------------------------------------------------------------------


def wheel_regression(s: Series, robot: RobotParams, wheel: int, opt: IdentifyOptions) -> tuple[np.ndarray, np.ndarray]:
    """Rows ``[int tau, -Delta tau, -Delta theta, -int sign(w)]`` and ``Delta w + a.Delta omega``
    (times J by the caller), one per window of ``opt.window_s`` after ``opt.settle_s``.

    ``-Delta tau`` (the command acting just before each end) is a delay's first-order term: a
    command reaching the motor ``d`` late integrates to ``int tau - d Delta tau``, so its
    coefficient is ``k d``. Left out, a millisecond of drive delay biased the yaw wheel's
    viscous and Coulomb terms by 4 sigma (the dither's torque changes correlate with the speed)."""
    t = s.t_joints
    t0 = min(s.t_state[0] if len(s.t_state) else t[0], t[0]) + opt.settle_s
    axis = np.asarray(robot.wheel_axes[wheel], dtype=float)
    omega_axis = np.interp(t, s.t_imu, s.gyro @ axis)
    w = s.wheel_vel[:, wheel]
    theta = s.wheel_pos[:, wheel]
    # the command stamped t_j acts over [t_j, t_{j+1}): its integral is piecewise linear in time
    tau = s.wheel_torque[:, wheel]
    cum_tau = np.concatenate(([0.0], np.cumsum(tau[:-1] * np.diff(s.t_cmd))))
    limit = opt.torque_margin * opt.wheel_torque_max
    dt = np.diff(t, append=t[-1])
    cum_sign = np.concatenate(([0.0], np.cumsum(np.sign(w[:-1]) * dt[:-1])))
    rows, ys = [], []
    start = int(np.searchsorted(t, t0))
    while start < len(t) - 1:
        end = int(np.searchsorted(t, t[start] + opt.window_s))
        if end >= len(t):
            break
        ta, tb = t[start], t[end]
        if ta >= s.t_cmd[0] and tb <= s.t_cmd[-1]:
            ca, cb = np.searchsorted(s.t_cmd, [ta, tb], side="left") - 1  # the commands acting just before ta and tb
            clamped = np.any(np.abs(tau[max(ca, 0):cb + 1]) >= limit)
            if not clamped:
                i_tau = float(np.interp(tb, s.t_cmd, cum_tau) - np.interp(ta, s.t_cmd, cum_tau))
                d_tau = tau[cb] - tau[max(ca, 0)]
                rows.append((i_tau, -d_tau, -(theta[end] - theta[start]), -(cum_sign[end] - cum_sign[start])))
                ys.append((w[end] - w[start]) + (omega_axis[end] - omega_axis[start]))
        start = end + 1  # endpoints not shared: each window's speed noise its own
    return np.array(rows, dtype=float).reshape(-1, 4), np.array(ys, dtype=float)


def fit_wheels(s: Series, robot: RobotParams, opt: IdentifyOptions = IdentifyOptions()) -> tuple[dict[str, list[Estimate]], int]:
    """Per wheel: ``wheel_torque_constant`` (k - 1), ``wheel_viscous``, ``wheel_coulomb``; and the
    drives' ``actuator_delay`` [s], the three wheels' estimates combined (inverse-variance)."""
    j = robot.wheel_spin_inertia
    out: dict[str, list[Estimate]] = {"wheel_torque_constant": [], "wheel_viscous": [], "wheel_coulomb": []}
    fewest = 1 << 30
    delays: list[tuple[float, float]] = []
    for wheel in range(3):
        a, y = wheel_regression(s, robot, wheel, opt)
        if len(y) < opt.min_windows:
            raise IdentificationError(f"wheel {wheel}: {len(y)} usable windows of {opt.window_s} s (needs {opt.min_windows}): "
                                      "too short a recording, or the torque always at its limit")
        fewest = min(fewest, len(y))
        x, cov, _ = least_squares(a, j * y)
        sd = np.sqrt(np.diag(cov))
        js = opt.wheel_inertia_sigma  # each value is J times what the window sees: J's own error scales it
        k, kd, b, c = x
        delays.append((kd / k, sd[1] / abs(k)))  # the delay is a ratio of two J-scaled values: J cancels
        out["wheel_torque_constant"].append(Estimate(k - 1.0, math.hypot(sd[0], js * k), ""))
        out["wheel_viscous"].append(Estimate(b, math.hypot(sd[2], js * b), "N m s/rad"))
        out["wheel_coulomb"].append(Estimate(c, math.hypot(sd[3], js * c), "N m"))
    w = np.array([1.0 / sd_d ** 2 for _, sd_d in delays])
    out["actuator_delay"] = [Estimate(float(np.sum(w * [d for d, _ in delays]) / np.sum(w)), float(1.0 / math.sqrt(np.sum(w))), "s")]
    return out, fewest


# --- balance point --------------------------------------------------------------------------------


def _rotation(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def fit_com_offset(s: Series, robot: RobotParams, opt: IdentifyOptions = IdentifyOptions()) -> tuple[dict[str, list[Estimate]], int]:
    """``com_x``, ``com_y``: the CoM's offset from where the MJCF puts it, body frame [m]."""
    t0 = (s.t_state[0] if len(s.t_state) else 0.0) + opt.settle_s
    tds = s.t_touchdown[s.t_touchdown >= t0]
    if len(tds) < opt.min_touchdowns:
        raise IdentificationError(f"{len(tds)} touchdowns after {opt.settle_s} s (needs {opt.min_touchdowns}): "
                                  "no phase events recorded, or the robot did not hop")
    lever = robot.leg_length - robot.foot_radius  # torso origin to the foot sphere's centre
    c_nom = np.asarray(robot.com_offset_body, dtype=float) - np.array([0.0, 0.0, -lever])
    idx = np.clip(np.searchsorted(s.t_state, tds), 0, len(s.t_state) - 1)
    rows, ys = [], []
    for i in idx:
        rot = _rotation(s.quat[i])
        v = s.velocity[i]
        r = rot @ c_nom
        for ax in range(2):  # world x, y: R_ax . d + r_ax = a v_ax
            rows.append((rot[ax, 0], rot[ax, 1], -v[ax]))
            ys.append(-r[ax])
    x, cov, _ = least_squares(np.array(rows), np.array(ys))
    # a mount error e reads as L e of offset, unless motion capture gives the estimate its attitude
    mount = 0.0 if s.has_pose else (robot.com_offset_body[2] + lever) * opt.imu_mount_sigma
    sd = np.sqrt(np.diag(cov))
    floor = math.hypot(mount, opt.com_model_sigma)
    return {"com_x": [Estimate(float(x[0]), math.hypot(sd[0], floor), "m")],
            "com_y": [Estimate(float(x[1]), math.hypot(sd[1], floor), "m")]}, len(tds)


def fit_spring(s: Series, robot: RobotParams, opt: IdentifyOptions = IdentifyOptions()) -> tuple[dict[str, list[Estimate]], int]:
    """``spring_stiffness`` (relative to the MJCF's), from stance samples with the cable slack: the
    sprung body's specific force along the spine is the spring's push, ``m_s f_z = k x + c xdot + f_0``
    (``f_0``: the accelerometer's bias). The damping ``c`` is fitted but not reported: a time offset
    ``d`` between the accelerometer and the foot encoder reads as ``-k d`` of damping (the twin's
    accelerometer lags its encoders by a physics step or two: ``c`` came out -11.6 N s/m with none
    drawn, k x 1 ms), and no routine here separates the two."""
    assert s.foot_pos is not None and s.foot_vel is not None and s.cable_slack is not None
    assert s.foot_contact is not None and s.accel is not None
    t = s.t_joints
    t0 = (s.t_state[0] if len(s.t_state) else t[0]) + opt.settle_s
    fz = np.interp(t, s.t_imu, s.accel[:, 2])
    use = (t >= t0) & s.foot_contact & (s.cable_slack > opt.cable_slack_min) & (s.foot_pos < 0.95 * robot.foot_travel)
    n = int(np.count_nonzero(use))
    if n < opt.min_stance_samples:
        raise IdentificationError(f"{n} stance samples with the cable slack (needs {opt.min_stance_samples})")
    a = np.column_stack((s.foot_pos[use], s.foot_vel[use], np.ones(n)))
    x, cov, _ = least_squares(a, robot.sprung_mass * fz[use])
    sd = np.sqrt(np.diag(cov))
    k0 = robot.spring_stiffness
    ms = opt.sprung_mass_sigma  # both scale with the sprung mass the force is computed from
    k_rel = x[0] / k0
    return {"spring_stiffness": [Estimate(k_rel - 1.0, math.hypot(sd[0] / k0, ms * k_rel), "")]}, n


def identify(s: Series, robot: RobotParams, opt: IdentifyOptions = IdentifyOptions()) -> Identified:
    """Every fit on one recording."""
    out = Identified()
    wheels, n_windows = fit_wheels(s, robot, opt)
    com, n_td = fit_com_offset(s, robot, opt)
    out.params.update(com)
    out.params.update(wheels)
    out.counts = {"wheel_windows": n_windows, "touchdowns": n_td}
    if s.foot_pos is not None:
        spring, n_stance = fit_spring(s, robot, opt)
        out.params.update(spring)
        out.counts["stance_samples"] = n_stance
    return out
