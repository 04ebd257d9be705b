"""Lockstep runs that keep what a thesis figure draws, and campaigns of them.

A run is a spec (a JSON-able dict: scenario, seed, variant, duration, estimator, planner,
parameter overrides per section, and whether to keep the trace); :func:`run_one` runs it in the
lockstep runner and returns its record: the run's report (as ``archer sim --json``), and, where
asked, its trace at the metrics' 100 Hz, its phase events, and at every touchdown the impact
attitude the low level commanded (its last flight setpoint) against the one the estimate saw.

:func:`campaign` runs the specs of one item on the campaigns' pool (local processes or Ray),
one JSON line per run in ``DIR/runs/ITEM.jsonl``: a run already there is not run again, so an
interrupted ``archer reproduce`` resumes where it stopped.
"""

from __future__ import annotations

import json
import math
import os
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from services.cli.campaign import Progress, read_records, spec_key

RUNS_DIR = "runs"
TRACE_FIELDS = ("t", "com", "est", "ref", "wheel_vel", "torque", "tracking_error")
ATTITUDE_EVERY_NS = 10_000_000  # the attitude error's samples, at the trace's 100 Hz
TRACE_MAX_SAMPLES = 20_000  # a longer run's trace is thinned to about this many samples (a 600 s maze: 60,000)


@dataclass
class Context:
    """What every item shares: where it writes, how heavy it may be, where runs execute."""

    out: Path
    quick: bool = False
    workers: int = field(default_factory=lambda: os.cpu_count() or 1)
    ray: str | None = None
    progress: bool = True

    def seeds(self, full: int, quick: int = 2) -> list[int]:
        """The seeds of an item's campaign: ``full`` of them, ``quick`` with ``--quick``."""
        return list(range(quick if self.quick else full))

    def duration(self, quick_s: float, full_s: float | None = None) -> float | None:
        """A run's simulated seconds: ``full_s`` (None: the scenario's own), ``quick_s`` with ``--quick``."""
        return quick_s if self.quick else full_s

    def path(self, name: str) -> Path:
        self.out.mkdir(parents=True, exist_ok=True)
        return self.out / name


def run_spec(scenario: str, seed: int = 0, **options: Any) -> dict:
    """A spec with the defaults the items share: the Kalman estimator on noisy sensors, as on the robot."""
    spec: dict[str, Any] = {"scenario": scenario, "seed": seed, "variant": "indoor", "duration": None, "estimator": "kalman",
                            "planner": "auto", "obstacles": None, "params": {}, "step_reference": False, "keep_going": False,
                            "trace": False}
    unknown = set(options) - set(spec)
    if unknown:
        raise ValueError(f"unknown run options {sorted(unknown)}")
    spec.update(options)
    return spec


def _quat_tilt(q: Any) -> tuple[float, float]:
    """The body z axis's lean [rad] toward world x and toward world y (the impact angle's two components)."""
    w, x, y, z = q
    zx, zy, zz = 2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y)
    return math.atan2(zx, zz), math.atan2(zy, zz)


class _Watcher:
    """The run's messages as they happen: phase events and, at each touchdown, the commanded impact
    attitude (the controller's last flight setpoint) beside the estimated one."""

    def __init__(self, attitude_every_ns: int = 0) -> None:
        self.runner: Any = None
        self.phases: list[tuple[float, str]] = []
        self.impacts: list[dict[str, float]] = []
        # (t, angle [rad] between the estimated attitude and the low level's setpoint) every this often; 0: none
        self.attitude_every_ns = attitude_every_ns
        self.attitude_error: list[tuple[float, float]] = []
        self._next_attitude_ns = 0
        self._state: Any = None
        self._flight_q_des: Any = None

    def __call__(self, topic: str, now_ns: int, msg: Any) -> None:
        if topic == "state":
            self._state = msg
        elif topic == "torque_cmd" and self._state is not None:
            if not self._state.contact:
                self._flight_q_des = tuple(self.runner.controller.ctrl.q_des)
            if self.attitude_every_ns and now_ns >= self._next_attitude_ns:
                self._next_attitude_ns = now_ns + self.attitude_every_ns
                dot = abs(float(np.dot(self._state.quat, self.runner.controller.ctrl.q_des)))
                self.attitude_error.append((round(now_ns / 1e9, 4), 2.0 * math.acos(min(1.0, dot))))
        elif topic == "phase":
            t = now_ns / 1e9
            self.phases.append((round(t, 4), msg.event))
            if msg.event == "touchdown" and self._flight_q_des is not None and self._state is not None:
                cx, cy = _quat_tilt(self._flight_q_des)
                ax, ay = _quat_tilt(self._state.quat)
                self.impacts.append({"t": round(t, 4), "cmd_x": cx, "cmd_y": cy, "act_x": ax, "act_y": ay,
                                     "vx": msg.velocity[0], "vy": msg.velocity[1]})


class _PlannerClock:
    """Wall time of each call of the graph planner's steps: ``plan`` (what the replanning costs: the
    graph ``build`` when the region needs a new one, the ``cut``, the ``search``) and ``refine``
    (the MPC), every call timed: what rate this machine sustains, the lockstep runner calling
    them at their rates in twin time."""

    STEPS = ("plan", "refine", "_ensure_graph", "cut", "_search")
    NAMES = {"_ensure_graph": "build", "_search": "search"}

    def __init__(self, planner: Any) -> None:
        self.samples: dict[str, list[float]] = {}
        for step in self.STEPS:
            samples = self.samples.setdefault(self.NAMES.get(step, step), [])
            setattr(planner, step, self._timed(getattr(planner, step), samples))

    @staticmethod
    def _timed(fn: Any, samples: list[float]) -> Any:
        def timed(*args: Any, **kwargs: Any) -> Any:
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                samples.append((time.perf_counter() - t0) * 1e3)

        return timed

    def summary(self) -> dict[str, float | int | None]:
        out: dict[str, float | int | None] = {}
        for name, samples in self.samples.items():
            out[f"{name}_calls"] = len(samples)
            for q in (50, 99):
                out[f"{name}_ms_p{q}"] = round(float(np.percentile(samples, q)), 3) if samples else None
            out[f"{name}_ms_max"] = round(max(samples), 3) if samples else None
        return out


def _config(spec: dict, sink: Any) -> Any:
    from onboard.contracts.params import with_overrides
    from services.runtime.config import load_params
    from sim_twin.lockstep import RunConfig

    params = load_params(None)
    for section, overrides in spec["params"].items():
        params[section] = with_overrides(params[section], overrides)
    return RunConfig(scenario=spec["scenario"], seed=spec["seed"], duration_s=spec["duration"], variant=spec["variant"],
                     estimator=spec["estimator"], planner=spec["planner"], obstacles=spec["obstacles"], twin=params["twin"],
                     estimator_params=params["estimator"], planner_params=params["planner"], control_params=params["control"],
                     gmpc_params=params["gmpc"], stop_on_fall=not spec["keep_going"], sink=sink)


def run_one(spec: dict) -> dict:
    """One lockstep run as a campaign worker does it: its record; never raises for the run's own failure."""
    from services.runtime.process_env import prepare_environment

    prepare_environment()  # a pool or Ray worker did not start through archer's entry point
    record: dict[str, Any] = {"key": spec_key(spec), "spec": spec}
    t0 = time.perf_counter()
    try:
        from sim_twin.lockstep import LockstepRunner

        watcher = _Watcher(ATTITUDE_EVERY_NS if spec["trace"] else 0)
        runner = LockstepRunner(_config(spec, watcher))
        watcher.runner = runner
        if spec["step_reference"]:
            runner.step_reference()
        graph = getattr(runner.planner, "planner", None)  # the graph planner's plug holds it
        clock = _PlannerClock(graph) if graph is not None and hasattr(graph, "refine") else None
        result = runner.run()
        if clock is not None:
            record["planner_timing"] = clock.summary()
            if graph.graph is not None:  # what the timings were taken on
                record["planner_timing"].update(graph_nodes=int(graph.graph.n_nodes), graph_edges=int(graph.graph.n_edges))
        record["report"] = result.metrics
        record["target"] = list(runner.scenario.target())
        record["end_com"] = list(result.trace.com[-1]) if result.trace.com else None  # where a fall ended the run
        record["impacts"] = watcher.impacts
        if spec["trace"]:
            stride = max(1, -(-len(result.trace.t) // TRACE_MAX_SAMPLES))
            record["trace"] = {name: getattr(result.trace, name)[::stride] for name in TRACE_FIELDS}
            record["trace"]["impact_points"] = result.trace.impacts
            record["phases"] = watcher.phases
            record["attitude_error"] = watcher.attitude_error
            record["obstacles"] = [[list(v) for v in o.vertices] for o in runner.scenario.obstacles]
    except Exception as exc:  # a failing run is data: recorded, and the item goes on
        record["error"] = f"{type(exc).__name__}: {exc}"
        record["traceback"] = traceback.format_exc()
    record["worker_wall_s"] = round(time.perf_counter() - t0, 3)
    return record


def _crash(spec: dict, reason: str) -> dict:
    return {"key": spec_key(spec), "spec": spec, "error": f"WorkerCrash: {reason}", "traceback": ""}


def campaign(ctx: Context, item: str, specs: list[dict]) -> list[dict]:
    """The records of ``specs`` in their order: those of ``DIR/runs/ITEM.jsonl``, the rest run now."""
    from services.cli import campaign_pool

    path = ctx.path(RUNS_DIR) / f"{item}.jsonl"
    path.parent.mkdir(parents=True, exist_ok=True)
    done = read_records(path)
    todo = [s for s in specs if spec_key(s) not in done]
    if todo:
        bar = Progress(len(todo), ctx.progress)
        pool = campaign_pool.RayPool(ctx.ray, ctx.workers) if ctx.ray else campaign_pool.LocalPool(min(ctx.workers, len(todo)))
        with path.open("a") as f, pool:
            for record in pool.map_unordered(run_one, todo, _crash):
                f.write(json.dumps(record) + "\n")
                f.flush()  # what is written survives a kill
                done[record["key"]] = record
                bar.advance(record)
    return [done[spec_key(s)] for s in specs]


def bench_args(bench: Any, **changes: Any) -> Any:
    """``archer bench``'s defaults for ``bench`` (a services.bench module), with ``changes``: the items
    measure through the benches' own functions, with the arguments a user would give them."""
    import argparse

    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    args = parser.parse_args([])
    for name, value in changes.items():
        setattr(args, name, value)
    return args


def report_of(record: dict) -> dict:
    """A record's report, or an empty one for a run that failed (it counts as not reaching its goal)."""
    return record.get("report") or {}


def succeeded(record: dict) -> bool:
    return bool(report_of(record).get("goal_reached")) and not report_of(record).get("falls")
