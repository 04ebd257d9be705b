"""``archer train zdp``: the thesis's Algorithm 2 (Monte Carlo Zero Dynamics Policy training).

The numerics are :mod:`offline.zdp_training` (iLQR with box input bounds through the reduced
impact map, the invariance loss (5.46) and its gradient, the 2 x 256 ReLU network pretrained on
the clipped Raibert policy); this module samples, runs the batches' iLQR solves on the
campaigns' engine (:mod:`services.cli.campaign_pool`: ``--workers N`` a local pool of spawned
worker processes, ``--ray ADDRESS`` Ray; by default in this process), and writes:

- the weights file the control service loads (``[control] policy = "mlp"``,
  ``mlp_weights = "<file>"``; :func:`robot_description.controller.load_policy_weights`): the
  layers ``W0, b0, ...`` and ``x_scale``, ``y_scale`` that :class:`onboard.low_level.planning.mlp.Mlp` reads, plus
  ``meta_settings`` (JSON: every training setting and the control parameters it was trained
  for), ``meta_loss_history`` (the batch loss of every iteration), ``meta_validation_*`` (the
  loss of a fixed held-out batch, every ``--validate-every`` iterations) and
  ``meta_seconds_per_iteration``;
- a loss plot (PNG).

The existing ``services/cli/train_zdp.py`` (a one-step regression) made ``zdp_mlp.npz``, the
network today's ``policy = "mlp"`` loads; this command writes ``zdp_mlp_alg2.npz`` by default so
the two can be compared (``archer train zdp-compare``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from offline import mlp_training as mt
from onboard.low_level.planning import zdp, zdp_policy
from offline import zdp_training as zt
from onboard.contracts.params import ControlParams
from robot_description import params as rd

DEFAULT_WEIGHTS = "zdp_mlp_alg2.npz"  # under onboard/data/
VALIDATE_EVERY = 25  # iterations between two evaluations of the held-out batch
VALIDATION_SEED_OFFSET = 1_000_003  # the held-out batch's generator: apart from the training draws
SMOOTH = 10  # iterations in the plotted running mean of the batch loss


def add_arguments(parser: argparse.ArgumentParser) -> None:
    d = zt.Alg2Settings()
    parser.add_argument("--batch", type=int, default=d.batch, help=f"Monte Carlo samples per iteration (default {d.batch}, the thesis's)")
    parser.add_argument("--iterations", type=int, default=d.iterations, help=f"training iterations (default {d.iterations})")
    parser.add_argument("--learning-rate", type=float, default=d.learning_rate, help=f"Adam's rate (default {d.learning_rate})")
    parser.add_argument("--horizon", type=int, default=d.horizon, help=f"hops of the iLQR problem before the LQR cost-to-go (default {d.horizon})")
    parser.add_argument("--ilqr-iterations", type=int, default=d.ilqr_iterations, help=f"at most (default {d.ilqr_iterations}, the thesis's)")
    parser.add_argument("--pretrain-steps", type=int, default=d.pretrain_steps, help=f"Adam steps on the clipped Raibert policy (default {d.pretrain_steps})")
    parser.add_argument("--validation", type=int, default=d.validation, help=f"held-out samples (default {d.validation}; 0: none)")
    parser.add_argument("--validate-every", type=int, default=VALIDATE_EVERY, help=f"iterations between validations (default {VALIDATE_EVERY})")
    parser.add_argument("--seed", type=int, default=d.seed)
    parser.add_argument("--variant", default=rd.DEFAULT_VARIANT, choices=rd.VARIANTS, help="robot whose reduced model is trained on")
    parser.add_argument("--config", default=None, help="TOML file overriding [control] (hop height, weights, clips)")
    # default in process: at batch 30 a solve's cost is per batched impact-map call (~660 stance steps of
    # small numpy operations), not per sample, so splitting the batch saves little; on this 2-core shared
    # machine a pool of 2 took 5.9 s an iteration against 3.2 s in process (docs/zdp_alg2.md)
    parser.add_argument("--workers", type=int, default=0,
                        help="pool workers the batch is split over (default 0: solve in this process)")
    parser.add_argument("--ray", default=None, metavar="ADDRESS", help="solve on this Ray cluster ('local': a private instance); needs .[cluster]")
    parser.add_argument("--out", default=None, help=f"weights file (default onboard/data/{DEFAULT_WEIGHTS})")
    parser.add_argument("--plot", default=None, help="loss plot PNG (default: beside --out, <stem>_loss.png)")
    parser.add_argument("--json", action="store_true", help="print the summary as one JSON object (last stdout line)")


def settings_from(args: argparse.Namespace) -> zt.Alg2Settings:
    return dataclasses.replace(zt.Alg2Settings(), batch=args.batch, iterations=args.iterations, learning_rate=args.learning_rate,
                               horizon=args.horizon, ilqr_iterations=args.ilqr_iterations, pretrain_steps=args.pretrain_steps,
                               validation=args.validation, seed=args.seed)


def raibert_policy(params: ControlParams) -> zdp_policy.LinearPolicy:
    """The clipped Raibert policy (eq. 5.48) the low level runs with ``policy = "raibert"``."""
    kp, kd = params.raibert_kp, params.raibert_kd
    s = -np.array([[kp, 0.0, kd, 0.0], [0.0, kp, 0.0, kd]])
    return zdp_policy.LinearPolicy.from_matrix(s, params.pos_err_max, params.vel_err_max, params.tilt_cmd_max)


# --- the batch's solves on the campaigns' engine ------------------------------------------------


def _solve_chunk(item: tuple[int, zt.ZdpProblem, np.ndarray, np.ndarray]) -> tuple[int, zt.BatchSolution]:
    """A worker's share of the batch (module level: the pool's spawned workers import it)."""
    index, problem, eta0, z = item
    return index, zt.solve_batch(problem, eta0, z)


def _crashed(item: Any, reason: str) -> tuple[int, None]:
    return item[0], None


def _merge(parts: list[zt.BatchSolution]) -> zt.BatchSolution:
    fields = {}
    for f in dataclasses.fields(zt.BatchSolution):
        values = [getattr(p, f.name) for p in parts]
        fields[f.name] = sum(values) if f.name == "impact_map_calls" else np.concatenate(values)
    return zt.BatchSolution(**fields)


class PoolSolver:
    """``solve(problem, eta0, z)`` split into one chunk per worker, solved in parallel."""

    def __init__(self, executor: Any, chunks: int) -> None:
        self.executor, self.chunks = executor, chunks

    def __call__(self, problem: zt.ZdpProblem, eta0: np.ndarray, z: np.ndarray) -> zt.BatchSolution:
        parts = [idx for idx in np.array_split(np.arange(z.shape[0]), self.chunks) if idx.size]
        items = [(i, problem, eta0[idx], z[idx]) for i, idx in enumerate(parts)]
        got = dict(self.executor.map_unordered(_solve_chunk, items, _crashed))
        if any(v is None for v in got.values()):
            raise RuntimeError("a worker died under an iLQR solve")
        return _merge([got[i] for i in range(len(items))])


def _executor(args: argparse.Namespace):
    from services.cli import campaign_pool

    if args.ray:
        return campaign_pool.RayPool(args.ray, max(args.workers, 1))
    return campaign_pool.LocalPool(args.workers) if args.workers > 0 else None


# --- the training ----------------------------------------------------------------------------


@dataclasses.dataclass
class Outcome:
    weights: mt.Weights
    scales: zt.Scales
    loss_history: list[float]
    iteration_s: list[float]
    solved: list[int]
    clamped: list[float]
    validation: list[tuple[int, float]]  # (iterations done, loss)
    pretrain_history: list[float]
    pretrain_s: float


def train(params: ControlParams, hopper: zdp.HopperModel, settings: zt.Alg2Settings, solve: zt.Solver,
          validate_every: int, log=None) -> Outcome:
    """Algorithm 2 from the pretrained network; ``solve`` is the batch solver (in process or pool)."""
    problem = zt.make_problem(params, hopper, settings)
    scales = zt.Scales.for_problem(problem)
    rng = np.random.default_rng(settings.seed)
    t0 = time.perf_counter()
    w, pre = zt.pretrain(problem, raibert_policy(params), scales, settings, rng)
    pretrain_s = time.perf_counter() - t0
    z_val = zt.sample_domain(problem, settings.validation, np.random.default_rng(settings.seed + VALIDATION_SEED_OFFSET))

    def validate(done: int, out: list[tuple[int, float]]) -> None:
        if settings.validation > 0:
            sol = solve(problem, zt.policy(w, scales, z_val), z_val)
            out.append((done, zt.invariance_loss(w, scales, z_val, sol)[0]))
            if log:
                log(f"validation after {done} iterations: loss {out[-1][1]:.3e}")

    validation: list[tuple[int, float]] = []
    validate(0, validation)
    opt = mt.Adam()
    losses, times, solved, clamped = [], [], [], []
    for i in range(settings.iterations):
        z = zt.sample_domain(problem, settings.batch, rng)
        t = time.perf_counter()
        loss, sol = zt.train_iteration(w, opt, problem, scales, z, settings.learning_rate, solve)
        times.append(time.perf_counter() - t)
        rep = zt.report(i, loss, sol)
        losses.append(loss)
        solved.append(rep.solved)
        clamped.append(rep.clamped_fraction)
        if log and (i + 1) % max(1, settings.iterations // 20) == 0:
            log(f"iteration {i + 1}/{settings.iterations}: batch loss {loss:.3e}, {times[-1]:.2f} s, "
                f"{rep.solved}/{settings.batch} solved, {rep.clamped_fraction:.0%} inputs on a bound")
        if validate_every > 0 and (i + 1) % validate_every == 0 and i + 1 < settings.iterations:
            validate(i + 1, validation)
    validate(settings.iterations, validation)
    return Outcome(w, scales, losses, times, solved, clamped, validation, pre, pretrain_s)


def weights_file_arrays(out: Outcome, params: ControlParams, settings: zt.Alg2Settings, variant: str) -> dict[str, np.ndarray]:
    # float32 layers: half the file, and far below the policy's precision (inference is float64)
    arrays: dict[str, np.ndarray] = {k: v.astype(np.float32) for k, v in out.weights.items()}
    meta = {"algorithm": "thesis Algorithm 2 (archer train zdp)", "variant": variant,
            "settings": {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(settings).items()},
            "control": {k: getattr(params, k) for k in ("hop_height", "tilt_cmd_max", "pos_err_max", "vel_err_max", "zdp_q_pos",
                                                         "zdp_q_vel", "zdp_q_tilt", "zdp_r", "raibert_kp", "raibert_kd")}}
    arrays.update(
        x_scale=out.scales.x, y_scale=out.scales.y,
        meta_settings=np.array(json.dumps(meta)),
        meta_loss_history=np.array(out.loss_history),
        meta_iteration_s=np.array(out.iteration_s),
        meta_validation_iterations=np.array([v[0] for v in out.validation], dtype=int),
        meta_validation_loss=np.array([v[1] for v in out.validation]),
        meta_pretrain_loss_history=np.array(out.pretrain_history),
        meta_seconds_per_iteration=np.array(float(np.median(out.iteration_s)) if out.iteration_s else math.nan),
        meta_hop_height=np.array(params.hop_height), meta_tilt_cmd_max=np.array(params.tilt_cmd_max),
        meta_pos_err_max=np.array(params.pos_err_max), meta_vel_err_max=np.array(params.vel_err_max),
    )
    return arrays


def plot_loss(out: Outcome, path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")  # files only, no display
    import matplotlib.pyplot as plt

    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 4), gridspec_kw={"width_ratios": [1, 2.2]})
    ax0.semilogy(out.pretrain_history, lw=0.6)
    ax0.set(title="pretraining on the clipped Raibert policy", xlabel="Adam step", ylabel="MSE (scaled units)")
    it = np.arange(1, len(out.loss_history) + 1)
    loss = np.array(out.loss_history)
    ax1.semilogy(it, loss, ".", ms=3, alpha=0.5, label="batch loss (5.46)")
    if loss.size >= SMOOTH:
        ax1.semilogy(it[SMOOTH - 1:], np.convolve(loss, np.ones(SMOOTH) / SMOOTH, mode="valid"), lw=1.5,
                     label=f"running mean of {SMOOTH}")
    if out.validation:
        vi, vl = zip(*out.validation)
        ax1.semilogy(vi, vl, "o-", color="k", label="held-out batch")
    ax1.set(title=title, xlabel="iteration", ylabel="invariance loss [rad^2]")
    ax1.legend()
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run(args: argparse.Namespace) -> int:
    from robot_description.controller import DATA_DIR
    from robot_description.params import hopper_model
    from services.runtime.config import load_params

    params: ControlParams = load_params(args.config, ("control",))["control"]
    settings = settings_from(args)
    if settings.batch < 1 or settings.iterations < 0 or args.workers < 0:
        print("archer train zdp: --batch must be >= 1, --iterations and --workers >= 0", file=sys.stderr)
        return 2
    out_path = Path(args.out) if args.out else DATA_DIR / DEFAULT_WEIGHTS
    plot_path = Path(args.plot) if args.plot else out_path.with_name(out_path.stem + "_loss.png")

    def log(text: str) -> None:
        print(text, file=sys.stderr, flush=True)

    executor = _executor(args)
    t0 = time.perf_counter()
    try:
        solve: zt.Solver = zt.solve_batch
        if executor is not None:
            executor.__enter__()
            solve = PoolSolver(executor, max(args.workers, 1))
        outcome = train(params, hopper_model(args.variant), settings, solve, args.validate_every, log)
    finally:
        if executor is not None:
            executor.close()
    wall = time.perf_counter() - t0
    out_path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out_path, **weights_file_arrays(outcome, params, settings, args.variant))
    where = "in process" if executor is None else (f"ray {args.ray}" if args.ray else f"pool of {args.workers}")
    spi = float(np.median(outcome.iteration_s)) if outcome.iteration_s else math.nan
    plot_loss(outcome, plot_path, f"Algorithm 2: batch {settings.batch}, {spi:.2f} s/iteration ({where})")
    val = outcome.validation
    summary = {
        "weights": str(out_path), "plot": str(plot_path), "iterations": settings.iterations, "batch": settings.batch,
        "executor": where, "seconds_per_iteration_median": round(spi, 3),
        "seconds_per_iteration_mean": round(float(np.mean(outcome.iteration_s)), 3) if outcome.iteration_s else None,
        "pretrain_s": round(outcome.pretrain_s, 2), "wall_s": round(wall, 1),
        "batch_loss_first": outcome.loss_history[0] if outcome.loss_history else None,
        "batch_loss_last10_mean": float(np.mean(outcome.loss_history[-10:])) if outcome.loss_history else None,
        "validation_loss_start": val[0][1] if val else None, "validation_loss_end": val[-1][1] if val else None,
        "samples_left_out": int(settings.batch * len(outcome.solved) - sum(outcome.solved)),
    }
    if args.json:
        print(json.dumps(summary))
    else:
        for k, v in summary.items():
            print(f"{k}: {v}")
    return 0
