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

from onboard.low_level.planning import gmpc_kernels

SOLVED = "solved"


@dataclass(frozen=True)
class BoxQpResult:
    x: np.ndarray
    status: str  # SOLVED, or why not
    iterations: int  # active-set guesses (one factorization each)
    kkt_residual: float  # largest violation of the KKT conditions, relative to 1 + max |g|


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
    """The minimizer, ``H`` symmetric positive definite, ``lo <= hi`` (equal: a fixed variable),
    all finite (the caller's check). ``tol``: the certificate's bound on :func:`kkt_residual`.
    The iteration runs compiled (:func:`onboard.low_level.planning.gmpc_kernels.box_qp_active_set`)."""
    x, code, iterations = gmpc_kernels.box_qp_active_set(h, g, lo, hi, max_iter)
    if code == 2:
        return BoxQpResult(x, "not positive definite", iterations, np.inf)
    if code == 1:
        return BoxQpResult(x, "max iterations", iterations, kkt_residual(h, g, lo, hi, x, tol))
    x = np.clip(x, lo, hi)
    resid = kkt_residual(h, g, lo, hi, x, tol)
    return BoxQpResult(x, SOLVED if resid <= tol else f"kkt residual {resid:.1e}", iterations, resid)
