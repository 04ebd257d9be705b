"""``archer bench SUBJECT``: speed measurements that print figures.

Each subject module exposes ``add_arguments(parser)`` and ``measure(args) -> dict``;
the figures are printed as one JSON object (``--json``) or as aligned text.
Only the chosen subject's module is imported.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys

BENCHES: dict[str, tuple[str, str]] = {
    # subject: (module, one-line help)
    "perception": ("services.bench.perception", "Algorithm 4 on 200 x 200 grids: time, coverage, soundness"),
    "zdp": ("services.bench.zdp", "clipped ZDP vs plain LQR, Raibert and the MLP on a 2 m setpoint in the twin (thesis Fig. 5.22)"),
    "control": ("services.bench.control", "the 1 kHz control loop in its own process with the other core busy: tick time, period jitter, overruns"),
    "messaging": ("services.bench.messaging", "Zenoh latency and loss between two processes at 1 kHz"),
    "hardware": ("services.bench.hardware", "four emulated ELMO drives at 1 kHz through the hardware service: late/lost frames, bus load"),
    "mpc": ("services.bench.mpc", "50-node planner Bezier MPC (OSQP, PIQP) solve times and the edge-test rate"),
    "gmpc": ("services.bench.gmpc", "geometric MPC (thesis 5.3) on the twin: horizon, variables, constraints, solve p50/p99, SQP iterations, rate"),
    "planner": ("services.bench.planner", "Bezier graph planner: build, cut, search, refine; unsound and missed edges"),
    "estimator": ("services.bench.estimator", "state estimator on the twin (20 ms pose latency, 10 percent pose dropouts): update time, CoM and attitude errors"),
    "mocap": ("services.bench.mocap", "estimator RMSE with twin poses through the NatNet emulator and motioncapture vs. straight from the twin (lockstep)"),
    "twin": ("services.bench.twin", "physics step, the twin's own tick, lockstep real-time factor with the onboard stack"),
    "overhead": ("services.bench.overhead", "indoor loop at the thesis's rates, 20 sliding obstacles: overhead camera step, cut + search, MPC refinement p50/p99"),
    "camera": ("services.bench.camera", "the D435 chain at 848x480/30 Hz through librealsense to polytopes: latency p50/p99 and CPU"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="subject", required=True, metavar="SUBJECT")
    argv = sys.argv[1:]
    chosen = next((a for a in argv[argv.index("bench") + 1:] if not a.startswith("-")), None) if "bench" in argv else None
    for subject, (module_name, help_text) in BENCHES.items():
        p = sub.add_parser(subject, help=help_text, description=help_text)
        p.add_argument("--json", action="store_true", help="print one JSON object")
        if chosen is not None and subject != chosen:
            continue
        module = importlib.import_module(module_name)
        module.add_arguments(p)
        p.set_defaults(_measure=module.measure)


def run(args: argparse.Namespace) -> int:
    figures = args._measure(args)
    if args.json:
        print(json.dumps(figures))
    else:
        width = max(len(k) for k in figures)
        for key, value in figures.items():
            print(f"{key:<{width}}  {value}")
    return 0
