"""Monte Carlo Zero Dynamics Policy training: the thesis's Algorithm 2 (lines 2662-2776).

The reduced hopper of :mod:`onboard.low_level.planning.zdp` in the thesis's coordinates: the state just before
an impact is ``x = (eta, z)``, ``eta`` (2) the impact attitude (horizontal components of the leg
axis) and ``z`` (4) the CoM error ``(x, y, vx, vy)``; the input ``v`` is the next impact
attitude, reached exactly by the low level (perfect tracking, thesis 2737-2743), so

    x_{k+1} = F(x_k, v_k) = (v_k, Omega(eta_k, z_k)).

The optimal control problem (5.41) is taken over ``horizon`` hops with the cost of eq. 5.43,
``x' Q x + v' R v`` (the linear ZDP's weights), the LQR cost-to-go ``x' P x`` of its
linearisation after the last hop (the infinite-horizon tail, which the constraints rarely
touch by then) and box input bounds ``|v_i| <= sin(tilt_cmd_max)`` (the tilt the low level may
command; its norm clip stays the last guard at run time). iLQR (:mod:`offline.ilqr`) solves it
from the LQR/Raibert initial guess: the clipped linear ZDP (5.44) as it runs on the robot, the
next attitude ``psi_lin(z_{k+1})`` of the predicted impact state.

Algorithm 2, one iteration: sample ``z`` uniformly over the domain the policy sees at run time
(the box of the error clips), put it on the network's manifold ``x_0 = (psi(z), z)``, solve,
read ``eta_1* = v_0*`` and ``z_1* = Omega(psi(z), z)``, and step Adam on the invariance loss
(5.46)

    L = mean || eta_1*(zeta(z)) - psi(z_1*(zeta(z))) ||^2

with its exact gradient through both network evaluations: ``d eta_1*/d eta_0`` is the iLQR
feedback gain ``K_0`` (zero on a bound-held input), ``d z_1*/d eta_0`` the impact map's
Jacobian. The network (2 x 256 ReLU) is pretrained on the clipped Raibert policy (eq. 5.48),
as the thesis does to keep iLQR's initial rollouts stabilisable.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from offline import ilqr
from onboard.low_level.planning import zdp, zdp_policy
from offline import mlp_training as mt
from onboard.low_level.controller import design_policy
from onboard.contracts.params import ControlParams

N_ETA, N_Z = 2, 4
ETA, Z = slice(0, N_ETA), slice(N_ETA, N_ETA + N_Z)


@dataclass(frozen=True)
class Alg2Settings:
    """Algorithm 2's hyper-parameters (thesis line 1: samples, learning rate, steps) and the
    rest of the training's choices; ``archer train zdp`` exposes each as an option."""

    batch: int = 30  # Monte Carlo samples per iteration (Xi; the thesis's timing is at 30)
    iterations: int = 150  # Upsilon
    learning_rate: float = 1e-4  # rho, Adam's; small: each step follows 30 noisy samples
    horizon: int = 4  # hops in the iLQR problem before the LQR cost-to-go takes over
    ilqr_iterations: int = 5  # thesis: five, "empirically enough"
    fd_step: float = 1e-3  # central-difference step of the impact map's Jacobian [rad, m/s] (the linear ZDP's)
    hidden: tuple[int, ...] = (256, 256)  # thesis: 2 layers of 256 ReLU units
    pretrain_samples: int = 4096  # states the Raibert pretraining regresses on
    pretrain_steps: int = 3000  # Adam steps of it
    pretrain_learning_rate: float = 1e-3
    pretrain_batch: int = 256
    validation: int = 60  # fixed held-out samples whose loss is measured before and after training
    seed: int = 0


@dataclass(frozen=True)
class ZdpProblem:
    """Everything an iLQR solve of the batch needs (plain data: it travels to pool workers)."""

    hopper: zdp.HopperModel
    vz: float  # nominal pre-impact vertical velocity [m/s] (the hop-height regulator holds it)
    preload: float  # nominal spring preload [m]
    q: np.ndarray  # (6, 6) state weight on (eta, z)
    r: np.ndarray  # (2, 2) input weight
    p: np.ndarray  # (6, 6) terminal weight: the LQR cost-to-go of eq. 5.43
    bound: float  # |v_i| <= bound (the box)
    initial: zdp_policy.LinearPolicy  # the initial guess's policy: the clipped linear ZDP
    z_half: np.ndarray  # (4,) the sampling box is [-z_half, z_half]
    fd_step: float
    horizon: int
    ilqr: ilqr.IlqrSettings


def make_problem(params: ControlParams, hopper: zdp.HopperModel, settings: Alg2Settings) -> ZdpProblem:
    """The problem at the control parameters' hop height and weights."""
    design = design_policy(params, hopper)
    lin = design.linear
    q_eta = np.eye(N_ETA) * params.zdp_q_tilt
    q_z = np.diag([params.zdp_q_pos, params.zdp_q_pos, params.zdp_q_vel, params.zdp_q_vel])
    r = np.eye(N_ETA) * params.zdp_r
    a = np.zeros((N_ETA + N_Z, N_ETA + N_Z))  # eq. 5.43 with eta_{k+1} = v_k
    a[Z, ETA], a[Z, Z] = lin.a_zeta, lin.a_zz
    b = np.zeros((N_ETA + N_Z, N_ETA))
    b[ETA] = np.eye(N_ETA)
    q = np.zeros((N_ETA + N_Z, N_ETA + N_Z))
    q[ETA, ETA], q[Z, Z] = q_eta, q_z
    _, p = zdp.dlqr(a, b, q, r)
    initial = zdp_policy.LinearPolicy.from_matrix(lin.s_eta, params.pos_err_max, params.vel_err_max, params.tilt_cmd_max)
    z_half = np.array([params.pos_err_max] * 2 + [params.vel_err_max] * 2)
    return ZdpProblem(hopper, -math.sqrt(2.0 * hopper.gravity * params.hop_height), design.preload_nominal, q, r, p,
                      math.sin(params.tilt_cmd_max), initial, z_half, settings.fd_step, settings.horizon,
                      ilqr.IlqrSettings(iterations=settings.ilqr_iterations))


class ImpactDynamics:
    """``F`` of the module docstring for :func:`offline.ilqr.ilqr`, with the impact map's
    values and Jacobians remembered per state (iLQR asks for the first step's, which no input
    changes, in every forward pass; each costs a batched stance integration)."""

    def __init__(self, problem: ZdpProblem) -> None:
        self.pb = problem
        self._omega: dict[bytes, np.ndarray] = {}
        self._jac: dict[bytes, np.ndarray] = {}
        self.calls = 0  # batched impact-map calls made (a figure for the benches)

    def _map(self, eta: np.ndarray, z: np.ndarray) -> np.ndarray:
        self.calls += 1
        return zdp.impact_map(self.pb.hopper, z, self.pb.vz, eta, self.pb.preload).z

    def omega(self, x: np.ndarray) -> np.ndarray:
        """``Omega(eta, z)`` (M, 4) of the rows of ``x`` (M, 6); NaN where the model falls or
        the row is not finite (never integrated: a NaN stance runs to the time limit)."""
        out = np.full((x.shape[0], N_Z), np.nan)
        keys = [row.tobytes() for row in x]
        todo = [i for i, k in enumerate(keys) if k not in self._omega and np.isfinite(x[i]).all()]
        if todo:
            uniq = {keys[i]: i for i in todo}  # rows repeated across step sizes: once each
            idx = np.array(list(uniq.values()))
            res = self._map(x[idx, ETA], x[idx, Z])
            for j, i in enumerate(idx):
                self._omega[keys[i]] = res[j]
        for i, k in enumerate(keys):
            if k in self._omega:
                out[i] = self._omega[k]
        return out

    def step(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return np.concatenate([u, self.omega(x)], axis=1)

    def omega_jacobian(self, x: np.ndarray) -> np.ndarray:
        """``d Omega / d (eta, z)`` (M, 4, 6) by central differences in one batched call.

        The map is exactly translation invariant (the position enters only the flight's
        start), so the position columns are ``[I; 0]`` and only ``eta`` and the velocity are
        perturbed: 8 rows per state, not 12."""
        keys = [row.tobytes() for row in x]
        todo = list({k: i for i, k in enumerate(keys) if k not in self._jac}.values())
        if todo:
            h = self.pb.fd_step
            cols = (0, 1, 4, 5)  # eta_x, eta_y, vx, vy in x
            base = x[todo]
            pert = np.repeat(base[:, None, :], 2 * len(cols), axis=1)
            for j, c in enumerate(cols):
                pert[:, 2 * j, c] += h
                pert[:, 2 * j + 1, c] -= h
            flat = pert.reshape(-1, N_ETA + N_Z)
            ok = np.isfinite(flat).all(axis=1)
            res = np.full((flat.shape[0], N_Z), np.nan)
            if ok.any():
                res[ok] = self._map(flat[ok, ETA], flat[ok, Z])
            res = res.reshape(len(todo), 2 * len(cols), N_Z)
            jac = np.zeros((len(todo), N_Z, N_ETA + N_Z))
            for j, c in enumerate(cols):
                jac[:, :, c] = (res[:, 2 * j] - res[:, 2 * j + 1]) / (2.0 * h)
            jac[:, 0, 2] = jac[:, 1, 3] = 1.0  # d(x, y)_{k+1} / d(x, y)_k
            for j, i in enumerate(todo):
                self._jac[keys[i]] = np.nan_to_num(jac[j])  # a fall beside the state: no slope known
        return np.stack([self._jac[k] for k in keys])

    def jacobians(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = N_ETA + N_Z
        a = np.zeros((x.shape[0], n, n))
        a[:, Z, :] = self.omega_jacobian(x)
        b = np.zeros((x.shape[0], n, N_ETA))
        b[:, ETA, :] = np.eye(N_ETA)
        return a, b


def initial_rollout(problem: ZdpProblem, dyn: ImpactDynamics, x0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The initial guess: each hop commands the clipped linear ZDP of the predicted next impact
    state (what the robot's low level does), held in the box."""
    n = x0.shape[0]
    x = np.empty((n, problem.horizon + 1, N_ETA + N_Z))
    u = np.zeros((n, problem.horizon, N_ETA))
    x[:, 0] = x0
    for k in range(problem.horizon):
        z_next = dyn.omega(x[:, k])
        for i in range(n):
            if np.isfinite(z_next[i]).all():
                u[i, k] = problem.initial(*z_next[i])
        u[:, k] = np.clip(u[:, k], -problem.bound, problem.bound)
        x[:, k + 1, ETA], x[:, k + 1, Z] = u[:, k], z_next
    return x, u


@dataclass(frozen=True)
class BatchSolution:
    """What the loss needs of one iLQR solve per sample (Algorithm 2, lines 7-9)."""

    v0: np.ndarray  # (N, 2) the optimal first input: eta_1*
    z1: np.ndarray  # (N, 4) z_1* = Omega(eta_0, z_0)
    dv0_deta0: np.ndarray  # (N, 2, 2) the feedback gain K_0's eta columns (zero rows where clamped)
    dz1_deta0: np.ndarray  # (N, 4, 2) the impact map's Jacobian at x_0
    free0: np.ndarray  # (N, 2) bool: v0's component not on a bound
    ok: np.ndarray  # (N,) bool: the initial rollout did not fall (else the sample is left out)
    cost_initial: np.ndarray  # (N,) the initial guess's cost
    cost: np.ndarray  # (N,) after iLQR
    impact_map_calls: int


def solve_batch(problem: ZdpProblem, eta0: np.ndarray, z: np.ndarray) -> BatchSolution:
    """iLQR from ``x_0 = (eta0, z)`` for every row (Algorithm 2, lines 7-9)."""
    dyn = ImpactDynamics(problem)
    x0 = np.concatenate([eta0, z], axis=1)
    xi, ui = initial_rollout(problem, dyn, x0)
    lo, hi = np.full(N_ETA, -problem.bound), np.full(N_ETA, problem.bound)
    res = ilqr.ilqr(dyn, xi, ui, problem.q, problem.r, problem.p, lo, hi, problem.ilqr)
    ok = np.isfinite(res.cost)
    jac0 = dyn.omega_jacobian(np.where(ok[:, None], x0, 0.0))
    return BatchSolution(res.u[:, 0], res.x[:, 1, Z], res.gains[:, 0, :, ETA], jac0[:, :, ETA], res.free[:, 0], ok,
                         res.cost_history[0], res.cost, dyn.calls)


# --- the network and the loss ----------------------------------------------------------------


@dataclass(frozen=True)
class Scales:
    """The network sees ``z / x`` and its output is multiplied by ``y`` (numbers of order one)."""

    x: np.ndarray  # (4,)
    y: np.ndarray  # (2,)

    @classmethod
    def for_problem(cls, problem: ZdpProblem) -> Scales:
        return cls(problem.z_half.copy(), np.full(N_ETA, problem.bound))


def policy(w: mt.Weights, scales: Scales, z: np.ndarray) -> np.ndarray:
    """``psi(z)`` (N, 2) of the network, unclipped."""
    out, _ = mt.forward(w, z / scales.x)
    return out * scales.y


def sample_domain(problem: ZdpProblem, n: int, rng: np.random.Generator) -> np.ndarray:
    """``z ~ UNIFORM(-z_half, z_half)`` (Algorithm 2, line 5)."""
    return rng.uniform(-problem.z_half, problem.z_half, size=(n, N_Z))


def pretrain(problem: ZdpProblem, raibert: zdp_policy.LinearPolicy, scales: Scales, settings: Alg2Settings,
             rng: np.random.Generator) -> tuple[mt.Weights, list[float]]:
    """Initialise the network on the clipped Raibert policy (Algorithm 2, line 3). Returns the
    weights and the regression's mini-batch loss per step (scaled units)."""
    w = mt.init_weights((N_Z, *settings.hidden, N_ETA), rng)
    z = sample_domain(problem, settings.pretrain_samples, rng)
    target = np.array([raibert(*row) for row in z])
    history = mt.fit(w, z / scales.x, target / scales.y, settings.pretrain_steps, settings.pretrain_learning_rate,
                     settings.pretrain_batch, rng)
    return w, history


def invariance_loss(w: mt.Weights, scales: Scales, z: np.ndarray, sol: BatchSolution) -> tuple[float, mt.Weights, np.ndarray]:
    """Loss (5.46) over the samples that solved, its gradient and the per-sample errors
    ``eta_1* - psi(z_1*)`` (N, 2; NaN where left out).

    With ``e = v0*(psi(z), z) - psi(z1)`` and ``z1 = Omega(psi(z), z)``:
    ``de = [dv0/deta0 - Jpsi(z1) dz1/deta0] dpsi(z) - dpsi(z1)``, back-propagated through the
    network at ``z`` and at ``z1``.
    """
    ok = sol.ok
    n_ok = int(ok.sum())
    errors = np.full((z.shape[0], N_ETA), np.nan)
    if n_ok == 0:
        return math.nan, {k: np.zeros_like(v) for k, v in w.items()}, errors
    zz, z1 = z[ok], sol.z1[ok]
    _, acts0 = mt.forward(w, zz / scales.x)
    out1, acts1 = mt.forward(w, z1 / scales.x)
    e = sol.v0[ok] - out1 * scales.y
    errors[ok] = e
    loss = float(np.mean(np.sum(e * e, axis=1)))
    jac1 = scales.y[None, :, None] * mt.input_jacobian(w, acts1) / scales.x[None, None, :]  # dpsi/dz at z1
    m = sol.dv0_deta0[ok] - jac1 @ sol.dz1_deta0[ok]  # (n, 2, 2): d e / d psi(z)
    g_psi0 = (2.0 / n_ok) * np.einsum("nji,nj->ni", m, e)
    g_psi1 = -(2.0 / n_ok) * e
    grads = mt.add_grads(mt.backward(w, acts0, g_psi0 * scales.y), mt.backward(w, acts1, g_psi1 * scales.y))
    return loss, grads, errors


Solver = Callable[[ZdpProblem, np.ndarray, np.ndarray], BatchSolution]


@dataclass(frozen=True)
class IterationReport:
    iteration: int
    loss: float  # of this iteration's batch, before its update
    solved: int  # samples whose initial rollout did not fall
    clamped_fraction: float  # of the solved samples' first-input components on a bound
    ilqr_cost_ratio: float  # mean iLQR cost / initial guess's cost (< 1: iLQR improved on the guess)


def train_iteration(w: mt.Weights, opt: mt.Adam, problem: ZdpProblem, scales: Scales, z: np.ndarray, rate: float,
                    solve: Solver = solve_batch) -> tuple[float, BatchSolution]:
    """One iteration of Algorithm 2 on the batch ``z`` (lines 6-10); ``w`` updated in place."""
    sol = solve(problem, policy(w, scales, z), z)
    loss, grads, _ = invariance_loss(w, scales, z, sol)
    if math.isfinite(loss):
        opt.step(w, grads, rate)
    return loss, sol


def report(iteration: int, loss: float, sol: BatchSolution) -> IterationReport:
    ok = sol.ok
    solved = int(ok.sum())
    clamped = float(np.mean(~sol.free0[ok])) if solved else math.nan
    ratio = float(np.mean(sol.cost[ok] / np.maximum(sol.cost_initial[ok], 1e-300))) if solved else math.nan
    return IterationReport(iteration, loss, solved, clamped, ratio)
