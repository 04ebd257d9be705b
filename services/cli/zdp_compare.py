"""``archer train zdp-compare``: a campaign comparing Zero Dynamics Policies on the twin.

Policies (``[control] policy`` and its weights):

- ``alg2``: the network trained by ``archer train zdp`` (``--weights``, default
  ``zdp_mlp_alg2.npz``);
- ``mlp``: today's network (``zdp_mlp.npz``, the one-step regression of ``train_zdp.py``);
- ``zdp``: the clipped linear ZDP (eq. 5.44), the robot's default;
- ``raibert``: the clipped Raibert policy (eq. 5.48).

Scenarios, each a lockstep run with the Kalman estimator on noisy sensors, as ``archer sim``:

- ``setpoint``: the goal 2 m away as a bare step from t = 0 (thesis Fig. 5.22: "tracking a
  setpoint 2 m away"; the scenario's own smooth reference would hide the policy's clipping);
- ``push``: hop in place under 2 N s lateral pushes every 5 s;
- ``square``: two laps of a 1 m square (thesis Fig. 5.23).

Per run, from the physics (the true CoM trace, sampled every 10 ms):

- ``success``: the run's ``goal_reached`` (final CoM within the goal tolerance, no fall);
- ``time_to_goal_s``: setpoint and square: the first time from which the CoM stays within
  ``ARRIVE_M`` of the final goal to the end; push: the mean over the pushes of the time from a
  push until the CoM is back within ``ARRIVE_M`` of the hold point for good (before the next
  push); None when it never is;
- ``overshoot_m``: setpoint: how far the CoM went past the goal along the start-goal line;
  square: how far the CoM went outside the square; push: the largest excursion from the hold
  point.

Runs go to the campaigns' engine (:mod:`services.cli.campaign_pool`), one JSON line per run in
``DIR/runs.jsonl`` (resumable: a run already there is not repeated); the table per scenario and
policy (success with its Wilson interval, medians of time to goal and overshoot, falls, RMS
tracking at impact) goes to ``DIR/summary.json`` and ``DIR/summary.txt``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
import traceback
from pathlib import Path
from typing import Any

import numpy as np

from services.cli.train_zdp_alg2 import DEFAULT_WEIGHTS

ARRIVE_M = 0.10  # [m] "at the goal" for the time to goal (the zdp bench's definition)
POLICIES = ("alg2", "mlp", "zdp", "raibert")
SCENARIOS = ("setpoint", "push", "square")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--weights", default=DEFAULT_WEIGHTS, help=f"the trained network for 'alg2' (default {DEFAULT_WEIGHTS})")
    parser.add_argument("--policies", default=",".join(POLICIES), help=f"comma list of {', '.join(POLICIES)}")
    parser.add_argument("--scenarios", default=",".join(SCENARIOS), help=f"comma list of {', '.join(SCENARIOS)}")
    parser.add_argument("--seeds", default="0-4", help="seeds (sensor noise, setpoint heading, push directions), e.g. 0-9")
    parser.add_argument("--duration", type=float, default=None, help="simulated seconds (default: each scenario's)")
    parser.add_argument("--out", required=True, help="folder: runs.jsonl, summary.json, summary.txt")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="local worker processes (default: one per core)")
    parser.add_argument("--ray", default=None, metavar="ADDRESS", help="run on this Ray cluster; needs .[cluster]")
    parser.add_argument("--json", action="store_true", help="print the summary as one JSON object (last stdout line)")


def control_params(policy: str, weights: str):
    from onboard.contracts.params import ControlParams

    base = ControlParams()
    if policy == "alg2":
        return dataclasses.replace(base, policy="mlp", mlp_weights=weights)
    if policy not in POLICIES:
        raise ValueError(f"unknown policy {policy!r}; known: {', '.join(POLICIES)}")
    return dataclasses.replace(base, policy=policy)


def _settle_time(t: np.ndarray, err: np.ndarray, start: float, end: float) -> float | None:
    """Time after ``start`` from which ``err <= ARRIVE_M`` holds up to ``end``; None if never."""
    inside = (t >= start) & (t < end)
    ts, es = t[inside], err[inside]
    if ts.size == 0 or es[-1] > ARRIVE_M:
        return None
    out = np.flatnonzero(es > ARRIVE_M)
    return float(ts[out[-1] + 1] - start) if out.size else 0.0


def scenario_metrics(scenario: str, scen: Any, t: np.ndarray, com: np.ndarray, goal: tuple[float, float],
                     end_s: float) -> dict[str, float | None]:
    """Time to goal and overshoot of one run (see the module docstring)."""
    xy = com[:, :2]
    err = np.hypot(xy[:, 0] - goal[0], xy[:, 1] - goal[1])
    if scenario == "push":
        starts = [scen.FIRST + k * scen.EVERY for k in range(int((end_s - scen.FIRST) // scen.EVERY) + 1)
                  if scen.FIRST + k * scen.EVERY < end_s]
        ends = starts[1:] + [end_s]
        settle = [_settle_time(t, err, s, e) for s, e in zip(starts, ends)]
        done = [s for s in settle if s is not None]
        ttg = float(np.mean(done)) if done and len(done) == len(settle) else None
        return {"time_to_goal_s": ttg, "overshoot_m": float(err.max()),
                "pushes_recovered": len(done), "pushes": len(settle)}
    ttg = _settle_time(t, err, 0.0, math.inf)
    if scenario == "setpoint":
        dist = math.hypot(*goal)
        along = (xy @ np.array(goal)) / dist
        overshoot = max(0.0, float(along.max() - dist))
    else:  # the square: distance outside [0, side]^2
        side = scen.SIDE
        dx = np.maximum(0.0, np.maximum(-xy[:, 0], xy[:, 0] - side))
        dy = np.maximum(0.0, np.maximum(-xy[:, 1], xy[:, 1] - side))
        overshoot = float(np.hypot(dx, dy).max())
    return {"time_to_goal_s": ttg, "overshoot_m": overshoot}


def run_one(spec: dict) -> dict:
    """One lockstep run: the record for ``runs.jsonl``; never raises for the run's own failure."""
    from services.runtime.process_env import prepare_environment

    prepare_environment()
    record: dict[str, Any] = {"key": json.dumps(spec, sort_keys=True), "spec": spec}
    t0 = time.perf_counter()
    try:
        from sim_twin.lockstep import LockstepRunner, RunConfig

        cfg = RunConfig(scenario=spec["scenario"], seed=spec["seed"], duration_s=spec["duration"], estimator="kalman",
                        control_params=control_params(spec["policy"], spec["weights"]))
        runner = LockstepRunner(cfg)
        goal = runner.scenario.target()
        if spec["scenario"] == "setpoint":  # the bare step (thesis Fig. 5.22), as archer bench zdp --reference step
            runner.step_reference()
        res = runner.run()
        t = np.array(res.trace.t)
        com = np.array(res.trace.com).reshape(-1, 3)
        d = res.metrics
        end_s = float(d["sim_time_s"])
        record["report"] = {
            "success": bool(d["goal_reached"]), "falls": d["falls"], "fall_time_s": d["fall_time_s"],
            "final_goal_error_m": d["final_goal_error_m"], "rms_tracking_error_m": d["rms_tracking_error_m"],
            "max_wheel_speed_rad_s": d["max_wheel_speed_rad_s"], "hops": d["hops"], "sim_time_s": end_s,
            **scenario_metrics(spec["scenario"], res.scenario, t, com, goal, end_s),
        }
    except Exception as exc:  # a failing run is data: recorded, the sweep goes on
        record["error"] = f"{type(exc).__name__}: {exc}"
        record["traceback"] = traceback.format_exc()
    record["worker_wall_s"] = round(time.perf_counter() - t0, 3)
    return record


def _crash(spec: dict, reason: str) -> dict:
    return {"key": json.dumps(spec, sort_keys=True), "spec": spec, "error": f"WorkerCrash: {reason}", "traceback": ""}


def _median(values: list[float]) -> float | None:
    return round(float(np.median(values)), 3) if values else None


def summarize(records: list[dict]) -> list[dict]:
    from services.cli.campaign_report import wilson_interval

    groups: dict[tuple[str, str], list[dict]] = {}
    for r in records:
        groups.setdefault((r["spec"]["scenario"], r["spec"]["policy"]), []).append(r)
    rows = []
    for (scenario, policy), members in groups.items():
        reports = [r["report"] for r in members if "report" in r]
        succ = sum(bool(r["success"]) for r in reports)
        low, high = wilson_interval(succ, len(members))
        ttg = [r["time_to_goal_s"] for r in reports if r["time_to_goal_s"] is not None]
        over = [r["overshoot_m"] for r in reports]
        rms = [r["rms_tracking_error_m"] for r in reports if r["rms_tracking_error_m"] is not None]
        rows.append({
            "scenario": scenario, "policy": policy, "runs": len(members), "errors": len(members) - len(reports),
            "successes": succ, "success_ci95": [round(low, 3), round(high, 3)],
            "falls": sum(r["falls"] for r in reports),
            "time_to_goal_s_median": _median(ttg), "time_to_goal_runs": len(ttg),
            "overshoot_m_median": _median(over), "overshoot_m_max": round(max(over), 3) if over else None,
            "rms_tracking_m_median": _median(rms),
        })
    order = {s: i for i, s in enumerate(SCENARIOS)}
    porder = {p: i for i, p in enumerate(POLICIES)}
    rows.sort(key=lambda row: (order.get(row["scenario"], 99), porder.get(row["policy"], 99)))
    return rows


def table(rows: list[dict]) -> str:
    head = ("scenario", "policy", "success", "95% CI", "falls", "time to goal [s]", "overshoot [m] p50/max", "RMS impact [m]")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        ttg = "-" if r["time_to_goal_s_median"] is None else f"{r['time_to_goal_s_median']:.2f} ({r['time_to_goal_runs']}/{r['runs']})"
        over = "-" if r["overshoot_m_median"] is None else f"{r['overshoot_m_median']:.3f} / {r['overshoot_m_max']:.3f}"
        rms = "-" if r["rms_tracking_m_median"] is None else f"{r['rms_tracking_m_median']:.3f}"
        lines.append(f"| {r['scenario']} | {r['policy']} | {r['successes']}/{r['runs']} | "
                     f"[{r['success_ci95'][0]:.2f}, {r['success_ci95'][1]:.2f}] | {r['falls']} | {ttg} | {over} | {rms} |")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from services.cli import campaign_pool
    from services.cli.campaign import Progress, parse_seeds, read_records

    try:
        policies = [p.strip() for p in args.policies.split(",") if p.strip()]
        scenarios = [s.strip() for s in args.scenarios.split(",") if s.strip()]
        bad = [p for p in policies if p not in POLICIES] + [s for s in scenarios if s not in SCENARIOS]
        if bad or not policies or not scenarios:
            raise ValueError(f"unknown or missing policies/scenarios {bad}")
        seeds = parse_seeds(args.seeds)
        if "alg2" in policies:
            from robot_description.controller import load_policy_weights

            load_policy_weights(args.weights)  # refuse a missing file before any run
    except (ValueError, FileNotFoundError) as exc:
        print(f"archer train zdp-compare: {exc}", file=sys.stderr)
        return 2
    specs = [{"scenario": s, "policy": p, "seed": seed, "duration": args.duration,
              "weights": args.weights if p == "alg2" else None}
             for s in scenarios for p in policies for seed in seeds]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    runs_path = out / "runs.jsonl"
    done = read_records(runs_path)
    todo = [s for s in specs if json.dumps(s, sort_keys=True) not in done]
    bar = Progress(len(todo), True)
    t0 = time.perf_counter()
    executor = campaign_pool.RayPool(args.ray, args.workers) if args.ray else campaign_pool.LocalPool(args.workers)
    with runs_path.open("a") as f, executor:
        for record in executor.map_unordered(run_one, todo, _crash):
            f.write(json.dumps(record) + "\n")
            f.flush()
            done[record["key"]] = record
            bar.advance(record)
    records = [done[json.dumps(s, sort_keys=True)] for s in specs]
    rows = summarize(records)
    summary = {"rows": rows, "seeds": seeds, "weights": args.weights, "wall_s": round(time.perf_counter() - t0, 1),
               "executor": f"ray {args.ray}" if args.ray else f"local pool of {args.workers}"}
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    (out / "summary.txt").write_text(table(rows) + "\n")
    if args.json:
        print(json.dumps(summary))
    else:
        print(table(rows))
    return 0
