"""``archer train``: offline training of what the robot loads.

- ``archer train zdp``: the neural Zero Dynamics Policy by the thesis's Algorithm 2
  (:mod:`services.cli.train_zdp_alg2`);
- ``archer train zdp-compare``: a campaign of lockstep runs comparing a trained policy with
  today's MLP, the linear ZDP and Raibert on the 2 m setpoint, push recovery and the square
  (:mod:`services.cli.zdp_compare`).
"""

from __future__ import annotations

import argparse
import importlib

SUBCOMMANDS = {
    "zdp": ("services.cli.train_zdp_alg2", "train the neural ZDP by Algorithm 2 (iLQR, invariance loss 5.46); writes the weights and a loss plot"),
    "zdp-compare": ("services.cli.zdp_compare", "campaign: a trained ZDP network against today's MLP, the linear ZDP and Raibert"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="what", required=True, metavar="WHAT")
    for name, (module_name, help_text) in SUBCOMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        module = importlib.import_module(module_name)
        module.add_arguments(p)
        p.set_defaults(_train_runner=module.run)


def run(args: argparse.Namespace) -> int:
    return int(args._train_runner(args) or 0)
