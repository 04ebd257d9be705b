"""Compiled inner loops of the geometric MPC (numba, cached on disk): the knots' matrix
exponentials (eq. 5.24) and the condensing of the QP onto its inputs.

Both are dozens of products of 20-24 wide matrices per solve; from Python each product costs
more in call overhead than in arithmetic (scipy's ``expm`` took 50 us a knot, most of it outside
the Pade evaluation), so the loops run compiled and call BLAS directly.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

# Taylor coefficients 1 / k!, k = 0..12
_TAYLOR = np.array([1.0 / math.factorial(k) for k in range(13)])
# the largest 1-norm the degree-12 Taylor polynomial takes unscaled: its truncation error is then
# below 1/13! / (1 - 1/14) = 1.7e-10 relative (tests/test_geometric_mpc.py compares it with scipy's Pade)
EXPM_THETA = 1.0


@nb.njit(cache=True)
def expm(m: np.ndarray) -> np.ndarray:
    """``exp(m)`` of one square matrix: scaling and squaring of the degree-12 Taylor polynomial,
    evaluated with five products (Paterson-Stockmeyer)."""
    d = m.shape[0]
    norm = 0.0
    for j in range(d):
        col = 0.0
        for i in range(d):
            col += abs(m[i, j])
        norm = max(norm, col)
    s = int(math.ceil(math.log2(norm / EXPM_THETA))) if norm > EXPM_THETA else 0
    c = _TAYLOR
    x = m * 0.5**s
    x2 = x @ x
    x3 = x2 @ x
    x4 = x2 @ x2
    p = c[9] * x + c[10] * x2 + c[11] * x3 + c[12] * x4
    for i in range(d):
        p[i, i] += c[8]
    p = c[5] * x + c[6] * x2 + c[7] * x3 + x4 @ p
    for i in range(d):
        p[i, i] += c[4]
    p = x + c[2] * x2 + c[3] * x3 + x4 @ p
    for i in range(d):
        p[i, i] += 1.0
    for _ in range(s):
        p = p @ p
    return p


@nb.njit(cache=True)
def discretize(a_c: np.ndarray, b_c: np.ndarray, f: np.ndarray, z: np.ndarray, u: np.ndarray, h: float,
               a: np.ndarray, b: np.ndarray, c: np.ndarray) -> None:
    """``(A_d, B_d, C_d)`` of eq. 5.24 into ``a, b, c``: the flow's Jacobians ``a_c`` (nz, nz),
    ``b_c`` (nz, nu) and derivative ``f`` at ``(z, u)`` over ``h`` seconds, from
    ``exp([A B C; 0] h)`` with eq. 5.23's ``C = f - A z - B u`` (exact for the affine model)."""
    nz, nu = b_c.shape
    d = nz + nu + 1
    aug = np.zeros((d, d))
    aug[:nz, :nz] = a_c * h
    aug[:nz, nz : nz + nu] = b_c * h
    aug[:nz, d - 1] = (f - a_c @ z - b_c @ u) * h
    e = expm(aug)
    a[:, :] = e[:nz, :nz]
    b[:, :] = e[:nz, nz : nz + nu]
    c[:] = e[:nz, d - 1]


@nb.njit(cache=True)
def rollout_step(a_c: np.ndarray, b_c: np.ndarray, f: np.ndarray, z: np.ndarray, u: np.ndarray, h: float,
                 a: np.ndarray, b: np.ndarray, c: np.ndarray, z_next: np.ndarray) -> None:
    """:func:`discretize`, then the discrete model's prediction ``z_next = A_d z + B_d u + C_d``."""
    discretize(a_c, b_c, f, z, u, h, a, b, c)
    z_next[:] = a @ z + b @ u + c


@nb.njit(cache=True)
def discretize_many(a_c: np.ndarray, b_c: np.ndarray, f: np.ndarray, z: np.ndarray, u: np.ndarray, h: np.ndarray,
                    knots: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> None:
    """:func:`discretize` for each index in ``knots`` (the flows) of the horizon's batch."""
    for k in knots:
        discretize(a_c[k], b_c[k], f[k], z[k], u[k], h[k], a[k], b[k], c[k])


@nb.njit(cache=True)
def condense(a: np.ndarray, b: np.ndarray, c: np.ndarray, z0: np.ndarray, flow: np.ndarray, p_z: np.ndarray,
             q_z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The states through the dynamics ``z_k+1 = A_k z_k + B_k u_k + c_k`` from ``z_0 = z0``:
    ``z = z_free + S u`` over the inputs of the knots where ``flow`` (a jump's input is zero).
    Returns ``(z_free (N+1, nz), S ((N+1) nz, m), S' diag(p_z) S, S'(p_z z_free + q_z))`` for
    the cost ``1/2 z' diag(p_z) z + q_z' z`` (``p_z``, ``q_z`` flat over the knots)."""
    n, nz, nu = b.shape[0], b.shape[1], b.shape[2]
    m = 0
    for k in range(n):
        if flow[k]:
            m += nu
    z_free = np.empty((n + 1, nz))
    s = np.zeros(((n + 1) * nz, m))
    z_free[0] = z0
    col = 0
    for k in range(n):
        z_free[k + 1] = a[k] @ z_free[k] + c[k]
        if col:  # whole rows (contiguous for BLAS): the columns from col on are still zero
            s[(k + 1) * nz : (k + 2) * nz] = a[k] @ s[k * nz : (k + 1) * nz]
        if flow[k]:
            s[(k + 1) * nz : (k + 2) * nz, col : col + nu] = b[k]
            col += nu
    weighted = s * p_z.reshape(-1, 1)
    h = s.T @ weighted
    g = s.T @ (p_z * z_free.ravel() + q_z)
    return z_free, s, h, g


# --- the box QP (onboard.low_level.planning.box_qp) -----------------------------------------------


@nb.njit(cache=True)
def _cholesky_solve(m: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, bool]:
    """``m^-1 rhs`` by Cholesky (m symmetric); False when ``m`` is not positive definite. Scalar
    loops: at this size (tens) a BLAS call per row costs more than its arithmetic."""
    n = m.shape[0]
    low = np.zeros((n, n))
    for j in range(n):
        d = m[j, j]
        for p in range(j):
            d -= low[j, p] * low[j, p]
        if not d > 0.0:
            return rhs.copy(), False
        ljj = math.sqrt(d)
        low[j, j] = ljj
        for i in range(j + 1, n):
            acc = m[i, j]
            for p in range(j):
                acc -= low[i, p] * low[j, p]
            low[i, j] = acc / ljj
    y = np.empty(n)
    for i in range(n):
        acc = rhs[i]
        for p in range(i):
            acc -= low[i, p] * y[p]
        y[i] = acc / low[i, i]
    x = np.empty(n)
    for i in range(n - 1, -1, -1):
        acc = y[i]
        for j in range(i + 1, n):
            acc -= low[j, i] * x[j]
        x[i] = acc / low[i, i]
    return x, True


@nb.njit(cache=True)
def box_qp_active_set(h: np.ndarray, g: np.ndarray, lo: np.ndarray, hi: np.ndarray, max_iter: int) -> tuple[np.ndarray, int, int]:
    """The primal-dual active-set iteration of :func:`onboard.low_level.planning.box_qp.solve`:
    ``(x, status, factorizations)``, status 0 converged, 1 iteration cap, 2 not positive definite."""
    n = g.size
    x, ok = _cholesky_solve(h, -g)  # the first guess: the bounds the unconstrained minimizer crosses
    if not ok:
        return x, 2, 0
    lam = np.zeros(n)  # H x + g + lam = 0: lam > 0 pushes at an upper bound, < 0 at a lower one
    upper = np.zeros(n, np.bool_)
    lower = np.zeros(n, np.bool_)
    fixed = lo >= hi
    for it in range(1, max_iter + 1):
        # a bound holds while its multiplier pushes outward; a free variable beyond a bound goes onto it
        changed = it == 1
        for i in range(n):
            if fixed[i]:
                new_u, new_l = False, False
            elif upper[i]:
                new_u, new_l = lam[i] > 0.0, False
            elif lower[i]:
                new_u, new_l = False, lam[i] < 0.0
            else:
                new_u, new_l = x[i] > hi[i], x[i] < lo[i]
            if new_u != upper[i] or new_l != lower[i]:
                changed = True
            upper[i], lower[i] = new_u, new_l
        if not changed:
            return x, 0, it - 1
        free = np.empty(n, np.int64)
        bound = np.empty(n, np.int64)
        nf, nb_ = 0, 0
        for i in range(n):
            if upper[i]:
                x[i] = hi[i]
            elif lower[i] or fixed[i]:
                x[i] = lo[i]
            if upper[i] or lower[i] or fixed[i]:
                bound[nb_] = i
                nb_ += 1
            else:
                free[nf] = i
                nf += 1
        free, bound = free[:nf], bound[:nb_]
        if nf:
            rhs = -(g[free] + h[free][:, bound] @ x[bound])
            xf, ok = _cholesky_solve(h[free][:, free], rhs)
            if not ok:
                return x, 2, it
            x[free] = xf
        lam = -(h @ x + g)
        lam[free] = 0.0
    return x, 1, max_iter
