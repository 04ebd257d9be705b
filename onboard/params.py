"""The one place for limits and tunable parameters.

The robot's physical parameters (masses, inertias, spring, travel) live in the MJCF
model ``sim_twin/models/archer.xml`` and nowhere else. What is here is what an
engineer tunes or what safety depends on. Each layer owns one frozen dataclass; a
config file (TOML, see :mod:`services.config`) overrides fields by section name,
and :func:`with_overrides` validates every override.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class SafetyLimits:
    """Limits every torque command passes through before it can reach a motor."""

    wheel_torque_max: float = 1.5  # [N m] per wheel, KV115 on 50.8 V, thesis lines 170-190
    foot_torque_max: float = 10.0  # [N m] foot cable motor after the 3:1 gearbox
    wheel_speed_max: float = 600.0  # [rad/s] beyond this the motor has no torque left
    tilt_max: float = math.radians(45.0)  # [rad] body z from vertical: a fall
    command_stale_s: float = 0.010  # [s] hardware/twin zero torque when no newer command
    estimate_stale_s: float = 0.005  # [s] control disarms on an older estimate
    reference_stale_s: float = 0.5  # [s] control falls back to hopping in place
    heartbeat_timeout_s: float = 0.100  # [s] Teensy / drive heartbeat consumer bound


@dataclass(frozen=True)
class MessagingParams:
    endpoint: str = "tcp/127.0.0.1:7447"  # the well-known local router endpoint
    status_period_s: float = 0.5  # how often a service refreshes its rate figures


@dataclass(frozen=True)
class HardwareParams:
    """The ``hardware`` service and its drivers (ELMO drives over CAN, Teensy over serial).

    Joint order everywhere: wheel 0, wheel 1, wheel 2, foot. Per-joint tuples are
    drive settings (motor torque constant, current clamp, gearbox) of the real
    robot; the emulators use the same values.
    """

    backend: str = "can"  # "can": ELMO drives over CANopen; "teensy": framed serial
    rate_hz: float = 1000.0  # exchange rate with the drives / the Teensy [Hz]
    # CAN (python-can arguments; the emulator prints them)
    can_interface: str = "socketcand"
    can_channel: str = "can0"
    can_host: str = "127.0.0.1"  # socketcand only
    can_port: int = 29536  # socketcand only
    can_bitrate: int = 1_000_000  # [bit/s]
    node_ids: tuple[int, ...] = (1, 2, 3, 4)  # CANopen node of each joint
    host_node_id: int = 127  # the host's heartbeat identifier 0x700 + id
    host_heartbeat_period_s: float = 0.025  # drives fault after SafetyLimits.heartbeat_timeout_s
    drive_heartbeat_period_s: float = 0.050  # drive heartbeat producer time (0x1017)
    position_every: int = 10  # position PDO on every n-th SYNC (bus budget)
    sdo_timeout_s: float = 0.5  # [s] per SDO response
    enable_timeout_s: float = 1.0  # [s] to reach OPERATION ENABLED
    torque_constant: tuple[float, ...] = (0.083, 0.083, 0.083, 0.083)  # [N m/A] KV115 wheels
    current_max: tuple[float, ...] = (12.0, 12.0, 12.0, 12.0)  # [A] drive current clamp
    gear_ratio: tuple[float, ...] = (1.0, 1.0, 1.0, 3.0)  # motor turns per joint turn
    joint_sign: tuple[int, ...] = (1, 1, 1, 1)  # motor direction vs joint direction
    # Teensy
    serial_port: str = ""  # e.g. /dev/ttyACM0 or the pty the emulator prints
    teensy_mode: str = "torque"  # "torque" or "attitude" (the Teensy runs the PD)
    reconnect_min_s: float = 0.05  # [s] first retry after the port vanished
    reconnect_max_s: float = 1.0  # [s] backoff ceiling
    link_timeout_s: float = 0.1  # [s] no sensor frame for this long: link lost


# Sections owned by each layer follow; each is registered in SECTIONS below.


SECTIONS: dict[str, type] = {
    "safety": SafetyLimits,
    "messaging": MessagingParams,
    "hardware": HardwareParams,
}


def with_overrides(obj: Any, overrides: dict[str, Any]) -> Any:
    """A copy of the dataclass ``obj`` with ``overrides`` applied, type-checked."""
    fields = {f.name: f for f in dataclasses.fields(obj)}
    clean: dict[str, Any] = {}
    for name, value in overrides.items():
        if name not in fields:
            raise ValueError(f"{type(obj).__name__} has no parameter {name!r}")
        current = getattr(obj, name)
        if isinstance(current, bool):
            if not isinstance(value, bool):
                raise ValueError(f"{name}: expected a bool, got {value!r}")
        elif isinstance(current, (int, float)):
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(f"{name}: expected a number, got {value!r}")
            if not math.isfinite(float(value)):
                raise ValueError(f"{name}: not finite")
            value = type(current)(value) if isinstance(current, float) else value
        elif isinstance(current, str):
            if not isinstance(value, str):
                raise ValueError(f"{name}: expected a string, got {value!r}")
        elif isinstance(current, tuple):
            value = tuple(value)
        clean[name] = value
    return dataclasses.replace(obj, **clean)


def as_dict(obj: Any) -> dict[str, Any]:
    return dataclasses.asdict(obj)
