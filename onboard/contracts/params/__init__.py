"""The one place for limits and tunable parameters.

The robot's physical parameters (masses, inertias, spring, travel) live in the MJCF
model ``robot_description/models/archer.xml`` and nowhere else. What is here is what an
engineer tunes or what safety depends on. Each layer owns one frozen dataclass, in this package's module for that layer; a
config file (TOML, see :mod:`services.runtime.config`) overrides fields by section name,
and :func:`with_overrides` validates every override.

Every field declares its type and its range in its annotation
(``Annotated[float, within(0.0, 500.0)]``); a section refuses, when it is built, any
field of the wrong type (an int field refuses 1.5 and True, a float field takes an
int) or out of its range, naming the field as ``section.name``. Live changes of a
running control loop are applied between two ticks except for :data:`NEEDS_RESTART`.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from onboard.contracts.params.base import (CAN_NODES, FOOT_TORQUE_PEAK, LOOP_HZ_MAX, SECTIONS, WHEEL_NO_LOAD_SPEED, WHEEL_TORQUE_PEAK,
                                           ParamError, _section_name)
from onboard.contracts.params.estimation import EstimatorParams
from onboard.contracts.params.high_level import PerceptionParams, PlannerParams
from onboard.contracts.params.low_level import ControlParams, GeometricMpcParams
from onboard.contracts.params.low_level import GMPC_THESIS_KNOTS
from onboard.contracts.params.platform import (ArcherFirmwareParams, CameraParams, HardwareParams, MessagingParams, MocapParams, RecorderParams,
                                               SafetyLimits, ViewParams)
from onboard.contracts.params.platform import CameraOverheadParams
from onboard.contracts.params.twin import TwinParams

__all__ = [  # the one place for parameters: every layer's section, and what works on any of them
    "SECTIONS", "NEEDS_RESTART", "ParamError", "restart_changes", "with_overrides", "as_dict",
    "CAN_NODES", "FOOT_TORQUE_PEAK", "LOOP_HZ_MAX", "WHEEL_NO_LOAD_SPEED", "WHEEL_TORQUE_PEAK",
    "SafetyLimits", "MessagingParams", "HardwareParams", "ArcherFirmwareParams", "RecorderParams", "ViewParams", "MocapParams",
    "CameraParams",
    "EstimatorParams", "ControlParams", "GeometricMpcParams", "PlannerParams", "PerceptionParams", "TwinParams",
    "CameraOverheadParams",
    "GMPC_THESIS_KNOTS",
]

# Fields a running control loop cannot take between two ticks: they shape the loop process
# (rate, scheduling), the robot model, or the policy design (linearized about the hop, or
# loaded from a file), or they size the tube statistics. The control service applies a change
# of one by restarting its loop, which it refuses while the controller is armed. Every other
# control and safety field is applied between two ticks. The estimator's loop thread takes
# its rate and scheduling when it starts: a change of those needs a restart of the service
# (refused live); every other estimator field rebuilds the filter.
NEEDS_RESTART: dict[str, frozenset[str]] = {
    "control": frozenset({"rate_hz", "robot", "rt_priority", "cpu", "output", "mid_level", "policy", "mlp_weights", "hop_height",
                          "zdp_q_pos", "zdp_q_vel", "zdp_q_tilt", "zdp_r", "tube_window"}),
    "estimator": frozenset({"rate_hz", "rt_priority", "cpu", "input_queue"}),
}


def restart_changes(section: str, before: Any, after: Any) -> list[str]:
    """The ``section.name`` of every restart-needing field that differs between two objects."""
    return [f"{section}.{name}" for name in sorted(NEEDS_RESTART.get(section, ()))
            if getattr(before, name) != getattr(after, name)]


def with_overrides(obj: Any, overrides: dict[str, Any]) -> Any:
    """A copy of the dataclass ``obj`` with ``overrides`` applied, all or nothing.

    Raises :class:`ParamError` (a ``ValueError``) naming every unknown, wrongly typed or
    out-of-range field as ``section.name``.
    """
    known = {f.name for f in dataclasses.fields(obj)}
    unknown = [name for name in overrides if name not in known]
    if unknown:
        section = _section_name(type(obj))
        raise ParamError("; ".join(f"{section} has no parameter {name!r}" for name in unknown))
    return dataclasses.replace(obj, **overrides)


def as_dict(obj: Any) -> dict[str, Any]:
    return dataclasses.asdict(obj)
