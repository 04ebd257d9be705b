"""The geometric MPC (thesis 5.3) solving on the twin: size, solve time, SQP iterations, rate.

A lockstep run of a scenario with ``control.mid_level = "geometric_mpc"``: every solve is
the mid level's full step on the tick's estimate (state conversion, mode schedule, the SQP's
linearizations and matrix exponentials, the QP updates and solves, the checks), timed with
the wall clock around that call only (and its CPU time: on a shared machine the wall time
includes waiting for a core). ``solve_ms_*`` cover every attempt, whatever its answer;
``ok_solve_ms_*`` the certified ones alone; a call refused before any solve (an unusable
estimate) is counted, never timed as a solve. Flight and stance solves are reported apart (the
stance's knots are finer and its jumps closer). ``rate_hz_at_p99`` is the solve rate one core
sustains when every attempt takes the p99 time.

``--thesis-settings``: the knots of the thesis's Table 5.3 (``GMPC_THESIS_KNOTS``); on the twin they
do not keep the robot up (README, issue 29), so ``--shadow`` times them beside a run driven by
the default settings: the same estimates and references, the thesis-knot MPC's answers dropped.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from onboard.contracts.params import GMPC_THESIS_KNOTS, ControlParams, GeometricMpcParams, SafetyLimits, with_overrides
from robot_description.controller import build_gmpc_mid_level
from sim_twin.lockstep import LockstepRunner, RunConfig

MS = 1e3


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", default="square", help="the twin scenario the states come from")
    parser.add_argument("--variant", default="sim15nm", help="robot model variant")
    parser.add_argument("--duration", type=float, default=10.0, help="simulated seconds")
    parser.add_argument("--backend", choices=("condensed", "piqp", "osqp"), default=None, help="QP solver (default: gmpc.backend)")
    parser.add_argument("--thesis-settings", action="store_true",
                        help="the thesis's Table 5.3 knots (GMPC_THESIS_KNOTS: horizon 20, 0.01 s flight, 0.001 s stance) "
                             "in place of the stack's default ones")
    parser.add_argument("--shadow", action="store_true",
                        help="the twin driven by the default settings, the MPC at the chosen ones solving beside it on the same "
                             "estimates and references, timed, its answers dropped (the thesis's knots do not keep the twin up: "
                             "a closed-loop run times only the few solves before its fall)")
    parser.add_argument("--seed", type=int, default=0)


def _percentiles(samples: list[float]) -> dict[str, float]:
    a = np.asarray(samples) * MS
    return {"p50": round(float(np.percentile(a, 50)), 3), "p99": round(float(np.percentile(a, 99)), 3), "max": round(float(a.max()), 3)}


def measure(args: argparse.Namespace) -> dict:
    gmpc = GeometricMpcParams()
    if args.thesis_settings:
        gmpc = with_overrides(gmpc, GMPC_THESIS_KNOTS)
    if args.backend:
        gmpc = with_overrides(gmpc, {"backend": args.backend})
    drive = with_overrides(GeometricMpcParams(), {"backend": gmpc.backend}) if args.shadow else gmpc
    cfg = RunConfig(scenario=args.scenario, seed=args.seed, duration_s=args.duration, variant=args.variant, estimator="kalman",
                    control_params=ControlParams(mid_level="geometric_mpc"), gmpc_params=drive)
    times: dict[str, list[float]] = {"flight": [], "stance": []}  # certified solves, by the first knot's mode
    attempts: list[float] = []  # every call that solved, whatever its answer
    cpu: list[float] = []
    iterations: list[int] = []
    runner = LockstepRunner(cfg)
    driver = runner.controller.mid_level
    drive_step = driver.step
    mid = driver  # the mid level timed
    if args.shadow:
        mid = build_gmpc_mid_level(args.variant, gmpc, cfg.control_params, SafetyLimits(wheel_torque_max=driver.mpc.limit))
    solve = mid.step

    def timed(now_ns, state, reference):
        out = drive_step(now_ns, state, reference) if args.shadow else None
        solves_before = mid.solves
        t0, c0 = time.perf_counter(), time.process_time()
        answer = solve(now_ns, state, reference)
        dt, dc = time.perf_counter() - t0, time.process_time() - c0
        out = out if args.shadow else answer
        if mid.solves == solves_before:  # refused before solving: last_solution is an old one
            return out
        attempts.append(dt)
        cpu.append(dc)
        sol = mid.last_solution
        iterations.extend(sol.qp_iterations)
        if sol.ok:
            times[sol.knots[0].kind if not sol.knots[0].is_jump else "flight"].append(dt)
        return out

    driver.step = timed
    result = runner.run()
    certified = times["flight"] + times["stance"]
    if not attempts:
        raise RuntimeError(f"no solve ran ({mid.rejected} refused, last status {mid.last_status!r})")
    mpc = mid.mpc
    p99 = float(np.percentile(attempts, 99))
    overall = _percentiles(attempts)
    return {
        "backend": mpc.backend,
        "variant": args.variant,
        "scenario": args.scenario,
        "horizon": mpc.n,
        "knots_s": {"flight": gmpc.flight_step_s, "stance": gmpc.stance_step_s},
        "shadow": bool(args.shadow),  # timed beside a run the default settings drive
        "state_dim": 20,
        "variables": mpc.nvar,
        "constraints": mpc.neq + mpc.n * 3,  # dynamics and initial state (equalities), input box
        "equality_rows": mpc.neq,
        "sqp_iterations": gmpc.sqp_iterations,
        "solves": len(attempts),
        "solves_certified": len(certified),
        "refused": mid.rejected,  # calls that returned no set point: unusable estimate or an answer that failed its checks
        "solve_ms_p50": overall["p50"],  # every attempt
        "solve_ms_p99": overall["p99"],
        "solve_ms_max": overall["max"],
        "ok_solve_ms": _percentiles(certified) if certified else None,  # the certified attempts alone
        # CPU time of the same solves: what the solve costs, apart from waiting for a core
        "solve_cpu_ms_p50": _percentiles(cpu)["p50"],
        "solve_cpu_ms_p99": _percentiles(cpu)["p99"],
        "flight_solve_ms": _percentiles(times["flight"]) if times["flight"] else None,
        "stance_solve_ms": _percentiles(times["stance"]) if times["stance"] else None,
        "qp_iterations_p50": int(np.percentile(iterations, 50)),
        "qp_iterations_max": int(max(iterations)),
        "rate_hz_target": gmpc.rate_hz,
        "rate_hz_at_p99": round(1.0 / p99, 1),
        "p99_under_10_ms": p99 < 0.010,
        "p99_under_5_ms": p99 < 0.005,  # the thesis's 100 Hz with a 2x margin (issue 29)
        "falls": result.metrics["falls"],
        "rms_tracking_error_m": result.metrics["rms_tracking_error_m"],
    }
