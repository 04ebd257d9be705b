"""The onboard low level configured for this robot: the one place where the MJCF's numbers
meet :mod:`onboard.low_level`, so that the control service, the lockstep runner, the bench
and the trainer build the very same controller."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from onboard.low_level import LowLevelController
from onboard.params import ControlParams, SafetyLimits
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
    """The low level for robot ``variant`` with its parameters read from the MJCF."""
    params = params or ControlParams()
    weights = load_policy_weights(params.mlp_weights) if params.policy == "mlp" else None
    return LowLevelController(params, robot_params(variant), hopper_model(variant), safety, weights)
