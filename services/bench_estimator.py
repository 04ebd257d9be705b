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
from dataclasses import dataclass
from typing import Any

import msgspec
import numpy as np

from onboard import messages as m
from onboard import quaternion as quat
from onboard.params import EstimatorParams, TwinParams
from sim_twin import lockstep as ls
from sim_twin import stack as st

NS = 1_000_000_000


@dataclass
class Faults:
    """What the wrapper does to the sensor stream before the estimator sees it."""

    outlier_every: int = 0  # every n-th pose moved ``outlier_m`` in a random direction (0: none)
    outlier_m: float = 1.0
    pose_outage: tuple[float, float] | None = None  # [s] poses captured in this window are lost
    nan_every: int = 0  # every n-th IMU, joint and pose message gets a NaN (0: none)
    no_foot_sensor: bool = False  # joint frames without foot readings (CAN-only hardware)


class MeasuredEstimator:
    """Wraps the lockstep runner's estimator adapter: times it and scores it against the truth.

    ``closed_loop``: the low level flies on the estimate; otherwise on the truth (the
    estimator is only scored, so two configurations see the same trajectory).
    """

    def __init__(self, inner: st.Estimator, truth: st.TruthEstimator, settle_s: float,
                 faults: Faults | None = None, closed_loop: bool = True, seed: int = 0) -> None:
        self.inner = inner
        self.name = inner.name
        self.truth = truth
        self.settle_ns = int(settle_s * NS)
        self.faults = faults or Faults()
        self.closed_loop = closed_loop
        self.outliers_injected = 0
        self.nans_injected = 0
        self._n = {"imu": 0, "joints": 0, "pose": 0}
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
        self.modes: list[str] = []
        self.contact_agree: list[bool] = []

    def _tamper(self, topic: str, msg: Any) -> Any:
        f = self.faults
        n = self._n[topic] = self._n.get(topic, 0) + 1
        if f.nan_every and n % f.nan_every == 0:
            self.nans_injected += 1
            if topic == "imu":
                return msgspec.structs.replace(msg, gyro=[math.nan, msg.gyro[1], msg.gyro[2]])
            if topic == "joints":
                return msgspec.structs.replace(msg, foot_vel=math.nan)
            return msgspec.structs.replace(msg, position=[msg.position[0], math.nan, msg.position[2]])
        if topic == "pose":
            if f.pose_outage is not None and f.pose_outage[0] * NS <= msg.stamp_ns < f.pose_outage[1] * NS:
                return None
            if f.outlier_every and n % f.outlier_every == 0:
                d = self._rng.normal(size=3)
                d *= f.outlier_m / float(np.linalg.norm(d))
                self.outliers_injected += 1
                return msgspec.structs.replace(msg, position=[p + float(v) for p, v in zip(msg.position, d)])
        if topic == "joints" and f.no_foot_sensor:
            return msgspec.structs.replace(msg, foot_pos=0.0, foot_vel=0.0, foot_contact=False, foot_sensed=False)
        return msg

    def feed(self, topic: str, msg: object, now_ns: int) -> None:
        if topic in self._n:
            msg = self._tamper(topic, msg)
            if msg is None:
                return
        t0 = time.perf_counter_ns()
        self.inner.feed(topic, msg, now_ns)
        self._tick_ns += time.perf_counter_ns() - t0

    def estimate(self, now_ns: int, data: Any) -> m.StateEstimate:
        t0 = time.perf_counter_ns()
        est = self.inner.estimate(now_ns, data)
        t1 = time.perf_counter_ns()
        if self._tick_ns:
            self.update_ns.append(self._tick_ns)
            self.estimate_ns.append(t1 - t0)
        self._tick_ns = 0
        true = self.truth.estimate(now_ns, data)
        if now_ns >= self.settle_ns:
            self.t.append(now_ns / NS)
            self.pos_err.append(math.dist(est.position, true.position))
            self.vel_err.append(math.dist(est.velocity, true.velocity))
            self.att_err.append(quat.angle_between(est.quat, true.quat))
            self.pos_std.append(math.sqrt(est.pos_vel_cov[0]))
            self.valid.append(est.valid)
            self.modes.append(str(self.inner.est.status()["mode"]))
            self.contact_agree.append(est.contact == true.contact)
        return est if self.closed_loop else true

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
    faults: Faults | None = None,
    closed_loop: bool = True,
    controller: str = "lowlevel",
) -> tuple[MeasuredEstimator, dict[str, Any]]:
    """One lockstep run with the Kalman estimator; returns the wrapper and the run's metrics."""
    cfg = ls.RunConfig(
        scenario=scenario, seed=seed, duration_s=duration_s, estimator="kalman",
        twin=twin or TwinParams(), estimator_params=params or EstimatorParams(), controller=controller,
    )
    runner = ls.LockstepRunner(cfg)
    measured = MeasuredEstimator(runner.estimator, runner.truth, settle_s, faults, closed_loop, seed)
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
    faults = Faults(outlier_every=args.outlier_every, outlier_m=args.outlier_m)
    measured, metrics = run_twin(
        scenario=args.scenario, seed=args.seed, duration_s=args.duration, twin=twin, params=params, faults=faults,
    )
    counters = measured.counters()
    figures = measured.figures()
    figures.update({
        "outliers_rejected": counters.get("pose_outliers", 0),
        "outliers_injected": measured.outliers_injected,
        "poses_pending_at_end": measured.inner.est.com.pending_poses,  # not yet fused or gated
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
