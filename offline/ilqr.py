"""Iterative LQR with box input bounds, batched over independent problems (thesis 2.5, lines
1121-1145; the control-limited variant of Tassa, Mansard and Todorov, the thesis's [190]).

Each of ``N`` problems is

    min_{u_0..u_{T-1}}  sum_k  x_k' Q x_k + u_k' R u_k  +  x_T' P x_T
    s.t.  x_{k+1} = f(x_k, u_k),   lo <= u_k <= hi   (element-wise)

from its own ``x_0``. The problems share ``f``, the weights and the bounds, so every call of
the dynamics carries all of them at once (one batched call per time step, not one per problem:
the dynamics here is a numerically integrated stance whose cost is mostly per call).

Backward pass: the Gauss-Newton quadratic model of ``Q(dx, du)`` (no dynamics Hessians: iLQR,
not DDP); the input step solves the box-constrained QP ``min 1/2 du' Quu du + Qu' du`` with
``lo - u <= du <= hi - u`` exactly, by enumerating its active sets (3^m of them: 9 for the
hopper's 2 inputs), and the feedback gain is ``K = -Quu_ff^-1 Qux`` on the free inputs and zero
on the clamped ones. Forward pass: ``u = clip(u_bar + alpha k + K (x - x_bar))`` for every step
size at once, each problem keeping the best one if it lowers its cost (else its
Levenberg-Marquardt term ``mu`` grows).

After the last iteration one more linearisation and backward pass at the returned trajectory
give ``K_0``: where no bound is active it is the derivative of the optimal first input with
respect to the initial state (thesis 2743: "if no constraints are active, then this gradient is
exactly the feedback matrix"); on a clamped input that derivative is zero for a fixed bound.

A problem whose rollout fails (the dynamics return a non-finite state: the hopper fell) costs
infinity: such a step is never accepted.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Protocol

import numpy as np


class Dynamics(Protocol):
    """Batched dynamics: rows are states ``x`` (M, n) and inputs ``u`` (M, m)."""

    def step(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """``x_next`` (M, n); non-finite where the step fails."""
        ...

    def jacobians(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(df/dx (M, n, n), df/du (M, n, m))``."""
        ...


@dataclass(frozen=True)
class IlqrSettings:
    iterations: int = 5  # thesis 2753: "we limit the number of iLQR iterations to five"
    # step sizes tried together in each forward pass (all in one batched call, so trying several
    # costs little); the full step first, shrinking where the quadratic model overreaches
    step_sizes: tuple[float, ...] = (1.0, 0.5, 0.25, 0.1)
    # Levenberg-Marquardt term on Quu: starts negligible against R (order 1), grows tenfold after a
    # step that lowered nothing and shrinks tenfold after one that did
    mu_init: float = 1e-6
    mu_factor: float = 10.0
    mu_max: float = 1e6
    # an input within this of a bound counts as on it when the active set is read [input units]
    bound_tol: float = 1e-9
    # stop before ``iterations`` once no problem's cost fell by more than this fraction in an
    # iteration: converged (each further iteration costs a linearisation and a forward pass)
    converged_rel: float = 1e-6


@dataclass(frozen=True)
class IlqrResult:
    x: np.ndarray  # (N, T+1, n) states
    u: np.ndarray  # (N, T, m) inputs, within the bounds
    cost: np.ndarray  # (N,) final cost (inf where even the initial rollout failed)
    cost_history: np.ndarray  # (iterations run + 1, N): the initial rollout's, then after each iteration
    gains: np.ndarray  # (N, T, m, n) feedback gains K_k of the backward pass at the returned trajectory
    free: np.ndarray  # (N, T, m) bool: input not held at a bound by that backward pass's QP


def trajectory_cost(x: np.ndarray, u: np.ndarray, q: np.ndarray, r: np.ndarray, p: np.ndarray) -> np.ndarray:
    """``sum_k x_k' Q x_k + u_k' R u_k + x_T' P x_T`` per problem; inf where a state is not finite.

    ``x`` (..., T+1, n), ``u`` (..., T, m)."""
    stage = np.einsum("...ki,ij,...kj->...", x[..., :-1, :], q, x[..., :-1, :]) + np.einsum("...ki,ij,...kj->...", u, r, u)
    terminal = np.einsum("...i,ij,...j->...", x[..., -1, :], p, x[..., -1, :])
    c = stage + terminal
    return np.where(np.isfinite(c), c, np.inf)


def rollout(dynamics: Dynamics, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
    """States (N, T+1, n) under the open-loop inputs ``u`` (N, T, m)."""
    n_prob, horizon = u.shape[:2]
    x = np.empty((n_prob, horizon + 1, x0.shape[1]))
    x[:, 0] = x0
    for k in range(horizon):
        x[:, k + 1] = dynamics.step(x[:, k], u[:, k])
    return x


def box_qp(h: np.ndarray, g: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``argmin 1/2 d' H d + g' d`` s.t. ``lo <= d <= hi``, batched: ``H`` (N, m, m) positive
    definite, ``g``, ``lo``, ``hi`` (N, m). Returns ``(d, free)``, ``free`` (N, m) bool.

    Exact: every active set (each input free, at its lower or at its upper bound) is solved; the
    optimum of a convex QP is the feasible candidate of least objective. For small ``m`` only.
    """
    n, m = g.shape
    best = np.zeros((n, m))
    best_free = np.zeros((n, m), dtype=bool)
    best_obj = np.full(n, np.inf)
    slack = 1e-12 * (1.0 + np.abs(lo) + np.abs(hi))  # round-off in the free inputs' solve
    for combo in itertools.product((0, -1, 1), repeat=m):
        code = np.array(combo)
        clamped = code != 0
        fixed = np.where(code < 0, lo, hi) * clamped  # clamped inputs sit on their bound
        # the reduced KKT system: identity rows for the clamped inputs, H_ff for the free ones
        keep = ~clamped
        hm = h * keep[None, :, None] * keep[None, None, :] + np.diag(clamped.astype(float))[None]
        rhs = np.where(keep, -g - np.einsum("nij,nj->ni", h, fixed), fixed)
        d = np.linalg.solve(hm, rhs[..., None])[..., 0]
        feasible = np.all((d >= lo - slack) & (d <= hi + slack), axis=1)
        obj = 0.5 * np.einsum("ni,nij,nj->n", d, h, d) + np.einsum("ni,ni->n", g, d)
        better = feasible & (obj < best_obj)
        best[better] = d[better]
        best_free[better] = keep
        best_obj[better] = obj[better]
    return best, best_free


def _backward(a: np.ndarray, b: np.ndarray, x: np.ndarray, u: np.ndarray, q: np.ndarray, r: np.ndarray, p: np.ndarray,
              lo: np.ndarray, hi: np.ndarray, mu: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Feed-forward steps ``k`` (N, T, m), gains ``K`` (N, T, m, n), free inputs (N, T, m)."""
    n_prob, horizon, m = u.shape
    n = x.shape[2]
    vx = 2.0 * np.einsum("ij,nj->ni", p, x[:, -1])
    vxx = np.broadcast_to(2.0 * p, (n_prob, n, n)).copy()
    ks = np.zeros((n_prob, horizon, m))
    gains = np.zeros((n_prob, horizon, m, n))
    free = np.zeros((n_prob, horizon, m), dtype=bool)
    reg = mu[:, None, None] * np.eye(m)[None]
    for k in range(horizon - 1, -1, -1):
        ak, bk = a[:, k], b[:, k]
        qx = 2.0 * np.einsum("ij,nj->ni", q, x[:, k]) + np.einsum("nji,nj->ni", ak, vx)
        qu = 2.0 * np.einsum("ij,nj->ni", r, u[:, k]) + np.einsum("nji,nj->ni", bk, vx)
        vxx_a = vxx @ ak
        vxx_b = vxx @ bk
        qxx = 2.0 * q + np.transpose(ak, (0, 2, 1)) @ vxx_a
        quu = 2.0 * r + np.transpose(bk, (0, 2, 1)) @ vxx_b + reg
        qux = np.transpose(bk, (0, 2, 1)) @ vxx_a
        d, fr = box_qp(quu, qu, lo[None] - u[:, k], hi[None] - u[:, k])
        # gains on the free inputs only: solve with identity rows for the clamped ones
        hm = quu * fr[:, :, None] * fr[:, None, :] + (~fr)[:, :, None] * np.eye(m)[None]
        gk = np.linalg.solve(hm, -qux * fr[:, :, None])
        ks[:, k], gains[:, k], free[:, k] = d, gk, fr
        gt = np.transpose(gk, (0, 2, 1))
        vx = qx + np.einsum("nji,njl,nl->ni", gk, quu, d) + np.einsum("nji,nj->ni", gk, qu) + np.einsum("nji,nj->ni", qux, d)
        vxx = qxx + gt @ quu @ gk + gt @ qux + np.transpose(qux, (0, 2, 1)) @ gk
        vxx = 0.5 * (vxx + np.transpose(vxx, (0, 2, 1)))
    return ks, gains, free


def _linearize(dynamics: Dynamics, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n_prob, horizon, m = u.shape
    n = x.shape[2]
    a, b = dynamics.jacobians(x[:, :-1].reshape(-1, n), u.reshape(-1, m))
    return a.reshape(n_prob, horizon, n, n), b.reshape(n_prob, horizon, n, m)


def ilqr(dynamics: Dynamics, x_init: np.ndarray, u_init: np.ndarray, q: np.ndarray, r: np.ndarray, p: np.ndarray,
         lo: np.ndarray, hi: np.ndarray, settings: IlqrSettings = IlqrSettings()) -> IlqrResult:
    """Run ``settings.iterations`` iLQR iterations from the trajectory ``x_init`` (N, T+1, n),
    ``u_init`` (N, T, m) (a rollout of the initial guess: the caller's stabilising policy).

    ``q`` (n, n), ``r`` (m, m), ``p`` (n, n) symmetric; ``lo``, ``hi`` (m,). See the module
    docstring.
    """
    lo, hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
    x = np.array(x_init, dtype=float)
    u = np.clip(np.array(u_init, dtype=float), lo, hi)
    n_prob, horizon, m = u.shape
    n = x.shape[2]
    alphas = np.asarray(settings.step_sizes, dtype=float)
    n_alpha = alphas.size
    cost = trajectory_cost(x, u, q, r, p)
    history = [cost.copy()]
    mu = np.full(n_prob, settings.mu_init)
    alive = np.isfinite(cost)  # a problem whose initial rollout failed is left alone
    for _ in range(settings.iterations):
        a, b = _linearize(dynamics, np.where(alive[:, None, None], x, 0.0), u)
        ks, gains, _ = _backward(a, b, np.where(alive[:, None, None], x, 0.0), u, q, r, p, lo, hi, mu)
        # every step size at once: rows (problem, step size)
        xn = np.empty((n_prob, n_alpha, horizon + 1, n))
        un = np.empty((n_prob, n_alpha, horizon, m))
        xn[:, :, 0] = x[:, None, 0]
        for k in range(horizon):
            dx = xn[:, :, k] - x[:, None, k]
            step = alphas[None, :, None] * ks[:, None, k] + np.einsum("nij,naj->nai", gains[:, k], dx)
            un[:, :, k] = np.clip(u[:, None, k] + step, lo, hi)
            xn[:, :, k + 1] = dynamics.step(xn[:, :, k].reshape(-1, n), un[:, :, k].reshape(-1, m)).reshape(n_prob, n_alpha, n)
        cn = trajectory_cost(xn, un, q, r, p)
        pick = np.argmin(cn, axis=1)
        rows = np.arange(n_prob)
        better = alive & (cn[rows, pick] < cost)
        x[better] = xn[rows, pick][better]
        u[better] = un[rows, pick][better]
        cost[better] = cn[rows, pick][better]
        mu = np.where(better, np.maximum(mu / settings.mu_factor, settings.mu_init),
                      np.minimum(mu * settings.mu_factor, settings.mu_max))
        history.append(cost.copy())
        gain = np.where(alive, (history[-2] - cost) / np.maximum(np.abs(history[-2]), 1e-300), 0.0)
        if float(np.max(gain, initial=0.0)) <= settings.converged_rel:
            break
    a, b = _linearize(dynamics, np.where(alive[:, None, None], x, 0.0), u)
    _, gains, free = _backward(a, b, np.where(alive[:, None, None], x, 0.0), u, q, r, p, lo, hi, mu)
    # an input the trajectory holds on a bound is clamped whatever the QP's last step was
    on_bound = (u <= lo + settings.bound_tol) | (u >= hi - settings.bound_tol)
    free &= ~on_bound
    gains = gains * free[..., None]
    return IlqrResult(x, u, cost, np.array(history), gains, free)
