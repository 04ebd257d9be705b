"""Attitude and gyro bias: a multiplicative EKF on the unit quaternion.

The nominal state is the attitude ``q`` (body -> world, ``[w, x, y, z]``) and the
gyro bias ``bias`` (body frame, rad/s). The filter's error state is 6-dimensional:

- ``dtheta`` [rad], a rotation vector in the *world* frame: ``q_true = exp(dtheta) q``;
- ``beta`` [rad/s], the bias error expressed in the world frame: ``R (b_true - b)``.

Integrating the bias-corrected gyro, ``q <- q exp((gyro - bias) dt)``, the error obeys
``dtheta' = dtheta - beta dt - R n_gyro dt`` and ``beta' = beta + n_bias dt``: no
``omega x`` term, because a world-frame error does not see the body turn. Two things
follow that make the filter cheap and exact where it matters:

- Every correction is a world-frame left product ``q <- exp(k r) q`` and every
  propagation a body-frame right product, so the attitude at a past time ``s`` with
  all corrections made since is ``C_now C_s^-1 q_s``, where ``C`` is the product of
  all corrections so far (a short history keeps ``q_s`` and ``C_s``). A pose captured
  ``T`` seconds ago is compared with that, and its correction applies now: the
  delayed measurement of ``dtheta`` is ``dtheta_now + T beta`` (``H = [1, T]`` per
  axis), so latency costs nothing but a lookup.
- A pose observes all three world axes and the accelerometer's gravity direction
  observes world x and y, so the covariance stays block diagonal per world axis:
  a 2x2 ``[dtheta_i, beta_i]`` block per axis, x and y sharing one. Per-tick work
  is a few float operations (no numpy: ARCHITECTURE.md timing table).

The one approximation: ``beta`` is a body-fixed error seen from the world, so body
rotation mixes its world components; the per-axis covariance ignores that mixing
(exact when the horizontal and vertical bias variances agree, which they do until a
long quasi-static spell has let gravity refine the horizontal ones).

IMU gaps: between two gyro samples the rate is interpolated; over an interval longer
than the IMU's period the body may have accelerated unseen, so the caller adds that
variance (``propagate``'s ``gap_var``), and :meth:`AttitudeFilter.predicted_variances`
predicts past the newest sample with it. An attitude error cannot exceed pi: the
variance stops there.

Gravity is used only when the robot is quasi-static (the caller decides: specific
force close to ``g`` and small body rate); on a hopping robot the accelerometer
reads the spring, not gravity, for most of a hop.
"""

from __future__ import annotations

import math
from collections import deque

from onboard.geometry import quaternion as quat

NS = 1_000_000_000
MAX_ANGLE_VAR = math.pi * math.pi  # [rad^2] an attitude error is at most half a turn


class AttitudeFilter:
    """Quaternion MEKF with gyro bias; see the module docstring for the model."""

    def __init__(
        self,
        *,
        gyro_noise_density: float,
        gyro_bias_walk: float,
        init_att_std: float,
        init_bias_std: float,
        history_len: int,
    ) -> None:
        """Densities in rad/s/sqrt(Hz) and rad/s^2/sqrt(Hz); stds in rad and rad/s;
        ``history_len``: gyro-only attitudes kept for delayed poses (one per IMU sample)."""
        if history_len < 2:
            raise ValueError("history_len must be at least 2")
        self._q_angle = gyro_noise_density * gyro_noise_density  # [rad^2/s]
        self._q_bias = gyro_bias_walk * gyro_bias_walk  # [(rad/s)^2/s]
        self._init_att_var = init_att_std * init_att_std
        self._init_bias_var = init_bias_std * init_bias_std
        self.q: quat.Quat = quat.IDENTITY
        self.bias: quat.Vec3 = (0.0, 0.0, 0.0)
        self.omega: quat.Vec3 = (0.0, 0.0, 0.0)  # latest bias-corrected body rate [rad/s]
        self.t_ns = 0
        self.initialized = False
        self._c: quat.Quat = quat.IDENTITY  # product of every correction so far (world, left)
        self._gyro_prev: quat.Vec3 = (0.0, 0.0, 0.0)  # raw gyro at the previous sample
        self._hist: deque[tuple[int, quat.Quat, quat.Quat]] = deque(maxlen=history_len)  # (t, q, C)
        # [P_theta_theta, P_theta_beta, P_beta_beta] for world x and y (shared) and z
        self._ph = [self._init_att_var, 0.0, self._init_bias_var]
        self._pv = [self._init_att_var, 0.0, self._init_bias_var]

    # --- state -------------------------------------------------------------------

    def initialize(self, q: quat.Quat, t_ns: int, gyro: quat.Vec3) -> None:
        """Start from attitude ``q`` and gyro sample ``gyro`` [rad/s, body] at ``t_ns``."""
        self.q = quat.normalize(q)
        self._gyro_prev = (gyro[0], gyro[1], gyro[2])
        self.omega = self._gyro_prev
        self._c = quat.IDENTITY
        self.t_ns = t_ns
        self._hist.clear()
        self._hist.append((t_ns, self.q, self._c))
        self._ph = [self._init_att_var, 0.0, self._init_bias_var]
        self._pv = [self._init_att_var, 0.0, self._init_bias_var]
        self.initialized = True

    def variances(self) -> tuple[float, float]:
        """Attitude error variance [rad^2] about world x (= y) and world z."""
        return self._ph[0], self._pv[0]

    def bias_variances(self) -> tuple[float, float]:
        """Gyro bias error variance [(rad/s)^2] about world x (= y) and world z."""
        return self._ph[2], self._pv[2]

    def predicted_variances(self, tau: float, extra_var: float) -> tuple[float, float]:
        """:meth:`variances` ``tau`` [s] past the newest sample, with no gyro sample since:
        process noise and bias drift over ``tau``, plus ``extra_var`` [rad^2] (what the
        caller's model of the unseen rate change adds)."""
        qa = self._q_angle * tau + extra_var
        a, c, d = self._ph
        h = a + tau * (tau * d - 2.0 * c) + qa
        a, c, d = self._pv
        v = a + tau * (tau * d - 2.0 * c) + qa
        return min(h, MAX_ANGLE_VAR), min(v, MAX_ANGLE_VAR)

    def body_variances(self, q: quat.Quat | None = None, world: tuple[float, float] | None = None) -> tuple[float, float, float]:
        """Attitude error variance [rad^2] about the body axes (diagonal of R^T P R); ``q`` and
        ``world`` (:meth:`variances`-like) default to the filter's own."""
        w, x, y, z = self.q if q is None else q
        # third row of R: world z components of the body axes
        r20 = 2.0 * (x * z - w * y)
        r21 = 2.0 * (y * z + w * x)
        r22 = 1.0 - 2.0 * (x * x + y * y)
        h, v = (self._ph[0], self._pv[0]) if world is None else world
        return (h + (v - h) * r20 * r20, h + (v - h) * r21 * r21, h + (v - h) * r22 * r22)

    # --- propagation -------------------------------------------------------------

    def propagate(self, t_ns: int, gx: float, gy: float, gz: float, dt: float, gap_var: float = 0.0) -> None:
        """Integrate up to the gyro sample [rad/s, body] at ``t_ns``, ``dt`` [s] after the previous;
        ``gap_var`` [rad^2]: what an interval longer than the IMU's period adds (see the module)."""
        bx, by, bz = self.bias
        wx = gx - bx
        wy = gy - by
        wz = gz - bz
        self.omega = (wx, wy, wz)
        # gyro samples are instantaneous: integrate the interval's trapezoid
        ux, uy, uz = self._gyro_prev
        self._gyro_prev = (gx, gy, gz)
        vx = (0.5 * (gx + ux) - bx) * dt
        vy = (0.5 * (gy + uy) - by) * dt
        vz = (0.5 * (gz + uz) - bz) * dt
        angle = math.sqrt(vx * vx + vy * vy + vz * vz)
        if angle < 1e-9:
            c, s = 1.0, 0.5
        else:
            c = math.cos(0.5 * angle)
            s = math.sin(0.5 * angle) / angle
        dx = s * vx
        dy = s * vy
        dz = s * vz
        w, x, y, z = self.q  # q <- q exp(omega dt)
        w, x, y, z = (
            w * c - x * dx - y * dy - z * dz,
            w * dx + x * c + y * dz - z * dy,
            w * dy - x * dz + y * c + z * dx,
            w * dz + x * dy - y * dx + z * c,
        )
        n = 1.0 / math.sqrt(w * w + x * x + y * y + z * z)
        q = self.q = (w * n, x * n, y * n, z * n)
        self._hist.append((t_ns, q, self._c))
        self.t_ns = t_ns
        qa = self._q_angle * dt + gap_var
        qb = self._q_bias * dt
        a, cr, d = self._ph
        self._ph = [min(a + dt * (dt * d - 2.0 * cr) + qa, MAX_ANGLE_VAR), cr - dt * d, d + qb]
        a, cr, d = self._pv
        self._pv = [min(a + dt * (dt * d - 2.0 * cr) + qa, MAX_ANGLE_VAR), cr - dt * d, d + qb]

    # --- corrections ---------------------------------------------------------------

    def _past_attitude(self, stamp_ns: int) -> quat.Quat | None:
        """The estimate at ``stamp_ns`` with every correction made since, or None if too old."""
        hist = self._hist
        first, last = hist[0][0], hist[-1][0]
        if stamp_ns < first:
            return None
        # the newest entry at or before the stamp: guess from the mean spacing, then step
        n = len(hist)
        i = n - 1
        if stamp_ns < last and n > 1:
            i = n - 1 - int((last - stamp_ns) * (n - 1) / (last - first) + 0.5)
            while hist[i][0] > stamp_ns:
                i -= 1
            while i + 1 < n and hist[i + 1][0] <= stamp_ns:
                i += 1
        _, q_s, c_s = hist[i]
        if c_s is self._c:  # no correction since
            return q_s
        return quat.mul(quat.mul(self._c, quat.conj(c_s)), q_s)

    def correct_pose(self, q_meas: quat.Quat, stamp_ns: int, var: float, gate_chi2: float) -> bool | None:
        """Fuse a measured attitude captured at ``stamp_ns`` (noise ``var`` [rad^2] per axis).

        Returns True if fused, False if the Mahalanobis gate (3 dof) refused it, None if
        it is older than the history.
        """
        q_s = self._past_attitude(stamp_ns)
        if q_s is None:
            return None
        # r = log(q_meas q_s^-1), the world-frame rotation from the estimate to the measurement
        aw, ax, ay, az = q_meas
        bw, bx, by, bz = q_s
        ew = aw * bw + ax * bx + ay * by + az * bz
        ex = -aw * bx + ax * bw - ay * bz + az * by
        ey = -aw * by + ax * bz + ay * bw - az * bx
        ez = -aw * bz - ax * by + ay * bx + az * bw
        if ew < 0.0:  # the shorter way round
            ew, ex, ey, ez = -ew, -ex, -ey, -ez
        sn = math.sqrt(ex * ex + ey * ey + ez * ez)
        k = 2.0 * math.atan2(sn, ew) / sn if sn > 1e-12 else 2.0
        rx, ry, rz = k * ex, k * ey, k * ez
        lag = max(0.0, (self.t_ns - stamp_ns) / NS)
        ah, ch, dh = self._ph
        av, cv, dv = self._pv
        # H = [1, lag] per axis: the past error is today's plus the bias drift since
        h0, h1 = ah + lag * ch, ch + lag * dh
        v0, v1 = av + lag * cv, cv + lag * dv
        sh = h0 + lag * h1 + var
        sv = v0 + lag * v1 + var
        if (rx * rx + ry * ry) / sh + rz * rz / sv > gate_chi2:
            return False
        kh, kv = h0 / sh, v0 / sv
        bh, bv = h1 / sh, v1 / sv
        self._apply(kh * rx, kh * ry, kv * rz, bh * rx, bh * ry, bv * rz)
        self._ph = [ah - h0 * h0 / sh, ch - h0 * h1 / sh, dh - h1 * h1 / sh]
        self._pv = [av - v0 * v0 / sv, cv - v0 * v1 / sv, dv - v1 * v1 / sv]
        return True

    def correct_gravity(self, fx: float, fy: float, fz: float, var: float, gate_chi2: float) -> bool:
        """Fuse the accelerometer's specific force [m/s^2, body] as the direction of up.

        Only valid while quasi-static (the caller checks). Observes world x and y.
        """
        n = math.sqrt(fx * fx + fy * fy + fz * fz)
        if n == 0.0:
            return False
        ux, uy, _ = quat.rotate(self.q, (fx / n, fy / n, fz / n))
        # (R f / |f|) x z = (dtheta_x, dtheta_y, 0) to first order
        rx, ry = uy, -ux
        ah, ch, dh = self._ph
        sh = ah + var
        if (rx * rx + ry * ry) / sh > gate_chi2:
            return False
        kh, bh = ah / sh, ch / sh
        self._apply(kh * rx, kh * ry, 0.0, bh * rx, bh * ry, 0.0)
        self._ph = [ah - ah * ah / sh, ch - ah * ch / sh, dh - ch * ch / sh]
        return True

    def _apply(self, tx: float, ty: float, tz: float, bx: float, by: float, bz: float) -> None:
        """Inject an error estimate: world rotation ``t`` [rad] and world bias error ``b`` [rad/s]."""
        angle = math.sqrt(tx * tx + ty * ty + tz * tz)
        if angle < 1e-9:
            dw, sc = 1.0, 0.5
        else:
            dw, sc = math.cos(0.5 * angle), math.sin(0.5 * angle) / angle
        dx, dy, dz = sc * tx, sc * ty, sc * tz
        # q <- exp(t) q and C <- exp(t) C, renormalized
        w, x, y, z = self.q
        w, x, y, z = (
            dw * w - dx * x - dy * y - dz * z,
            dw * x + dx * w + dy * z - dz * y,
            dw * y - dx * z + dy * w + dz * x,
            dw * z + dx * y - dy * x + dz * w,
        )
        n = 1.0 / math.sqrt(w * w + x * x + y * y + z * z)
        w, x, y, z = w * n, x * n, y * n, z * n
        self.q = (w, x, y, z)
        cw, cx, cy, cz = self._c
        cw, cx, cy, cz = (
            dw * cw - dx * cx - dy * cy - dz * cz,
            dw * cx + dx * cw + dy * cz - dz * cy,
            dw * cy - dx * cz + dy * cw + dz * cx,
            dw * cz + dx * cy - dy * cx + dz * cw,
        )
        n = 1.0 / math.sqrt(cw * cw + cx * cx + cy * cy + cz * cz)
        self._c = (cw * n, cx * n, cy * n, cz * n)
        # the bias error into the body frame: R^T b
        ox, oy, oz = self.bias
        self.bias = (
            ox + (1.0 - 2.0 * (y * y + z * z)) * bx + 2.0 * (x * y + w * z) * by + 2.0 * (x * z - w * y) * bz,
            oy + 2.0 * (x * y - w * z) * bx + (1.0 - 2.0 * (x * x + z * z)) * by + 2.0 * (y * z + w * x) * bz,
            oz + 2.0 * (x * z + w * y) * bx + 2.0 * (y * z - w * x) * by + (1.0 - 2.0 * (x * x + y * y)) * bz,
        )
