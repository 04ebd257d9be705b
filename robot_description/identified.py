"""An identified robot: what ``archer identify`` measured, as overrides of the MJCF's values.

One TOML file serves both sides:

- ``[identified]``: each parameter's value and 1-sigma (``[identified.NAME]`` with ``value``,
  ``sigma``, ``unit``; a list per wheel for wheel parameters), and what it was fitted from. The
  stack reads it through :func:`apply`: the CoM offset moves ``RobotParams.com_offset_body``
  (the estimator's CoM). The wheels' torque constant and drag are the twin's to use; the stack's
  model has no wheel friction.
- ``[factors]``: the same values as a model-error profile of fixed values
  (:mod:`sim_twin.model_error`), so that ``archer sim --model-error FILE`` builds the twin as identified.

Names and units are the model-error factors' (``com_x`` [m], ``wheel_viscous`` [N m s/rad],
``wheel_coulomb`` [N m], ``wheel_torque_constant`` relative: 0.02 is 2 % above the MJCF's).
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

from robot_description import params as rd
from robot_description.params import RobotParams

SECTION = "identified"
PROFILE_SECTION = "factors"
COM_NAMES = ("com_x", "com_y", "com_z")


@dataclass(frozen=True)
class Parameter:
    values: tuple[float, ...]  # one, or one per wheel
    sigmas: tuple[float, ...]  # 1-sigma, same unit
    unit: str = ""


def _fmt(v: float) -> str:
    return repr(float(f"{v:.6g}"))


def dumps(params: dict[str, Parameter], meta: dict[str, str | int | float]) -> str:
    """The file's text (written by ``archer identify``)."""
    lines = ["# archer identify: fitted parameters, value and 1-sigma (robot_description/identified.py).",
             "# [factors]: the same values as a twin profile: archer sim --model-error THIS_FILE", f"[{SECTION}]"]
    for key, v in meta.items():
        lines.append(f"{key} = {v!r}" if not isinstance(v, str) else f'{key} = "{v}"')
    for name, p in params.items():
        one = len(p.values) == 1
        value = _fmt(p.values[0]) if one else "[" + ", ".join(_fmt(v) for v in p.values) + "]"
        sigma = _fmt(p.sigmas[0]) if one else "[" + ", ".join(_fmt(v) for v in p.sigmas) + "]"
        lines += ["", f"[{SECTION}.{name}]", f"value = {value}", f"sigma = {sigma}", f'unit = "{p.unit}"']
    lines += ["", f"[{PROFILE_SECTION}]"]
    for name, p in params.items():
        value = _fmt(p.values[0]) if len(p.values) == 1 else "[" + ", ".join(_fmt(v) for v in p.values) + "]"
        lines.append(f"{name} = {value}")
    return "\n".join(lines) + "\n"


def load(path: str | Path) -> dict[str, Parameter]:
    """The identified parameters of a file :func:`dumps` wrote; a clear error on anything else."""
    with open(path, "rb") as f:
        doc = tomllib.load(f)
    table = doc.get(SECTION)
    if not isinstance(table, dict):
        raise ValueError(f"{path}: no [{SECTION}] table (write it with archer identify)")
    out: dict[str, Parameter] = {}
    for name, entry in table.items():
        if not isinstance(entry, dict):
            continue  # what it was fitted from
        values, sigmas = entry.get("value"), entry.get("sigma")
        values = tuple(values) if isinstance(values, list) else (values,)
        sigmas = tuple(sigmas) if isinstance(sigmas, list) else (sigmas,)
        if len(values) != len(sigmas) or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values + sigmas):
            raise ValueError(f"{path}: [{SECTION}.{name}] needs finite value and sigma of the same length")
        out[name] = Parameter(tuple(float(v) for v in values), tuple(float(v) for v in sigmas), str(entry.get("unit", "")))
    return out


def robot_params(variant: str, path: str = "") -> RobotParams:
    """The variant's parameters, as identified in ``path`` ("": the MJCF's): what the estimator reads
    (``[estimator] identified``)."""
    robot = rd.robot_params(variant)
    return apply(robot, load(path)) if path else robot


def apply(robot: RobotParams, params: dict[str, Parameter]) -> RobotParams:
    """``robot`` as identified: the CoM moved by the identified offset (body frame)."""
    shift = [params[n].values[0] if n in params else 0.0 for n in COM_NAMES]
    if not any(shift):
        return robot
    com = tuple(c + s for c, s in zip(robot.com_offset_body, shift))
    return dataclasses.replace(robot, com_offset_body=com)  # type: ignore[arg-type]
