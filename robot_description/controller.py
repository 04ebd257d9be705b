"""The onboard low level configured for this robot: the one place where the MJCF's numbers
meet :mod:`onboard.low_level.controller`, so that the control service, the lockstep runner, the bench
and the trainer build the very same controller."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from onboard.low_level.planning.geometric_mpc import GeometricMpc
from onboard.low_level.planning.gmpc_mid_level import GmpcMidLevel
from onboard.low_level.controller import LowLevelController, design_policy
from onboard.contracts.params import ControlParams, GeometricMpcParams, SafetyLimits
from robot_description import identified
from robot_description.hopper_dynamics import HopperDynamics
from robot_description.params import DEFAULT_VARIANT, hopper_model, robot_params

DATA_DIR = Path(__file__).resolve().parents[1] / "onboard" / "data"


def load_policy_weights(name: str) -> dict[str, np.ndarray]:
    """Read an MLP weights file (``.npz``) from ``onboard/data/`` (or a path)."""
    path = Path(name)
    if not path.is_absolute() and not path.exists():
        path = DATA_DIR / name
    with np.load(path) as f:
        return {k: f[k] for k in f.files}


def build_controller(
    variant: str = DEFAULT_VARIANT,
    params: ControlParams | None = None,
    safety: SafetyLimits | None = None,
) -> LowLevelController:
    """The low level for robot ``variant`` with its parameters read from the MJCF (and the CoM's
    offset from ``params.identified``, archer identify's file, where one is given)."""
    params = params or ControlParams()
    weights = load_policy_weights(params.mlp_weights) if params.policy == "mlp" else None
    return LowLevelController(params, identified.robot_params(variant, params.identified), hopper_model(variant), safety, weights)


def build_gmpc_mid_level(
    variant: str = DEFAULT_VARIANT,
    params: GeometricMpcParams | None = None,
    control: ControlParams | None = None,
    safety: SafetyLimits | None = None,
) -> GmpcMidLevel:
    """The geometric MPC mid level for robot ``variant``: Pinocchio dynamics from the same MJCF,
    the input set the wheels' torque limit (the safety limit, capped at the drive's peak)."""
    params = params or GeometricMpcParams()
    control = control or ControlParams()
    safety = safety or SafetyLimits()
    robot, hopper = robot_params(variant), hopper_model(variant)
    dynamics = HopperDynamics(variant)
    limit = min(safety.wheel_torque_max, robot.wheel_torque_peak)
    touchdown = hopper.touchdown_height(design_policy(control, hopper).preload_nominal)
    stance_omega = (robot.spring_stiffness / robot.sprung_mass) ** 0.5
    return GmpcMidLevel(GeometricMpc(dynamics, params, limit), dynamics.com_offset, params, control, touchdown, stance_omega,
                        robot.gravity)
