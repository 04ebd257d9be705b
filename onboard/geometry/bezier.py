"""Bezier curves: Bernstein basis, derivative, boundary-value, split and elevation matrices.

Thesis section 2.6 (lines 1183-1281). A curve of order ``p`` on ``[0, tau]`` is
``b(t) = sum_j C[j] * z_j(t / tau)`` with ``z_j`` the Bernstein polynomials of degree
``p``.

Conventions used throughout the project:

- Control points are an array ``C`` of shape ``(p + 1, m)``, one row per point
  (the thesis writes the transpose, ``p = C.T`` of shape ``(m, p + 1)``). The row-major
  flattening ``C.reshape(-1)`` is the thesis's ``vec(p)``.
- Batches put extra axes in front: ``C`` of shape ``(..., p + 1, m)``.
- The matrices ``H``, ``D``, ``R``, ``Q`` are returned exactly as the thesis defines them
  (acting on ``p`` from the right), so they act on ``C`` from the left as ``X.T @ C``.
  The helpers :func:`derivative_points`, :func:`split`, :func:`elevate` apply them.
- Time ``t`` is in seconds on ``[0, tau]``; a derivative of order ``k`` is taken with
  respect to ``t`` (so it carries ``tau ** -k``).
- A state of relative degree ``gamma`` stacks derivatives coordinate-block first:
  ``x = [q, q', ..., q^(gamma-1)]`` with each block of size ``m`` (``n = m * gamma``).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from math import comb
from typing import Literal

import numpy as np
import scipy.linalg

Weighting = Literal["effort", "min_norm"]


def _readonly(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


@lru_cache(maxsize=64)
def _binomials(p: int) -> np.ndarray:
    return _readonly(np.array([comb(p, j) for j in range(p + 1)], dtype=float))


def bernstein(p: int, s: np.ndarray | float) -> np.ndarray:
    """Bernstein basis of degree ``p`` at normalized times ``s`` in [0, 1].

    Returns shape ``s.shape + (p + 1,)``; rows sum to one.
    """
    if p < 0:
        raise ValueError(f"order must be >= 0, got {p}")
    s = np.asarray(s, dtype=float)[..., None]
    j = np.arange(p + 1)
    # Powers via exponent arrays: exact zeros at the ends (0**0 == 1).
    return _binomials(p) * s**j * (1.0 - s) ** (p - j)


def evaluate(C: np.ndarray, tau: float, t: np.ndarray | float) -> np.ndarray:
    """Curve values at times ``t`` [s].

    ``C`` of shape ``(..., p + 1, m)``, ``t`` of shape ``(k,)`` (or scalar) ->
    ``(..., k, m)`` (``(..., m)`` for a scalar ``t``).
    """
    C = np.asarray(C, dtype=float)
    Z = bernstein(C.shape[-2] - 1, np.asarray(t, dtype=float) / tau)
    return Z @ C if Z.ndim == 2 else np.einsum("j,...jm->...m", Z, C)


@lru_cache(maxsize=256)
def elevation_matrix(p: int, r: int) -> np.ndarray:
    """Degree-elevation matrix ``R`` (Property 2.48), shape ``(p + 1, r + 1)``.

    The order-``r`` control points of the same curve are ``R.T @ C``.
    """
    if r < p:
        raise ValueError(f"cannot elevate order {p} to lower order {r}")
    R = np.zeros((p + 1, r + 1))
    for j in range(r + 1):
        for i in range(max(0, j - (r - p)), min(p, j) + 1):
            R[i, j] = comb(p, i) * comb(r - p, j - i) / comb(r, j)
    return _readonly(R)


@lru_cache(maxsize=256)
def derivative_matrix(p: int, tau: float) -> np.ndarray:
    """Derivative matrix ``H`` of the thesis (``b' = p H z``), shape ``(p + 1, p + 1)``.

    ``H.T @ C`` are the control points of ``db/dt``, degree-elevated back to order
    ``p`` so that state curves of every derivative share one basis (eq. 2.22).
    """
    if p < 1:
        raise ValueError("a derivative needs order >= 1")
    delta = np.zeros((p + 1, p))
    idx = np.arange(p)
    delta[idx, idx] = -p / tau
    delta[idx + 1, idx] = p / tau
    return _readonly(delta @ elevation_matrix(p - 1, p))


@lru_cache(maxsize=256)
def _derivative_power(p: int, tau: float, k: int) -> np.ndarray:
    return _readonly(np.linalg.matrix_power(derivative_matrix(p, tau), k))


def derivative_points(C: np.ndarray, tau: float, k: int = 1) -> np.ndarray:
    """Control points of the ``k``-th time derivative, kept at the order of ``C``."""
    C = np.asarray(C, dtype=float)
    if k == 0:
        return C
    return _derivative_power(C.shape[-2] - 1, float(tau), k).T @ C


def hodograph(C: np.ndarray, tau: float) -> np.ndarray:
    """Control points of ``db/dt`` at its natural order ``p - 1``."""
    C = np.asarray(C, dtype=float)
    p = C.shape[-2] - 1
    return (p / tau) * np.diff(C, axis=-2)


@lru_cache(maxsize=256)
def split_matrix(p: int, a: float, b: float) -> np.ndarray:
    """Matrix ``Q`` of Property 2.47 for the normalized sub-interval ``[a, b]`` of [0, 1].

    ``Q.T @ C`` are the control points of the piece ``t -> B(tau*a + t*(b - a))``,
    i.e. the same values over the sub-interval, reparameterized to the full domain.
    Built by de Casteljau's algorithm on the identity (exact, stable).
    """
    if not 0.0 <= a < b <= 1.0:
        raise ValueError(f"need 0 <= a < b <= 1, got [{a}, {b}]")

    def left(M: np.ndarray, s: float) -> np.ndarray:  # points of [0, s]
        rows = [M[0]]
        cur = M
        while len(cur) > 1:
            cur = (1.0 - s) * cur[:-1] + s * cur[1:]
            rows.append(cur[0])
        return np.array(rows)

    def right(M: np.ndarray, s: float) -> np.ndarray:  # points of [s, 1]
        return left(M[::-1], 1.0 - s)[::-1]

    S = left(np.eye(p + 1), b)  # [0, b]
    if a > 0.0:
        S = right(S, a / b)  # [a, b]
    return _readonly(S.T.copy())


def refinement_breaks(k: int | np.ndarray) -> np.ndarray:
    """Normalized break times of a k-refinement (Definition 2.46).

    An integer gives ``k`` equal pieces; an array is checked and returned.
    """
    if np.isscalar(k):
        if int(k) < 1:
            raise ValueError("a refinement needs at least one piece")
        return np.linspace(0.0, 1.0, int(k) + 1)
    breaks = np.asarray(k, dtype=float)
    if breaks[0] != 0.0 or breaks[-1] != 1.0 or np.any(np.diff(breaks) <= 0.0):
        raise ValueError("breaks must increase strictly from 0 to 1")
    return breaks


def split(C: np.ndarray, breaks: int | np.ndarray) -> np.ndarray:
    """Control points of the pieces of a k-refinement: ``(..., k, p + 1, m)``."""
    C = np.asarray(C, dtype=float)
    br = refinement_breaks(breaks)
    p = C.shape[-2] - 1
    Qs = np.stack([split_matrix(p, float(a), float(b)).T for a, b in zip(br[:-1], br[1:])])
    return np.einsum("kij,...jm->...kim", Qs, C)


def elevate(C: np.ndarray, r: int) -> np.ndarray:
    """Control points of the same curve at order ``r``."""
    C = np.asarray(C, dtype=float)
    return elevation_matrix(C.shape[-2] - 1, r).T @ C


@lru_cache(maxsize=256)
def boundary_matrix(p: int, gamma: int, tau: float) -> np.ndarray:
    """``D`` of Property 2.45, shape ``(p + 1, 2 * gamma)``.

    ``D.T @ C`` stacks ``[q(0), q'(0), ..., q^(gamma-1)(0), q(tau), ..., q^(gamma-1)(tau)]``
    as rows, i.e. ``(D.T @ C).reshape(-1) == [x0; xT]`` for states ordered as in the
    module docstring.
    """
    if gamma < 1:
        raise ValueError("relative degree must be >= 1")
    if p < 2 * gamma - 1:
        raise ValueError(f"order {p} < 2*gamma - 1 = {2 * gamma - 1}: boundary values not reachable")
    cols0, colsT = [], []
    for k in range(gamma):
        Hk = np.linalg.matrix_power(derivative_matrix(p, tau), k) if k else np.eye(p + 1)
        cols0.append(Hk[:, 0])
        colsT.append(Hk[:, p])
    return _readonly(np.column_stack(cols0 + colsT))


@lru_cache(maxsize=256)
def gram_matrix(p: int, tau: float) -> np.ndarray:
    """``G[i, j] = integral_0^tau z_i(t/tau) z_j(t/tau) dt`` (exact)."""
    i = np.arange(p + 1)
    b = _binomials(p)
    denom = np.array([[comb(2 * p, a + c) for c in i] for a in i], dtype=float)
    return _readonly(tau * np.outer(b, b) / (denom * (2 * p + 1)))


@lru_cache(maxsize=256)
def boundary_solution(
    p: int, gamma: int, tau: float, weighting: Weighting = "effort"
) -> tuple[np.ndarray, np.ndarray]:
    """Linear parameterization of every curve meeting given boundary states.

    Returns ``(M, N)`` with ``M`` of shape ``(p + 1, 2 * gamma)`` and ``N`` of shape
    ``(p + 1, p + 1 - 2 * gamma)`` such that the curves with ``D.T @ C = X`` are exactly
    ``C = M @ X + N @ Z`` for free ``Z`` of shape ``(p + 1 - 2 * gamma, m)``, where
    ``X = [x0; xT].reshape(2 * gamma, m)``.

    For ``p == 2 * gamma - 1`` the curve is unique (``N`` is empty). For higher orders
    ``M @ X`` is the least-squares particular solution: with ``weighting="effort"`` it
    minimizes ``integral ||q^(gamma)(t)||^2 dt`` (the input effort of an integrator
    chain, translation invariant); ``"min_norm"`` is the thesis's ``D^+`` (minimum
    control-point norm). ``N`` is an orthonormal null-space basis of ``D.T``.
    """
    D = boundary_matrix(p, gamma, tau)
    pinv = np.linalg.pinv(D.T)
    if p == 2 * gamma - 1:
        return _readonly(np.linalg.inv(D.T)), _readonly(np.zeros((p + 1, 0)))
    N = scipy.linalg.null_space(D.T)
    if weighting == "min_norm":
        M = pinv
    elif weighting == "effort":
        Hg = _derivative_power(p, float(tau), gamma)
        W = Hg @ gram_matrix(p, tau) @ Hg.T  # C.T W C integrates ||q^(gamma)||^2
        NW = N.T @ W
        M = pinv - N @ np.linalg.solve(NW @ N, NW @ pinv)
    else:
        raise ValueError(f"unknown weighting {weighting!r}")
    return _readonly(M), _readonly(N)


def boundary_values(x0: np.ndarray, xT: np.ndarray, gamma: int) -> np.ndarray:
    """Stack boundary states ``(..., n)`` into ``X`` of shape ``(..., 2 * gamma, m)``."""
    x0 = np.asarray(x0, dtype=float)
    xT = np.asarray(xT, dtype=float)
    n = x0.shape[-1]
    if n % gamma:
        raise ValueError(f"state size {n} is not a multiple of gamma={gamma}")
    both = np.concatenate([x0, xT], axis=-1)
    return both.reshape(both.shape[:-1] + (2 * gamma, n // gamma))


def connect(
    x0: np.ndarray,
    xT: np.ndarray,
    tau: float,
    gamma: int,
    p: int | None = None,
    weighting: Weighting = "effort",
) -> np.ndarray:
    """Control points ``(..., p + 1, m)`` of the particular curve from ``x0`` to ``xT``.

    Batched over leading axes of ``x0``/``xT`` (shape ``(..., n)``). ``p`` defaults to
    the unique order ``2 * gamma - 1``.
    """
    p = 2 * gamma - 1 if p is None else p
    M, _ = boundary_solution(p, gamma, float(tau), weighting)
    return M @ boundary_values(x0, xT, gamma)


def state_points(C: np.ndarray, tau: float, gamma: int) -> np.ndarray:
    """State-space control points ``P`` of eq. 2.22 as rows: ``(..., p + 1, m * gamma)``."""
    return np.concatenate([derivative_points(C, tau, k) for k in range(gamma)], axis=-1)


def state_values(C: np.ndarray, tau: float, gamma: int, t: np.ndarray) -> np.ndarray:
    """States ``[q, q', ..., q^(gamma-1)]`` at times ``t``: ``(..., len(t), m * gamma)``."""
    return np.concatenate([evaluate(derivative_points(C, tau, k), tau, t) for k in range(gamma)], axis=-1)


def path_length_bound(C: np.ndarray) -> np.ndarray:
    """Upper bound on the arc length (Property 2.49): sum of control polygon legs.

    ``C`` of shape ``(..., p + 1, m)`` -> ``(...)``, in the units of ``C``.
    """
    return np.linalg.norm(np.diff(np.asarray(C, dtype=float), axis=-2), axis=-1).sum(axis=-1)


@dataclass(frozen=True)
class BezierCurve:
    """One Bezier curve on ``[0, duration]`` [s]; ``control_points`` of shape ``(p + 1, m)``."""

    control_points: np.ndarray
    duration: float

    def __post_init__(self) -> None:
        C = np.array(self.control_points, dtype=float)
        if C.ndim != 2 or C.shape[0] < 1:
            raise ValueError(f"control points must be (p + 1, m), got {C.shape}")
        if not (self.duration > 0.0 and np.isfinite(self.duration)) or not np.all(np.isfinite(C)):
            raise ValueError("duration must be positive and control points finite")
        object.__setattr__(self, "control_points", _readonly(C))

    @property
    def order(self) -> int:
        return self.control_points.shape[0] - 1

    def __call__(self, t: np.ndarray | float) -> np.ndarray:
        return evaluate(self.control_points, self.duration, t)

    def derivative(self, k: int = 1) -> BezierCurve:
        """The ``k``-th time derivative at the same order."""
        return BezierCurve(derivative_points(self.control_points, self.duration, k), self.duration)

    def split(self, breaks: int | np.ndarray) -> list[BezierCurve]:
        """Pieces of a k-refinement; each keeps its own duration in seconds."""
        br = refinement_breaks(breaks)
        pieces = split(self.control_points, br)
        return [BezierCurve(P, self.duration * (b - a)) for P, a, b in zip(pieces, br[:-1], br[1:])]

    def elevate(self, r: int) -> BezierCurve:
        return BezierCurve(elevate(self.control_points, r), self.duration)

    def path_length_bound(self) -> float:
        return float(path_length_bound(self.control_points))
