"""``archer run SERVICE``: run one service in this process until SIGINT/SIGTERM.

Started by a supervisor (``archer sim --mode realtime``), the service stops with it:
the supervisor names itself in ``$ARCHER_SUPERVISOR_PID`` and the kernel sends the
service SIGTERM when it dies, even by ``kill -9`` (systemd, which outlives its
units, sets nothing).
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
from typing import NoReturn

from services.runtime.config import ConfigError, load_params
from services.runtime.realtime import die_with_parent
from services.runtime.service import Service, add_service_arguments, run_service, setup_logging
from services.runtime.supervisor import SUPERVISOR_PID_ENV
from services.table import SERVICES

def service_class(name: str) -> type[Service]:
    return SERVICES[name].service_class()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("service", choices=sorted(SERVICES))
    add_service_arguments(parser)


def build_service(args: argparse.Namespace) -> Service:
    cls = service_class(args.service)
    params = load_params(args.config, cls.params_sections)
    return cls(ns=args.namespace, endpoint=args.endpoint, params=params, config_file=args.zenoh_config)


def run(args: argparse.Namespace) -> int:
    die_with_parent(int(os.environ.get(SUPERVISOR_PID_ENV, "0") or 0), signal.SIGTERM)
    setup_logging(args.log_level)
    lacking = SERVICES[args.service].missing()
    if lacking:
        print(f"archer run: {'; '.join(lacking)}", file=sys.stderr)
        return 2
    try:
        service = build_service(args)
    except ConfigError as exc:
        print(f"archer run: {exc}", file=sys.stderr)
        return 2
    leave(run_service(service))


def leave(code: int) -> NoReturn:
    """Exit with ``code`` now, once the service has stopped (its session closed, its helper processes
    joined): the interpreter's finalization after that adds 0.1-0.2 s per process on a loaded machine
    (tearing down numpy, Zenoh's runtime, every module), and a stopped stack must be gone within 3 s."""
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


