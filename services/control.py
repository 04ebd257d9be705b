"""The ``control`` service: the 1 kHz low level (issue 4).

Builds the :class:`onboard.low_level.LowLevelController` from the MJCF
(:func:`build_controller`, also used by the lockstep runner).
"""

from __future__ import annotations

import functools
from pathlib import Path

import mujoco
import numpy as np

from onboard import zdp
from onboard.low_level import LowLevelController
from onboard.params import ControlParams, SafetyLimits
from sim_twin import model as twin_model

DATA_DIR = Path(__file__).resolve().parent.parent / "onboard" / "data"


@functools.lru_cache(maxsize=None)
def hopper_model(variant: str = twin_model.DEFAULT_VARIANT) -> zdp.HopperModel:
    """The reduced hopper of :mod:`onboard.zdp`, read from the compiled MJCF.

    Uses :func:`sim_twin.model.robot_params` for what it provides and the compiled
    model for the split into sprung body and foot (the reduced stance model needs
    the sprung body's own inertia and the foot's, which ``RobotParams`` lumps).
    """
    robot = twin_model.robot_params(variant)
    model = twin_model.load_model(variant)
    data = mujoco.MjData(model)
    data.qpos[:] = model.qpos0
    adr = int(model.joint(twin_model.ROOT_JOINT).qposadr[0])
    data.qpos[adr:adr + 7] = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]  # torso upright at the origin
    mujoco.mj_forward(model, data)
    torso = model.body(twin_model.TORSO).id
    foot = model.body(twin_model.FOOT).id

    def in_subtree(b: int, root: int) -> bool:
        while b > 0:
            if b == root:
                return True
            b = int(model.body_parentid[b])
        return False

    robot_bodies = [b for b in range(model.nbody) if in_subtree(b, torso)]
    foot_bodies = [b for b in robot_bodies if in_subtree(b, foot)]
    sprung_bodies = [b for b in robot_bodies if b not in foot_bodies]

    def composite(bodies: list[int], about: np.ndarray) -> np.ndarray:
        inertia = np.zeros((3, 3))
        for b in bodies:
            rot = data.ximat[b].reshape(3, 3)
            r = data.xipos[b] - about
            inertia += rot @ np.diag(model.body_inertia[b]) @ rot.T + model.body_mass[b] * (r @ r * np.eye(3) - np.outer(r, r))
        return inertia

    def com(bodies: list[int]) -> tuple[float, np.ndarray]:
        m = float(sum(model.body_mass[b] for b in bodies))
        return m, sum(model.body_mass[b] * data.xipos[b] for b in bodies) / m

    m_s, c_s = com(sprung_bodies)
    m_f, c_f = com(foot_bodies)
    pivot_z = -(robot.leg_length - robot.foot_radius)  # contact sphere centre, torso frame
    i_s = composite(sprung_bodies, c_s)
    i_f = composite(foot_bodies, np.array([0.0, 0.0, pivot_z]))
    return zdp.HopperModel(
        mass_sprung=m_s,
        mass_foot=m_f,
        inertia_sprung=0.5 * float(i_s[0, 0] + i_s[1, 1]),
        inertia_foot=0.5 * float(i_f[0, 0] + i_f[1, 1]),
        spring_k=robot.spring_stiffness,
        spring_damping=robot.spring_damping,
        leg_rest=float(c_s[2] - pivot_z),
        foot_com=float(c_f[2] - pivot_z),
        foot_radius=robot.foot_radius,
        travel=robot.foot_travel,
        gravity=robot.gravity,
    )


def load_policy_weights(name: str) -> dict[str, np.ndarray]:
    """Read an MLP weights file (``.npz``) from ``onboard/data/`` (or a path)."""
    path = Path(name)
    if not path.is_absolute() and not path.exists():
        path = DATA_DIR / name
    with np.load(path) as f:
        return {k: f[k] for k in f.files}


def build_controller(
    variant: str = twin_model.DEFAULT_VARIANT,
    params: ControlParams | None = None,
    safety: SafetyLimits | None = None,
) -> LowLevelController:
    """The low level for robot ``variant`` with its parameters read from the MJCF."""
    params = params or ControlParams()
    weights = load_policy_weights(params.mlp_weights) if params.policy == "mlp" else None
    return LowLevelController(params, twin_model.robot_params(variant), hopper_model(variant), safety, weights)
