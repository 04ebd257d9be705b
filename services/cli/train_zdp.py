"""Train the neural Zero Dynamics Policy offline and write ``onboard/data/zdp_mlp.npz``.

    python -m services.cli.train_zdp [--samples 3000] [--steps 6000] [--out PATH]

What is regressed (thesis 2733-2745 trains with iLQR through the impact map; this is a
cheaper relative of it, computable here): for each sampled impact-state error
``z = (x, y, vx, vy)`` (uniform over the box the runtime clips to) the impact attitude

    eta*(z) = argmin_{|eta| <= sin(tilt_cmd_max)}  eta' R eta + V(Omega(eta, z))

with ``Omega`` the *nonlinear* reduced impact map of :mod:`onboard.low_level.planning.zdp` (spring-mass
stance pivoting about the foot, ballistic flight) and ``V(z) = z' P z`` the cost-to-go
of the LQR on its linearization (the same ``Q``, ``R`` as the linear ZDP). So the
target respects the tilt limit optimally and sees the stance's nonlinearity, where
the linear ZDP is clipped after the fact. The minimization is a batched search: a
polar grid over the admissible disk, then two shrinking local grids around the best.

The network is 4 -> 256 -> 256 -> 2 with ReLU (the thesis's size), inputs scaled by
the error clips and outputs by the tilt limit, trained with Adam on the mean squared
error in numpy (no deep-learning framework needed for 67k weights). The file also
stores the settings it was trained for (``meta_*``) and the validation error.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from onboard.low_level.planning import zdp, zdp_policy
from onboard.low_level.controller import design_policy
from onboard.contracts.params import ControlParams
from robot_description.controller import DATA_DIR
from robot_description.params import hopper_model

HIDDEN = 256
GRID_RINGS = 4  # polar grid: rings x spokes, plus the origin
GRID_SPOKES = 12
REFINE = 5  # local grid side
REFINE_ROUNDS = 2


def optimal_targets(params: ControlParams, hopper: zdp.HopperModel, z: np.ndarray) -> np.ndarray:
    """``eta*`` for every row of ``z`` (N, 4); see the module docstring."""
    design = design_policy(params, hopper)
    lin = design.linear
    q_eta = np.eye(2) * params.zdp_q_tilt
    q_z = np.diag([params.zdp_q_pos, params.zdp_q_pos, params.zdp_q_vel, params.zdp_q_vel])
    _, p = zdp.dlqr(lin.a_zz, lin.a_zeta, q_z, q_eta)
    vz = -math.sqrt(2.0 * hopper.gravity * params.hop_height)
    s_max = math.sin(params.tilt_cmd_max)
    n = z.shape[0]

    def cost(zz: np.ndarray, eta: np.ndarray) -> np.ndarray:
        nxt = zdp.impact_map(hopper, zz, vz, eta, design.preload_nominal).z
        c = np.einsum("ij,jk,ik->i", nxt, p, nxt) + np.einsum("ij,jk,ik->i", eta, q_eta, eta)
        return np.where(np.isfinite(c), c, np.inf)

    # polar grid over the admissible disk
    radii = s_max * np.arange(1, GRID_RINGS + 1) / GRID_RINGS
    ang = 2 * math.pi * np.arange(GRID_SPOKES) / GRID_SPOKES
    cand = np.concatenate([np.zeros((1, 2)), np.stack([np.outer(radii, np.cos(ang)).ravel(),
                                                       np.outer(radii, np.sin(ang)).ravel()], axis=1)])
    m = cand.shape[0]
    c = cost(np.repeat(z, m, axis=0), np.tile(cand, (n, 1))).reshape(n, m)
    best = cand[np.argmin(c, axis=1)]
    step = s_max / GRID_RINGS
    offs = np.linspace(-1.0, 1.0, REFINE)
    local = np.stack(np.meshgrid(offs, offs), axis=-1).reshape(-1, 2)
    for _ in range(REFINE_ROUNDS):
        trial = best[:, None, :] + step * local[None, :, :]
        norm = np.linalg.norm(trial, axis=2, keepdims=True)
        trial = np.where(norm > s_max, trial * (s_max / np.maximum(norm, 1e-12)), trial)
        k = trial.shape[1]
        c = cost(np.repeat(z, k, axis=0), trial.reshape(-1, 2)).reshape(n, k)
        best = trial[np.arange(n), np.argmin(c, axis=1)]
        step *= 2.0 / (REFINE - 1)
    return best


def sample_errors(params: ControlParams, n: int, rng: np.random.Generator) -> np.ndarray:
    """Uniform over the disks the runtime clips position and velocity errors to."""

    def disk(radius: float) -> np.ndarray:
        r = radius * np.sqrt(rng.random(n))
        a = rng.uniform(0, 2 * math.pi, n)
        return np.stack([r * np.cos(a), r * np.sin(a)], axis=1)

    p, v = disk(params.pos_err_max), disk(params.vel_err_max)
    return np.column_stack([p[:, 0], p[:, 1], v[:, 0], v[:, 1]])


def init_weights(rng: np.random.Generator) -> dict[str, np.ndarray]:
    sizes = [4, HIDDEN, HIDDEN, 2]
    w: dict[str, np.ndarray] = {}
    for i in range(3):
        fan_in = sizes[i]
        w[f"W{i}"] = rng.standard_normal((sizes[i + 1], fan_in)) * math.sqrt(2.0 / fan_in)
        w[f"b{i}"] = np.zeros(sizes[i + 1])
    return w


def forward(w: dict[str, np.ndarray], x: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    acts = [x]
    h = x
    for i in range(3):
        h = h @ w[f"W{i}"].T + w[f"b{i}"]
        if i < 2:
            h = np.maximum(h, 0.0)
        acts.append(h)
    return h, acts


def train(x: np.ndarray, y: np.ndarray, steps: int, rng: np.random.Generator, lr: float = 2e-3,
          batch: int = 256) -> tuple[dict[str, np.ndarray], float]:
    """Adam on the mean squared error; returns the weights and the final training loss."""
    w = init_weights(rng)
    m = {k: np.zeros_like(v) for k, v in w.items()}
    s = {k: np.zeros_like(v) for k, v in w.items()}
    b1, b2, eps = 0.9, 0.999, 1e-8
    loss = math.nan
    for t in range(1, steps + 1):
        idx = rng.integers(0, x.shape[0], batch)
        xb, yb = x[idx], y[idx]
        out, acts = forward(w, xb)
        diff = out - yb
        loss = float(np.mean(diff * diff))
        grad = 2.0 * diff / diff.size
        grads: dict[str, np.ndarray] = {}
        for i in (2, 1, 0):
            grads[f"W{i}"] = grad.T @ acts[i]
            grads[f"b{i}"] = grad.sum(axis=0)
            if i > 0:
                grad = (grad @ w[f"W{i}"]) * (acts[i] > 0.0)
        rate = lr * (0.1 if t > 0.8 * steps else 1.0)
        for k in w:
            m[k] = b1 * m[k] + (1 - b1) * grads[k]
            s[k] = b2 * s[k] + (1 - b2) * grads[k] ** 2
            mh = m[k] / (1 - b1**t)
            sh = s[k] / (1 - b2**t)
            w[k] -= rate * mh / (np.sqrt(sh) + eps)
    return w, loss


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=3000, help="training states")
    ap.add_argument("--steps", type=int, default=6000, help="Adam steps")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--variant", default="indoor")
    ap.add_argument("--out", default=str(DATA_DIR / ControlParams().mlp_weights))
    args = ap.parse_args(argv)
    params = ControlParams()
    hopper = hopper_model(args.variant)
    rng = np.random.default_rng(args.seed)
    t0 = time.perf_counter()
    z = sample_errors(params, args.samples + args.samples // 5, rng)
    eta = optimal_targets(params, hopper, z)
    print(f"targets: {z.shape[0]} states in {time.perf_counter() - t0:.1f} s")
    x_scale = np.array([params.pos_err_max] * 2 + [params.vel_err_max] * 2)
    y_scale = np.full(2, math.sin(params.tilt_cmd_max))
    xs, ys = z / x_scale, eta / y_scale
    n_train = args.samples
    w, loss = train(xs[:n_train], ys[:n_train], args.steps, rng)
    val_out, _ = forward(w, xs[n_train:])
    val_rms = float(np.sqrt(np.mean((val_out - ys[n_train:]) ** 2))) * y_scale[0]
    lin = design_policy(params, hopper).linear
    pol = zdp_policy.LinearPolicy.from_matrix(lin.s_eta, params.pos_err_max, params.vel_err_max, params.tilt_cmd_max)
    lin_out = np.array([pol(*row) for row in z[n_train:]])
    gap = float(np.sqrt(np.mean((lin_out - eta[n_train:]) ** 2)))
    print(f"trained: loss {loss:.2e}, validation RMS {val_rms:.4f} (policy units), clipped linear ZDP vs target RMS {gap:.4f}")
    out = {k: v.astype(np.float32) for k, v in w.items()}  # half the file; inference is float64
    out.update(
        x_scale=x_scale, y_scale=y_scale,
        meta_hop_height=np.array(params.hop_height), meta_tilt_cmd_max=np.array(params.tilt_cmd_max),
        meta_pos_err_max=np.array(params.pos_err_max), meta_vel_err_max=np.array(params.vel_err_max),
        meta_validation_rms=np.array(val_rms), meta_linear_gap_rms=np.array(gap), meta_samples=np.array(args.samples),
    )
    path = Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **out)
    print(f"wrote {path} ({path.stat().st_size} bytes) in {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
