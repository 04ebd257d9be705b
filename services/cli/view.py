"""``archer view``: the live Foxglove bridge (the ``view`` service, :mod:`services.view`) in this process.

The same as ``archer run view``, with the port on the command line: open Foxglove and
connect to ``ws://127.0.0.1:PORT`` (Foxglove's default 8765).
"""

from __future__ import annotations

import argparse
import os
import signal
import sys

from onboard.contracts.params import ParamError, with_overrides
from services.runtime.config import ConfigError, load_params
from services.runtime.realtime import die_with_parent
from services.runtime.service import add_service_arguments, run_service, setup_logging
from services.runtime.supervisor import SUPERVISOR_PID_ENV
from services.view import ViewService


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_service_arguments(parser)
    parser.add_argument("--port", type=int, default=None, help="WebSocket port (default view.port, 8765; 0: any free port)")
    parser.add_argument("--host", default=None, help="bind address (default view.host, 127.0.0.1)")
    parser.add_argument("--variant", default=None, help="robot model drawn (default view.variant, indoor)")


def run(args: argparse.Namespace) -> int:
    die_with_parent(int(os.environ.get(SUPERVISOR_PID_ENV, "0") or 0), signal.SIGTERM)
    setup_logging(args.log_level)
    overrides = {k: v for k, v in (("port", args.port), ("host", args.host), ("variant", args.variant)) if v is not None}
    try:
        params = load_params(args.config, ViewService.params_sections)
        params["view"] = with_overrides(params["view"], overrides)  # validated: a bad port is refused by name
    except (ConfigError, ParamError) as exc:
        print(f"archer view: {exc}", file=sys.stderr)
        return 2
    service = ViewService(ns=args.namespace, endpoint=args.endpoint, params=params, config_file=args.zenoh_config)
    return run_service(service)
