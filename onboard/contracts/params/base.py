"""What every parameter section shares: validation, ranges, the robot-wide ceilings, the registry of sections."""

from __future__ import annotations

import dataclasses
import functools
import typing
from typing import Annotated, Any

import msgspec
from msgspec import Meta


class ParamError(ValueError):
    """A parameter of the wrong type, out of its range or unknown; names ``section.name``."""


def within(lo: float, hi: float) -> Meta:
    """The closed range [lo, hi]."""
    return Meta(ge=lo, le=hi)


def above(lo: float, hi: float) -> Meta:
    """(lo, hi]: ``lo`` itself excluded (a period, a rate, a standard deviation)."""
    return Meta(gt=lo, le=hi)


# Ceilings read off the robot description (tests/test_params.py holds them to the MJCF of every
# variant). The controller further caps torques at the loaded variant's own peak.
WHEEL_TORQUE_PEAK = 15.0  # [N m] largest wheel drive peak of any variant (sim15nm; the real KV115 drive: 1.6)
FOOT_TORQUE_PEAK = 10.0  # [N m] the foot cable drive's peak at the gearbox output
WHEEL_NO_LOAD_SPEED = 3200.0  # [rad/s] fastest no-load wheel of any variant (sim15nm; the real KV115 on 50.8 V: 611.8)
CAN_NODES = 127  # CANopen node ids 1..127: per-node tuples are never longer (an emulated bus may carry more drives than joints)
LOOP_HZ_MAX = 2000.0  # [Hz] what a Python hard-rate loop keeps on the onboard computer

Probability = Annotated[float, within(0.0, 1.0)]
Dropout = Annotated[float, Meta(ge=0.0, lt=1.0)]  # a sensor that loses every sample is no sensor
RtPriority = Annotated[int, within(0, 99)]  # SCHED_FIFO 1..99; 0: leave the scheduler alone
Cpu = Annotated[int, within(-1, 1023)]  # a CPU index; -1: no pinning
Port = Annotated[int, within(1, 65535)]
Seed = Annotated[int, within(0, 2**32 - 1)]  # numpy's seed range
Request = Annotated[int, within(0, 2**53)]  # an operator command counter: a new value is the command
Name = Annotated[str, Meta(min_length=1)]
NodeId = Annotated[int, within(1, CAN_NODES)]
PER_NODE = Meta(min_length=1, max_length=CAN_NODES)  # a tuple with one entry per drive


@functools.cache
def _field_types(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls, include_extras=True)


SECTIONS: dict[str, type] = {}  # section name -> its class, filled as each section class is defined


def _section_name(cls: type) -> str:
    return next((name for name, c in SECTIONS.items() if c is cls), cls.__name__)


def _error_text(field: str, value: Any, exc: msgspec.ValidationError) -> str:
    """``section.name[i]: expected `int`, got `null``` from msgspec's ``... - at `$[i]```."""
    text, _, path = str(exc).partition(" - at `$")
    return f"{field}{path.rstrip('`')}: {text[:1].lower()}{text[1:]} (value {value!r})"


class _Section:
    """Validates and normalizes (int -> float, list -> tuple) every field when built.

    A subclass names its config section: ``class ControlParams(_Section, section="control")``.
    """

    def __init_subclass__(cls, section: str, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if section in SECTIONS:
            raise TypeError(f"two classes for the section [{section}]")
        SECTIONS[section] = cls

    def __post_init__(self) -> None:
        types = _field_types(type(self))
        errors = []
        for f in dataclasses.fields(self):  # type: ignore[arg-type]
            value = getattr(self, f.name)
            try:
                clean = msgspec.convert(value, type=types[f.name], strict=True)
            except msgspec.ValidationError as exc:
                errors.append(_error_text(f"{_section_name(type(self))}.{f.name}", value, exc))
                continue
            if clean is not value:
                object.__setattr__(self, f.name, clean)
        if not errors:
            errors = self._relations()
        if errors:
            raise ParamError("; ".join(errors))

    def _relations(self) -> list[str]:
        """Errors of constraints between fields (none unless a section says so)."""
        return []
