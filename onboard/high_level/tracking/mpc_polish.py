"""The active-set polish of the Bezier MPC's ADMM answer (as OSQP's polish, with our own checks).

An ADMM iterate is accurate to its tolerance only; the MPC certifies an answer against the
exact constraints. Solving the KKT system of the active set the iterate suggests gives the
vertex answer exactly (rows it then violates join the set). Two solvers of that system: P's
dense inverse (range space, when P is well conditioned: a small dense system per active set)
or the sparse KKT factorization with iterative refinement (any P).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

_POLISH_REGULARIZATION = 1e-9  # keeps the active-set KKT system factorizable
# iterative refinement steps at most; each shrinks the regularization's error by about
# reg / (the KKT system's smallest eigenvalue), which nearly dependent active rows make small
# (3 steps left 2e-6 of constraint residual and a 3 cm error on one Hypothesis example)
_POLISH_REFINEMENTS = 30
_POLISH_RESIDUAL_TOL = 1e-12  # relative to the right-hand side: refinement stops below this
_POLISH_ROUNDS = 5  # active-set solves per polish: violated rows join the set after each
_POLISH_RESIDUAL = 1e-9  # relative residual of the range-space system past which its rows count as dependent


@dataclass
class ActiveSetPolish:
    """The polish of one MPC's QP: its cost ``0.5 x' P x + q' x`` and the row structure of its
    constraint matrix (built once; the values of ``A`` change every tick, its pattern not)."""

    P_full: sp.csr_matrix  # the cost's P, both triangles
    P_full_coo: tuple[np.ndarray, np.ndarray, np.ndarray]  # its rows, columns, values
    P_inv: np.ndarray | None  # its dense inverse when well conditioned, else None (sparse KKT)
    row_ptr: np.ndarray  # A's entries by row: where each row starts...
    row_cols: np.ndarray  # ...their columns...
    row_data_pos: np.ndarray  # ...and their places in A.data (A is CSC)

    def polish(self, x, dual, A, ls, us, q) -> np.ndarray | None:
        """Solve the KKT system of the active set the ADMM iterate suggests (as OSQP's
        polish does). A row the answer then violates joins the set and the system is
        solved again (the iterate can miss a constraint it sits just inside of), at most
        ``_POLISH_ROUNDS`` times. None when the system is singular."""
        tol = 1e-7 * max(1.0, float(np.abs(dual).max(initial=0.0)))
        eq = ls == us
        active = eq | (np.abs(dual) > tol)
        upper = ~eq & (dual > 0)  # which bound an active row sits on
        for _ in range(_POLISH_ROUNDS):
            rows = np.flatnonzero(active)
            if len(rows) > len(q):
                # more active rows than variables cannot all be independent at a vertex: the
                # iterate is far from an answer, and the range-space system's least squares would
                # cost (rows)^3 (20 s for 1808 rows: seen on a dual that was an infeasibility certificate)
                return None
            rhs_rows = np.where(upper[rows], us[rows], ls[rows])
            if not np.all(np.isfinite(rhs_rows)):
                return None
            xp = self.solve_kkt(A, rows, q, rhs_rows)
            if xp is None:
                return None
            Ay = A @ xp
            over, under = ~active & (Ay > us), ~active & (Ay < ls)
            if not (over.any() or under.any()):
                break
            active |= over | under
            upper |= over
        return xp

    def _active_entries(self, A: sp.csc_matrix, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The entries of ``A[rows]``, row after row: where each row starts, columns, values.
        Every row has at least one stored entry (unused plane slots store zeros)."""
        start = self.row_ptr[rows]
        count = self.row_ptr[rows + 1] - start
        first = np.cumsum(count) - count
        pos = np.repeat(start - first, count) + np.arange(int(count.sum()))
        return first, self.row_cols[pos], A.data[self.row_data_pos[pos]]

    def solve_kkt(self, A: sp.csc_matrix, rows: np.ndarray, q: np.ndarray, rhs_rows: np.ndarray) -> np.ndarray | None:
        """``x`` of ``min 0.5 x' P x + q' x`` subject to ``A[rows] x = rhs_rows``."""
        first, cols, vals = self._active_entries(A, rows)
        if self.P_inv is not None:
            return self._polish_range_space(first, cols, vals, q, rhs_rows)
        nv, na = self.P_full.shape[0], len(rows)
        Aa = sp.csr_matrix((vals, cols, np.append(first, len(vals))), shape=(na, nv))
        Pr, Pc, Pv = self.P_full_coo
        ar, ac = np.repeat(np.arange(na), np.diff(Aa.indptr)), Aa.indices
        reg = _POLISH_REGULARIZATION
        diag = np.arange(nv + na)
        K = sp.csc_matrix(
            (
                np.concatenate([Pv, Aa.data, Aa.data, np.r_[np.full(nv, reg), np.full(na, -reg)]]),
                (np.concatenate([Pr, nv + ar, ac, diag]), np.concatenate([Pc, ac, nv + ar, diag])),
            ),
            shape=(nv + na, nv + na),
        )
        rhs = np.concatenate([-q, rhs_rows])
        try:
            lu = spla.splu(K)
            sol = lu.solve(rhs)
            tol = _POLISH_RESIDUAL_TOL * max(1.0, float(np.abs(rhs).max()))
            for _ in range(_POLISH_REFINEMENTS):  # iterative refinement undoes the regularization
                xs, nu = sol[:nv], sol[nv:]
                res = rhs - np.concatenate([self.P_full @ xs + Aa.T @ nu, Aa @ xs])
                if np.abs(res).max() <= tol:
                    break
                sol = sol + lu.solve(res)
        except (RuntimeError, ValueError):
            return None
        xp = sol[:nv]
        return xp if np.all(np.isfinite(xp)) else None

    def _polish_range_space(self, first: np.ndarray, cols: np.ndarray, vals: np.ndarray, q: np.ndarray, b: np.ndarray) -> np.ndarray | None:
        """The polish's KKT system ``[P, Aa'; Aa, 0] [x; nu] = [-q; b]`` (``Aa = A[rows]``)
        solved by eliminating ``x`` with P's dense inverse: ``(Aa P^-1 Aa') nu = Aa P^-1
        (-q) - b``, ``x = P^-1 (-q - Aa' nu)``. Each active row has a few entries, so the
        products are gathers of P^-1's rows (entries from :meth:`_active_entries`);
        dependent rows get the least-squares ``nu``."""
        x_free = self.P_inv @ -q  # the unconstrained minimizer
        W = np.add.reduceat(vals[:, None] * self.P_inv[cols], first, axis=0)  # Aa P^-1
        S = np.add.reduceat(W[:, cols] * vals, first, axis=1)  # Aa P^-1 Aa'
        r = np.add.reduceat(vals * x_free[cols], first) - b
        try:
            nu = np.linalg.solve(S, r)
            singular = np.linalg.norm(S @ nu - r) > _POLISH_RESIDUAL * (1.0 + np.linalg.norm(r))
        except np.linalg.LinAlgError:
            singular = True
        if singular:  # dependent active rows
            try:
                nu = np.linalg.lstsq(S, r)[0]
            except np.linalg.LinAlgError:  # "SVD did not converge": no polish this time
                return None
        x = x_free - W.T @ nu
        return x if np.all(np.isfinite(x)) else None
