"""Load the ARCHER MJCF by variant name and read the robot's parameters from it.

The MJCF files in ``robot_description/models/`` are the one source of the robot's physical parameters.
Controllers and estimators get them from :func:`robot_params`, never from constants of their own.

Variants:
- ``indoor`` (default): ``archer.xml``, about 5.9 kg, as flown indoors in the thesis.
- ``outdoor``: ``archer_outdoor.xml``, the indoor robot plus computer, batteries, shell and tennis
  ball, 8.25 kg; its welded payload parts are re-parented rigidly (see that file's header).
- ``sim15nm``: the indoor robot with the wheel torque limit of the thesis's MuJoCo simulations
  (15 N m instead of 1.5), read from the MJCF numeric ``sim15nm_wheel_torque_peak``.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

MODELS_DIR = Path(__file__).resolve().parents[1] / "robot_description" / "models"
VARIANT_FILES: dict[str, str] = {
    "indoor": "archer.xml",
    "outdoor": "archer_outdoor.xml",
    "sim15nm": "archer.xml",
}
VARIANTS = tuple(VARIANT_FILES)
DEFAULT_VARIANT = "indoor"

TORSO = "torso"
FOOT = "foot"
WHEEL_JOINTS = ("wheel_x", "wheel_y", "wheel_z")
WHEEL_ACTUATORS = ("wheel_x", "wheel_y", "wheel_z")
FOOT_JOINT = "foot_slide"
FOOT_MOTOR_JOINT = "foot_motor"
FOOT_ACTUATOR = "foot_motor"
CABLE_TENDON = "cable"
ROOT_JOINT = "root"
_PAYLOAD_FREEJOINT_SUFFIX = "_free"


def model_path(variant: str = DEFAULT_VARIANT) -> Path:
    if variant not in VARIANT_FILES:
        raise ValueError(f"unknown robot variant {variant!r}; known: {', '.join(VARIANTS)}")
    return MODELS_DIR / VARIANT_FILES[variant]


def _numeric(spec: mujoco.MjSpec, name: str) -> mujoco.MjsNumeric:
    for num in spec.numerics:
        if num.name == name:
            return num
    raise KeyError(f"MJCF numeric {name!r} missing")


def _fuse_welded_payload(spec: mujoco.MjSpec) -> None:
    """Re-parent every welded payload part rigidly into its carrier body (outdoor variant)."""
    spec.copy_during_attach = True
    for eq in list(spec.equalities):
        if eq.type != mujoco.mjtEq.mjEQ_WELD:
            continue
        carrier, part = spec.body(eq.name1), spec.body(eq.name2)
        joint = part.first_joint()
        if carrier is None or part is None or joint is None or not joint.name.endswith(_PAYLOAD_FREEJOINT_SUFFIX):
            raise ValueError(f"weld {eq.name!r} is not a payload mount (carrier, part with a free joint)")
        relpos, relquat = [float(v) for v in eq.data[3:6]], [float(v) for v in eq.data[6:10]]
        name = part.name
        spec.delete(joint)
        part.pos = relpos
        part.quat = relquat
        # An identity frame: MuJoCo writes the part as a plain child body, which Pinocchio reads.
        carrier.add_frame().attach_body(part, "", "_mounted")
        spec.delete(eq)
        spec.delete(part)
        spec.body(name + "_mounted").name = name
        for geom in spec.body(name).geoms:
            geom.name = geom.name.removesuffix("_mounted")


def load_spec(variant: str = DEFAULT_VARIANT) -> mujoco.MjSpec:
    """The editable model of ``variant`` (scenarios add their world to it before compiling)."""
    spec = mujoco.MjSpec.from_file(str(model_path(variant)))
    if variant == "outdoor":
        _fuse_welded_payload(spec)
    elif variant == "sim15nm":
        peak = float(_numeric(spec, "sim15nm_wheel_torque_peak").data[0])
        _numeric(spec, "wheel_torque_peak").data = [peak]
        for name in WHEEL_ACTUATORS:
            spec.actuator(name).ctrlrange = [-peak, peak]
    return spec


def load_model(variant: str = DEFAULT_VARIANT) -> mujoco.MjModel:
    return load_spec(variant).compile()


def pinocchio_xml(variant: str = DEFAULT_VARIANT) -> str:
    """MJCF text of ``variant`` as MuJoCo compiles it, for ``pinocchio.buildModelFromXML``."""
    spec = load_spec(variant)
    spec.compile()
    return spec.to_xml()


Vec3 = tuple[float, float, float]
Mat3 = tuple[Vec3, Vec3, Vec3]


@dataclass(frozen=True)
class RobotParams:
    """Physical parameters of one robot variant, read from its compiled MJCF.

    Frames: body = torso frame (origin at the torso's CoM, z up along the leg, x forward).
    Values at zero foot compression unless stated. SI units.
    """

    variant: str
    gravity: float  # [m/s^2], magnitude
    timestep: float  # physics step [s]
    total_mass: float  # [kg]
    foot_mass: float  # unsprung mass below the spring [kg]
    sprung_mass: float  # everything above the spring [kg]
    torso_mass: float  # [kg]
    torso_inertia: Mat3  # about the torso CoM, body frame [kg m^2]
    wheel_mass: float  # each [kg]
    wheel_spin_inertia: float  # about its spin axis [kg m^2]
    wheel_axes: Mat3  # row i: unit spin axis of wheel i in the body frame
    com_offset_body: Vec3  # whole-robot CoM relative to the torso origin, body frame [m]
    inertia_com: Mat3  # whole robot (wheels locked) about its CoM, body frame [kg m^2]
    leg_length: float  # torso origin to the foot's lowest point along -z, foot extended [m]
    footprint_radius: float  # largest horizontal reach of the robot's collision shapes from the spine [m]
    foot_radius: float  # radius of the foot's contact sphere [m]
    spring_stiffness: float  # [N/m]
    spring_damping: float  # [N s/m]
    foot_travel: float  # maximum compression [m]
    spool_radius: float  # cable spool radius: foot compression per spool angle [m/rad]
    spool_inertia: float  # reflected foot-motor rotor inertia at the spool [kg m^2]
    foot_gear_ratio: float  # foot motor gearbox ratio
    foot_torque_peak: float  # spool (gearbox output) torque limit [N m]
    wheel_torque_peak: float  # wheel drive peak torque [N m]
    wheel_speed_knee: float  # full torque available below this speed when driving [rad/s]
    wheel_no_load_speed: float  # no torque left when driving at this speed [rad/s]

    def wheel_torque_available(self, speed: float, torque: float) -> float:
        """Clip a wheel torque [N m] to what the motor delivers at ``speed`` [rad/s].

        Braking (torque against the speed) gets the full peak; driving falls linearly from the
        peak at ``wheel_speed_knee`` to zero at ``wheel_no_load_speed``.
        """
        peak = self.wheel_torque_peak
        if torque * speed > 0.0:
            s = abs(speed)
            if s > self.wheel_speed_knee:
                frac = (self.wheel_no_load_speed - s) / (self.wheel_no_load_speed - self.wheel_speed_knee)
                peak *= min(1.0, max(0.0, frac))
        return max(-peak, min(peak, torque))


def _mat3(a: np.ndarray) -> Mat3:
    a = np.asarray(a, dtype=float).reshape(3, 3)
    return tuple(tuple(float(v) for v in row) for row in a)  # type: ignore[return-value]


def _vec3(a: np.ndarray) -> Vec3:
    return tuple(float(v) for v in np.asarray(a, dtype=float).reshape(3))  # type: ignore[return-value]


def _numeric_value(model: mujoco.MjModel, name: str) -> float:
    nid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_NUMERIC, name)
    if nid < 0:
        raise KeyError(f"MJCF numeric {name!r} missing")
    return float(model.numeric_data[model.numeric_adr[nid]])


def _body_subtree(model: mujoco.MjModel, root: int) -> list[int]:
    return [b for b in range(model.nbody) if b == root or _is_descendant(model, b, root)]


def _is_descendant(model: mujoco.MjModel, body: int, root: int) -> bool:
    while body != 0:
        body = int(model.body_parentid[body])
        if body == root:
            return True
    return False


def params_from_model(model: mujoco.MjModel, variant: str) -> RobotParams:
    """Extract :class:`RobotParams` from a compiled model at its reference pose."""
    data = mujoco.MjData(model)
    data.qpos[:] = model.qpos0
    # Torso at the origin, upright: body-frame quantities read straight from world ones.
    root = model.joint(ROOT_JOINT)
    adr = int(root.qposadr[0])
    data.qpos[adr:adr + 7] = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
    mujoco.mj_forward(model, data)

    torso = model.body(TORSO).id
    foot = model.body(FOOT).id
    total_mass = float(model.body_subtreemass[torso])
    foot_mass = float(model.body_subtreemass[foot])
    com = data.subtree_com[torso].copy()

    # Composite inertia about the CoM (wheels counted as rigid bodies): parallel axis per body.
    inertia = np.zeros((3, 3))
    for b in _body_subtree(model, torso):
        m = float(model.body_mass[b])
        rot = data.ximat[b].reshape(3, 3)
        i_b = rot @ np.diag(model.body_inertia[b]) @ rot.T
        r = data.xipos[b] - com
        inertia += i_b + m * (float(r @ r) * np.eye(3) - np.outer(r, r))

    wheel_axes = []
    for name in WHEEL_JOINTS:
        j = model.joint(name)
        body = int(j.bodyid[0])
        wheel_axes.append(data.xmat[body].reshape(3, 3) @ j.axis)
    wheel_body = int(model.joint(WHEEL_JOINTS[0]).bodyid[0])
    wheel_inertia_local = model.body_inertia[wheel_body]
    spin_axis_local = model.joint(WHEEL_JOINTS[0]).axis
    wheel_spin_inertia = float(wheel_inertia_local @ np.abs(spin_axis_local))

    # Lowest foot contact point with the foot extended (spheres only: the foot's contact shapes).
    lowest = math.inf
    foot_radius = 0.0
    for g in range(model.ngeom):
        if model.geom_contype[g] == 0 and model.geom_conaffinity[g] == 0:
            continue
        body = int(model.geom_bodyid[g])
        if body != foot and not _is_descendant(model, body, foot):
            continue
        if model.geom_type[g] != mujoco.mjtGeom.mjGEOM_SPHERE:
            continue
        bottom = float(data.geom_xpos[g][2] - model.geom_size[g][0])
        if bottom < lowest:
            lowest, foot_radius = bottom, float(model.geom_size[g][0])
    if not math.isfinite(lowest):
        raise ValueError("model has no spherical foot contact geom")

    # Footprint: the horizontal reach of every collision geom of the robot (upright, spine at 0).
    footprint = 0.0
    robot_bodies = set(_body_subtree(model, torso))
    for g in range(model.ngeom):
        if int(model.geom_bodyid[g]) not in robot_bodies or (model.geom_contype[g] == 0 and model.geom_conaffinity[g] == 0):
            continue
        size = model.geom_size[g]
        if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX:
            rot = data.geom_xmat[g].reshape(3, 3)
            corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * size
            pts = data.geom_xpos[g] + corners @ rot.T
            reach = float(np.max(np.hypot(pts[:, 0], pts[:, 1])))
        else:  # sphere, capsule, cylinder: radius around its (vertical) axis
            reach = float(np.hypot(*data.geom_xpos[g][:2])) + float(size[0])
        footprint = max(footprint, reach)

    slide = model.joint(FOOT_JOINT)
    slide_dof = int(slide.dofadr[0])
    motor = model.joint(FOOT_MOTOR_JOINT)
    tendon = model.tendon(CABLE_TENDON)
    wrap = [(int(model.wrap_objid[model.tendon_adr[tendon.id] + k]), float(model.wrap_prm[model.tendon_adr[tendon.id] + k])) for k in range(int(model.tendon_num[tendon.id]))]
    coefs = {jid: coef for jid, coef in wrap}
    if coefs.get(slide.id) != 1.0 or motor.id not in coefs:
        raise ValueError("cable tendon must be foot_slide - r * foot_motor")

    return RobotParams(
        variant=variant,
        gravity=float(-model.opt.gravity[2]),
        timestep=float(model.opt.timestep),
        total_mass=total_mass,
        foot_mass=foot_mass,
        sprung_mass=total_mass - foot_mass,
        torso_mass=float(model.body_mass[torso]),
        torso_inertia=_mat3(data.ximat[torso].reshape(3, 3) @ np.diag(model.body_inertia[torso]) @ data.ximat[torso].reshape(3, 3).T),
        wheel_mass=float(model.body_subtreemass[wheel_body]),
        wheel_spin_inertia=wheel_spin_inertia,
        wheel_axes=_mat3(np.array(wheel_axes)),
        com_offset_body=_vec3(com - data.xpos[torso]),
        inertia_com=_mat3(inertia),
        leg_length=float(data.xpos[torso][2] - lowest),
        footprint_radius=footprint,
        foot_radius=foot_radius,
        spring_stiffness=float(model.jnt_stiffness[slide.id]),
        spring_damping=float(model.dof_damping[slide_dof]),
        foot_travel=float(model.jnt_range[slide.id][1] - model.jnt_range[slide.id][0]),
        spool_radius=-coefs[motor.id],
        spool_inertia=float(model.dof_armature[int(motor.dofadr[0])]),
        foot_gear_ratio=_numeric_value(model, "foot_gear_ratio"),
        foot_torque_peak=_numeric_value(model, "foot_torque_peak"),
        wheel_torque_peak=_numeric_value(model, "wheel_torque_peak"),
        wheel_speed_knee=_numeric_value(model, "wheel_speed_knee"),
        wheel_no_load_speed=_numeric_value(model, "wheel_no_load_speed"),
    )


@functools.lru_cache(maxsize=None)
def robot_params(variant: str = DEFAULT_VARIANT) -> RobotParams:
    """The parameters of ``variant`` (cached; the MJCF is compiled once)."""
    return params_from_model(load_model(variant), variant)
