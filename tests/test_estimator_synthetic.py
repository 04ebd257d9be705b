"""State estimator on synthetic hops that match its model exactly.

The trajectory is built kinematically from the robot's MJCF parameters: ballistic
flights, and stances in which the foot sphere rolls without slipping while the body
vaults over it and the spring compresses; touchdown stops the foot (the CoM loses the
foot's share of momentum). Sensors: gyro with bias and noise, accelerometer, foot
encoder and switch, a pose sensor with noise, latency and dropouts. Because the model
is exact, tolerances here are tight; the twin tests judge it against real physics.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import pytest

from onboard.geometry import quaternion as quat
from onboard.estimation.attitude_filter import AttitudeFilter
from onboard.estimation.com_filter import make_com_filter
from onboard.estimation.estimator import StateEstimator
from onboard.contracts.messages import ImuSample, JointSensors, PoseMeasurement
from onboard.contracts.params import EstimatorParams
from robot_description.params import robot_params

NS = 1_000_000_000
DT_NS = 1_000_000  # 1 kHz
ROBOT = robot_params("indoor")


def _hermite(t: float, T: float, p0: float, v0: float, p1: float, v1: float) -> tuple[float, float]:
    """Cubic Hermite value and rate on [0, T]."""
    u = t / T
    h00 = 2 * u**3 - 3 * u**2 + 1
    h10 = u**3 - 2 * u**2 + u
    h01 = -2 * u**3 + 3 * u**2
    h11 = u**3 - u**2
    d00 = (6 * u**2 - 6 * u) / T
    d10 = 3 * u**2 - 4 * u + 1
    d01 = (-6 * u**2 + 6 * u) / T
    d11 = 3 * u**2 - 2 * u
    return (h00 * p0 + h10 * T * v0 + h01 * p1 + h11 * T * v1, d00 * p0 + d10 * v0 + d01 * p1 + d11 * v1)


@dataclass
class Track:
    """Truth and model quantities at 1 kHz."""

    t_ns: np.ndarray
    pos: np.ndarray  # CoM [m, world]
    vel: np.ndarray  # CoM [m/s, world]
    quat: np.ndarray  # body->world
    omega: np.ndarray  # body rate [rad/s, body]
    accel_com: np.ndarray  # CoM acceleration [m/s^2, world]
    foot_s: np.ndarray
    foot_sd: np.ndarray
    contact: np.ndarray
    touchdowns: list[int] = field(default_factory=list)


class _Gait:
    """Sagittal vaulting gait along heading ``yaw`` (see the module docstring)."""

    def __init__(self, yaw: float, pitch: float, stance_s: float) -> None:
        self.g = ROBOT.gravity
        self.mu = ROBOT.foot_mass / ROBOT.total_mass
        self.rho = ROBOT.foot_radius
        self.r_cf0 = np.array(ROBOT.com_offset_body) + np.array([0.0, 0.0, ROBOT.leg_length - self.rho])
        self.qz = quat.from_euler(0.0, 0.0, yaw)
        self.fwd = np.array([math.cos(yaw), math.sin(yaw), 0.0])
        self.side = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
        self.pitch = pitch
        self.stance_s = stance_s
        self.flight_att_s = 0.08  # the pitch swings back within this after lift-off

    def att(self, theta: float) -> tuple:
        return quat.mul(self.qz, quat.from_euler(0.0, theta, 0.0))

    def rot(self, theta: float) -> np.ndarray:
        return np.array(quat.to_matrix(self.att(theta)))

    def r_cf(self, s: float) -> np.ndarray:
        return self.r_cf0 - np.array([0.0, 0.0, (1.0 - self.mu) * s])

    # flight: (p0, v0, theta0, thetad0)
    def flight(self, seg: dict, tau: float) -> tuple:
        ez = np.array([0.0, 0.0, 1.0])
        p = seg["p"] + seg["v"] * tau - 0.5 * self.g * tau * tau * ez
        v = seg["v"] - self.g * tau * ez
        if tau < self.flight_att_s:
            th, thd = _hermite(tau, self.flight_att_s, seg["theta"], seg["thetad"], -self.pitch, 0.0)
        else:
            th, thd = -self.pitch, 0.0
        return p, v, th, thd, 0.0, 0.0

    # stance: sphere centre rolls, body vaults, spring compresses
    def stance(self, seg: dict, tau: float) -> tuple:
        T = self.stance_s
        th, thd = _hermite(tau, T, -self.pitch, seg["thd0"], self.pitch, seg["thd0"])
        s, sd = _hermite(tau, T, 0.0, seg["sd0"], 0.0, -seg["sd0"] / (1.0 - self.mu) ** 2)
        ez = np.array([0.0, 0.0, 1.0])
        centre = seg["centre"] + self.rho * (th + self.pitch) * self.fwd
        r = self.rot(th)
        p = centre + r @ self.r_cf(s)
        omega_w = thd * self.side
        v = np.cross(omega_w, r @ self.r_cf(s) + self.rho * ez) - (1.0 - self.mu) * sd * (r @ ez)
        return p, v, th, thd, s, sd

    def touchdown(self, p: np.ndarray, v: np.ndarray, th: float) -> dict:
        ez = np.array([0.0, 0.0, 1.0])
        vplus = (1.0 - self.mu) * v  # the foot (moving with the CoM, no rotation) stops
        r = self.rot(th)
        centre = p - r @ self.r_cf0
        lever = r @ self.r_cf0 + self.rho * ez
        a_col = np.cross(self.side, lever)
        b_col = -(1.0 - self.mu) * (r @ ez)
        m = np.array([[a_col @ self.fwd, b_col @ self.fwd], [a_col[2], b_col[2]]])
        thd0, sd0 = np.linalg.solve(m, np.array([vplus @ self.fwd, vplus[2]]))
        return {"centre": centre, "thd0": float(thd0), "sd0": float(sd0)}


def synthetic_hops(duration_s: float = 3.0, yaw: float = 0.4, pitch: float = 0.12, stance_s: float = 0.1) -> Track:
    """Hops on flat ground (z = 0), starting in flight 2 cm above touchdown."""
    gait = _Gait(yaw, pitch, stance_s)
    n = int(duration_s * 1000)
    out = Track(
        t_ns=np.arange(n, dtype=np.int64) * DT_NS + NS, pos=np.zeros((n, 3)), vel=np.zeros((n, 3)),
        quat=np.zeros((n, 4)), omega=np.zeros((n, 3)), accel_com=np.zeros((n, 3)),
        foot_s=np.zeros(n), foot_sd=np.zeros(n), contact=np.zeros(n, dtype=bool),
    )
    ez = np.array([0.0, 0.0, 1.0])
    th0 = -pitch
    p0 = gait.rot(th0) @ gait.r_cf0 + (gait.rho + 0.02) * ez
    seg = {"p": p0, "v": 0.4 * gait.fwd, "theta": th0, "thetad": 0.0}
    phase, t0 = "flight", 0.0
    h = 1e-5  # central difference for the CoM acceleration in stance
    k = 0
    while k < n:
        tau = k * 1e-3 - t0
        if phase == "flight":
            p, v, th, thd, s, sd = gait.flight(seg, tau)
            centre_z = p[2] - (gait.rot(th) @ gait.r_cf0)[2]
            if centre_z <= gait.rho and v[2] < 0.0:
                seg = gait.touchdown(p, v, th)
                phase, t0 = "stance", k * 1e-3
                out.touchdowns.append(k)
                continue
            acc = np.array([0.0, 0.0, -gait.g])
        else:
            if tau >= gait.stance_s:
                p, v, th, thd, _, _ = gait.stance(seg, gait.stance_s)
                seg = {"p": p, "v": v, "theta": th, "thetad": thd}
                phase, t0 = "flight", t0 + gait.stance_s
                continue
            p, v, th, thd, s, sd = gait.stance(seg, tau)
            lo, hi = max(tau - h, 0.0), min(tau + h, gait.stance_s)
            acc = (gait.stance(seg, hi)[1] - gait.stance(seg, lo)[1]) / (hi - lo)
            out.contact[k] = True
        out.pos[k], out.vel[k], out.accel_com[k] = p, v, acc
        out.quat[k] = gait.att(th)
        out.omega[k] = (0.0, thd, 0.0)
        out.foot_s[k], out.foot_sd[k] = s, sd
        k += 1
    return out


@dataclass
class SensorConfig:
    pose_rate_hz: float = 100.0
    latency_s: float = 0.02
    dropout: float = 0.1
    pos_std: float = 0.001
    att_std: float = 0.003
    gyro_std: float = 0.005  # per sample [rad/s]
    gyro_bias: tuple[float, float, float] = (0.01, -0.015, 0.008)
    accel_std: float = 0.05  # per sample [m/s^2]
    outage: tuple[float, float] | None = None  # [s] no pose captured in this window
    outlier_every: int = 0  # every n-th delivered pose is moved by outlier_m
    outlier_m: float = 1.0
    jump_at_s: float | None = None  # from then on every pose is moved by jump_m: the track is lost
    jump_m: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass
class Run:
    est: StateEstimator
    pos: np.ndarray
    vel: np.ndarray
    quat: np.ndarray
    pos_std: np.ndarray
    valid: np.ndarray
    modes: list[str]
    outliers_injected: int


def run_synthetic(track: Track, params: EstimatorParams, cfg: SensorConfig, seed: int = 1) -> Run:
    rng = np.random.default_rng(seed)
    est = StateEstimator(params, ROBOT)
    mu = ROBOT.foot_mass / ROBOT.total_mass
    mu_b = 1.0 - mu
    c0 = np.array(ROBOT.com_offset_body)
    n = len(track.t_ns)
    pose_every = int(round(1000 / cfg.pose_rate_hz))
    latency_ticks = int(round(cfg.latency_s * 1000))
    deliveries: dict[int, list[PoseMeasurement]] = {}
    delivered = 0
    injected = 0
    out_pos, out_vel, out_q = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 4))
    out_std, out_valid, modes = np.zeros(n), np.zeros(n, dtype=bool), []
    for k in range(n):
        t = int(track.t_ns[k])
        q = tuple(track.quat[k])
        r = np.array(quat.to_matrix(q))
        if track.contact[k]:
            f = r.T @ (track.accel_com[k] / mu_b + np.array([0.0, 0.0, ROBOT.gravity]))
        else:
            f = np.zeros(3)
        f = f + rng.normal(0.0, cfg.accel_std, 3)
        gyro = track.omega[k] + np.array(cfg.gyro_bias) + rng.normal(0.0, cfg.gyro_std, 3)
        q_imu = quat.mul(q, quat.exp(tuple(rng.normal(0.0, 0.02, 3))))
        est.update_imu(ImuSample(stamp_ns=t, quat=list(q_imu), gyro=list(gyro), accel=list(f)))
        est.update_joints(JointSensors(
            stamp_ns=t, wheel_pos=[0.0] * 3, wheel_vel=[1.0, 2.0, 3.0], wheel_torque=[0.0] * 3,
            foot_pos=float(track.foot_s[k]), foot_vel=float(track.foot_sd[k]), foot_contact=bool(track.contact[k]),
        ))
        ts = k * 1e-3
        in_outage = cfg.outage is not None and cfg.outage[0] <= ts < cfg.outage[1]
        if k % pose_every == 0 and not in_outage and rng.random() >= cfg.dropout:
            origin = track.pos[k] - r @ (c0 + np.array([0.0, 0.0, mu * track.foot_s[k]]))
            origin = origin + rng.normal(0.0, cfg.pos_std, 3)
            delivered += 1
            if cfg.jump_at_s is not None and ts >= cfg.jump_at_s:
                origin = origin + np.array(cfg.jump_m)
            if cfg.outlier_every and delivered % cfg.outlier_every == 0:
                direction = rng.normal(size=3)
                origin = origin + cfg.outlier_m * direction / np.linalg.norm(direction)
                injected += 1
            qm = quat.mul(quat.exp(tuple(rng.normal(0.0, cfg.att_std, 3))), q)
            deliveries.setdefault(k + latency_ticks, []).append(
                PoseMeasurement(stamp_ns=t, position=list(origin), quat=list(qm)))
        for pose in deliveries.pop(k, []):
            est.update_pose(pose)
        msg = est.estimate(t)
        out_pos[k], out_vel[k], out_q[k] = msg.position, msg.velocity, msg.quat
        out_std[k] = math.sqrt(msg.pos_vel_cov[0])
        out_valid[k] = msg.valid
        modes.append(est.status()["mode"])
    return Run(est, out_pos, out_vel, out_q, out_std, out_valid, modes, injected)


def att_err_deg(qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
    return np.degrees([quat.angle_between(tuple(a), tuple(b)) for a, b in zip(qa, qb)])


def rmse(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


SETTLE = 500  # [samples] ignored while the filter converges from its initial guess
# The synthetic accelerometer samples the instant of its stamp (the twin's lags half a tick).
PARAMS = EstimatorParams(accel_delay_s=0.0)


@pytest.fixture(scope="module")
def track() -> Track:
    return synthetic_hops(3.0)


def errors(run: Run, track: Track) -> tuple[float, float, float]:
    s = slice(SETTLE, None)
    att = float(np.sqrt(np.mean(att_err_deg(run.quat[s], track.quat[s]) ** 2)))
    return rmse(run.pos[s], track.pos[s]), rmse(run.vel[s], track.vel[s]), att


def test_converges_on_synthetic_hops(track: Track) -> None:
    run = run_synthetic(track, PARAMS, SensorConfig())
    pos, vel, att = errors(run, track)
    assert pos < 0.003 and vel < 0.04 and att < 0.2
    assert run.valid[SETTLE:].all()
    assert run.modes[-1] == "ok"
    c = run.est.counters
    assert c["touchdowns"] == len(track.touchdowns)
    assert c.get("pose_outliers", 0) <= 2
    assert c["leg_fused"] > 500
    # the gyro bias is learnt
    assert np.linalg.norm(np.array(run.est.att.bias) - np.array(SensorConfig().gyro_bias)) < 0.005


def test_latency_compensation_beats_none(track: Track) -> None:
    with_comp = errors(run_synthetic(track, PARAMS, SensorConfig()), track)
    without = errors(run_synthetic(track, replace(PARAMS, compensate_latency=False), SensorConfig()), track)
    assert with_comp[0] < 0.3 * without[0]  # position
    assert with_comp[1] < 0.5 * without[1]  # velocity
    assert with_comp[2] < 0.3 * without[2]  # attitude


def test_pose_outage_degrades_and_recovers(track: Track) -> None:
    cfg = SensorConfig(outage=(1.2, 1.7))
    run = run_synthetic(track, PARAMS, cfg)
    k0, k1 = 1200, 1700 + 20  # the last pose before the outage arrives 20 ms late
    assert run.modes[k0 + 150] == "pose_outage"
    normal = float(np.median(run.pos_std[k0 - 300:k0]))
    assert run.pos_std[k1 - 1] > 3.0 * normal  # the covariance grows
    err = np.linalg.norm(run.pos - track.pos, axis=1)
    assert err[k0:k1].max() < 0.02  # graceful: projectile and leg kinematics carry it
    # recovered 0.2 s after poses return
    assert run.modes[k1 + 200] == "ok"
    assert np.median(run.pos_std[k1 + 200:k1 + 500]) < 1.5 * normal
    assert err[k1 + 200:].max() < 0.006


def test_one_metre_outliers_are_rejected(track: Track) -> None:
    run = run_synthetic(track, PARAMS, SensorConfig(outlier_every=5))
    c = run.est.counters
    assert run.outliers_injected >= 40
    assert c["pose_outliers"] == run.outliers_injected
    assert c.get("pose_resets", 0) == 0 and c["pose_reacquired"] == 0  # the real poses keep the track
    pos, vel, att = errors(run, track)
    assert pos < 0.003 and vel < 0.04 and att < 0.2


def test_a_lost_track_is_taken_back_from_the_poses(track: Track) -> None:
    """Every pose 30 cm off from some time on (the state went wrong: a stall, a robot put
    back): the gate refuses them for ``pose_reacquire_s``, then the covariance is inflated
    and the poses pull the state over; before, the gate refused them for good."""
    jump = (0.3, -0.2, 0.0)
    run = run_synthetic(track, PARAMS, SensorConfig(jump_at_s=1.5, jump_m=jump, dropout=0.0))
    moved = track.pos + np.array(jump)
    err = np.linalg.norm(run.pos - moved, axis=1)
    k0 = 1500 + 20  # the first moved pose arrives 20 ms late
    assert run.est.counters["pose_reacquired"] >= 1
    settle = k0 + int(1000 * (PARAMS.pose_reacquire_s + 0.2))
    assert err[settle:].max() < 0.01
    assert run.modes[settle] == "ok"


def test_lean_arithmetic_matches_filterpy(track: Track) -> None:
    cfg = SensorConfig(outlier_every=7)
    lean = run_synthetic(track, PARAMS, cfg)
    ref = run_synthetic(track, replace(PARAMS, kf_backend="filterpy"), cfg)
    np.testing.assert_allclose(lean.pos, ref.pos, atol=1e-9)
    np.testing.assert_allclose(lean.vel, ref.vel, atol=1e-9)
    np.testing.assert_allclose(lean.pos_std, ref.pos_std, rtol=1e-9)
    assert lean.est.counters == ref.est.counters
    h_lean, h_ref = lean.est.com, ref.est.com
    np.testing.assert_allclose(h_lean.horizon_state(), h_ref.horizon_state(), atol=1e-9)
    np.testing.assert_allclose(h_lean.horizon_p2(), h_ref.horizon_p2(), rtol=1e-9)
    # the filterpy covariance keeps the kron(P2, I3) structure the lean one relies on
    p = h_ref._kf.P
    p00, p01, p11 = h_ref.horizon_p2()
    np.testing.assert_allclose(p, np.kron(np.array([[p00, p01], [p01, p11]]), np.eye(3)), atol=1e-15)


def test_bad_samples_are_rejected_and_counted() -> None:
    est = StateEstimator(PARAMS, ROBOT)
    t0 = NS
    up = [1.0, 0.0, 0.0, 0.0]
    def imu(t: int, gyro=(0.0, 0.0, 0.0), accel=(0.0, 0.0, 9.81)) -> ImuSample:
        return ImuSample(stamp_ns=t, quat=up, gyro=list(gyro), accel=list(accel))
    def joints(t: int, s: float = 0.01) -> JointSensors:
        return JointSensors(stamp_ns=t, wheel_pos=[0.0] * 3, wheel_vel=[0.0] * 3, wheel_torque=[0.0] * 3,
                            foot_pos=s, foot_vel=0.0, foot_contact=True)
    nan = math.nan
    assert est.update_imu(imu(t0))
    assert est.update_joints(joints(t0))
    for k in range(1, 50):
        assert est.update_imu(imu(t0 + k * DT_NS))
        assert est.update_joints(joints(t0 + k * DT_NS))
        if k % 10 == 0:
            assert est.update_pose(PoseMeasurement(stamp_ns=t0 + k * DT_NS, position=[0.0, 0.0, 0.5], quat=up))
    t = t0 + 49 * DT_NS
    before = est.estimate(t)
    assert not est.update_imu(imu(t + DT_NS, gyro=(nan, 0.0, 0.0)))
    assert not est.update_imu(imu(t + DT_NS, accel=(0.0, math.inf, 9.81)))
    assert not est.update_imu(imu(t))  # not newer than the last sample
    assert not est.update_imu(imu(t + DT_NS, gyro=(100.0, 0.0, 0.0)))  # beyond the gyro's range
    assert not est.update_joints(joints(t + DT_NS, s=nan))
    assert not est.update_joints(joints(t - DT_NS))
    assert not est.update_joints(joints(t + DT_NS, s=0.5))  # beyond the foot's travel
    assert not est.update_pose(PoseMeasurement(stamp_ns=t, position=[nan, 0.0, 0.5], quat=up))
    assert not est.update_pose(PoseMeasurement(stamp_ns=t, position=[0.0, 0.0, 0.5], quat=[0.0, 0.0, 0.0, 0.0]))
    assert not est.update_pose(PoseMeasurement(stamp_ns=t - 20 * DT_NS, position=[0.0, 0.0, 0.5], quat=up))  # older than the last
    assert not est.update_pose(PoseMeasurement(stamp_ns=t + 50 * DT_NS, position=[0.0, 0.0, 0.5], quat=up))  # from the future
    after = est.estimate(t)
    assert after.position == before.position and after.quat == before.quat
    assert all(math.isfinite(v) for v in after.position + after.velocity + after.quat + after.pos_vel_cov)
    c = est.counters
    assert c["imu_nonfinite"] == 2 and c["imu_out_of_order"] == 1 and c["imu_out_of_range"] == 1
    assert c["joints_nonfinite"] == 1 and c["joints_out_of_order"] == 1 and c["joints_out_of_range"] == 1
    assert c["pose_nonfinite"] == 1 and c["pose_bad_quat"] == 1 and c["pose_out_of_order"] == 1 and c["pose_future"] == 1


def test_estimate_before_any_pose_is_not_valid() -> None:
    est = StateEstimator(PARAMS, ROBOT)
    est.update_imu(ImuSample(stamp_ns=NS, quat=[1.0, 0.0, 0.0, 0.0], gyro=[0.0] * 3, accel=[0.0, 0.0, 9.81]))
    msg = est.estimate(NS)
    assert not msg.valid
    assert est.status()["mode"] == "init"
    # and stale once the IMU stops
    assert not est.estimate(NS + int(0.1 * NS)).valid


def test_delayed_pose_is_compared_with_the_past_attitude() -> None:
    """A pose captured before a fast turn matches the estimate of its capture time exactly."""
    f = AttitudeFilter(gyro_noise_density=0.001, gyro_bias_walk=1e-5, init_att_std=0.01, init_bias_std=1e-4, history_len=100)
    f.initialize(quat.IDENTITY, 0, (0.0, 0.0, 5.0))
    truth = [quat.IDENTITY]
    for k in range(1, 41):
        f.propagate(k * DT_NS, 0.0, 0.0, 5.0, 1e-3)  # 5 rad/s about z
        truth.append(quat.mul(truth[-1], quat.exp((0.0, 0.0, 5e-3))))
    q_before = f.q
    assert f.correct_pose(truth[15], 15 * DT_NS, 1e-6, 16.0)  # 25 ms old, 7 degrees ago
    assert quat.angle_between(f.q, q_before) < 1e-9  # consistent: no correction
    assert quat.angle_between(f.q, truth[-1]) < 1e-9


def test_gravity_levels_a_tilted_start() -> None:
    """Quasi-static: the accelerometer's gravity direction corrects tilt (not heading)."""
    est = StateEstimator(PARAMS, ROBOT)
    tilt = quat.from_euler(0.05, -0.04, 0.3)
    g_body = quat.rotate_inv(tilt, (0.0, 0.0, ROBOT.gravity))
    for k in range(2000):
        est.update_imu(ImuSample(stamp_ns=NS + k * DT_NS, quat=[1.0, 0.0, 0.0, 0.0], gyro=[0.0] * 3, accel=list(g_body)))
    roll, pitch, _ = quat.to_euler(est.att.q)
    assert abs(roll - 0.05) < 0.002 and abs(pitch + 0.04) < 0.002


def test_poses_later_than_the_horizon_are_still_used(track: Track) -> None:
    """40 ms latency on a 25 ms horizon: fused at the horizon, extrapolated back, counted."""
    run = run_synthetic(track, PARAMS, SensorConfig(latency_s=0.040))
    c = run.est.counters
    assert c["pose_late"] > 200 and c["pose_fused"] == c["pose_late"]
    pos, vel, att = errors(run, track)
    assert pos < 0.006 and vel < 0.06 and att < 0.3


@pytest.mark.parametrize("change", [
    {"pose_pos_std_m": 0.0}, {"gate_probability": 1.0}, {"pose_delay_s": -0.01},
    {"contact_on_samples": 0}, {"kf_backend": "numpy"}, {"pose_delay_s": 1.0},
])
def test_unusable_parameters_are_refused(change: dict) -> None:
    with pytest.raises(ValueError):
        StateEstimator(replace(PARAMS, **change), ROBOT)
