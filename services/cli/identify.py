"""``archer identify RECORDING.mcap --out FILE.toml``: the robot's parameters fitted from a recording.

The routine: hop in place with ``[control] identify = true`` for ~20 s (``archer run control`` on the
robot; on the twin ``archer sim --scenario hop-in-place --duration 20 --config identify.toml --record
F.mcap``), recorded by the flight recorder. The fits (:mod:`offline.identification`) give each
wheel's torque constant, viscous and Coulomb drag, the drives' delay, the spring's stiffness and the
CoM's offset from the spine, each with a 1-sigma uncertainty; ``--out`` writes them as an identified robot (:mod:`robot_description.identified`:
the stack reads it, and ``archer sim --model-error FILE`` builds the twin from it).

``archer identify --validate N [--profile calibrated]``: N twins with hidden drawn errors, each runs
the routine in lockstep and is identified from its messages; prints, per parameter, the error
against the drawn truth in units of the stated sigma (the share within 1 and 2 sigma).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from offline import identification as idf
from robot_description import identified as ident
from robot_description import params as rd

PARAM_ORDER = ("com_x", "com_y", "wheel_torque_constant", "wheel_viscous", "wheel_coulomb", "actuator_delay", "spring_stiffness")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("recording", nargs="*", metavar="RECORDING.mcap", help="recording files (or the recorder's directory)")
    parser.add_argument("--out", default=None, metavar="FILE.toml", help="write the identified robot here")
    parser.add_argument("--variant", choices=rd.VARIANTS, default=rd.DEFAULT_VARIANT, help="the nominal robot the fit starts from")
    d = idf.IdentifyOptions()
    parser.add_argument("--window", type=float, default=d.window_s, help=f"wheel fit window [s] (default {d.window_s})")
    parser.add_argument("--settle", type=float, default=d.settle_s, help=f"seconds skipped at the start (default {d.settle_s})")
    parser.add_argument("--wheel-inertia-sigma", type=float, default=d.wheel_inertia_sigma,
                        help=f"relative 1-sigma of the MJCF's wheel inertia, added to the wheel values' (default {d.wheel_inertia_sigma})")
    parser.add_argument("--imu-mount-sigma", type=float, default=d.imu_mount_sigma,
                        help=f"IMU mount 1-sigma [rad], added to the CoM offset's as lever x it (default {d.imu_mount_sigma})")
    parser.add_argument("--com-model-sigma", type=float, default=d.com_model_sigma,
                        help=f"the balance-point model's own error [m], added to the CoM offset's (default {d.com_model_sigma})")
    parser.add_argument("--sprung-mass-sigma", type=float, default=d.sprung_mass_sigma,
                        help=f"relative 1-sigma of the MJCF's sprung mass, added to the spring stiffness's (default {d.sprung_mass_sigma})")
    parser.add_argument("--validate", type=int, default=None, metavar="N", help="identify N twins with hidden drawn errors instead")
    parser.add_argument("--profile", default="calibrated", help="--validate: the model-error profile drawn per seed")
    parser.add_argument("--first-seed", type=int, default=0, help="--validate: seeds first..first+N-1")
    parser.add_argument("--duration", type=float, default=20.0, help="--validate: routine length [s]")
    parser.add_argument("--estimator", choices=("kalman", "truth"), default="kalman", help="--validate: the stack's estimator")
    parser.add_argument("--tracking", default="", metavar="SCENARIO,...",
                        help="--validate: also run these scenarios per seed on the nominal twin, on the drawn twin with the "
                             "nominal stack, and on it with the identified estimator ([estimator] identified)")
    parser.add_argument("--json", action="store_true", help="print one JSON object (last stdout line)")


def options(args: argparse.Namespace) -> idf.IdentifyOptions:
    from onboard.contracts.params import SafetyLimits

    robot = rd.robot_params(args.variant)
    return idf.IdentifyOptions(window_s=args.window, settle_s=args.settle, wheel_inertia_sigma=args.wheel_inertia_sigma,
                               imu_mount_sigma=args.imu_mount_sigma, com_model_sigma=args.com_model_sigma,
                               sprung_mass_sigma=args.sprung_mass_sigma,
                               wheel_torque_max=min(rd.safety_limits_for(SafetyLimits(), robot).wheel_torque_max, robot.wheel_torque_peak))


def read_recording(paths: list[str]) -> dict[str, list]:
    """Decoded messages by topic; a clear error for what the fit cannot use."""
    from services.cli.plot import load
    from services.recorder import recording_files

    files = recording_files(paths)
    if not files:
        raise idf.IdentificationError(f"no .mcap files in {', '.join(paths)}")
    try:
        series, skipped = load([str(f) for f in files])
    except Exception as exc:  # a truncated or foreign file: the reader's own words
        raise idf.IdentificationError(f"cannot read {', '.join(map(str, files))}: {type(exc).__name__}: {exc}") from None
    bad = {k: n for k, n in skipped.items() if k.startswith("invalid ") and k.removeprefix("invalid ") in idf.REQUIRED_TOPICS}
    if bad:
        raise idf.IdentificationError("recording has invalid samples (malformed or non-finite): "
                                      + ", ".join(f"{n} on {k.removeprefix('invalid ')}" for k, n in bad.items()))
    return {name: s.msgs for name, s in series.items()}


def as_parameters(result: idf.Identified) -> dict[str, ident.Parameter]:
    return {name: ident.Parameter(tuple(float(e.value) for e in ests), tuple(float(e.sigma) for e in ests), ests[0].unit)
            for name, ests in result.params.items()}


def report(result: idf.Identified) -> dict:
    return {name: {"value": [round(float(e.value), 7) for e in ests], "sigma": [round(float(e.sigma), 7) for e in ests],
                   "unit": ests[0].unit} for name, ests in result.params.items()}


def run(args: argparse.Namespace) -> int:
    if args.validate is not None:
        return validate(args)
    if not args.recording:
        print("archer identify: give a recording (RECORDING.mcap) or --validate N", file=sys.stderr)
        return 2
    robot = rd.robot_params(args.variant)
    try:
        series = idf.series_from_messages(read_recording(args.recording), robot.spool_radius)
        result = idf.identify(series, robot, options(args))
    except idf.IdentificationError as exc:
        print(f"archer identify: {exc}", file=sys.stderr)
        return 1
    if args.out:
        meta = {"variant": args.variant, "source": ", ".join(Path(p).name for p in args.recording), **result.counts}
        Path(args.out).write_text(ident.dumps(as_parameters(result), meta))
    out = {"identified": report(result), **result.counts, "out": args.out}
    if args.json:
        print(json.dumps(out))
    else:
        for name, ests in result.params.items():
            vals = ", ".join(f"{e.value:+.6g} +- {e.sigma:.2g}" for e in ests)
            print(f"{name:24s} {vals} {ests[0].unit}")
        if args.out:
            print(f"wrote {args.out}")
    return 0


def _tracking_summary(values: dict[str, list]) -> dict:
    """Means over the seeds (RMS tracking, goal error), total falls."""
    def mean(k: str) -> float:
        vs = [v for v in values.get(k, []) if v is not None]
        return float(np.mean(vs)) if vs else math.nan
    return {"rms_tracking_error_m": mean("rms_tracking_error_m"), "final_goal_error_m": mean("final_goal_error_m"),
            "falls": int(sum(int(v or 0) for v in values.get("falls", [])))}


# --- validation on twins with hidden drawn errors -------------------------------------------------


def truth_of(runner, robot: rd.RobotParams) -> dict[str, list[float]]:
    """The twin's drawn values in the identified parameters' terms."""
    from sim_twin import model_error as me

    draw = runner.model_error
    com = me.true_com_offset(runner.model)
    return {
        "com_x": [com[0] - robot.com_offset_body[0]],
        "com_y": [com[1] - robot.com_offset_body[1]],
        "wheel_torque_constant": [max(me.REL_FLOOR, draw.get("wheel_torque_constant", i)) for i in range(3)],
        "wheel_viscous": [max(0.0, draw.get("wheel_viscous", i)) for i in range(3)],
        "wheel_coulomb": [max(0.0, draw.get("wheel_coulomb", i)) for i in range(3)],
        "actuator_delay": [runner.delay_ticks * runner.tick_ns / 1e9],  # the runner queues whole ticks
        "spring_stiffness": [max(me.REL_FLOOR, draw.get("spring_stiffness"))],
    }


def identify_twin(seed: int, profile: str | None, args: argparse.Namespace, record: str | None = None) -> tuple[idf.Identified, dict, dict]:
    """One lockstep run of the routine on a drawn twin: (identified, truth, run metrics)."""
    from onboard.contracts.params import ControlParams, with_overrides
    from sim_twin import lockstep as ls

    cfg = ls.RunConfig(scenario="hop-in-place", seed=seed, duration_s=args.duration, variant=args.variant,
                       estimator=args.estimator, record=True, model_error=profile,
                       control_params=with_overrides(ControlParams(), {"identify": True}))
    runner = ls.LockstepRunner(cfg)
    res = runner.run()
    by_topic: dict[str, list] = defaultdict(list)
    for topic, _, msg in res.messages:
        by_topic[topic].append(msg)
    robot = rd.robot_params(args.variant)
    result = idf.identify(idf.series_from_messages(by_topic, robot.spool_radius), robot, options(args))
    return result, truth_of(runner, robot), res.metrics


TRACKING_ARMS = ("nominal", "drawn", "identified")
TRACKING_METRICS = ("rms_tracking_error_m", "final_goal_error_m", "falls")


def tracking(seed: int, scenario: str, profile: str, result: idf.Identified, args: argparse.Namespace, tmp: Path) -> dict:
    """The scenario on the nominal twin, on the drawn twin with the nominal stack, and on it with the identified estimator."""
    from onboard.contracts.params import EstimatorParams, with_overrides
    from sim_twin import lockstep as ls

    path = tmp / f"identified_{seed}.toml"
    path.write_text(ident.dumps(as_parameters(result), {"variant": args.variant, "seed": seed}))
    out = {}
    for arm in TRACKING_ARMS:
        cfg = ls.RunConfig(scenario=scenario, seed=seed, variant=args.variant, estimator=args.estimator,
                           model_error=None if arm == "nominal" else profile,
                           estimator_params=with_overrides(EstimatorParams(), {"identified": str(path)}) if arm == "identified" else None)
        metrics = ls.run(cfg).metrics
        out[arm] = {k: metrics.get(k) for k in TRACKING_METRICS}
    return out


def validate(args: argparse.Namespace) -> int:
    import tempfile

    scenarios = [s for s in args.tracking.split(",") if s]
    tmp = Path(tempfile.mkdtemp(prefix="archer_identify_"))
    track: dict[str, dict[str, dict[str, list]]] = {s: {a: defaultdict(list) for a in TRACKING_ARMS} for s in scenarios}
    rows: list[dict] = []
    z: dict[str, list[float]] = defaultdict(list)  # (identified - truth) / sigma
    err: dict[str, list[float]] = defaultdict(list)
    sig: dict[str, list[float]] = defaultdict(list)
    failed = 0
    for seed in range(args.first_seed, args.first_seed + args.validate):
        try:
            result, truth, metrics = identify_twin(seed, args.profile, args)
        except idf.IdentificationError as exc:
            failed += 1
            print(f"seed {seed}: {exc}", file=sys.stderr)
            continue
        row = {"seed": seed, "falls": metrics.get("falls"), "identified": report(result), "truth": truth}
        for scenario in scenarios:
            row[scenario] = tracking(seed, scenario, args.profile, result, args, tmp)
            for arm, vals in row[scenario].items():
                for k, v in vals.items():
                    track[scenario][arm][k].append(v)
        rows.append(row)
        for name in PARAM_ORDER:
            for e, t in zip(result.params.get(name, ()), truth[name]):
                z[name].append((e.value - t) / e.sigma)
                err[name].append(abs(e.value - t))
                sig[name].append(e.sigma)
        if not args.json:
            print(json.dumps({"seed": seed, **{n: [round(v, 2) for v in z[n][-len(truth[n]):]] for n in PARAM_ORDER if z[n]},
                              **{s: row[s] for s in scenarios}}), flush=True)
    summary = {}
    for name in PARAM_ORDER:
        zs = np.abs(np.array(z[name]))
        if len(zs) == 0:
            continue
        summary[name] = {"n": int(len(zs)), "mean_abs_error": float(np.mean(err[name])), "mean_sigma": float(np.mean(sig[name])),
                         "within_1sigma": float(np.mean(zs <= 1.0)), "within_2sigma": float(np.mean(zs <= 2.0)),
                         "max_abs_z": float(np.max(zs))}
    out = {"profile": args.profile, "seeds": args.validate, "estimator": args.estimator, "duration_s": args.duration,
           "failed": failed, "falls": sum(int(r["falls"] or 0) for r in rows), "summary": summary,
           "tracking": {s: {a: _tracking_summary(v) for a, v in arms.items()} for s, arms in track.items()}}
    if args.json:
        print(json.dumps(out))
    else:
        print(f"\nprofile {args.profile}, {len(rows)} twins identified ({failed} failed), {out['falls']} falls")
        print(f"{'parameter':24s} {'n':>3s} {'mean |err|':>11s} {'mean sigma':>11s} {'<=1 sigma':>9s} {'<=2 sigma':>9s} {'max |z|':>8s}")
        for name, s in summary.items():
            print(f"{name:24s} {s['n']:3d} {s['mean_abs_error']:11.3g} {s['mean_sigma']:11.3g} {s['within_1sigma']:9.0%} "
                  f"{s['within_2sigma']:9.0%} {s['max_abs_z']:8.2f}")
        for scenario, arms in out["tracking"].items():
            print(f"\n{scenario}: {'twin / stack':28s} {'RMS tracking':>13s} {'goal error':>11s} {'falls':>6s}")
            for arm, s in arms.items():
                label = {"nominal": "nominal / nominal", "drawn": f"{args.profile} / nominal", "identified": f"{args.profile} / identified"}[arm]
                print(f"{'':{len(scenario) + 1}s} {label:28s} {s['rms_tracking_error_m']:13.4f} {s['final_goal_error_m']:11.4f} {s['falls']:6d}")
    return 0 if not failed and math.isfinite(sum(len(v) for v in z.values())) else 1
