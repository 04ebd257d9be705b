"""``archer run SERVICE``: run one service in this process until SIGINT/SIGTERM."""

from __future__ import annotations

import argparse
import importlib
import sys

from services.config import ConfigError, load_params
from services.runtime import Service, add_service_arguments, run_service, setup_logging

SERVICE_CLASSES: dict[str, str] = {
    "twin": "sim_twin.twin_service:TwinService",
    "scenario_reference": "sim_twin.twin_service:ScenarioReferenceService",
    "perception": "services.perception:PerceptionService",
    "router": "services.router:RouterService",
    "hardware": "services.hardware:HardwareService",
    "control": "services.control:ControlService",
    "planner": "services.planner:PlannerService",
    "estimator": "services.estimator:EstimatorService",
    "recorder": "services.recorder:RecorderService",
}


def service_class(name: str) -> type[Service]:
    module_name, _, class_name = SERVICE_CLASSES[name].partition(":")
    return getattr(importlib.import_module(module_name), class_name)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("service", choices=sorted(SERVICE_CLASSES))
    add_service_arguments(parser)


def build_service(args: argparse.Namespace) -> Service:
    cls = service_class(args.service)
    params = load_params(args.config, cls.params_sections)
    return cls(ns=args.namespace, endpoint=args.endpoint, params=params, config_file=args.zenoh_config)


def run(args: argparse.Namespace) -> int:
    setup_logging(args.log_level)
    try:
        service = build_service(args)
    except ConfigError as exc:
        print(f"archer run: {exc}", file=sys.stderr)
        return 2
    return run_service(service)


