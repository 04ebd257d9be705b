"""A small dense strictly convex QP with a box: ``min 1/2 x'Hx + g'x`` s.t. ``lo <= x <= hi``.

The geometric MPC's QP, condensed onto its inputs (the states eliminated through the
dynamics), is of this form: some tens of variables, the wheel torques' box the only constraint.
The primal-dual active-set method (Hintermueller, Ito, Kunisch, SIAM J. Optim. 13(3), 2002)
guesses the bounds that hold, solves the free variables exactly on that guess, and moves every
bound whose multiplier has the wrong sign or every free variable that left its box; on these
problems it ends in 2-4 guesses, each one Cholesky factorization of the free block.

The answer comes with its own certificate: the exact KKT conditions of a box QP (the
gradient zero on free variables, pushing outward at active bounds), checked before it is
returned.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

SOLVED = "solved"


@dataclass(frozen=True)
class BoxQpResult:
    x: np.ndarray
    status: str  # SOLVED, or why not
    iterations: int  # active-set guesses (one factorization each)
    kkt_residual: float  # largest violation of the KKT conditions, relative to 1 + max |g|


def _chol_solve(h: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    # the inputs are checked finite by the caller: skip scipy's own checks (a third of the time here)
    return scipy.linalg.cho_solve(scipy.linalg.cho_factor(h, check_finite=False), rhs, check_finite=False)


def kkt_residual(h: np.ndarray, g: np.ndarray, lo: np.ndarray, hi: np.ndarray, x: np.ndarray, tol: float) -> float:
    """Largest violation of a box QP's KKT conditions at ``x`` (relative to ``1 + max|g|``):
    bounds; the gradient ``r = Hx + g`` zero off the bounds, ``r >= 0`` at a lower bound,
    ``r <= 0`` at an upper one (a variable within ``tol`` of a bound counts as on it)."""
    scale = 1.0 + float(np.abs(g).max(initial=0.0))
    r = (h @ x + g) / scale
    at_lo = x <= lo + tol
    at_hi = x >= hi - tol
    viol = np.where(at_lo & at_hi, 0.0, np.where(at_lo, np.maximum(-r, 0.0), np.where(at_hi, np.maximum(r, 0.0), np.abs(r))))
    bounds = np.maximum(lo - x, x - hi)
    return float(max(viol.max(initial=0.0), bounds.max(initial=0.0), 0.0))


def solve(h: np.ndarray, g: np.ndarray, lo: np.ndarray, hi: np.ndarray, tol: float, max_iter: int = 50) -> BoxQpResult:
    """The minimizer, ``H`` symmetric positive definite, ``lo <= hi`` (equal: a fixed variable).

    ``tol``: the certificate's bound on :func:`kkt_residual`."""
    n = g.size
    # the first guess from the unconstrained minimizer: the bounds it crosses
    try:
        x = _chol_solve(h, -g) if n else g.copy()
    except np.linalg.LinAlgError:
        return BoxQpResult(np.zeros(n), "not positive definite", 0, np.inf)
    lam = np.zeros(n)  # H x + g + lam = 0: lam > 0 pushes at an upper bound, < 0 at a lower one
    upper = np.zeros(n, bool)
    lower = np.zeros(n, bool)
    fixed = lo >= hi
    for it in range(1, max_iter + 1):
        # the guess: a bound holds while its multiplier pushes outward; a free variable beyond
        # a bound goes onto it (the method's rule with its constant c large against lam)
        new_upper = ~fixed & np.where(upper, lam > 0.0, ~lower & (x > hi))
        new_lower = ~fixed & np.where(lower, lam < 0.0, ~upper & (x < lo))
        if it > 1 and np.array_equal(new_upper, upper) and np.array_equal(new_lower, lower):
            break
        upper, lower = new_upper, new_lower
        x = np.where(upper, hi, np.where(lower | fixed, lo, x))
        free = ~(upper | lower | fixed)
        if free.any():
            rhs = -(g[free] + h[np.ix_(free, ~free)] @ x[~free])
            try:
                x[free] = _chol_solve(h[np.ix_(free, free)], rhs)
            except np.linalg.LinAlgError:
                return BoxQpResult(x, "not positive definite", it, np.inf)
        lam = -(h @ x + g)
        lam[free] = 0.0
    else:
        return BoxQpResult(x, "max iterations", max_iter, kkt_residual(h, g, lo, hi, x, tol))
    x = np.clip(x, lo, hi)
    resid = kkt_residual(h, g, lo, hi, x, tol)
    return BoxQpResult(x, SOLVED if resid <= tol else f"kkt residual {resid:.1e}", it - 1, resid)
