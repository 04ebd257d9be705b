"""CoM position and velocity: a linear Kalman filter on a delayed fusion horizon.

State ``x = [p, v]`` (world, m and m/s) of the whole robot's centre of mass, driven by
a known acceleration per IMU sample:

- flight: projectile dynamics, ``a = g`` exactly (thesis line 2751: "a Kalman filter
  with projectile dynamics is used to filter the position estimates ... in the flight
  phase"); process noise only for what the model leaves out (drag);
- stance, the foot pinned: the accelerometer drives it, ``a = (m_sprung / m) a_body``
  (the pinned foot does not accelerate, so the CoM's acceleration is the sprung
  mass's share), and leg kinematics measure the CoM velocity about the foot;
- touchdown: the impact stops the foot, an impulse ``-m_foot v_foot / m`` on the CoM
  velocity, with added uncertainty;
- IMU gaps: an interval longer than the IMU's period integrates an acceleration the
  accelerometer did not see in between; the caller passes the variance that adds
  (:meth:`ComFilter.push` ``gap_cov``), and :meth:`ComFilter.output_p2` includes it
  from the moment it is pushed, not only once the horizon reaches it.

Gating: every pose is tested against the state at its capture time before it is used
at all (:meth:`ComFilter.admits_pose`), and again when the horizon fuses it. There is
no reset after a run of rejections: the covariance grows while no pose is fused, so a
real pose that the gate refuses today is admitted once the uncertainty has grown to
admit it, while a stream of gross outliers (a foreign publisher, a wrong frame) stays
refused as long as the real poses keep the covariance small.

Latency compensation (buffer and replay, as PX4's EKF2 does it): the filter runs
``delay`` behind the newest IMU sample. Each sample is buffered with its input and
any leg measurement; the horizon consumes a sample once it is ``delay`` old, so a
pose captured up to ``delay`` ago is fused exactly at its capture time, in order. The
output at the newest sample is the horizon state propagated through the buffered
inputs; the propagation is linear, so it is kept incrementally (``x_out = Phi x_h +
inputs``) and each correction ``dx`` at the horizon moves it by ``Phi(T) dx``:
O(1) per sample, no replay loop.

Noise is isotropic (every measurement observes all three axes with the same
variance), so the 6x6 covariance is ``kron(P2, I3)`` with one 2x2 ``P2`` shared by x,
y and z: the lean backend keeps three floats. The ``filterpy`` backend runs the same
model through :class:`filterpy.kalman.KalmanFilter` on the full 6-state matrices; it is
the reference the lean arithmetic is tested against, and ~10x slower.
"""

from __future__ import annotations

import math
from bisect import insort
from collections import deque
from collections.abc import Sequence
from operator import itemgetter

import numpy as np

NS = 1_000_000_000
_stamp = itemgetter(0)

Entry = list  # [t_ns, dt, ax, ay, az, stance, foot_s, impulse | None, leg | None, gap_cov | None]
_T, _DT, _AX, _AY, _AZ, _STANCE, _S, _IMP, _LEG, _GAP = range(10)
Cov2 = tuple[float, float, float]  # (P_pp, P_pv, P_vv) of one axis


REACQUIRE_MARGIN = 2.0  # re-acquiring a lost track: the pose's innovation at half the gate


def _advance(x: list[float], dt: float, ax: float, ay: float, az: float) -> None:
    """The mean ``[p, v]`` over ``dt`` under constant acceleration ``a`` (in place)."""
    h = 0.5 * dt * dt
    x[0] += x[3] * dt + ax * h
    x[1] += x[4] * dt + ay * h
    x[2] += x[5] * dt + az * h
    x[3] += ax * dt
    x[4] += ay * dt
    x[5] += az * dt


class ComFilter:
    """CoM Kalman filter with a delayed fusion horizon (lean float arithmetic)."""

    def __init__(
        self,
        *,
        delay_s: float,
        compensate_latency: bool,
        accel_psd_flight: float,
        accel_psd_stance: float,
        init_pos_std: float,
        init_vel_std: float,
        gate_chi2: float,
        com_offset_body: Sequence[float],
        com_per_compression: Sequence[float],
        reacquire_s: float = math.inf,
    ) -> None:
        """``com_offset_body``: CoM relative to the pose sensor's point at zero foot
        compression [m, body]; ``com_per_compression``: its derivative with respect to the
        compression [m/m, body]; ``gate_chi2``: 3-dof Mahalanobis gate; ``reacquire_s``:
        with no pose fused for this long, a gated pose means the filter is the one that is
        wrong (see :meth:`admits_pose`)."""
        self.compensate = compensate_latency
        self._delay_ns = int(round(delay_s * NS)) if compensate_latency else 0
        self._q_flight = accel_psd_flight
        self._q_stance = accel_psd_stance
        self._gate = gate_chi2
        self._reacquire_ns = reacquire_s * NS
        self._c0 = tuple(float(v) for v in com_offset_body)
        self._ck = tuple(float(v) for v in com_per_compression)
        self._init_pos_var = init_pos_std * init_pos_std
        self._init_vel_var = init_vel_std * init_vel_std
        self._entries: deque[Entry] = deque()
        self._pending: list[tuple] = []  # poses waiting for the horizon, sorted by stamp
        self._gaps: deque[tuple[int, float, float, float]] = deque()  # gap covariances pushed, not yet at the horizon
        self._x = [0.0] * 6  # horizon mean
        self._p = [self._init_pos_var, 0.0, self._init_vel_var]  # horizon P2
        self._out = [0.0] * 6  # output mean at t_out
        self.t_out = 0
        self._t_h = 0
        self._q_out = accel_psd_flight
        self._last_a = (0.0, 0.0, 0.0)  # input and foot compression at the horizon
        self._last_s = 0.0
        self.last_fused_stamp = -1  # capture stamp of the newest fused pose [ns]
        self.counters = {"pose_fused": 0, "pose_outliers": 0, "pose_late": 0, "pose_reacquired": 0, "leg_fused": 0, "leg_outliers": 0}

    # --- inputs ------------------------------------------------------------------

    def start(self, t_ns: int) -> None:
        self.t_out = self._t_h = t_ns

    def push(self, t_ns: int, dt: float, ax: float, ay: float, az: float, stance: bool, foot_s: float,
             gap_cov: Cov2 | None = None) -> None:
        """One IMU sample: the CoM acceleration [m/s^2, world] over the ``dt`` [s] ending at ``t_ns``;
        ``gap_cov``: per-axis covariance the interval adds beyond the process noise (an IMU gap)."""
        out = self._out
        vx, vy, vz = out[3], out[4], out[5]
        h = 0.5 * dt * dt
        out[0] += vx * dt + ax * h
        out[1] += vy * dt + ay * h
        out[2] += vz * dt + az * h
        out[3] = vx + ax * dt
        out[4] = vy + ay * dt
        out[5] = vz + az * dt
        self.t_out = t_ns
        self._q_out = self._q_stance if stance else self._q_flight
        self._entries.append([t_ns, dt, ax, ay, az, stance, foot_s, None, None, gap_cov])
        if gap_cov is not None:
            self._gaps.append((t_ns, *gap_cov))
        limit = t_ns - self._delay_ns
        entries = self._entries
        while entries and entries[0][_T] <= limit:
            self._step(entries.popleft())

    def set_stance_psd(self, psd: float) -> None:
        """The stance process noise from now on [(m/s^2)^2/Hz] (its input changed: measured or modelled)."""
        self._q_stance = psd

    def add_impulse(self, dvx: float, dvy: float, dvz: float, var: float, at_ns: int) -> None:
        """A velocity jump [m/s] after the newest sample stamped at or before ``at_ns``
        (at the horizon if that one is consumed already), with variance ``var`` [(m/s)^2]
        per axis."""
        t_at = self._t_h
        for e in reversed(self._entries):
            if e[_T] <= at_ns:
                old = e[_IMP]
                e[_IMP] = (dvx, dvy, dvz, var) if old is None else (old[0] + dvx, old[1] + dvy, old[2] + dvz, old[3] + var)
                t_at = e[_T]
                break
        else:
            self._impulse(dvx, dvy, dvz, var)
        # the output has been moving with the new velocity since then
        lag = (self.t_out - t_at) / NS
        out = self._out
        out[0] += dvx * lag
        out[1] += dvy * lag
        out[2] += dvz * lag
        out[3] += dvx
        out[4] += dvy
        out[5] += dvz

    def anchor(self, px: float, py: float, pz: float, var: float) -> None:
        """Define the position now [m]: the output moves there and the horizon with it, its position
        variance ``var`` [m^2] per axis (the velocity and its variance stay): an odometry origin."""
        out = self._out
        dx, dy, dz = px - out[0], py - out[1], pz - out[2]
        out[0], out[1], out[2] = px, py, pz
        self._anchor_horizon(dx, dy, dz, var)

    def shift_height(self, dz: float) -> None:
        """Move the CoM's height by ``dz`` [m], output and horizon alike (its covariance stays)."""
        self._out[2] += dz
        self._shift_horizon_height(dz)

    def shift_horizontal(self, dx: float, dy: float) -> None:
        """Move the CoM by ``(dx, dy)`` [m, world], output and horizon alike (its covariance stays):
        a correction of the odometry frame from a displacement measured elsewhere (visual odometry)."""
        self._out[0] += dx
        self._out[1] += dy
        self._shift_horizon_xy(dx, dy)

    def _shift_horizon_height(self, dz: float) -> None:
        self._x[2] += dz

    def _shift_horizon_xy(self, dx: float, dy: float) -> None:
        self._x[0] += dx
        self._x[1] += dy

    def _anchor_horizon(self, dx: float, dy: float, dz: float, var: float) -> None:
        x = self._x
        x[0] += dx
        x[1] += dy
        x[2] += dz
        self._p = [var, 0.0, self._p[2]]

    def add_leg_velocity(self, vx: float, vy: float, vz: float, var: float) -> None:
        """CoM velocity [m/s, world] from leg kinematics at the newest sample."""
        if self._entries:
            self._entries[-1][_LEG] = (vx, vy, vz, var)
        else:
            self._fuse_leg((vx, vy, vz, var))

    def add_pose(self, stamp_ns: int, origin: Sequence[float], rot: Sequence[float], var: float) -> None:
        """A pose sensor position [m, world] captured at ``stamp_ns``; ``rot``: its attitude
        as a row-major body->world matrix; ``var``: position noise [m^2] per axis."""
        pose = (stamp_ns, origin[0], origin[1], origin[2], tuple(rot), var)
        if not self.compensate:
            self._fuse_pose(pose, self._t_h, 0.0, 0.0, 0.0, self._entries[-1][_S] if self._entries else self._last_s, as_current=True)
        elif stamp_ns <= self._t_h:  # older than the horizon: fuse there, extrapolated back
            self.counters["pose_late"] += 1
            self._fuse_pose(pose, self._t_h, *self._last_a, self._last_s)
        else:
            insort(self._pending, pose, key=_stamp)

    # --- the horizon ----------------------------------------------------------------

    def _step(self, e: Entry) -> None:
        t = e[_T]
        pending = self._pending
        if pending and pending[0][0] <= (self._t_h + t) // 2:
            # nearer the interval's start: fused there (over an IMU gap the far end is far)
            mid = (self._t_h + t) // 2
            while pending and pending[0][0] <= mid:
                self._fuse_pose(pending.pop(0), self._t_h, *self._last_a, self._last_s)
        ax, ay, az = e[_AX], e[_AY], e[_AZ]
        self._predict(e[_DT], ax, ay, az, self._q_stance if e[_STANCE] else self._q_flight)
        self._t_h = t
        self._last_a = (ax, ay, az)
        self._last_s = e[_S]
        gap = e[_GAP]
        if gap is not None:
            self._add_cov(*gap)
            self._gaps.popleft()
        imp = e[_IMP]
        if imp is not None:
            self._impulse(*imp)
        while pending and pending[0][0] <= t:
            self._fuse_pose(pending.pop(0), t, ax, ay, az, e[_S])
        leg = e[_LEG]
        if leg is not None:
            self._fuse_leg(leg)

    def _com_point(self, pose: tuple, foot_s: float) -> tuple[float, float, float]:
        """The CoM [m, world] a pose (sensor point and attitude) puts at foot compression ``foot_s``."""
        _, ox, oy, oz, r, _ = pose
        c0, ck = self._c0, self._ck
        cx = c0[0] + ck[0] * foot_s
        cy = c0[1] + ck[1] * foot_s
        cz = c0[2] + ck[2] * foot_s
        return (ox + r[0] * cx + r[1] * cy + r[2] * cz, oy + r[3] * cx + r[4] * cy + r[5] * cz,
                oz + r[6] * cx + r[7] * cy + r[8] * cz)

    def admits_pose(self, stamp_ns: int, origin: Sequence[float], rot: Sequence[float], var: float) -> bool:
        """The gate, before the pose is used at all: its CoM point against the state predicted
        to its capture time (the horizon stepped through the buffered samples, without their
        leg measurements, so the covariance errs large). A refusal is counted as an outlier."""
        x = list(self.horizon_state())
        p00, p01, p11 = self.horizon_p2()
        t = self._t_h
        s = self._last_s
        for e in self._entries:
            if e[_T] > stamp_ns:
                break
            dt = e[_DT]
            h = 0.5 * dt * dt
            _advance(x, dt, e[_AX], e[_AY], e[_AZ])
            q = self._q_stance if e[_STANCE] else self._q_flight
            p00, p01, p11 = (p00 + dt * (2.0 * p01 + dt * p11) + q * dt * dt * dt / 3.0, p01 + dt * p11 + q * h, p11 + q * dt)
            gap = e[_GAP]
            if gap is not None:
                p00, p01, p11 = p00 + gap[0], p01 + gap[1], p11 + gap[2]
            imp = e[_IMP]
            if imp is not None:
                x[3] += imp[0]
                x[4] += imp[1]
                x[5] += imp[2]
                p11 += imp[3]
            t, s = e[_T], e[_S]
        # the rest of the way (or back, for a pose older than the horizon): constant velocity,
        # the unmodelled acceleration in the variance
        tau = (stamp_ns - t) / NS
        zx, zy, zz = self._com_point((stamp_ns, origin[0], origin[1], origin[2], rot, var), s)
        q = max(self._q_stance, self._q_flight)
        a = abs(tau)
        sv = p00 + tau * (2.0 * p01 + tau * p11) + q * a * a * a / 3.0 + var
        yx = zx - x[0] - tau * x[3]
        yy = zy - x[1] - tau * x[4]
        yz = zz - x[2] - tau * x[5]
        d2 = yx * yx + yy * yy + yz * yz
        if d2 / sv <= self._gate:
            return True
        newest = max(self.last_fused_stamp, max((pose[0] for pose in self._pending), default=-1))
        if stamp_ns - newest <= self._reacquire_ns:
            self.counters["pose_outliers"] += 1
            return False
        # Every pose refused for reacquire_s while the IMU kept the filter going: it is the
        # state that went wrong (a stall, a missed touchdown), not the poses. Inflate the
        # position variance to what admits this one (with margin) and the velocity's over
        # the same time, as if that error had built up unseen: the pose then pulls the state
        # back. A foreign stream beside the real one never gets here: the real poses keep
        # being fused.
        excess = REACQUIRE_MARGIN * d2 / self._gate - sv
        window = self._reacquire_ns / NS
        self._add_cov(excess, 0.0, excess / (window * window))
        self.counters["pose_reacquired"] += 1
        return True

    def _fuse_pose(self, pose: tuple, t_ns: int, ax: float, ay: float, az: float, foot_s: float, as_current: bool = False) -> None:
        stamp, _, _, _, _, var = pose
        zx, zy, zz = self._com_point(pose, foot_s)
        tau = 0.0 if as_current else (t_ns - stamp) / NS
        if tau > 0.0:  # p(t - tau) = p(t) - v tau + a tau^2 / 2
            k = 0.5 * tau * tau
            zx -= ax * k
            zy -= ay * k
            zz -= az * k
        if self._update_position(zx, zy, zz, var, -tau):
            self.counters["pose_fused"] += 1
            self.last_fused_stamp = max(self.last_fused_stamp, stamp)
        else:
            self.counters["pose_outliers"] += 1

    def _fuse_leg(self, leg: tuple) -> None:
        if self._update_velocity(*leg):
            self.counters["leg_fused"] += 1
        else:
            self.counters["leg_outliers"] += 1

    def _shift_output(self, dpx: float, dpy: float, dpz: float, dvx: float, dvy: float, dvz: float) -> None:
        """Carry a horizon correction to the output: ``x_out += Phi(T) dx``."""
        lag = (self.t_out - self._t_h) / NS
        out = self._out
        out[0] += dpx + lag * dvx
        out[1] += dpy + lag * dvy
        out[2] += dpz + lag * dvz
        out[3] += dvx
        out[4] += dvy
        out[5] += dvz

    # --- Kalman arithmetic (overridden by the filterpy backend) ------------------------

    def _predict(self, dt: float, ax: float, ay: float, az: float, q: float) -> None:
        _advance(self._x, dt, ax, ay, az)
        h = 0.5 * dt * dt
        p00, p01, p11 = self._p
        # F P F^T + Q, Q the discretized continuous white-noise acceleration model
        self._p = [
            p00 + dt * (2.0 * p01 + dt * p11) + q * dt * dt * dt / 3.0,
            p01 + dt * p11 + q * h,
            p11 + q * dt,
        ]

    def _add_cov(self, pp: float, pv: float, vv: float) -> None:
        p = self._p
        self._p = [p[0] + pp, p[1] + pv, p[2] + vv]

    def _impulse(self, dvx: float, dvy: float, dvz: float, var: float) -> None:
        x = self._x
        x[3] += dvx
        x[4] += dvy
        x[5] += dvz
        self._p[2] += var

    def _update_position(self, zx: float, zy: float, zz: float, var: float, h1: float) -> bool:
        """Measurement ``z = p + h1 v`` per axis; returns False when gated out."""
        x = self._x
        p00, p01, p11 = self._p
        a = p00 + h1 * p01  # (P H^T)_p
        b = p01 + h1 * p11  # (P H^T)_v
        s = a + h1 * b + var
        yx = zx - x[0] - h1 * x[3]
        yy = zy - x[1] - h1 * x[4]
        yz = zz - x[2] - h1 * x[5]
        if (yx * yx + yy * yy + yz * yz) / s > self._gate:
            return False
        ka, kb = a / s, b / s
        self._correct(ka, kb, yx, yy, yz, [p00 - ka * a, p01 - ka * b, p11 - kb * b])
        return True

    def _update_velocity(self, zx: float, zy: float, zz: float, var: float) -> bool:
        """Measurement ``z = v`` per axis; returns False when gated out."""
        x = self._x
        p00, p01, p11 = self._p
        s = p11 + var
        yx = zx - x[3]
        yy = zy - x[4]
        yz = zz - x[5]
        if (yx * yx + yy * yy + yz * yz) / s > self._gate:
            return False
        ka, kb = p01 / s, p11 / s
        self._correct(ka, kb, yx, yy, yz, [p00 - ka * p01, p01 - ka * p11, p11 - kb * p11])
        return True

    def _correct(self, ka: float, kb: float, yx: float, yy: float, yz: float, p_new: list[float]) -> None:
        """Apply the per-axis gains ``(ka, kb)`` to the innovation and adopt ``p_new``."""
        x = self._x
        dpx, dpy, dpz = ka * yx, ka * yy, ka * yz
        dvx, dvy, dvz = kb * yx, kb * yy, kb * yz
        x[0] += dpx
        x[1] += dpy
        x[2] += dpz
        x[3] += dvx
        x[4] += dvy
        x[5] += dvz
        self._p = p_new
        self._shift_output(dpx, dpy, dpz, dvx, dvy, dvz)

    def horizon_p2(self) -> tuple[float, float, float]:
        """``(P_pp, P_pv, P_vv)`` of one axis at the horizon."""
        p00, p01, p11 = self._p
        return p00, p01, p11

    def horizon_state(self) -> tuple[float, ...]:
        """``(p, v)`` at the horizon."""
        return tuple(self._x)

    @property
    def pending_poses(self) -> int:
        """Poses received but not yet reached by the fusion horizon."""
        return len(self._pending)

    # --- output -----------------------------------------------------------------------

    @property
    def position(self) -> tuple[float, float, float]:
        out = self._out
        return out[0], out[1], out[2]

    @property
    def velocity(self) -> tuple[float, float, float]:
        out = self._out
        return out[3], out[4], out[5]

    def output_p2(self, extra_s: float = 0.0) -> tuple[float, float, float]:
        """Per-axis ``(P_pp, P_pv, P_vv)`` at the output time plus ``extra_s`` [s]:
        the horizon covariance propagated over the lag with the current phase's noise."""
        p00, p01, p11 = self.horizon_p2()
        lag = (self.t_out - self._t_h) / NS + extra_s
        q = self._q_out
        p00, p01, p11 = (
            p00 + lag * (2.0 * p01 + lag * p11) + q * lag * lag * lag / 3.0,
            p01 + lag * p11 + 0.5 * q * lag * lag,
            p11 + q * lag,
        )
        t_end = self.t_out + int(extra_s * NS)
        for t, gpp, gpv, gvv in self._gaps:  # pushed but not yet at the horizon (rare: IMU gaps)
            lag = (t_end - t) / NS
            p00 += gpp + lag * (2.0 * gpv + lag * gvv)
            p01 += gpv + lag * gvv
            p11 += gvv
        return p00, p01, p11


class FilterpyComFilter(ComFilter):
    """The same filter with filterpy's :class:`~filterpy.kalman.KalmanFilter` doing the
    Kalman arithmetic on the full 6-state matrices (the reference for the lean one)."""

    def attach_filterpy(self) -> None:
        """Hands the Kalman arithmetic to filterpy, from the lean filter's initial covariance.
        Not an ``__init__`` forwarding ``**kwargs``: a compiled build (setup.py) refuses that."""
        from filterpy.common import Q_continuous_white_noise
        from filterpy.kalman import KalmanFilter

        self._qcwn = Q_continuous_white_noise
        kf = KalmanFilter(dim_x=6, dim_z=3)
        kf.x = np.zeros((6, 1))
        kf.P = np.kron(np.array([[self._p[0], self._p[1]], [self._p[1], self._p[2]]]), np.eye(3))
        self._kf = kf
        self._mats: dict[tuple[float, float], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._h_vel = np.hstack([np.zeros((3, 3)), np.eye(3)])

    def _matrices(self, dt: float, q: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        key = (dt, q)
        mats = self._mats.get(key)
        if mats is None:
            f = np.eye(6)
            f[0:3, 3:6] = dt * np.eye(3)
            b = np.vstack([0.5 * dt * dt * np.eye(3), dt * np.eye(3)])
            # state order [x y z x' y' z']: filterpy's order_by_dim=False
            qm = self._qcwn(2, dt=dt, spectral_density=q, block_size=3, order_by_dim=False)
            mats = self._mats[key] = (f, b, qm)
        return mats

    def _predict(self, dt: float, ax: float, ay: float, az: float, q: float) -> None:
        f, b, qm = self._matrices(dt, q)
        self._kf.predict(u=np.array([[ax], [ay], [az]]), B=b, F=f, Q=qm)

    def _add_cov(self, pp: float, pv: float, vv: float) -> None:
        self._kf.P += np.kron(np.array([[pp, pv], [pv, vv]]), np.eye(3))

    def _shift_horizon_height(self, dz: float) -> None:
        self._kf.x[2, 0] += dz

    def _shift_horizon_xy(self, dx: float, dy: float) -> None:
        self._kf.x[0, 0] += dx
        self._kf.x[1, 0] += dy

    def _anchor_horizon(self, dx: float, dy: float, dz: float, var: float) -> None:
        kf = self._kf
        kf.x[0:3, 0] += (dx, dy, dz)
        kf.P[0:3, :] = 0.0
        kf.P[:, 0:3] = 0.0
        kf.P[0:3, 0:3] = var * np.eye(3)

    def _impulse(self, dvx: float, dvy: float, dvz: float, var: float) -> None:
        kf = self._kf
        kf.x[3:6, 0] += (dvx, dvy, dvz)
        kf.P[3:6, 3:6] += var * np.eye(3)

    def _gated_update(self, z: np.ndarray, h: np.ndarray, var: float) -> bool:
        kf = self._kf
        r = var * np.eye(3)
        y = z - h @ kf.x
        s = h @ kf.P @ h.T + r
        if (y.T @ np.linalg.solve(s, y)).item() > self._gate:
            return False
        before = kf.x.copy()
        kf.update(z, R=r, H=h)
        d = (kf.x - before)[:, 0]
        self._shift_output(*(float(v) for v in d))
        return True

    def _update_position(self, zx: float, zy: float, zz: float, var: float, h1: float) -> bool:
        h = np.hstack([np.eye(3), h1 * np.eye(3)])
        return self._gated_update(np.array([[zx], [zy], [zz]]), h, var)

    def _update_velocity(self, zx: float, zy: float, zz: float, var: float) -> bool:
        return self._gated_update(np.array([[zx], [zy], [zz]]), self._h_vel, var)

    def horizon_p2(self) -> tuple[float, float, float]:
        p = self._kf.P
        return float(p[0, 0]), float(p[0, 3]), float(p[3, 3])

    def horizon_state(self) -> tuple[float, ...]:
        return tuple(float(v) for v in self._kf.x[:, 0])


def make_com_filter(backend: str, **kwargs: float | bool | Sequence[float]) -> ComFilter:
    """``backend``: ``"lean"`` (float arithmetic) or ``"filterpy"`` (reference)."""
    if backend == "lean":
        return ComFilter(**kwargs)  # type: ignore[arg-type]
    if backend == "filterpy":
        reference = FilterpyComFilter(**kwargs)  # type: ignore[arg-type]
        reference.attach_filterpy()
        return reference
    raise ValueError(f"unknown CoM filter backend {backend!r}; use 'lean' or 'filterpy'")
