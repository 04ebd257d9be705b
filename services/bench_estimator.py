"""State estimator on the twin: update time and error against the physics.

Runs a lockstep scenario with ``onboard.estimator.StateEstimator`` in the loop (the
low level flies on its estimate) and compares every tick with the true state.
``update_us`` is the estimator's work per 1 kHz tick (every IMU, joint and pose message
of the tick); ``estimate_us`` builds the StateEstimate. Errors are over the ticks after
``settle_s``: ``rmse_pos_m`` / ``rmse_vel_m_s`` of the whole-robot CoM, ``rmse_att_deg``
the rotation angle between the estimated and true torso attitude.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time
from typing import Any

import numpy as np

from onboard import messages as m
from onboard import quaternion as quat
from onboard.params import EstimatorParams, TwinParams
from sim_twin import lockstep as ls
from sim_twin import stack as st

NS = 1_000_000_000


class MeasuredEstimator:
    """Wraps the lockstep runner's estimator adapter: times it and scores it against the truth.

    ``outlier_every``: every n-th pose delivered is moved ``outlier_m`` in a random
    direction before the estimator sees it (0: none).
    """

    def __init__(self, inner: st.Estimator, truth: st.TruthEstimator, settle_s: float,
                 outlier_every: int = 0, outlier_m: float = 1.0, seed: int = 0) -> None:
        self.inner = inner
        self.name = inner.name
        self.truth = truth
        self.settle_ns = int(settle_s * NS)
        self.outlier_every = outlier_every
        self.outlier_m = outlier_m
        self.outliers_injected = 0
        self._poses = 0
        self._rng = np.random.default_rng(seed)
        self._tick_ns = 0
        self.update_ns: list[int] = []
        self.estimate_ns: list[int] = []
        self.t: list[float] = []
        self.pos_err: list[float] = []
        self.vel_err: list[float] = []
        self.att_err: list[float] = []
        self.pos_std: list[float] = []
        self.valid: list[bool] = []
        self.contact_agree: list[bool] = []

    def feed(self, topic: str, msg: object) -> None:
        if topic == "pose" and self.outlier_every:
            self._poses += 1
            if self._poses % self.outlier_every == 0:
                d = self._rng.normal(size=3)
                d *= self.outlier_m / float(np.linalg.norm(d))
                msg = dataclasses.replace(msg, position=[p + float(v) for p, v in zip(msg.position, d)])
                self.outliers_injected += 1
        t0 = time.perf_counter_ns()
        self.inner.feed(topic, msg)
        self._tick_ns += time.perf_counter_ns() - t0

    def estimate(self, now_ns: int, data: Any) -> m.StateEstimate:
        t0 = time.perf_counter_ns()
        est = self.inner.estimate(now_ns, data)
        t1 = time.perf_counter_ns()
        if self._tick_ns:
            self.update_ns.append(self._tick_ns)
            self.estimate_ns.append(t1 - t0)
        self._tick_ns = 0
        if now_ns >= self.settle_ns:
            true = self.truth.estimate(now_ns, data)
            self.t.append(now_ns / NS)
            self.pos_err.append(math.dist(est.position, true.position))
            self.vel_err.append(math.dist(est.velocity, true.velocity))
            self.att_err.append(quat.angle_between(est.quat, true.quat))
            self.pos_std.append(math.sqrt(est.pos_vel_cov[0]))
            self.valid.append(est.valid)
            self.contact_agree.append(est.contact == true.contact)
        return est

    def counters(self) -> dict[str, int]:
        return self.inner.counters()

    def figures(self) -> dict[str, Any]:
        def rms(v: list[float]) -> float:
            return math.sqrt(sum(x * x for x in v) / len(v)) if v else math.nan

        upd = np.array(self.update_ns) / 1e3
        est = np.array(self.estimate_ns) / 1e3
        return {
            "update_us_p50": round(float(np.percentile(upd, 50)), 2),
            "update_us_p99": round(float(np.percentile(upd, 99)), 2),
            "update_us_max": round(float(upd.max()), 2),
            "estimate_us_p50": round(float(np.percentile(est, 50)), 2),
            "estimate_us_p99": round(float(np.percentile(est, 99)), 2),
            "rmse_pos_m": round(rms(self.pos_err), 5),
            "rmse_vel_m_s": round(rms(self.vel_err), 5),
            "rmse_att_deg": round(math.degrees(rms(self.att_err)), 4),
            "max_pos_err_m": round(max(self.pos_err), 5),
            "max_vel_err_m_s": round(max(self.vel_err), 5),
            "valid_fraction": round(sum(self.valid) / len(self.valid), 4),
            "contact_agreement": round(sum(self.contact_agree) / len(self.contact_agree), 4),
        }


def run_twin(
    *,
    scenario: str = "hop-in-place",
    seed: int = 0,
    duration_s: float = 10.0,
    settle_s: float = 0.5,
    twin: TwinParams | None = None,
    params: EstimatorParams | None = None,
    outlier_every: int = 0,
    outlier_m: float = 1.0,
    controller: str = "lowlevel",
) -> tuple[MeasuredEstimator, dict[str, Any]]:
    """One lockstep run with the Kalman estimator in the loop; returns the wrapper and the run's metrics."""
    cfg = ls.RunConfig(
        scenario=scenario, seed=seed, duration_s=duration_s, estimator="kalman",
        twin=twin or TwinParams(), estimator_params=params or EstimatorParams(), controller=controller,
    )
    runner = ls.LockstepRunner(cfg)
    measured = MeasuredEstimator(runner.estimator, runner.truth, settle_s, outlier_every, outlier_m, seed)
    runner.estimator = measured
    result = runner.run()
    return measured, result.metrics


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", default="hop-in-place")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--duration", type=float, default=10.0, help="simulated seconds")
    parser.add_argument("--pose-latency", type=float, default=0.020, help="pose sensor latency [s]")
    parser.add_argument("--pose-dropout", type=float, default=0.10, help="pose sample loss probability")
    parser.add_argument("--outlier-every", type=int, default=0, help="move every n-th pose by --outlier-m (0: none)")
    parser.add_argument("--outlier-m", type=float, default=1.0)
    parser.add_argument("--backend", choices=("lean", "filterpy"), default="lean", help="CoM filter arithmetic")
    parser.add_argument("--no-latency-compensation", action="store_true", help="fuse poses as if current")


def measure(args: argparse.Namespace) -> dict[str, Any]:
    twin = dataclasses.replace(TwinParams(), pose_latency_s=args.pose_latency, pose_dropout=args.pose_dropout)
    params = dataclasses.replace(EstimatorParams(), kf_backend=args.backend, compensate_latency=not args.no_latency_compensation)
    measured, metrics = run_twin(
        scenario=args.scenario, seed=args.seed, duration_s=args.duration, twin=twin, params=params,
        outlier_every=args.outlier_every, outlier_m=args.outlier_m,
    )
    counters = measured.counters()
    figures = measured.figures()
    figures.update({
        "outliers_rejected": counters.get("pose_outliers", 0),
        "outliers_injected": measured.outliers_injected,
        "scenario": args.scenario,
        "sim_time_s": metrics["sim_time_s"],
        "hops": metrics["hops"],
        "falls": metrics["falls"],
        "pose_latency_s": args.pose_latency,
        "pose_dropout": args.pose_dropout,
        "backend": args.backend,
        "counters": counters,
    })
    return figures
