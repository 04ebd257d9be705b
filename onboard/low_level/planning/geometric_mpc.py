"""Geometric MPC on S^3 for the hopper (thesis section 5.3, eqs. 5.17-5.26).

Decision state ``z`` (R^20, eq. 5.23): torso position ``p`` [m, world], the attitude pulled
back to the identity and lifted into the Lie algebra ``xi = Log(q0^-1 q)`` [rad] (eq. 5.17,
``q0`` the measured attitude, so ``xi_0 = 0``), wheel angles ``theta`` [rad], foot compression
``l`` [m], then ``(p_dot [m/s, world], omega [rad/s, body], theta_dot [rad/s], l_dot [m/s])``.
Input ``u``: the three wheel motor torques [N m]; the foot is planned as passive (thesis
lines 2230-2236: the low level regulates the hop height).

Per solve:

1. :func:`mode_schedule`: the knots' modes fixed a priori from the predicted impact time
   (ballistic, as if upright, thesis line 2230) and the spring's lift-off; flight knots
   coarse, stance knots fine, the horizon a fixed number of knots (so it shrinks when an
   impact comes into view, as the thesis's did);
2. SQP (eq. 5.26): each iteration linearizes the hybrid dynamics along the last iterate
   (the first along a rollout of the linearization itself with zero torque), discretizes
   each flow knot exactly with the matrix exponential of the affine system (eq. 5.24) and
   each jump by its momentum-transfer Jacobian (eq. 5.25), and solves the QP. By default
   (backend "condensed") the QP is condensed onto its inputs: the states are the dynamics'
   own rollout ``z = z_free + S u``, which leaves 3 inputs per flow knot and their torque box,
   a dense QP that an active-set method solves exactly (:mod:`box_qp`); the exponentials and
   the condensing run compiled (:mod:`gmpc_kernels`). PIQP and OSQP solve the same QP in its
   sparse form (480 variables, 420 equalities), set up once and updated by value (never the
   sparsity pattern); PIQP is the cross-check and takes the QP when the tilt rows are on.
   The second iteration starts from the first's answer (its linearization point); OSQP also
   warm starts from its last iterate (PIQP, an interior-point method, starts afresh by design).
3. Every answer is checked (solver status, finiteness, dynamics residual, input bounds)
   before it may be used; :class:`GmpcSolution.ok` is that verdict.

The dynamics come from outside through :class:`HybridDynamics` (the robot description
builds them from the MJCF with Pinocchio), so this module stays free of the robot model.
Linearization in the Lie algebra follows the thesis: a perturbation ``eta`` of the attitude
about the reference knot (``q exp(eta)``) moves ``xi`` by ``eta`` to first order in ``xi``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import osqp
import piqp
import scipy.sparse as sp

from onboard.geometry import quaternion as qt
from onboard.contracts.params import GeometricMpcParams

STATE_DIM = 20
INPUT_DIM = 3
FLIGHT, STANCE = "flight", "stance"  # flows
TOUCHDOWN, LIFTOFF = "touchdown", "liftoff"  # jumps
JUMPS = {FLIGHT: TOUCHDOWN, STANCE: LIFTOFF}  # the jump that ends each flow
AFTER = {TOUCHDOWN: STANCE, LIFTOFF: FLIGHT}

# indices into z
POS, XI, THETA, FOOT = slice(0, 3), slice(3, 6), slice(6, 9), 9
VEL, OMEGA, WHEEL_RATE, FOOT_RATE = slice(10, 13), slice(13, 16), slice(16, 19), 19

_PIQP_OK = "PIQP_SOLVED"
_OSQP_OK = "solved"
# active-set guesses of the condensed QP: each one factorization; on these QPs 2-4 (a cycle ends here)
_ACTIVE_SET_MAX_ITER = 30


class HybridDynamics(Protocol):
    """Flows and jumps of the robot in Lie-algebra coordinates (manifold state ``x``: see
    :mod:`robot_description.hopper_dynamics`; 21 numbers, quaternion ``w, x, y, z`` at 3:7)."""

    def flow(self, mode: str, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(z_dot, A, B)``: the state derivative and its Jacobians (eq. 5.20)."""
        ...

    def jump(self, edge: str, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(x_plus, D)``: the post-impact state and its Jacobian (eq. 5.22)."""
        ...


# --- coordinates ------------------------------------------------------------------------------


def lift(x: np.ndarray, q0: Sequence[float]) -> np.ndarray:
    """Manifold state -> ``z`` with the attitude as ``Log(q0^-1 q)`` (eq. 5.17)."""
    xi = qt.log(qt.mul(qt.conj(q0), x[3:7]))
    return np.concatenate([x[0:3], xi, x[7:]])


def retract(z: np.ndarray, q0: Sequence[float]) -> np.ndarray:
    """``z`` -> manifold state, ``q = q0 exp(xi)`` (inverse of :func:`lift`)."""
    q = qt.mul(q0, qt.exp(z[XI]))
    return np.concatenate([z[0:3], q, z[6:]])


# --- the mode sequence ------------------------------------------------------------------------


@dataclass(frozen=True)
class Knot:
    """One step of the horizon: a flow of ``h`` seconds in a mode, or a jump (``h = 0``)."""

    kind: str  # FLIGHT, STANCE, TOUCHDOWN or LIFTOFF
    h: float  # [s]
    t: float  # time from now at the start of the knot [s]

    @property
    def is_jump(self) -> bool:
        return self.kind in AFTER


def time_to_touchdown(height: float, vz: float, touchdown_height: float, gravity: float) -> float:
    """Ballistic time [s] until the CoM falls to ``touchdown_height`` (as if upright); 0 if
    it is already below and falling."""
    disc = vz * vz + 2.0 * gravity * (height - touchdown_height)
    return max(0.0, (vz + math.sqrt(disc)) / gravity) if disc > 0.0 else 0.0


def time_to_liftoff(compression: float, rate: float, stance_omega: float, gravity: float, nominal: float) -> float:
    """Time [s] until the spring is back at full extension, the sprung body oscillating
    harmonically (angular frequency ``stance_omega`` [rad/s]) about its static compression
    ``g / omega^2``; ``nominal`` when the oscillation never reaches the extension."""
    rest = gravity / (stance_omega * stance_omega)
    y = compression - rest
    amp = math.hypot(y, rate / stance_omega)
    if amp <= rest:
        return nominal
    start = math.atan2(-rate / stance_omega, y)  # y = amp cos(omega t + start)
    end = math.acos(-rest / amp)  # y = -rest, compression falling
    return ((end - start) % (2.0 * math.pi)) / stance_omega


def mode_schedule(
    mode: str, time_to_event: float, params: GeometricMpcParams, flight_time: float, stance_time: float
) -> list[Knot]:
    """``params.horizon`` knots from ``mode``, the first switch after ``time_to_event`` [s];
    later modes last the nominal ``flight_time`` / ``stance_time`` [s]. A flow knot ends at
    its mode's switch; a remainder shorter than ``params.min_step_s`` joins the knot before."""
    if mode not in JUMPS:
        raise ValueError(f"unknown mode {mode!r}")
    step = {FLIGHT: params.flight_step_s, STANCE: params.stance_step_s}
    nominal = {FLIGHT: flight_time, STANCE: stance_time}
    knots: list[Knot] = []
    left, t = max(0.0, time_to_event), 0.0
    while len(knots) < params.horizon:
        if left < params.min_step_s:
            edge = JUMPS[mode]
            knots.append(Knot(edge, 0.0, t))
            mode, left = AFTER[edge], nominal[AFTER[edge]]
            continue
        h = min(step[mode], left)
        if left - h < params.min_step_s:
            h = left
        knots.append(Knot(mode, h, t))
        left -= h
        t += h
    return knots


# --- the solution -----------------------------------------------------------------------------


@dataclass(frozen=True)
class GmpcSolution:
    """One SQP solve. Only ``ok`` answers may reach the low level."""

    ok: bool
    status: str  # the last QP's status, or why the answer was refused
    q0: tuple[float, float, float, float]  # the attitude the Lie algebra is pulled back to
    knots: list[Knot]
    z: np.ndarray  # (N + 1, 20)
    u: np.ndarray  # (N, 3) wheel torques [N m]
    qp_iterations: list[int]  # per SQP iteration
    dynamics_residual: float  # largest |z_k+1 - A z_k - B u_k - C| of the last QP [state units]

    def setpoint(self, lead_s: float) -> tuple[tuple[float, float, float, float], tuple[float, float, float], tuple[float, float, float]]:
        """``(q_d, omega_d, u_ff)`` ``lead_s`` seconds ahead, interpolated on the first flow
        knot: ``q_d = q0 exp(xi)``, the thesis's ``q0 exp(xi_1*)`` at ``lead_s = h_0``."""
        first = next(k for k, knot in enumerate(self.knots) if not knot.is_jump)
        knot = self.knots[first]
        s = min(1.0, max(0.0, (lead_s - knot.t) / knot.h))
        z = (1.0 - s) * self.z[first] + s * self.z[first + 1]
        w, x, y, zq = qt.normalize(qt.mul(self.q0, qt.exp(z[XI])))
        u = self.u[first]
        # plain floats: the setpoint is encoded into a message
        return (float(w), float(x), float(y), float(zq)), (float(z[13]), float(z[14]), float(z[15])), (float(u[0]), float(u[1]), float(u[2]))


    def plan(self, span_s: float) -> tuple[list[float], list[tuple[float, ...]], list[tuple[float, ...]], list[tuple[float, ...]]]:
        """The knots up to ``span_s`` seconds ahead: times, attitudes ``q0 exp(xi_k)``, rates,
        and the torque from each knot to the next (one fewer); a jump repeats its time."""
        times, quats, omegas, torques = [], [], [], []
        for k in range(len(self.knots) + 1):
            t = self.knots[k].t if k < len(self.knots) else self.knots[-1].t + self.knots[-1].h
            z = self.z[k]
            times.append(float(t))
            quats.append(tuple(float(v) for v in qt.normalize(qt.mul(self.q0, qt.exp(z[XI])))))
            omegas.append((float(z[13]), float(z[14]), float(z[15])))
            if t >= span_s or k == len(self.knots):
                break
            u = self.u[k]
            torques.append((float(u[0]), float(u[1]), float(u[2])))
        return times, quats, omegas, torques


# --- the QP -----------------------------------------------------------------------------------


def _blocks(n_knots: int) -> tuple[np.ndarray, np.ndarray]:
    """The dynamics rows' pattern, knot after knot: ``-A_k`` (dense), ``I``, ``-B_k`` (dense)."""
    nz, nu = STATE_DIM, INPUT_DIM
    u0 = (n_knots + 1) * nz
    rows, cols = [], []
    r_a, c_a = np.meshgrid(np.arange(nz), np.arange(nz), indexing="ij")
    r_b, c_b = np.meshgrid(np.arange(nz), np.arange(nu), indexing="ij")
    for k in range(n_knots):
        base = nz + k * nz  # row 0..nz-1: the initial state
        rows += [base + r_a.ravel(), base + np.arange(nz), base + r_b.ravel()]
        cols += [k * nz + c_a.ravel(), (k + 1) * nz + np.arange(nz), u0 + k * nu + c_b.ravel()]
    return np.concatenate(rows), np.concatenate(cols)


class GeometricMpc:
    """The FTOCP of eq. 5.26 over ``params.horizon`` knots, solved in SQP fashion.

    ``torque_limit`` [N m]: the input set ``U`` (a box). ``backend``: "condensed", "piqp" or
    "osqp" (default ``params.backend``). "condensed" eliminates the states through the
    dynamics (``z = z_free + S u``, the dynamics' exact solution for any inputs) and solves the
    dense QP on the inputs alone (:mod:`onboard.low_level.planning.box_qp`): 60 variables and
    their box instead of 480 variables and 420 equalities. It has no general inequalities, so
    with the tilt rows (``params.tilt_max_plan > 0``) the QP goes to PIQP.
    """

    def __init__(self, dynamics: HybridDynamics, params: GeometricMpcParams, torque_limit: float, backend: str | None = None) -> None:
        if not torque_limit > 0.0:
            raise ValueError("torque_limit must be positive")
        # numba's kernels load with the MPC, not with this module: the module's constants are the robot
        # description's too, and a process that never builds an MPC (the ZDP control loop) runs under
        # MemoryDenyWriteExecute, which numba's compiled code cannot load under
        from onboard.low_level.planning import box_qp, gmpc_kernels

        self._box_qp, self._kernels = box_qp, gmpc_kernels
        self.dyn = dynamics
        self.p = params
        self.backend = backend or params.backend
        if self.backend not in ("osqp", "piqp", "condensed"):
            raise ValueError(f"unknown backend {self.backend!r}")
        if self.backend == "condensed" and params.tilt_max_plan > 0.0:
            self.backend = "piqp"
        self.limit = float(torque_limit)
        n, nz, nu = params.horizon, STATE_DIM, INPUT_DIM
        self.n = n
        self.nvar = (n + 1) * nz + n * nu
        self.neq = (n + 1) * nz
        self._u0 = (n + 1) * nz
        q_diag = self.state_weights(params)
        r_diag = np.full(nu, params.weight_input)
        self.q_diag = q_diag
        self._p_diag = 2.0 * np.concatenate([np.tile(q_diag, n + 1), np.tile(r_diag, n)])
        # the solvers need P positive definite on every variable: the unweighted states
        # (wheel angles, for one) get a weight far below any physical one
        self._p_diag = np.maximum(self._p_diag, params.weight_floor)
        self.P = sp.diags(self._p_diag, format="csc")
        rows, cols = _blocks(n)
        rows = np.concatenate([np.arange(nz), rows])
        cols = np.concatenate([np.arange(nz), cols])
        nnz = len(rows)
        order = sp.csc_matrix((np.arange(1, nnz + 1, dtype=float), (rows, cols)), shape=(self.neq, self.nvar))
        order.sort_indices()
        self._perm = order.data.astype(int) - 1  # CSC slot -> entry in our (row-major per knot) order
        self.A_eq = order.copy()
        self._values = np.zeros(nnz)
        self._values[:nz] = 1.0
        self.b_eq = np.zeros(self.neq)
        self.u_lo = np.full(n * nu, -self.limit)
        self.u_hi = np.full(n * nu, self.limit)
        self._solver = None
        # the flows' continuous linearization (eq. 5.23) per knot, discretized in one call
        self._a_c, self._b_c = np.zeros((n, nz, nz)), np.zeros((n, nz, nu))
        self._f, self._h = np.zeros((n, nz)), np.zeros(n)
        self._fill(np.zeros((n, nz, nz)), np.zeros((n, nz, nu)), np.zeros((n, nz)))
        self._build_tilt_rows()
        self._setup()
        if self.backend == "condensed":
            self._compile()

    def _compile(self) -> None:
        """One solve of a still robot in the air, its answer dropped: numba compiles the kernels
        at their first call (seconds; loaded from its on-disk cache after), here rather than in
        the first solve that counts."""
        x = np.zeros(STATE_DIM + 1)
        x[2], x[3] = 1.0, 1.0
        p = self.p
        knots = mode_schedule(FLIGHT, 2.0 * p.flight_step_s, p, 2.0 * p.flight_step_s, p.horizon * p.stance_step_s)
        self.solve(x, knots, np.zeros((self.n + 1, STATE_DIM)))

    @staticmethod
    def state_weights(p: GeometricMpcParams) -> np.ndarray:
        """The diagonal of ``Q`` (and of the terminal ``V``) over ``z``."""
        w = np.zeros(STATE_DIM)
        w[0:2] = p.weight_position
        w[2] = p.weight_height
        w[XI] = p.weight_orientation
        w[10:12] = p.weight_velocity
        w[12] = p.weight_vertical_velocity
        w[OMEGA] = p.weight_omega
        w[WHEEL_RATE] = p.weight_wheel_speed
        return w

    # --- values in the fixed pattern ---------------------------------------------------------

    def _fill(self, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> None:
        """Dynamics rows ``z_k+1 - A_k z_k - B_k u_k = C_k`` for all knots."""
        n, nz, nu = self.n, STATE_DIM, INPUT_DIM
        per = nz * nz + nz + nz * nu
        vals = self._values[nz:].reshape(n, per)
        vals[:, : nz * nz] = -a.reshape(n, -1)
        vals[:, nz * nz : nz * nz + nz] = 1.0
        vals[:, nz * nz + nz :] = -b.reshape(n, -1)
        self.A_eq.data[:] = self._values[self._perm]
        self.b_eq[nz:] = c.reshape(-1)

    def _set_start_and_bounds(self, z0: np.ndarray, knots: list[Knot]) -> None:
        """``z_0 = z(t)`` (eq. 5.26c) and the input box (5.26d), zero on jumps."""
        lo, hi = self.u_lo.reshape(self.n, INPUT_DIM), self.u_hi.reshape(self.n, INPUT_DIM)
        jump = np.array([k.is_jump for k in knots])
        lo[:], hi[:] = -self.limit, self.limit
        lo[jump], hi[jump] = 0.0, 0.0  # a jump takes no time: no torque acts
        self.b_eq[:STATE_DIM] = z0

    def _build_tilt_rows(self) -> None:
        """With ``params.tilt_max_plan`` > 0: per knot 1..N, two rows bounding the world-horizontal
        components of the body z axis, ``R0 exp(xi) e_z ~ R0 (e_z + xi x e_z)``, linear in
        ``(xi_x, xi_y)``; their values follow ``q0`` at each solve (the pattern stays)."""
        n, nz = self.n, STATE_DIM
        self.n_tilt = 2 * n if self.p.tilt_max_plan > 0.0 else 0
        knots = range(1, n + 1) if self.n_tilt else range(0)
        rows = np.repeat(np.arange(self.n_tilt), 2)
        cols = np.array([k * nz + XI.start + j for k in knots for _ in range(2) for j in range(2)], dtype=int)
        marked = sp.csc_matrix((np.arange(1.0, len(rows) + 1.0), (rows, cols)), shape=(self.n_tilt, self.nvar))
        marked.sort_indices()
        self._tilt_perm = marked.data.astype(int) - 1
        self.G_tilt = marked
        self.tilt_lo = np.zeros(self.n_tilt)
        self.tilt_hi = np.zeros(self.n_tilt)

    def _set_tilt_rows(self, q0: Sequence[float]) -> None:
        if not self.n_tilt:
            return
        r = qt.to_matrix(q0)
        g = np.array([[-r[0][1], r[0][0]], [-r[1][1], r[1][0]]])  # rows: world x, y; columns: xi_x, xi_y
        c = np.array([r[0][2], r[1][2]])  # the body z axis now
        bound = max(math.sin(self.p.tilt_max_plan), float(np.abs(c).max()))  # the present tilt is always allowed
        self.G_tilt.data[:] = np.tile(g.reshape(-1), self.n)[self._tilt_perm]
        self.tilt_lo[:] = np.tile(-bound - c, self.n)
        self.tilt_hi[:] = np.tile(bound - c, self.n)

    def _setup(self) -> None:
        q = np.zeros(self.nvar)
        if self.backend == "condensed":
            return
        if self.backend == "osqp":
            # the input rows below the dynamics; in each column A_eq's entries come first, in
            # their own order, so they sit at the stacked matrix's rows < neq
            marked = self.A_eq.copy()
            marked.data = np.arange(1.0, marked.nnz + 1.0)
            box = sp.hstack([sp.csc_matrix((self.n * INPUT_DIM, self._u0)), sp.eye(self.n * INPUT_DIM)])
            a = sp.vstack([marked, box, self.G_tilt]).tocsc()
            a.sort_indices()
            self._osqp_pos = np.flatnonzero(a.indices < self.neq)
            self._osqp_tilt_pos = np.flatnonzero(a.indices >= self.neq + self.n * INPUT_DIM)  # below the input rows
            if not np.array_equal(a.data[self._osqp_pos], marked.data):
                raise RuntimeError("the stacked constraint matrix reordered the dynamics entries")
            a.data[self._osqp_pos] = self.A_eq.data
            self._A_full = a
            lo, hi = self._osqp_bounds()
            self._solver = osqp.OSQP()
            self._solver.setup(P=sp.triu(self.P, format="csc"), q=q, A=a, l=lo, u=hi, verbose=False,
                               eps_abs=self.p.eps, eps_rel=self.p.eps, max_iter=self.p.max_qp_iter,
                               warm_starting=True, polishing=True, check_termination=self.p.osqp_check_termination)
        else:
            self._solver = piqp.SparseSolver()
            s = self._solver.settings
            s.verbose = False
            s.eps_abs = self.p.eps
            s.eps_rel = self.p.eps
            s.max_iter = self.p.max_qp_iter
            # the KKT factorization that follows the horizon's stage structure: half the QP time
            # of the general sparse LDL' here (1.3 ms against 2.7 ms, measured)
            s.kkt_solver = piqp.KKTSolver.sparse_multistage
            x_l, x_u = self._piqp_box()
            if self.n_tilt:
                self._solver.setup(self.P, q, self.A_eq, self.b_eq, self.G_tilt, self.tilt_lo, self.tilt_hi, x_l, x_u)
            else:
                self._solver.setup(self.P, q, self.A_eq, self.b_eq, None, None, None, x_l, x_u)

    def _osqp_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return np.concatenate([self.b_eq, self.u_lo, self.tilt_lo]), np.concatenate([self.b_eq, self.u_hi, self.tilt_hi])

    def _piqp_box(self) -> tuple[np.ndarray, np.ndarray]:
        x_l = np.concatenate([np.full(self._u0, -np.inf), self.u_lo])
        x_u = np.concatenate([np.full(self._u0, np.inf), self.u_hi])
        return x_l, x_u

    def _solve_qp(self, q: np.ndarray) -> tuple[np.ndarray | None, str, int]:
        if self.backend == "osqp":
            self._A_full.data[self._osqp_pos] = self.A_eq.data
            self._A_full.data[self._osqp_tilt_pos] = self.G_tilt.data
            lo, hi = self._osqp_bounds()
            self._solver.update(q=q, l=lo, u=hi, Ax=self._A_full.data)
            res = self._solver.solve(raise_error=False)
            status = str(res.info.status)
            return (res.x.copy() if status == _OSQP_OK else None), status, int(res.info.iter)
        x_l, x_u = self._piqp_box()
        if self.n_tilt:
            self._solver.update(c=q, A=self.A_eq, b=self.b_eq, G=self.G_tilt, h_l=self.tilt_lo, h_u=self.tilt_hi, x_l=x_l, x_u=x_u)
        else:
            self._solver.update(c=q, A=self.A_eq, b=self.b_eq, x_l=x_l, x_u=x_u)
        st = self._solver.solve()
        status = str(st).split(".")[-1]
        res = self._solver.result
        return (np.array(res.x) if status == _PIQP_OK else None), status, int(res.info.iter)

    def _solve_condensed(self, z0: np.ndarray, knots: list[Knot], a: np.ndarray, b: np.ndarray, c: np.ndarray,
                         q_lin: np.ndarray) -> tuple[np.ndarray | None, str, int]:
        """The same QP with the states eliminated: ``z = z_free + S u`` over the flow knots'
        inputs (a jump's input is zero), ``S`` built knot by knot (``S_k+1 = A_k S_k + [B_k]``),
        then ``min 1/2 u'(S'P_z S + P_u)u + (S'(P_z z_free + q_z))'u`` in the torque box."""
        n, nz, nu = self.n, STATE_DIM, INPUT_DIM
        flow = np.array([not knot.is_jump for knot in knots])
        flows = np.flatnonzero(flow)
        z_free, s_flat, h, g = self._kernels.condense(a, b, c, z0, flow, self._p_diag[: self._u0], q_lin)
        h[np.diag_indices(h.shape[0])] += self._p_diag[self._u0 :].reshape(n, nu)[flows].ravel()
        lo = self.u_lo.reshape(n, nu)[flows].ravel()
        hi = self.u_hi.reshape(n, nu)[flows].ravel()
        res = self._box_qp.solve(h, g, lo, hi, self.p.eps, min(self.p.max_qp_iter, _ACTIVE_SET_MAX_ITER))
        if res.status != self._box_qp.SOLVED:
            return None, res.status, res.iterations
        u = np.zeros((n, nu))
        u[flows] = res.x.reshape(-1, nu)
        z = z_free.ravel() + s_flat @ res.x
        return np.concatenate([z, u.ravel()]), res.status, res.iterations

    # --- linearization -----------------------------------------------------------------------

    def _discretize_all(self, knots: list[Knot], q0, z_bar, u_bar, a, b, c, rollout: bool) -> bool:
        """Fill ``a, b, c`` along ``(z_bar, u_bar)``: a jump's ``(D, 0, E)`` (eq. 5.25), a flow's
        exact discretization of eq. 5.23 (eq. 5.24). With ``rollout`` each knot's point is the
        previous knot's prediction (sequential), else all flows exponentiate in one compiled call."""
        flows = []
        a_c, b_c, f, h = self._a_c, self._b_c, self._f, self._h
        for k, knot in enumerate(knots):
            x_k = retract(z_bar[k], q0)
            if not np.isfinite(x_k).all():
                return False
            if knot.is_jump:
                x_plus, d = self.dyn.jump(knot.kind, x_k)
                z_plus = np.concatenate([z_bar[k, :10], x_plus[11:]])  # the attitude does not jump
                a[k], b[k], c[k] = d, 0.0, z_plus - d @ z_bar[k]
                if rollout:
                    z_bar[k + 1] = z_plus
                continue
            f[k], a_c[k], b_c[k] = self.dyn.flow(knot.kind, x_k, u_bar[k])
            h[k] = knot.h
            if rollout:
                self._kernels.rollout_step(a_c[k], b_c[k], f[k], z_bar[k], u_bar[k], knot.h, a[k], b[k], c[k], z_bar[k + 1])
            else:
                flows.append(k)
        if flows:
            self._kernels.discretize_many(a_c, b_c, f, z_bar, u_bar, h, np.array(flows), a, b, c)
        return bool(np.isfinite(a).all() and np.isfinite(b).all() and np.isfinite(c).all())

    def solve(self, x0: np.ndarray, knots: list[Knot], z_ref: np.ndarray) -> GmpcSolution:
        """Solve from the measured manifold state ``x0`` (21) along ``knots`` toward ``z_ref``
        ``(N + 1, 20)`` (its attitude part relative to ``x0``'s attitude, see :func:`lift`)."""
        n, nz, nu = self.n, STATE_DIM, INPUT_DIM
        x0 = np.asarray(x0, float)
        z_ref = np.asarray(z_ref, float)
        q0 = qt.normalize(x0[3:7]) if np.all(np.isfinite(x0)) else (1.0, 0.0, 0.0, 0.0)
        empty = np.full((n + 1, nz), np.nan), np.full((n, nu), np.nan)

        def refuse(why: str, iters: list[int], resid: float = math.inf) -> GmpcSolution:
            return GmpcSolution(False, why, q0, knots, empty[0], empty[1], iters, resid)

        if x0.shape != (nz + 1,) or z_ref.shape != (n + 1, nz) or len(knots) != n:
            raise ValueError(f"x0 must be ({nz + 1},), z_ref ({n + 1}, {nz}), knots {n}")
        if not (np.all(np.isfinite(x0)) and np.all(np.isfinite(z_ref))):
            return refuse("non-finite input", [])
        x0 = np.concatenate([x0[:3], q0, x0[7:]])
        z0 = lift(x0, q0)
        self._set_tilt_rows(q0)
        q_lin = -2.0 * (self.q_diag * z_ref).reshape(-1)
        q_cost = np.concatenate([q_lin, np.zeros(n * nu)])
        a = np.empty((n, nz, nz))
        b = np.empty((n, nz, nu))
        c = np.empty((n, nz))
        z_bar = np.empty((n + 1, nz))
        u_bar = np.zeros((n, nu))
        z_bar[0] = z0
        iters: list[int] = []
        y = None
        status = ""
        for it in range(self.p.sqp_iterations):
            # the first linearization point: the linearized model's own rollout at zero torque
            if not self._discretize_all(knots, q0, z_bar, u_bar, a, b, c, rollout=it == 0):
                return refuse("non-finite linearization", iters)
            self._set_start_and_bounds(z0, knots)
            if self.backend == "condensed":
                y, status, count = self._solve_condensed(z0, knots, a, b, c, q_lin)
            else:
                self._fill(a, b, c)
                y, status, count = self._solve_qp(q_cost)
            iters.append(count)
            if y is None:
                return refuse(status, iters)
            if not np.all(np.isfinite(y)):
                return refuse("non-finite solution", iters)
            z_bar = y[: self._u0].reshape(n + 1, nz)
            u_bar = y[self._u0 :].reshape(n, nu)
        # eq. 5.26a-c at the answer, whichever solver gave it: z_0 = z(t), z_k+1 = A z_k + B u_k + C
        predicted = np.einsum("kij,kj->ki", a, z_bar[:-1]) + np.einsum("kij,kj->ki", b, u_bar) + c
        resid = float(max(np.abs(z_bar[0] - z0).max(), np.abs(z_bar[1:] - predicted).max()))
        tol = self.p.residual_tol
        if resid > tol:
            return refuse(f"dynamics residual {resid:.2e}", iters, resid)
        u_out = np.clip(u_bar, self.u_lo.reshape(n, nu), self.u_hi.reshape(n, nu))
        if np.abs(u_out - u_bar).max() > tol:
            return refuse("input bound violated", iters, resid)
        if self.n_tilt:
            g = self.G_tilt @ y
            if np.any(g < self.tilt_lo - tol) or np.any(g > self.tilt_hi + tol):
                return refuse("tilt bound violated", iters, resid)
        return GmpcSolution(True, status, q0, knots, z_bar.copy(), u_out, iters, resid)


def reference_states(
    q0: Sequence[float], positions: np.ndarray, velocities: np.ndarray, q_target: Sequence[float]
) -> np.ndarray:
    """``z_ref`` ``(N + 1, 20)``: positions [m] and velocities [m/s] per knot, the attitude
    ``q_target`` in ``q0``'s Lie algebra; every other entry zero (unweighted or at rest)."""
    positions = np.asarray(positions, float)
    z = np.zeros((len(positions), STATE_DIM))
    z[:, POS] = positions
    z[:, VEL] = velocities
    z[:, XI] = qt.log(qt.mul(qt.conj(q0), q_target))
    return z
