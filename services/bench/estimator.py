"""State estimator on the twin: update time and error against the physics.

Runs a lockstep scenario with ``onboard.estimation.estimator.StateEstimator`` in the loop (the
low level flies on its estimate) and compares every tick with the true state.
``update_us`` is the estimator's work per 1 kHz tick (every IMU, joint and pose message
of the tick); ``estimate_us`` builds the StateEstimate. Errors are over the ticks after
``settle_s``: ``rmse_pos_m`` / ``rmse_vel_m_s`` of the whole-robot CoM, ``rmse_att_deg``
the rotation angle between the estimated and true torso attitude.

``--stalls 0.2,0.5,1,2``: the consistency table instead. For each stalled sensor
(``--stall-sensors``, IMU and pose by default) and each duration, a hop-in-place run
whose sensor loses every sample for that long from ``--stall-at`` (a
:class:`sim_twin.sensors.SensorOutage` in the run config), scored on the ticks from
the stall's start to ``--recovery`` after its end (or the run's end): the fraction of
ticks whose normalized estimation error squared (NEES; position and velocity, 6 dof,
against the published 6x6 covariance; attitude, 3 dof, against the published body
variances) is within the chi-square bound (``--nees-quantile``), the ticks the
estimate was invalid, whether the robot fell and whether control disarmed, and
``confident_wrong_ticks``: ticks on which control commanded torque from an estimate
further from the truth than three times a validity limit (a valid estimate's standard
deviation is under that limit) in position, velocity or attitude.
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
from scipy.stats import chi2

from onboard.contracts import messages as m
from onboard.geometry import quaternion as quat
from onboard.contracts.params import EstimatorParams, TwinParams
from sim_twin import lockstep as ls
from sim_twin import stack as st
from sim_twin.sensors import SensorOutage

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


class ConsistencyProbe:
    """Wraps the runner's estimator and controller: per tick, the NEES of the published
    estimate against the truth, its validity, the true errors and whether the command that
    followed it was armed."""

    def __init__(self, runner: ls.LockstepRunner) -> None:
        self.inner = runner.estimator
        self.name = self.inner.name
        self.truth = runner.truth
        self._step = runner.controller.step
        self.t: list[float] = []
        self.nees_pv: list[float] = []
        self.nees_att: list[float] = []
        self.valid: list[bool] = []
        self.err: list[tuple[float, float, float]] = []  # position [m], velocity [m/s], attitude [rad]
        self.armed: list[bool] = []
        runner.estimator = self
        runner.controller.step = self.step  # type: ignore[method-assign]

    def feed(self, topic: str, msg: object, now_ns: int) -> None:
        self.inner.feed(topic, msg, now_ns)

    def counters(self) -> dict[str, int]:
        return self.inner.counters()

    def estimate(self, now_ns: int, data: Any) -> m.StateEstimate:
        est = self.inner.estimate(now_ns, data)
        true = self.truth.estimate(now_ns, data)
        ep = [a - b for a, b in zip(est.position, true.position)]
        ev = [a - b for a, b in zip(est.velocity, true.velocity)]
        c = est.pos_vel_cov  # kron(P2, I3): one 2x2 block per axis
        pp, pv, vv = c[0], c[3], c[21]
        det = pp * vv - pv * pv
        nees_pv = sum((vv * p * p - 2.0 * pv * p * v + pp * v * v) / det for p, v in zip(ep, ev)) if det > 0 else math.inf
        r = quat.log(quat.mul(quat.conj(est.quat), true.quat))  # body-frame attitude error
        nees_att = sum(x * x / v for x, v in zip(r, est.att_cov)) if min(est.att_cov) > 0 else math.inf
        self.t.append(now_ns / NS)
        self.nees_pv.append(nees_pv)
        self.nees_att.append(nees_att)
        self.valid.append(est.valid)
        self.err.append((math.sqrt(sum(x * x for x in ep)), math.sqrt(sum(x * x for x in ev)), math.sqrt(sum(x * x for x in r))))
        return est

    def step(self, now_ns: int, state: m.StateEstimate, reference: Any, joints: Any) -> m.TorqueCommand:
        cmd = self._step(now_ns, state, reference, joints)
        self.armed.append(bool(cmd.armed))
        return cmd


def stall_run(sensor: str, stall_s: float, *, seed: int = 0, stall_at_s: float = 2.0, recovery_s: float = 1.0,
              quantile: float = 0.99, params: EstimatorParams | None = None) -> dict[str, Any]:
    """One hop-in-place run with ``sensor`` silent for ``stall_s`` from ``stall_at_s``; see the module."""
    p = params or EstimatorParams()
    end_s = stall_at_s + stall_s
    cfg = ls.RunConfig(scenario="hop-in-place", seed=seed, duration_s=end_s + recovery_s, estimator="kalman",
                       estimator_params=p, sensor_outages=(SensorOutage(sensor, stall_at_s, end_s),))
    runner = ls.LockstepRunner(cfg)
    probe = ConsistencyProbe(runner)
    metrics = runner.run().metrics
    window = [i for i, t in enumerate(probe.t) if t >= stall_at_s]
    bound_pv, bound_att = float(chi2.ppf(quantile, 6)), float(chi2.ppf(quantile, 3))
    limits = (3.0 * p.valid_pos_std_m, 3.0 * p.valid_vel_std_m_s, 3.0 * p.valid_att_std_rad)
    confident_wrong = sum(
        1 for i in window
        if probe.armed[i] and any(e > lim for e, lim in zip(probe.err[i], limits))
    )
    n = max(len(window), 1)
    return {
        "sensor": sensor,
        "stall_s": stall_s,
        "seed": seed,
        "ticks": len(window),
        "nees_pv_inside": round(sum(probe.nees_pv[i] <= bound_pv for i in window) / n, 4),
        "nees_att_inside": round(sum(probe.nees_att[i] <= bound_att for i in window) / n, 4),
        "invalid_ticks": sum(not probe.valid[i] for i in window),
        "max_pos_err_m": round(max((probe.err[i][0] for i in window), default=0.0), 4),
        "max_att_err_rad": round(max((probe.err[i][2] for i in window), default=0.0), 4),
        "fell": bool(metrics["falls"]),
        "disarmed": not probe.armed[-1] if probe.armed else True,
        "confident_wrong_ticks": confident_wrong,
        "hops": metrics["hops"],
    }


def consistency_table(stalls: list[float], sensors: list[str], seed: int = 0, stall_at_s: float = 2.0,
                      recovery_s: float = 1.0, quantile: float = 0.99) -> list[dict[str, Any]]:
    return [stall_run(sensor, d, seed=seed, stall_at_s=stall_at_s, recovery_s=recovery_s, quantile=quantile)
            for sensor in sensors for d in stalls]


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
    parser.add_argument("--stalls", default="", help="comma-separated stall durations [s]: print the consistency table")
    parser.add_argument("--stall-sensors", default="imu,pose", help="sensors stalled in turn for --stalls")
    parser.add_argument("--stall-at", type=float, default=2.0, help="[s] when each stall starts (hop-in-place)")
    parser.add_argument("--recovery", type=float, default=1.0, help="[s] scored after each stall ends")
    parser.add_argument("--nees-quantile", type=float, default=0.99, help="chi-square quantile of the NEES bound")


def measure(args: argparse.Namespace) -> dict[str, Any]:
    if args.stalls:
        stalls = [float(v) for v in args.stalls.split(",")]
        rows = consistency_table(stalls, args.stall_sensors.split(","), args.seed, args.stall_at, args.recovery,
                                 args.nees_quantile)
        return {f"{r['sensor']} {r['stall_s']:g} s": {k: v for k, v in r.items() if k not in ("sensor", "stall_s")}
                for r in rows}
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
