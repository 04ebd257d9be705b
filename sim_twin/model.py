"""Compile the ARCHER MJCF with MuJoCo for the twin, by variant name.

The MJCF files in ``robot_description/models/`` are the one source of the robot's physical
parameters; :mod:`robot_description.params` reads them without MuJoCo (what controllers and
estimators use), and this module builds the physics from the same files, with the same
variant edits (see there).
"""

from __future__ import annotations

import mujoco

from robot_description.params import DEFAULT_VARIANT, FOOT_TOUCH_SENSOR, OUTDOOR_FOOT_CONTACT_SITE, PAYLOAD_FREEJOINT_SUFFIX, WHEEL_ACTUATORS, model_path


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
        if carrier is None or part is None or joint is None or not joint.name.endswith(PAYLOAD_FREEJOINT_SUFFIX):
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
        for element in (*spec.body(name).geoms, *spec.body(name).sites):
            element.name = element.name.removesuffix("_mounted")


def load_spec(variant: str = DEFAULT_VARIANT) -> mujoco.MjSpec:
    """The editable model of ``variant`` (scenarios add their world to it before compiling)."""
    spec = mujoco.MjSpec.from_file(str(model_path(variant)))
    if variant == "outdoor":
        _fuse_welded_payload(spec)
        spec.sensor(FOOT_TOUCH_SENSOR).objname = OUTDOOR_FOOT_CONTACT_SITE  # the tennis ball touches first
        _numeric(spec, "hop_speed_max").data = list(_numeric(spec, "outdoor_hop_speed_max").data)
    elif variant == "sim15nm":
        peak = float(_numeric(spec, "sim15nm_wheel_torque_peak").data[0])
        _numeric(spec, "wheel_torque_peak").data = [peak]
        for curve in ("wheel_speed_knee", "wheel_no_load_speed"):
            _numeric(spec, curve).data = list(_numeric(spec, f"sim15nm_{curve}").data)
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
