"""The Bezier MPC's two QP solvers, set up once and warm started (thesis 6.1 and 7.2, eq. 7.2).

A mixin of :class:`onboard.high_level.tracking.bezier_mpc.BezierMpc`: OSQP (ADMM, warm started
from the shifted last solution, with the stack's own active-set polish) or PIQP (an interior
point method: the waypoint rows become variable bounds and equalities). It reads the MPC's
problem data (``P``, ``_P_full``, the row layout ``r_box``, ``l_static``/``u_static``, ``nvar``,
``nx``, ``x0_radius``, ``terminal``, ``horizon``, ``reach``) and settings (``backend``, ``eps``,
``max_iter``, ``polish``, ``unit_rows``, ``time_limit_s``), and sets ``_solver``, ``_polisher``,
``_A`` and ``_ready``.
"""

from __future__ import annotations

import numpy as np
import osqp
import piqp
import scipy.sparse as sp

from onboard.high_level.tracking.mpc_polish import ActiveSetPolish

_PIQP_FREE_ROW_BOUND = 1e4  # on rows that are all zero: never active
_POLISH_MAX_COND = 1e8  # P better conditioned than this: polish with its dense inverse (range space)
# OSQP's Ruiz equilibration passes: none on unit rows (already equilibrated), where the
# equilibration OSQP recomputes on every matrix update (the plane normals change every
# tick) cost 0.26 ms of a 0.3 ms update on the 50-knot planner MPC and more iterations;
# physical rows (coefficients from 1 to (p / tau)^2) need it.
_OSQP_SCALING_UNIT_ROWS = 0
_OSQP_SCALING_PHYSICAL_ROWS = 10
_OSQP_CHECK_TERMINATION = 5  # a warm-started tick converges in 10-20 iterations: check often
# rho may change at every termination check (it refactors only on a change past OSQP's
# tolerance): on 7 bench seeds the p99 was 0.99-1.61 ms against 1.13-2.60 ms every 100
_OSQP_ADAPTIVE_RHO_INTERVAL = 5
# OSQP's verdicts that the problem has no answer: its ``y`` is then a certificate of that, not a
# dual, so neither a polish of it nor a tighter pass can certify anything
OSQP_INFEASIBLE = frozenset(int(s) for s in (
    osqp.SolverStatus.OSQP_PRIMAL_INFEASIBLE, osqp.SolverStatus.OSQP_PRIMAL_INFEASIBLE_INACCURATE,
    osqp.SolverStatus.OSQP_DUAL_INFEASIBLE, osqp.SolverStatus.OSQP_DUAL_INFEASIBLE_INACCURATE))


class QpBackends:
    """Solver setup and warm starts of the Bezier MPC's QP (see the module docstring)."""

    def _setup_solver(self) -> None:
        A = self._A = self._A_matrix()
        q = np.zeros(self.nvar)
        l, u = self.l_static.copy(), self.u_static.copy()
        l[self.r_box], u[self.r_box] = -1e3, 1e3  # placeholders, replaced at the first solve
        if self.backend == "osqp":
            # Our polish eliminates x with P's inverse when P is well conditioned (positive
            # state and terminal weights): a small dense system per active set, ten times
            # faster than factorizing the sparse KKT system each time.
            P_inv = None
            if self.polish:
                Pd = self._P_full.toarray()
                ev = np.linalg.eigvalsh(Pd)
                if ev[0] > 0 and ev[-1] < _POLISH_MAX_COND * ev[0]:
                    P_inv = np.linalg.inv(Pd)
            self._polisher = ActiveSetPolish(self._P_full, self._P_full_coo, P_inv, self._row_ptr, self._row_cols,
                                             self._row_data_pos)
            # OSQP's polish prints a line when it finds no active constraint; an equality
            # row (x_0 pinned in some component, or x_N) is always active, so it stays silent.
            has_equality = bool(np.any(self.x0_radius == 0.0)) or self.terminal == "equal"
            self._solver = osqp.OSQP()
            self._solver.setup(
                self.P, q, A, l, u,
                verbose=False, warm_starting=True, polishing=self.polish and has_equality,
                eps_abs=self.eps, eps_rel=self._eps_rel, max_iter=self.max_iter,
                eps_prim_inf=1e-6, eps_dual_inf=1e-6, scaling=_OSQP_SCALING_UNIT_ROWS if self.unit_rows else _OSQP_SCALING_PHYSICAL_ROWS,
                **({"time_limit": self.time_limit_s} if self.time_limit_s > 0 else {}),  # OSQP refuses 0
                check_termination=_OSQP_CHECK_TERMINATION, adaptive_rho_interval=_OSQP_ADAPTIVE_RHO_INTERVAL,
            )  # fmt: skip
        elif self.backend == "piqp":
            self._setup_piqp(A, q, l, u)
        else:
            raise ValueError(f"unknown backend {self.backend!r}")
        self._ready = True

    def _piqp_split(self, l: np.ndarray, u: np.ndarray):
        """PIQP form: waypoint rows become variable bounds or equalities, the rest G."""
        box_l, box_u = l[self.r_box], u[self.r_box]
        x_l = np.full(self.nvar, -np.inf)
        x_u = np.full(self.nvar, np.inf)
        eq = self._eq_mask
        x_l[: self.nx][~eq] = box_l[~eq]
        x_u[: self.nx][~eq] = box_u[~eq]
        b = box_l[eq]
        rest = slice(self.r_box.stop, self.n_rows)
        g_l, g_u = l[rest], u[rest].copy()
        # PIQP wants no free rows (unused plane slots): give them a harmless finite bound
        g_u[~np.isfinite(g_l) & ~np.isfinite(g_u)] = _PIQP_FREE_ROW_BOUND
        return x_l, x_u, b, g_l, g_u

    def _setup_piqp(self, A: sp.csc_matrix, q: np.ndarray, l: np.ndarray, u: np.ndarray) -> None:
        n, N = self.reach.n, self.horizon
        eq = np.zeros(self.nx, bool)
        eq[:n] = self.x0_radius == 0.0
        if self.terminal == "equal":
            eq[N * n :] = True
        self._eq_mask = eq
        E = sp.csc_matrix((np.ones(eq.sum()), (np.arange(eq.sum()), np.flatnonzero(eq))), shape=(int(eq.sum()), self.nvar))
        self._piqp_E = E
        x_l, x_u, b, g_l, g_u = self._piqp_split(l, u)
        self._solver = piqp.SparseSolver()
        s = self._solver.settings
        s.verbose = False
        s.eps_abs = self.eps * 1e-2  # interior point: cheap to be accurate
        s.eps_rel = self.eps * 1e-2
        s.max_iter = 200
        self._solver.setup(
            self.P, q, E, b, A[self.r_box.stop :, :].tocsc(), g_l, g_u, x_l, x_u
        )

    def _osqp_warm_start(self, warm_start: np.ndarray | None, shift: int, ref: np.ndarray) -> None:
        """Primal warm start; OSQP keeps its last dual. Shifting the duals too was measured
        to cost iterations (plane rows are re-chosen per tick, so their duals do not carry;
        on the bench's knot ticks 25 -> 100-260 iterations, zero duals as bad)."""
        R, N, n = self.reach, self.horizon, self.reach.n
        last = getattr(self, "_last", None)
        if shift < 0 or shift > N:
            raise ValueError(f"shift must be in [0, {N}]")
        if warm_start is None and not (shift and last is not None):
            return  # OSQP starts from its last solution
        if last is None:
            x = np.zeros(self.nvar)
        elif shift:
            x = _shift_blocks(last, [(0, N + 1, n), (self.nx, N, R.nz)], shift)
            x[(N + 1 - shift) * n : self.nx] = ref[N + 1 - shift :].reshape(-1)  # new knots: the reference
        else:
            x = last.copy()
        if warm_start is not None:
            x[: self.nx] = np.asarray(warm_start, float).reshape(-1)
        self._solver.warm_start(x=x)


def _shift_blocks(vec: np.ndarray, blocks: list[tuple[int, int, int]], shift: int) -> np.ndarray:
    """Shift knot-major blocks ``(start, units, size)`` of ``vec`` by ``shift`` units; the tail repeats the last."""
    out = vec.copy()
    for start, units, size in blocks:
        if size == 0 or units == 0:
            continue
        blk = vec[start : start + units * size].reshape(units, size)
        new = np.empty_like(blk)
        new[: units - shift] = blk[shift:]
        new[units - shift :] = blk[-1]
        out[start : start + units * size] = new.reshape(-1)
    return out
