"""The ``archer`` command line.

Each subcommand lives in its own module exposing ``add_arguments(parser)`` and
``run(args) -> int`` (or ``add_<name>_arguments`` / ``run_<name>`` when one module
serves several); this table is the only place that lists them. Only the chosen
command's module is imported, so a slow import (MuJoCo, numba) costs only the
commands that need it.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from services.runtime.process_env import prepare_environment

COMMANDS: dict[str, tuple[str, str]] = {
    # name: (module, one-line help)
    "run": ("services.cli.run", "run one service until SIGINT/SIGTERM"),
    "topics": ("services.cli.introspect", "print the topic table"),
    "services": ("services.cli.introspect", "print the service table: class, unit, parameters, what each reads and writes"),
    "echo": ("services.cli.introspect", "print decoded live messages of one topic"),
    "status": ("services.cli.introspect", "list live services and their status"),
    "view": ("services.cli.view", "live Foxglove view of a running stack: a WebSocket server on 127.0.0.1:8765"),
    "emulate": ("services.cli.emulate", "run emulated ELMO drives (socketcand on 127.0.0.1), a Teensy (pty), ARCHER boards, NatNet or a D435 (librealsense); prints one JSON line"),
    "sim": ("services.cli.sim", "run a scenario on the MuJoCo twin with the onboard stack (lockstep or real time)"),
    "campaign": ("services.cli.campaign", "a sweep of lockstep runs (scenarios x seeds x variants x options) on a process pool or Ray; JSONL + summary + plot"),
    "train": ("services.cli.train", "offline training: 'zdp' (the thesis's Algorithm 2) and 'zdp-compare' (a campaign against the other policies)"),
    "bench": ("services.bench.main", "measure speed and print figures"),
    "plot": ("services.cli.plot", "PNG plots of a recording (path, tracking, attitude, wheels, torques, loop timing)"),
    "deploy": ("services.cli.deploy", "install systemd units and configs; verify units; regenerate Zenoh access control"),
    "perceive": ("services.cli.perceive", "convex free cells or obstacles of an occupancy grid (.npy)"),
    "obstacles": ("services.cli.obstacles", "overhead camera: calibrate the floor by its ArUco markers; list and name the obstacles it sees"),
    "plan": ("services.cli.plan", "plan offline in a scene (JSON): Bezier graph path, clearance, timings"),
    "goal": ("services.cli.plan", "send the robot a goal position X Y [m]"),
    "reproduce": ("services.cli.reproduce", "regenerate the thesis's ARCHER figures and tables and compare them with its numbers (report.md)"),
    "identify": ("services.cli.identify", "fit the robot's wheel torque constants and drag, spring stiffness and CoM offset from a recording of the identification routine, with uncertainties; --validate N on drawn twins"),
    "margins": ("services.cli.margins", "one-factor model-error sweeps: how far each factor may grow before the robot misses its goal and falls, per controller config; table and plot"),
    "soak": ("deploy.sil_soak", "chaos soak: the real-time stack on the twin with a schedule of faults; a JSON summary per fault"),
}


def _chosen_command(argv: list[str]) -> str | None:
    for arg in argv:
        if not arg.startswith("-"):
            return arg if arg in COMMANDS else None
    return None


def build_parser(argv: list[str]) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="archer", description="ARCHER hopping-robot onboard stack")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    chosen = _chosen_command(argv)
    for name, (module_name, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name != chosen:
            continue
        module = importlib.import_module(module_name)
        adder = getattr(module, f"add_{name}_arguments", None) or module.add_arguments
        adder(p)
        p.set_defaults(_runner=getattr(module, f"run_{name}", None) or module.run)
    return parser


TICK_COMMANDS = ("sim", "campaign", "bench", "soak", "reproduce")  # what runs the lockstep tick (and starts the real-time stack from this checkout)


def _check_compiled_tick() -> None:
    """A stale compiled module (an edit since the build) refuses to run; a missing build says so in one line."""
    from sim_twin.compiled import check_fresh, compiled_modules  # reads file times only: no MuJoCo

    check_fresh()
    if not compiled_modules():
        print("archer: the compiled tick is not built here (no C compiler or mypyc at install, or ARCHER_COMPILE=0); "
              "lockstep runs about 2.5x slower", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    prepare_environment()  # before a command's module loads numba
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser(argv).parse_args(argv)
    if args.command in TICK_COMMANDS:
        try:
            _check_compiled_tick()
        except ImportError as exc:
            print(f"archer: {exc}", file=sys.stderr)
            return 2
    try:
        return int(args._runner(args) or 0)
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
