"""``archer emulate drives|teensy``: run an emulated device in this process.

Prints ONE JSON line on stdout telling a client how to connect, then serves until
SIGINT/SIGTERM. Only loopback TCP or pseudo-terminals, nothing else.

- ``drives``: ELMO CiA 402 drives behind a socketcand server on 127.0.0.1. The line
  holds ``interface`` and ``channel`` plus ``bus``, the complete keyword arguments of
  ``can.Bus(**bus)`` for a stock python-can client, and ``eds``, the drives' object
  dictionary as an EDS file (what a CANopen master such as the ``canopen`` package
  loads).
- ``teensy``: a Teensy on a pseudo-terminal; ``port`` is the path to open (a stable
  symlink to the pty), speaking ``docs/teensy_protocol.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import signal
import sys
import tempfile
import threading

from drivers.elmo.emulator import SocketcandRunner, make_emulator
from drivers.elmo.od import drive_dictionary, to_eds
from drivers.teensy.emulator import TeensyEmulator
from drivers.teensy.protocol import VERSION
from onboard.params import HardwareParams
from services.config import ConfigError, load_params

DOCS = "docs/teensy_protocol.md"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("device", choices=("drives", "teensy"))
    parser.add_argument("--node-ids", help="comma-separated CANopen node ids (default: hardware.node_ids)")
    parser.add_argument("--port", type=int, default=0, help="drives: TCP port on 127.0.0.1 (default: a free one)")
    parser.add_argument("--channel", default=None, help="drives: socketcand channel name (default: hardware.can_channel)")
    parser.add_argument("--config", help="TOML file overriding parameters (sections hardware, safety)")


def _node_ids(text: str) -> tuple[int, ...]:
    try:
        ids = tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise ConfigError(f"--node-ids {text!r}: expected comma-separated integers") from None
    if not ids or any(not 1 <= i <= 127 for i in ids) or len(set(ids)) != len(ids):
        raise ConfigError(f"--node-ids {text!r}: distinct ids in 1..127 needed")
    return ids


def _stop_on_signal() -> threading.Event:
    """Installed before the JSON line goes out: a client may signal as soon as it reads it."""
    done = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: done.set())
    return done


def _wait(done: threading.Event) -> None:
    while not done.wait(0.5):
        pass


def _gear_ratios() -> tuple[float, ...]:
    from services.hardware import gear_ratios

    return gear_ratios()


def run_drives(params: HardwareParams, port: int, channel: str) -> int:
    n = len(params.node_ids)
    per_joint = {name: getattr(params, name) for name in ("torque_constant", "current_max")}
    for name, values in per_joint.items():
        if len(values) < n:  # more drives than configured joints: repeat the last joint's settings
            per_joint[name] = tuple(values) + (values[-1],) * (n - len(values))
    params = dataclasses.replace(params, **per_joint)
    done = _stop_on_signal()
    emulator = make_emulator(params)
    eds_dir = tempfile.mkdtemp(prefix="archer-drives-")
    eds_path = os.path.join(eds_dir, "archer_elmo.eds")
    first = params.node_ids[0]
    with open(eds_path, "w") as f:
        f.write(to_eds(drive_dictionary(first, emulator.drive(first).cfg), first))
    runner = SocketcandRunner(emulator, channel, port).start()
    bus = runner.bus_kwargs()
    print(
        json.dumps(
            {
                "device": "drives",
                "interface": bus["interface"],
                "channel": bus["channel"],
                "bus": bus,
                "bitrate": params.can_bitrate,
                "node_ids": list(params.node_ids),
                "host_node_id": params.host_node_id,
                "eds": eds_path,
                "pid": os.getpid(),
            }
        ),
        flush=True,
    )
    try:
        _wait(done)
    finally:
        runner.stop()
        os.unlink(eds_path)
        os.rmdir(eds_dir)
        print(json.dumps({"final": emulator.summary()}), file=sys.stderr, flush=True)  # counters for benches
    return 0 if runner.error is None else 1


def run_teensy(params: HardwareParams) -> int:
    done = _stop_on_signal()
    emulator = TeensyEmulator(params, _gear_ratios()).start()
    print(
        json.dumps(
            {
                "device": "teensy",
                "port": emulator.port,
                "pty": os.path.realpath(emulator.port),
                "protocol": DOCS,
                "version": VERSION,
                "pid": os.getpid(),
            }
        ),
        flush=True,
    )
    try:
        _wait(done)
    finally:
        emulator.stop()
        print(json.dumps({"final": emulator.counts}), file=sys.stderr, flush=True)  # counters for benches
    return 0 if emulator.error is None else 1


def run(args: argparse.Namespace) -> int:
    try:
        params = load_params(args.config, ("hardware", "safety"))["hardware"]
        if args.node_ids:
            ids = _node_ids(args.node_ids)
            params = dataclasses.replace(params, node_ids=ids)
    except ConfigError as exc:
        print(f"archer emulate: {exc}", file=sys.stderr)
        return 2
    if args.device == "drives":
        return run_drives(params, args.port, args.channel or params.can_channel)
    return run_teensy(params)
