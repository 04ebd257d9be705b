"""The twin's sensors: what the hardware service would publish, read from the physics.

One :class:`SensorSuite` per run. Each control tick the runner calls :meth:`SensorSuite.tick`
with the physics data and the simulated time; the suite captures every sensor that is due
(IMU and joint frame every tick at 1 kHz, pose at ``pose_rate_hz``, depth at ``depth_rate_hz``),
adds seeded noise and a per-run bias, drops samples with the configured probability, holds each
sample back for its latency, and returns the messages whose delivery time has come. ``stamp_ns``
is always the capture time, as on the robot.

Sensors (all from :class:`onboard.contracts.params.TwinParams`):
- ``imu``: :class:`ImuSample`. Orientation and body rate from the torso's state (the IMU site
  sits at the torso origin with the torso's axes); specific force from MuJoCo's accelerometer
  at that site (evaluated at the start of the last physics step). Gyro and accelerometer carry
  white noise (density * sqrt(rate)) plus a constant bias; the orientation carries white noise.
- ``joints``: :class:`JointSensors`. Wheel and spool angles quantized by the encoder resolution;
  wheel speed, current-derived torque, foot compression and rate with white noise; foot contact
  is the foot's normal load (MuJoCo touch sensor) over ``contact_threshold_n``.
- ``pose``: :class:`PoseMeasurement` of the torso origin (motion capture / tracking camera).
- ``depth``: :class:`onboard.contracts.binary_messages.DepthImage` by ray casting (``mujoco.mj_multiRay``)
  from the MJCF site ``depth_camera`` against world geoms (group 0) only; z-depth with noise
  growing with depth squared; 0 = no return.

With ``noise=False`` every sensor reads the true state (no noise, bias, quantization or dropouts);
latencies still apply. Outages (:class:`SensorOutage`, a schedule for the run) lose every sample a
sensor captures in a window, noise or not: a stalled sensor, as opposed to random dropouts.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field

import mujoco
import numpy as np

from onboard.contracts import messages as m
from onboard.contracts.binary_messages import DepthImage
from onboard.contracts.params import TwinParams
from robot_description import params as rd

NS = 1_000_000_000
_BLOCK = 4096  # noise samples drawn per refill: per-tick work stays a list index
_DEPTH_GROUPS = np.array([1, 0, 0, 0, 0, 0], dtype=np.uint8)  # world geoms only
# Optical frame (x right, y down, z forward) in the camera site frame (x forward, y left, z up).
_SITE_FROM_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


class _Gauss:
    """Seeded unit normals in rows of ``width``, drawn in blocks."""

    def __init__(self, rng: np.random.Generator, width: int) -> None:
        self._rng = rng
        self._width = width
        self._rows: list[list[float]] = []
        self._i = 0

    def row(self) -> list[float]:
        if self._i >= len(self._rows):
            self._rows = self._rng.standard_normal((_BLOCK, self._width)).tolist()
            self._i = 0
        r = self._rows[self._i]
        self._i += 1
        return r


class _Dropout:
    def __init__(self, rng: np.random.Generator, probability: float) -> None:
        self._rng = rng
        self.p = probability
        self._u: list[float] = []
        self._i = 0

    def lost(self) -> bool:
        if self.p <= 0.0:
            return False
        if self._i >= len(self._u):
            self._u = self._rng.random(_BLOCK).tolist()
            self._i = 0
        u = self._u[self._i]
        self._i += 1
        return u < self.p


def _qmul_small(q: list[float], dx: float, dy: float, dz: float) -> list[float]:
    """``q * exp([dx, dy, dz])`` for a small rotation vector (body-frame perturbation), normalized."""
    w, x, y, z = q
    bw, bx, by, bz = 1.0, 0.5 * dx, 0.5 * dy, 0.5 * dz
    rw = w * bw - x * bx - y * by - z * bz
    rx = w * bx + x * bw + y * bz - z * by
    ry = w * by - x * bz + y * bw + z * bx
    rz = w * bz + x * by - y * bx + z * bw
    n = 1.0 / math.sqrt(rw * rw + rx * rx + ry * ry + rz * rz)
    return [rw * n, rx * n, ry * n, rz * n]


def _qmul(p: list[float], q: list[float]) -> list[float]:
    """The quaternion product ``p * q`` (w, x, y, z)."""
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return [pw * qw - px * qx - py * qy - pz * qz, pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx, pw * qz + px * qy - py * qx + pz * qw]


@dataclass(frozen=True)
class SensorOutage:
    """Every sample ``sensor`` captures in ``[start_s, end_s)`` of sim time is lost."""

    sensor: str  # "imu", "joints", "pose" or "depth"
    start_s: float
    end_s: float


@dataclass
class _Stream:
    """One sensor's schedule, latency queue, dropout and outages."""

    period_ns: int
    latency_ns: int
    dropout: _Dropout
    next_ns: int = 0
    seq: int = 0
    outages: list[tuple[int, int]] = field(default_factory=list)  # [start, end) in ns

    def lost(self, now_ns: int) -> bool:
        """Whether the sample captured now is lost (a dropout or an outage)."""
        if self.dropout.p > 0.0 and self.dropout.lost():
            return True
        for start, end in self.outages:
            if start <= now_ns < end:
                return True
        return False

    def __post_init__(self) -> None:
        self.queue: deque[tuple[int, object]] = deque()

    def due(self, now_ns: int) -> bool:
        if now_ns < self.next_ns:
            return False
        self.next_ns += self.period_ns
        if self.next_ns <= now_ns:  # fell behind (a long tick): resynchronize, never burst
            self.next_ns = now_ns + self.period_ns
        return True

    def push(self, now_ns: int, msg: object) -> None:
        self.queue.append((now_ns + self.latency_ns, msg))

    def pop_ready(self, now_ns: int, out: list[tuple[str, object]], topic: str) -> None:
        q = self.queue
        while q and q[0][0] <= now_ns:
            out.append((topic, q.popleft()[1]))


def _period_ns(rate_hz: float) -> int:
    if not (rate_hz > 0 and math.isfinite(rate_hz)):
        raise ValueError(f"sensor rate must be positive, got {rate_hz}")
    return int(round(NS / rate_hz))


def _latency_ns(latency_s: float) -> int:
    if not (latency_s >= 0 and math.isfinite(latency_s)):
        raise ValueError(f"sensor latency must be >= 0, got {latency_s}")
    return int(round(latency_s * NS))


class SensorSuite:
    """All the twin's sensors for one run, seeded by ``seed``."""

    def __init__(self, model: mujoco.MjModel, params: TwinParams | None = None, seed: int = 0,
                 outages: Sequence[SensorOutage] = ()) -> None:
        p = params or TwinParams()
        self.params = p
        self.model = model
        noisy = p.noise
        streams = np.random.SeedSequence(seed).spawn(8)
        rngs = [np.random.default_rng(s) for s in streams]

        def drop(rng: np.random.Generator, prob: float) -> _Dropout:
            if not 0.0 <= prob < 1.0:
                raise ValueError(f"dropout probability must be in [0, 1), got {prob}")
            return _Dropout(rng, prob if noisy else 0.0)

        self.imu = _Stream(_period_ns(p.imu_rate_hz), _latency_ns(p.imu_latency_s), drop(rngs[0], p.imu_dropout))
        self.joints = _Stream(_period_ns(p.control_rate_hz), _latency_ns(p.joints_latency_s), drop(rngs[1], p.joints_dropout))
        self.pose = _Stream(_period_ns(p.pose_rate_hz), _latency_ns(p.pose_latency_s), drop(rngs[2], p.pose_dropout))
        self.depth = _Stream(_period_ns(p.depth_rate_hz), _latency_ns(p.depth_latency_s), drop(rngs[3], p.depth_dropout))
        streams_by_name = {"imu": self.imu, "joints": self.joints, "pose": self.pose, "depth": self.depth}
        for o in outages:
            if o.sensor not in streams_by_name:
                raise ValueError(f"unknown sensor {o.sensor!r} in an outage; known: {', '.join(streams_by_name)}")
            if not (math.isfinite(o.start_s) and math.isfinite(o.end_s) and 0.0 <= o.start_s < o.end_s):
                raise ValueError(f"an outage needs 0 <= start < end, got {o.start_s} .. {o.end_s} s")
            streams_by_name[o.sensor].outages.append((int(round(o.start_s * NS)), int(round(o.end_s * NS))))

        scale = 1.0 if noisy else 0.0
        self._gyro_std = scale * p.gyro_noise_density * math.sqrt(p.imu_rate_hz)
        self._accel_std = scale * p.accel_noise_density * math.sqrt(p.imu_rate_hz)
        self._imu_att_std = scale * p.imu_att_std
        bias_rng = rngs[4]
        self.gyro_bias = (scale * p.gyro_bias_std * bias_rng.standard_normal(3)).tolist()
        self.accel_bias = (scale * p.accel_bias_std * bias_rng.standard_normal(3)).tolist()
        self._imu_noise = _Gauss(rngs[0], 9)
        self._joint_noise = _Gauss(rngs[1], 8)
        self._pose_noise = _Gauss(rngs[2], 6)
        self._depth_rng = rngs[3]
        self._wheel_vel_std = scale * p.wheel_vel_std
        self._wheel_torque_std = scale * p.wheel_torque_std
        self._foot_pos_std = scale * p.foot_pos_std
        self._foot_vel_std = scale * p.foot_vel_std
        self._pose_pos_std = scale * p.pose_pos_std
        self._pose_att_std = scale * p.pose_att_std
        self._depth_noise = scale * p.depth_noise_per_m2
        if p.encoder_counts_per_rev <= 0:
            raise ValueError("encoder_counts_per_rev must be positive")
        self._enc_res = 2 * math.pi / p.encoder_counts_per_rev if noisy else 0.0
        self._contact_threshold = p.contact_threshold_n
        # False: depth images are not made at all (a lockstep run whose depth nobody reads;
        # the depth stream draws from its own generator, so the other sensors are unchanged)
        self.capture_depth = True
        # IMU mount misalignment (a model error): the IMU's axes are the body's turned by this
        # rotation; None: mounted as the MJCF says (the per-tick path skips it)
        self._imu_mount_q: list[float] | None = None
        self._imu_mount_rt: list[float] = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]

        # Addresses into qpos / qvel / sensordata / actuator_force.
        root = model.joint(rd.ROOT_JOINT)
        self._qp = int(root.qposadr[0])
        self._qv = int(root.dofadr[0])
        self._wheel_qp = [int(model.joint(n).qposadr[0]) for n in rd.WHEEL_JOINTS]
        self._wheel_qv = [int(model.joint(n).dofadr[0]) for n in rd.WHEEL_JOINTS]
        self._wheel_act = [int(model.actuator(n).id) for n in rd.WHEEL_ACTUATORS]
        self._foot_qp = int(model.joint(rd.FOOT_JOINT).qposadr[0])
        self._foot_qv = int(model.joint(rd.FOOT_JOINT).dofadr[0])
        self._spool_qp = int(model.joint(rd.FOOT_MOTOR_JOINT).qposadr[0])
        self._accel_adr = int(model.sensor("imu_accel").adr[0])
        self._touch_adr = int(model.sensor(rd.FOOT_TOUCH_SENSOR).adr[0])

        # Depth camera: pixel ray directions in the optical frame, fixed for the run.
        w, h = p.depth_width, p.depth_height
        if w <= 0 or h <= 0 or not 0.0 < p.depth_hfov_deg < 180.0:
            raise ValueError("depth camera needs a positive size and 0 < hfov < 180 deg")
        self.fx = self.fy = 0.5 * w / math.tan(math.radians(p.depth_hfov_deg) / 2)
        self.cx, self.cy = 0.5 * w, 0.5 * h
        u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
        rays = np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, np.ones_like(u)], axis=-1).reshape(-1, 3)
        self._ray_z = 1.0 / np.linalg.norm(rays, axis=1)  # z component of each unit ray
        self._rays_optical = rays * self._ray_z[:, None]
        self._cam_site = int(model.site("depth_camera").id)
        self._ray_geom = np.zeros(w * h, dtype=np.int32)
        self._ray_dist = np.zeros(w * h)

    # --- per tick -----------------------------------------------------------------

    def tick(self, data: mujoco.MjData, now_ns: int) -> list[tuple[str, object]]:
        """Capture what is due at ``now_ns`` and return ``(topic, message)`` pairs delivered now."""
        out: list[tuple[str, object]] = []
        # plain floats, each array read once: numpy scalars and array views are slow per tick
        qpos, qvel, sd = data.qpos.tolist(), data.qvel.tolist(), data.sensordata.tolist()
        # the schedule and queue tests inline (four streams a tick; most are not due)
        imu, joints, pose, depth = self.imu, self.joints, self.pose, self.depth
        if now_ns >= imu.next_ns and imu.due(now_ns) and not ((imu.dropout.p > 0.0 or imu.outages) and imu.lost(now_ns)):
            imu.push(now_ns, self._imu(sd, qpos, qvel, now_ns))
        if (now_ns >= joints.next_ns and joints.due(now_ns)
                and not ((joints.dropout.p > 0.0 or joints.outages) and joints.lost(now_ns))):
            joints.push(now_ns, self._joints(data, sd, qpos, qvel, now_ns))
        if now_ns >= pose.next_ns and pose.due(now_ns) and not ((pose.dropout.p > 0.0 or pose.outages) and pose.lost(now_ns)):
            pose.push(now_ns, self._pose(qpos, now_ns))
        if (self.capture_depth and now_ns >= depth.next_ns and depth.due(now_ns)
                and not ((depth.dropout.p > 0.0 or depth.outages) and depth.lost(now_ns))):
            depth.push(now_ns, self.depth_image(data, now_ns))
        if imu.queue and imu.queue[0][0] <= now_ns:
            imu.pop_ready(now_ns, out, "imu")
        if joints.queue and joints.queue[0][0] <= now_ns:
            joints.pop_ready(now_ns, out, "joints")
        if pose.queue and pose.queue[0][0] <= now_ns:
            pose.pop_ready(now_ns, out, "pose")
        if depth.queue and depth.queue[0][0] <= now_ns:
            depth.pop_ready(now_ns, out, "depth")
        return out

    def set_imu_misalignment(self, rx: float, ry: float, rz: float) -> None:
        """Mount the IMU turned by the rotation vector ``(rx, ry, rz)`` [rad] from the body's axes:
        it reports the orientation of its own axes and the rate and specific force in them."""
        angle = math.sqrt(rx * rx + ry * ry + rz * rz)
        if angle == 0.0:
            self._imu_mount_q = None
            return
        s = math.sin(0.5 * angle) / angle
        q = [math.cos(0.5 * angle), rx * s, ry * s, rz * s]
        self._imu_mount_q = q
        w, x, y, z = q  # R (body <- imu); the IMU reads R^T v
        r = [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
             2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
             2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]
        self._imu_mount_rt = [r[0], r[3], r[6], r[1], r[4], r[7], r[2], r[5], r[8]]

    def _imu(self, sd: list[float], qpos: list[float], qvel: list[float], now_ns: int) -> m.ImuSample:
        n = self._imu_noise.row()
        a, g, b = self._imu_att_std, self._gyro_std, self._accel_std
        gb, ab = self.gyro_bias, self.accel_bias
        i, j, k = self._qp + 3, self._qv + 3, self._accel_adr
        q_body = qpos[i:i + 4]
        wx, wy, wz = qvel[j], qvel[j + 1], qvel[j + 2]
        fx, fy, fz = sd[k], sd[k + 1], sd[k + 2]
        mq = self._imu_mount_q
        if mq is not None:
            q_body = _qmul(q_body, mq)
            rt = self._imu_mount_rt
            wx, wy, wz = rt[0] * wx + rt[1] * wy + rt[2] * wz, rt[3] * wx + rt[4] * wy + rt[5] * wz, rt[6] * wx + rt[7] * wy + rt[8] * wz
            fx, fy, fz = rt[0] * fx + rt[1] * fy + rt[2] * fz, rt[3] * fx + rt[4] * fy + rt[5] * fz, rt[6] * fx + rt[7] * fy + rt[8] * fz
        quat = _qmul_small(q_body, a * n[0], a * n[1], a * n[2]) if a > 0 else q_body
        self.imu.seq += 1
        return m.ImuSample(
            stamp_ns=now_ns,
            seq=self.imu.seq,
            quat=quat,
            gyro=[wx + gb[0] + g * n[3], wy + gb[1] + g * n[4], wz + gb[2] + g * n[5]],
            accel=[fx + ab[0] + b * n[6], fy + ab[1] + b * n[7], fz + ab[2] + b * n[8]],
        )

    def _joints(self, data: mujoco.MjData, sd: list[float], qpos: list[float], qvel: list[float], now_ns: int) -> m.JointSensors:
        force = data.actuator_force.tolist()
        n = self._joint_noise.row()
        wv, wt = self._wheel_vel_std, self._wheel_torque_std
        wp, wq, wa = self._wheel_qp, self._wheel_qv, self._wheel_act
        r = self._enc_res  # encoder quantization, inline (four angles a tick)
        if r > 0:
            p0, p1, p2 = round(qpos[wp[0]] / r) * r, round(qpos[wp[1]] / r) * r, round(qpos[wp[2]] / r) * r
            spool = round(qpos[self._spool_qp] / r) * r
        else:
            p0, p1, p2, spool = qpos[wp[0]], qpos[wp[1]], qpos[wp[2]], qpos[self._spool_qp]
        self.joints.seq += 1
        return m.JointSensors(
            stamp_ns=now_ns,
            seq=self.joints.seq,
            wheel_pos=[p0, p1, p2],
            wheel_vel=[qvel[wq[0]] + wv * n[0], qvel[wq[1]] + wv * n[1], qvel[wq[2]] + wv * n[2]],
            wheel_torque=[force[wa[0]] + wt * n[3], force[wa[1]] + wt * n[4], force[wa[2]] + wt * n[5]],
            foot_pos=qpos[self._foot_qp] + self._foot_pos_std * n[6],
            foot_vel=qvel[self._foot_qv] + self._foot_vel_std * n[7],
            foot_contact=sd[self._touch_adr] > self._contact_threshold,
            foot_motor_pos=spool,
        )

    def _pose(self, qpos: list[float], now_ns: int) -> m.PoseMeasurement:
        n = self._pose_noise.row()
        s, a, i = self._pose_pos_std, self._pose_att_std, self._qp
        quat = qpos[i + 3:i + 7]
        self.pose.seq += 1
        return m.PoseMeasurement(
            stamp_ns=now_ns,
            seq=self.pose.seq,
            position=[qpos[i] + s * n[0], qpos[i + 1] + s * n[1], qpos[i + 2] + s * n[2]],
            quat=_qmul_small(quat, a * n[3], a * n[4], a * n[5]) if a > 0 else quat,
            source=self.params.pose_source,
        )

    def depth_image(self, data: mujoco.MjData, now_ns: int = 0) -> DepthImage:
        """Ray-cast a depth image from the camera site's pose in ``data`` (last forward pass)."""
        p = self.params
        pos = data.site_xpos[self._cam_site].copy()
        rot = data.site_xmat[self._cam_site].reshape(3, 3) @ _SITE_FROM_OPTICAL  # optical -> world
        vec = self._rays_optical @ rot.T
        n = vec.shape[0]
        mujoco.mj_multiRay(self.model, data, pos, vec.reshape(-1), _DEPTH_GROUPS, True, -1,
                           self._ray_geom, self._ray_dist, None, n, p.depth_max_range_m)
        dist = self._ray_dist
        z = dist * self._ray_z
        hit = (dist >= 0.0) & (z <= p.depth_max_range_m)
        if self._depth_noise > 0:
            z = z + self._depth_noise * z * z * self._depth_rng.standard_normal(n)
        depth = np.where(hit & (z > 0), z, 0.0).astype(np.float32).reshape(p.depth_height, p.depth_width)
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, rot.reshape(-1))
        self.depth.seq += 1
        return DepthImage(depth=depth, fx=self.fx, fy=self.fy, cx=self.cx, cy=self.cy, cam_pos=pos, cam_quat=quat,
                          stamp_ns=now_ns, seq=self.depth.seq)
