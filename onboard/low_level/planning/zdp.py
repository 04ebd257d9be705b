"""Zero Dynamics Policies for the hopper (thesis section 5.5, lines 2377-2777).

The hybrid hopper is reduced to its impact-to-impact map (eq. 5.33). With the
pre-impact state split into actuated coordinates ``eta`` (the attitude at impact;
here the horizontal components ``(a_x, a_y)`` of the body z axis in the world, i.e.
where the foot lands relative to the CoM) and unactuated ones ``z = (x, y, vx, vy)``
(horizontal CoM position [m] and velocity [m/s] just before impact), the map is

    z_{k+1} = Omega(eta_k, z_k)           (the stance and the next flight)
    eta_{k+1} = v_k                      (the attitude controller reaches the command)

The last line is the thesis's "perfect low-level tracking" assumption used for the
optimisation (lines 2733-2740). This module provides

- :class:`HopperModel` and :func:`impact_map`: the reduced model (a spring-mass leg
  pivoting about the foot with the body's inertia, then ballistic flight), batched;
- :func:`linearize`: its Jacobians at the periodic in-place hop, by central
  differences (the same routine checks the twin's map, see the tests);
- :func:`dlqr` and :func:`invariant_subspace_policy`: discrete LQR on eq. 5.43 and
  the invariant-subspace policy ``psi(z) = S_eta z`` of eq. 5.44;
- :class:`LinearPolicy` (in :mod:`onboard.low_level.planning.zdp_policy`, the part that runs at 1 kHz): the Raibert
  form of eq. 5.48 with every signal clipped.

Units: SI; world frame z up; all positions of the whole robot's CoM.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.linalg

STANCE_STEP_S = 1e-4  # RK4 step of the stance integration [s]
STANCE_MAX_S = 0.4  # a stance longer than this is a fall, not a hop [s]
UPRIGHT_MIN = 0.3  # leg axis z component below which the reduced model calls it a fall


# --- linear algebra -------------------------------------------------------------------


def dlqr(a: np.ndarray, b: np.ndarray, q: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Discrete LQR: gain ``K`` (``u = -K x``) and Riccati solution ``P``."""
    p = scipy.linalg.solve_discrete_are(a, b, q, r)
    k = np.linalg.solve(r + b.T @ p @ b, b.T @ p @ a)
    return k, p


def invariant_subspace_policy(a_cl: np.ndarray, n_eta: int) -> tuple[np.ndarray, np.ndarray]:
    """``S_eta`` of eq. 5.44 from the closed loop ``A_cl`` on ``[eta; z]``.

    Selects the ``dim(z)`` slowest modes (largest ``|lambda|``): the subspace the
    closed loop converges onto, hence attractive and invariant. The basis comes from
    an ordered real Schur form rather than from eigenvectors, because the symmetric
    hopper has repeated eigenvalues (x and y axes) whose eigenvectors are
    ill-conditioned. Returns ``(S_eta, eigenvalues of the selected modes)``; on the
    manifold ``eta = S_eta z`` the zero dynamics have exactly those eigenvalues.
    """
    n = a_cl.shape[0]
    n_z = n - n_eta
    mags = np.sort(np.abs(np.linalg.eigvals(a_cl)))[::-1]
    if n_z < n and mags[n_z - 1] - mags[n_z] < 1e-9 * max(1.0, mags[0]):
        raise ValueError("slow and fast modes have the same magnitude: no unique subspace")
    cut = 0.5 * (mags[n_z - 1] + mags[n_z]) if n_z < n else -1.0
    _, vecs, sdim = scipy.linalg.schur(a_cl, output="real", sort=lambda re, im: math.hypot(re, im) > cut)
    if sdim != n_z:
        raise ValueError(f"selected {sdim} slow modes, need {n_z}")
    s = vecs[:, :n_z]
    s_z = s[n_eta:, :]
    if np.linalg.cond(s_z) > 1e10:
        raise ValueError("selected subspace is (nearly) orthogonal to z")
    s_eta = s[:n_eta, :] @ np.linalg.inv(s_z)
    return s_eta, mags[:n_z]


@dataclass(frozen=True)
class LinearZdp:
    """Result of the linear construction (eqs. 5.43-5.44)."""

    a_zz: np.ndarray  # d z_{k+1} / d z_k
    a_zeta: np.ndarray  # d z_{k+1} / d eta_k
    k_aug: np.ndarray  # LQR gain on [eta; z] of eq. 5.43 (v = -K [eta; z])
    k_lqr: np.ndarray  # plain LQR on z with eta as the input (eta = -K z)
    s_eta: np.ndarray  # the ZDP: eta = S_eta z
    zero_dynamics_eigs: np.ndarray  # eigenvalues of z_{k+1} = (A_zz + A_zeta S_eta) z


def linear_zdp(a_zz: np.ndarray, a_zeta: np.ndarray, q_eta: np.ndarray, q_z: np.ndarray, r: np.ndarray) -> LinearZdp:
    """Build eq. 5.43 with perfect tracking (``eta_{k+1} = v_k``), solve it, take eq. 5.44."""
    n_z, n_eta = a_zeta.shape
    a = np.zeros((n_eta + n_z, n_eta + n_z))
    a[n_eta:, :n_eta] = a_zeta
    a[n_eta:, n_eta:] = a_zz
    b = np.zeros((n_eta + n_z, n_eta))
    b[:n_eta, :] = np.eye(n_eta)
    q = scipy.linalg.block_diag(q_eta, q_z)
    k_aug, _ = dlqr(a, b, q, r)
    s_eta, _ = invariant_subspace_policy(a - b @ k_aug, n_eta)
    k_lqr, _ = dlqr(a_zz, a_zeta, q_z, q_eta)
    eigs = np.linalg.eigvals(a_zz + a_zeta @ s_eta)
    return LinearZdp(a_zz, a_zeta, k_aug, k_lqr, s_eta, eigs)


# --- the reduced hopper ---------------------------------------------------------------


@dataclass(frozen=True)
class HopperModel:
    """The reduced model's parameters, all derived from the MJCF (never typed in).

    The sprung body is everything but the foot; the leg axis (body -z) passes
    through its CoM. In stance the foot pivots on the ground (no slip) and the body
    turns with the leg; the spring pushes along the leg.
    """

    mass_sprung: float  # [kg]
    mass_foot: float  # unsprung [kg]
    inertia_sprung: float  # sprung body about a horizontal axis through its CoM [kg m^2]
    inertia_foot: float  # foot about a horizontal axis through the pivot [kg m^2]
    spring_k: float  # [N/m]
    spring_damping: float  # [N s/m]
    leg_rest: float  # sprung CoM to the foot pivot, spring fully extended [m]
    foot_com: float  # foot CoM above the pivot along the leg [m]
    foot_radius: float  # pivot height above the ground in stance [m]
    travel: float  # spring travel [m]
    gravity: float = 9.81  # [m/s^2]

    @property
    def mass(self) -> float:
        return self.mass_sprung + self.mass_foot

    def com_to_pivot(self, compression: float) -> float:
        """Distance [m] from the whole robot's CoM to the foot pivot, along the leg."""
        leg = self.leg_rest - compression
        return leg - self.mass_foot / self.mass * (leg - self.foot_com)

    def touchdown_height(self, compression: float, axis_z: float = 1.0) -> float:
        """Whole-robot CoM height [m] above the ground at touchdown."""
        return self.foot_radius + self.com_to_pivot(compression) * axis_z


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.stack(
        (
            a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1],
            a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
            a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0],
        ),
        axis=1,
    )


def _stance_rhs(m: HopperModel, u, h, l, ld):
    j = m.mass_sprung * l * l + m.inertia_sprung + m.inertia_foot
    ud = _cross(h, u) / j[:, None]
    zhat = np.zeros_like(u)
    zhat[:, 2] = 1.0
    hd = -m.mass_sprung * m.gravity * l[:, None] * _cross(u, zhat)
    w2 = np.einsum("ij,ij->i", ud, ud)
    force = m.spring_k * (m.leg_rest - l) - m.spring_damping * ld
    ldd = l * w2 + force / m.mass_sprung - m.gravity * u[:, 2]
    return ud, hd, ld, ldd


@dataclass(frozen=True)
class ImpactResult:
    """Batched outcome of :func:`impact_map` (NaN rows where the model fell)."""

    z: np.ndarray  # (N, 4) next pre-impact x, y, vx, vy
    vz: np.ndarray  # (N,) next pre-impact vertical velocity [m/s]
    liftoff_velocity: np.ndarray  # (N, 3) whole-robot CoM velocity after lift-off
    stance_time: np.ndarray  # (N,) [s]
    flight_time: np.ndarray  # (N,) [s]
    ok: np.ndarray  # (N,) bool


def impact_map(
    m: HopperModel,
    z: np.ndarray,
    vz: np.ndarray | float,
    eta: np.ndarray,
    preload: np.ndarray | float,
    next_preload: np.ndarray | float | None = None,
    ground_step: float = 0.0,
) -> ImpactResult:
    """Pre-impact state -> next pre-impact state (eq. 5.33), for a batch.

    ``z`` (N, 4): CoM x, y, vx, vy just before impact; ``vz``: vertical velocity
    (negative); ``eta`` (N, 2): horizontal components of the leg axis (body z) at
    impact, held through stance (the body turns with the leg); ``preload`` [m]: spring
    compression held by the cable, released at touchdown (scalar or per row). The next touchdown happens
    with the leg upright and ``next_preload`` (default: the same) on ground
    ``ground_step`` [m] higher.

    Touchdown: the foot stops; angular momentum about the foot is conserved, the
    body keeps its velocity along the leg. Lift-off: the spring reaches full
    extension and its stop jerks the foot (momentum conserved, foot at rest before).
    """
    z = np.atleast_2d(np.asarray(z, dtype=float))
    eta = np.atleast_2d(np.asarray(eta, dtype=float))
    n = z.shape[0]
    vz = np.broadcast_to(np.asarray(vz, dtype=float), (n,))
    preload = np.broadcast_to(np.asarray(preload, dtype=float), (n,))
    nxt = preload if next_preload is None else np.broadcast_to(np.asarray(next_preload, dtype=float), (n,))
    big_m, mf, mb = m.mass, m.mass_foot, m.mass_sprung

    u = np.empty((n, 3))
    u[:, :2] = eta
    u[:, 2] = np.sqrt(np.clip(1.0 - eta[:, 0] ** 2 - eta[:, 1] ** 2, 0.0, None))
    v = np.column_stack((z[:, 2], z[:, 3], vz))
    l0 = m.leg_rest - preload
    l_c = m.com_to_pivot(preload)
    pivot = np.column_stack((z[:, 0], z[:, 1], np.zeros(n))) - l_c[:, None] * u
    pivot[:, 2] = 0.0  # pivot frame: the foot pivot is at z = 0
    # angular momentum about the pivot is conserved through the impact
    h = big_m * l_c[:, None] * _cross(u, v)
    l = l0.copy()
    ld = np.einsum("ij,ij->i", u, v)

    done = np.zeros(n, dtype=bool)
    ok = np.ones(n, dtype=bool)
    t_st = np.zeros(n)
    dt = STANCE_STEP_S
    t = 0.0
    while not done.all():
        act = ~done
        ua, ha, la, lda = u[act], h[act], l[act], ld[act]
        k1 = _stance_rhs(m, ua, ha, la, lda)
        k2 = _stance_rhs(m, ua + 0.5 * dt * k1[0], ha + 0.5 * dt * k1[1], la + 0.5 * dt * k1[2], lda + 0.5 * dt * k1[3])
        k3 = _stance_rhs(m, ua + 0.5 * dt * k2[0], ha + 0.5 * dt * k2[1], la + 0.5 * dt * k2[2], lda + 0.5 * dt * k2[3])
        k4 = _stance_rhs(m, ua + dt * k3[0], ha + dt * k3[1], la + dt * k3[2], lda + dt * k3[3])
        un = ua + dt / 6.0 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
        un /= np.linalg.norm(un, axis=1)[:, None]
        hn = ha + dt / 6.0 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
        ln = la + dt / 6.0 * (k1[2] + 2 * k2[2] + 2 * k3[2] + k4[2])
        ldn = lda + dt / 6.0 * (k1[3] + 2 * k2[3] + 2 * k3[3] + k4[3])
        t += dt
        # lift-off: the leg reaches full extension; interpolate the crossing
        crossed = (ln >= m.leg_rest) & (ldn > 0.0)
        frac = np.where(crossed, (m.leg_rest - la) / np.where(ln - la > 0, ln - la, 1.0), 1.0)
        frac = np.clip(frac, 0.0, 1.0)
        idx = np.flatnonzero(act)
        u[idx] = np.where(crossed[:, None], ua + frac[:, None] * (un - ua), un)
        h[idx] = np.where(crossed[:, None], ha + frac[:, None] * (hn - ha), hn)
        l[idx] = np.where(crossed, m.leg_rest, ln)
        ld[idx] = np.where(crossed, lda + frac * (ldn - lda), ldn)
        t_st[idx] = np.where(crossed, t - dt + frac * dt, t)
        fell = (un[:, 2] < UPRIGHT_MIN) | (ln < m.leg_rest - m.travel - 0.05) | (t > STANCE_MAX_S)
        done[idx[crossed | fell]] = True
        ok[idx[fell & ~crossed]] = False
        u[:] = u / np.linalg.norm(u, axis=1)[:, None]

    j = mb * l * l + m.inertia_sprung + m.inertia_foot
    u_dot = _cross(h, u) / j[:, None]
    v_body = ld[:, None] * u + l[:, None] * u_dot
    v_lo = mb / big_m * v_body  # the foot is jerked along at the extension stop
    p_body = pivot + l[:, None] * u
    p_lo = p_body - (mf / big_m) * (m.leg_rest - m.foot_com) * u

    h_td = m.touchdown_height(nxt) + ground_step - m.foot_radius  # pivot frame: ground z = 0
    g = m.gravity
    disc = v_lo[:, 2] ** 2 + 2.0 * g * (p_lo[:, 2] - h_td)
    ok &= disc >= 0.0
    t_fl = (v_lo[:, 2] + np.sqrt(np.clip(disc, 0.0, None))) / g
    z_next = np.column_stack(
        (p_lo[:, 0] + v_lo[:, 0] * t_fl, p_lo[:, 1] + v_lo[:, 1] * t_fl, v_lo[:, 0], v_lo[:, 1])
    )
    vz_next = v_lo[:, 2] - g * t_fl
    z_next[~ok] = np.nan
    vz_next = np.where(ok, vz_next, np.nan)
    return ImpactResult(z_next, vz_next, v_lo, t_st, t_fl, ok)


def periodic_preload(m: HopperModel, hop_height: float) -> float:
    """The preload [m] whose released energy makes an upright in-place hop of
    ``hop_height`` [m] (CoM rise from touchdown to apex) repeat exactly.

    Two rounds of a batched grid search, then linear interpolation (one batched
    call per round is far cheaper than a scalar bisection)."""
    vz = -math.sqrt(2.0 * m.gravity * hop_height)
    lo, hi = 0.0, m.travel
    grid = np.zeros(1)
    excess = np.zeros(1)
    for _ in range(2):
        grid = np.linspace(lo, hi, 48)
        r = impact_map(m, np.zeros((grid.size, 4)), vz, np.zeros((grid.size, 2)), grid)
        excess = np.where(r.ok, -r.vz + vz, np.inf)  # > 0: hops higher than asked
        above = np.flatnonzero(excess > 0)
        if above.size == 0:
            raise ValueError(f"hop height {hop_height} m needs more than the full spring travel")
        i = int(above[0])
        if i == 0:
            return float(grid[0])
        lo, hi = float(grid[i - 1]), float(grid[i])
    i = int(np.flatnonzero(excess > 0)[0])
    e0, e1 = excess[i - 1], excess[i]
    return float(grid[i - 1] + (grid[i] - grid[i - 1]) * (-e0) / (e1 - e0))


def linearize(
    step,  # (z (N,4), eta (N,2)) -> z_next (N,4)
    z0: np.ndarray | None = None,
    eta0: np.ndarray | None = None,
    dz: Sequence[float] = (1e-3, 1e-3, 1e-3, 1e-3),
    deta: float = 1e-3,
) -> tuple[np.ndarray, np.ndarray]:
    """Central-difference Jacobians ``(A_zz, A_zeta)`` of an impact-to-impact map.

    ``step`` takes batches so that all perturbations run at once (the reduced model
    or the twin).
    """
    z0 = np.zeros(4) if z0 is None else np.asarray(z0, dtype=float)
    eta0 = np.zeros(2) if eta0 is None else np.asarray(eta0, dtype=float)
    zs, etas = [], []
    for i in range(4):
        for s in (1.0, -1.0):
            zp = z0.copy()
            zp[i] += s * dz[i]
            zs.append(zp)
            etas.append(eta0)
    for i in range(2):
        for s in (1.0, -1.0):
            ep = eta0.copy()
            ep[i] += s * deta
            zs.append(z0)
            etas.append(ep)
    out = np.asarray(step(np.array(zs), np.array(etas)), dtype=float)
    a_zz = np.column_stack([(out[2 * i] - out[2 * i + 1]) / (2 * dz[i]) for i in range(4)])
    a_ze = np.column_stack([(out[8 + 2 * i] - out[8 + 2 * i + 1]) / (2 * deta) for i in range(2)])
    return a_zz, a_ze


def reduced_step(m: HopperModel, hop_height: float, preload: float):
    """The reduced impact map at the nominal vertical hop, as a batch function for
    :func:`linearize` and for rollouts."""
    vz = -math.sqrt(2.0 * m.gravity * hop_height)

    def step(z: np.ndarray, eta: np.ndarray) -> np.ndarray:
        return impact_map(m, z, vz, eta, preload).z

    return step


