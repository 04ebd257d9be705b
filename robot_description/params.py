"""ARCHER's physical parameters, read from its MJCF by variant name without MuJoCo.

The MJCF files in ``robot_description/models/`` are the one source of the robot's physical
parameters. Controllers and estimators get them from :func:`robot_params` (and the reduced
hopper of :mod:`onboard.low_level.planning.zdp` from :func:`hopper_model`), never from constants of their own.
The robot's services run this module; the simulator compiles the same files with MuJoCo
(:mod:`sim_twin.model`), and ``tests/test_robot_description.py`` holds both readings equal.

How: the XML is flattened (includes inlined, the variant's edits applied) and handed to
Pinocchio for the kinematic tree (placements, masses, inertias, joint axes, armature, limits);
what Pinocchio does not carry (collision shapes, spring stiffness and damping, the cable
tendon, the physics options, the custom numerics) is read from the XML itself.

Variants:
- ``indoor`` (default): ``archer.xml``, about 5.9 kg, as flown indoors in the thesis.
- ``outdoor``: ``archer_outdoor.xml``, the indoor robot plus computer, batteries, shell and tennis
  ball, 8.25 kg; its welded payload parts are re-parented rigidly (see that file's header).
- ``sim15nm``: the indoor robot with the wheel torque limit of the thesis's MuJoCo simulations
  (15 N m instead of 1.5), read from the MJCF numeric ``sim15nm_wheel_torque_peak``, and the
  wheels' speed curve moved out to ``sim15nm_wheel_speed_knee`` / ``..._no_load_speed`` (the
  thesis names torque limits only; its flip spins the wheels past what the KV115 reaches).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin

from onboard.low_level.planning import zdp
from onboard.contracts.params import PlannerParams, SafetyLimits, with_overrides

MODELS_DIR = Path(__file__).resolve().parent / "models"
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
FOOT_TOUCH_SENSOR = "foot_force"
OUTDOOR_FOOT_CONTACT_SITE = "tennis_ball_contact"  # the outdoor foot meets the ground with its tennis ball
PAYLOAD_FREEJOINT_SUFFIX = "_free"


def model_path(variant: str = DEFAULT_VARIANT) -> Path:
    if variant not in VARIANT_FILES:
        raise ValueError(f"unknown robot variant {variant!r}; known: {', '.join(VARIANTS)}")
    return MODELS_DIR / VARIANT_FILES[variant]


Vec3 = tuple[float, float, float]
Mat3 = tuple[Vec3, Vec3, Vec3]


@dataclass(frozen=True)
class RobotParams:
    """Physical parameters of one robot variant, read from its MJCF.

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
    hop_speed_max: float  # CoM speed it sustains hopping [m/s]; faster, the wheels saturate (MJCF numeric)

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


# --- the MJCF as XML ------------------------------------------------------------------------------


def _floats(text: str) -> np.ndarray:
    return np.array([float(v) for v in text.split()])


def _inline_includes(root: ET.Element, directory: Path) -> None:
    """Replace each ``<include file=...>`` by the children of the included file's root (MJCF rule)."""
    for parent in list(root.iter()):
        for i, child in enumerate(list(parent)):
            if child.tag == "include":
                included = ET.parse(directory / child.get("file")).getroot()
                _inline_includes(included, directory)
                parent.remove(child)
                for k, grandchild in enumerate(included):
                    parent.insert(i + k, grandchild)
    worldbodies = root.findall("worldbody")
    for extra in worldbodies[1:]:  # sections of the same kind merge (Pinocchio reads the first only)
        worldbodies[0].extend(list(extra))
        root.remove(extra)


def _fuse_welded_payload(root: ET.Element) -> None:
    """Re-parent every welded payload part rigidly into its carrier body (outdoor variant).

    The part takes the weld's relpose as its pose in the carrier and loses its free joint, as
    ``sim_twin.model.load_spec`` does with MuJoCo's model editor.
    """
    bodies = {b.get("name"): b for b in root.iter("body")}
    parents = {child: parent for parent in root.iter() for child in parent}
    for equality in root.findall("equality"):
        for weld in equality.findall("weld"):
            carrier, part = bodies.get(weld.get("body1")), bodies.get(weld.get("body2"))
            joint = part.find("freejoint") if part is not None else None
            if carrier is None or joint is None or not joint.get("name", "").endswith(PAYLOAD_FREEJOINT_SUFFIX):
                raise ValueError(f"weld {weld.get('name')!r} is not a payload mount (carrier, part with a free joint)")
            relpose = weld.get("relpose").split()
            part.remove(joint)
            part.set("pos", " ".join(relpose[:3]))
            part.set("quat", " ".join(relpose[3:7]))
            parents[part].remove(part)
            carrier.append(part)
            equality.remove(weld)


def _numerics(root: ET.Element) -> dict[str, ET.Element]:
    return {n.get("name"): n for n in root.iter("numeric")}


def load_xml(variant: str = DEFAULT_VARIANT) -> ET.Element:
    """The MJCF of ``variant`` as one XML tree, with the variant's edits applied."""
    path = model_path(variant)
    root = ET.parse(path).getroot()
    _inline_includes(root, path.parent)
    if variant == "outdoor":
        _fuse_welded_payload(root)
        numerics = _numerics(root)
        numerics["hop_speed_max"].set("data", numerics["outdoor_hop_speed_max"].get("data"))
    elif variant == "sim15nm":
        numerics = _numerics(root)
        peak = numerics["sim15nm_wheel_torque_peak"].get("data")
        numerics["wheel_torque_peak"].set("data", peak)
        for curve in ("wheel_speed_knee", "wheel_no_load_speed"):
            numerics[curve].set("data", numerics[f"sim15nm_{curve}"].get("data"))
        for motor in root.iter("motor"):
            if motor.get("name") in WHEEL_ACTUATORS:
                motor.set("ctrlrange", f"-{peak} {peak}")
    return root


class _Defaults:
    """MJCF default classes: an element's attributes over its class's, over the parent classes'."""

    def __init__(self, root: ET.Element) -> None:
        self.classes: dict[str, dict[str, dict[str, str]]] = {}
        for top in root.findall("default"):
            self._read(top, {})

    def _read(self, node: ET.Element, inherited: dict[str, dict[str, str]]) -> None:
        mine = {tag: dict(attrs) for tag, attrs in inherited.items()}
        for child in node:
            if child.tag != "default":
                mine.setdefault(child.tag, {}).update(child.attrib)
        self.classes[node.get("class", "main")] = mine
        for child in node.findall("default"):
            self._read(child, mine)

    def attrs(self, element: ET.Element, childclass: str | None) -> dict[str, str]:
        cls = element.get("class") or childclass or "main"
        return {**self.classes.get(cls, {}).get(element.tag, {}), **element.attrib}


def _walk_bodies(node: ET.Element, childclass: str | None = None):
    """(body, childclass in force) for every body under ``node``, parents first."""
    for body in node.findall("body"):
        cls = body.get("childclass") or childclass
        yield body, cls
        yield from _walk_bodies(body, cls)


def _quat_matrix(wxyz: np.ndarray) -> np.ndarray:
    """Rotation of a unit quaternion, computed as MuJoCo does (mju_normalize4, mju_quat2Mat), so that
    round-off matches the twin's bit for bit (an exact 0 in the wheel axes stays exactly 0)."""
    norm = math.sqrt(float(wxyz @ wxyz))
    q = wxyz / norm if abs(norm - 1.0) > 1e-15 else wxyz
    w, x, y, z = (float(v) for v in q)
    return np.array([
        [w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z],
    ])


def _geom_pose(attrs: dict[str, str]) -> tuple[np.ndarray, np.ndarray]:
    """Centre and orientation of a geom in its body frame (pos/quat or fromto; no other forms)."""
    if "fromto" in attrs:
        ends = _floats(attrs["fromto"])
        a, b = ends[:3], ends[3:]
        axis = b - a
        if abs(axis[0]) > 1e-12 or abs(axis[1]) > 1e-12:
            raise ValueError("only vertical fromto geoms are read here")  # their reach needs no rotation
        return 0.5 * (a + b), np.eye(3)
    for form in ("euler", "axisangle", "xyaxes", "zaxis"):
        if form in attrs:
            raise ValueError(f"geom orientation by {form!r} is not read here: use quat")
    pos = _floats(attrs.get("pos", "0 0 0"))
    rot = _quat_matrix(_floats(attrs["quat"])) if "quat" in attrs else np.eye(3)
    return pos, rot


def _collides(attrs: dict[str, str]) -> bool:
    return int(attrs.get("contype", "1")) != 0 or int(attrs.get("conaffinity", "1")) != 0


# --- the tree, through Pinocchio ------------------------------------------------------------------


@dataclass(frozen=True)
class _Robot:
    xml: ET.Element
    model: pin.Model
    data: pin.Data  # at the neutral configuration: torso at the origin, upright, foot extended

    def body_placement(self, name: str) -> pin.SE3:
        return self.data.oMf[self.model.getFrameId(name, pin.BODY)]

    def joint_id(self, name: str) -> int:
        jid = self.model.getJointId(name)
        if jid >= self.model.njoints:
            raise KeyError(f"MJCF joint {name!r} missing")
        return jid

    def subtree(self, joint: int) -> list[int]:
        return [j for j in range(1, self.model.njoints) if joint in self.model.supports[j]]

    def inertia(self, joints: list[int]) -> pin.Inertia:
        """Everything the joints carry, in the world (= torso) frame."""
        total = pin.Inertia.Zero()
        for j in joints:
            total += self.data.oMi[j].act(self.model.inertias[j])
        return total


@functools.lru_cache(maxsize=None)
def _robot(variant: str) -> _Robot:
    xml = load_xml(variant)
    with tempfile.TemporaryDirectory() as tmp:  # Pinocchio's MJCF parser reads files only
        path = Path(tmp) / "robot.xml"
        ET.ElementTree(xml).write(path)
        model = pin.buildModelFromMJCF(str(path))
    data = model.createData()
    pin.forwardKinematics(model, data, pin.neutral(model))
    pin.updateFramePlacements(model, data)
    return _Robot(xml, model, data)


def _composite_about(inertia: pin.Inertia, point: np.ndarray) -> np.ndarray:
    r = inertia.lever - point
    return inertia.inertia + inertia.mass * (float(r @ r) * np.eye(3) - np.outer(r, r))


def _mat3(a: np.ndarray) -> Mat3:
    a = np.asarray(a, dtype=float).reshape(3, 3)
    return tuple(tuple(float(v) for v in row) for row in a)  # type: ignore[return-value]


def _vec3(a: np.ndarray) -> Vec3:
    return tuple(float(v) for v in np.asarray(a, dtype=float).reshape(3))  # type: ignore[return-value]


def _numeric_value(xml: ET.Element, name: str) -> float:
    numeric = _numerics(xml).get(name)
    if numeric is None:
        raise KeyError(f"MJCF numeric {name!r} missing")
    return float(numeric.get("data").split()[0])


def _named(xml: ET.Element, tag: str, name: str, defaults: _Defaults) -> dict[str, str]:
    for body, cls in [(xml, None), *_walk_bodies(xml.find("worldbody"))]:
        for element in body.findall(tag):
            if element.get("name") == name:
                return defaults.attrs(element, cls)
    raise KeyError(f"MJCF {tag} {name!r} missing")


def _option(xml: ET.Element) -> tuple[float, float]:
    """(gravity magnitude, timestep) with MuJoCo's defaults for what the file leaves out."""
    option = xml.find("option")
    attrs = option.attrib if option is not None else {}
    return -float(_floats(attrs.get("gravity", "0 0 -9.81"))[2]), float(attrs.get("timestep", "0.002"))


@functools.lru_cache(maxsize=None)
def robot_params(variant: str = DEFAULT_VARIANT) -> RobotParams:
    """The parameters of ``variant`` at its reference pose (cached; the MJCF is read once)."""
    r = _robot(variant)
    xml, model, data = r.xml, r.model, r.data
    defaults = _Defaults(xml)
    root, foot = r.joint_id(ROOT_JOINT), r.joint_id(FOOT_JOINT)
    whole = r.inertia(r.subtree(root))
    foot_part = r.inertia(r.subtree(foot))
    com = whole.lever
    torso_at = r.body_placement(TORSO).translation

    torso_body = next(b for b, _ in _walk_bodies(xml.find("worldbody")) if b.get("name") == TORSO)
    inertial = torso_body.find("inertial")
    rot = _quat_matrix(_floats(inertial.get("quat"))) if "quat" in inertial.attrib else np.eye(3)
    torso_inertia = rot @ np.diag(_floats(inertial.get("diaginertia"))) @ rot.T

    wheels = [r.joint_id(name) for name in WHEEL_JOINTS]
    # Each wheel body hangs off the torso, which is upright at the origin: its rotation is its own quat.
    wheel_axes = []
    for name in WHEEL_JOINTS:
        body = next(b for b, _ in _walk_bodies(torso_body) if b.find("joint") is not None and b.find("joint").get("name") == name)
        joint = _named(xml, "joint", name, defaults)
        axis = _floats(joint.get("axis", "0 0 1"))
        rot = _quat_matrix(_floats(body.get("quat"))) if "quat" in body.attrib else np.eye(3)
        wheel_axes.append(rot @ (axis / np.linalg.norm(axis)))
    wheel = r.inertia(wheels[:1])
    # About the spin axis, from the principal moments the file states (as MuJoCo reads them).
    wheel_body = next(b for b, _ in _walk_bodies(torso_body) if b.find("joint") is not None and b.find("joint").get("name") == WHEEL_JOINTS[0])
    wheel_inertial = wheel_body.find("inertial")
    if "quat" in wheel_inertial.attrib:
        raise ValueError("a wheel's inertial must be principal in its body frame")
    spin_local = _floats(_named(xml, "joint", WHEEL_JOINTS[0], defaults).get("axis", "0 0 1"))
    wheel_spin_inertia = float(_floats(wheel_inertial.get("diaginertia")) @ np.abs(spin_local / np.linalg.norm(spin_local)))

    # Collision geoms of the robot (every body under the torso), with their world poses.
    collision: list[tuple[dict[str, str], np.ndarray, np.ndarray, bool]] = []  # attrs, centre, rotation, on the foot
    foot_bodies = set()
    for body, cls in _walk_bodies(xml.find("worldbody")):
        placement = r.body_placement(body.get("name"))
        frame = model.frames[model.getFrameId(body.get("name"), pin.BODY)]
        on_foot = foot in model.supports[frame.parentJoint]
        if on_foot:
            foot_bodies.add(body.get("name"))
        for geom in body.findall("geom"):
            attrs = defaults.attrs(geom, cls)
            if not _collides(attrs):
                continue
            centre, grot = _geom_pose(attrs)
            collision.append((attrs, placement.act(centre), placement.rotation @ grot, on_foot))

    # Lowest foot contact point with the foot extended (spheres only: the foot's contact shapes).
    lowest, foot_radius = math.inf, 0.0
    for attrs, centre, _, on_foot in collision:
        if on_foot and attrs.get("type", "sphere") == "sphere":
            radius = float(_floats(attrs["size"])[0])
            if centre[2] - radius < lowest:
                lowest, foot_radius = float(centre[2] - radius), radius
    if not math.isfinite(lowest):
        raise ValueError("model has no spherical foot contact geom")

    # Footprint: the horizontal reach of every collision geom of the robot (upright, spine at 0).
    footprint = 0.0
    for attrs, centre, grot, _ in collision:
        size = _floats(attrs["size"])
        if attrs.get("type", "sphere") == "box":
            corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * size
            pts = centre + corners @ grot.T
            reach = float(np.max(np.hypot(pts[:, 0], pts[:, 1])))
        else:  # sphere, capsule, cylinder: radius around its (vertical) axis
            reach = float(np.hypot(*centre[:2])) + float(size[0])
        footprint = max(footprint, reach)

    slide = _named(xml, "joint", FOOT_JOINT, defaults)
    motor = r.joint_id(FOOT_MOTOR_JOINT)
    tendon = next((t for t in xml.iter("fixed") if t.get("name") == CABLE_TENDON), None)
    if tendon is None:
        raise KeyError(f"MJCF tendon {CABLE_TENDON!r} missing")
    coefs = {j.get("joint"): float(j.get("coef")) for j in tendon.findall("joint")}
    if coefs.get(FOOT_JOINT) != 1.0 or FOOT_MOTOR_JOINT not in coefs:
        raise ValueError("cable tendon must be foot_slide - r * foot_motor")
    gravity, timestep = _option(xml)
    slide_q = model.joints[foot].idx_q

    return RobotParams(
        variant=variant,
        gravity=gravity,
        timestep=timestep,
        total_mass=float(whole.mass),
        foot_mass=float(foot_part.mass),
        sprung_mass=float(whole.mass - foot_part.mass),
        torso_mass=float(inertial.get("mass")),
        torso_inertia=_mat3(torso_inertia),
        wheel_mass=float(wheel.mass),
        wheel_spin_inertia=wheel_spin_inertia,
        wheel_axes=_mat3(np.array(wheel_axes)),
        com_offset_body=_vec3(com - torso_at),
        inertia_com=_mat3(_composite_about(whole, com)),
        leg_length=float(torso_at[2] - lowest),
        footprint_radius=footprint,
        foot_radius=foot_radius,
        spring_stiffness=float(slide.get("stiffness", "0")),
        spring_damping=float(slide.get("damping", "0")),
        foot_travel=float(model.upperPositionLimit[slide_q] - model.lowerPositionLimit[slide_q]),
        spool_radius=-coefs[FOOT_MOTOR_JOINT],
        spool_inertia=float(model.armature[model.joints[motor].idx_v]),
        foot_gear_ratio=_numeric_value(xml, "foot_gear_ratio"),
        foot_torque_peak=_numeric_value(xml, "foot_torque_peak"),
        wheel_torque_peak=_numeric_value(xml, "wheel_torque_peak"),
        wheel_speed_knee=_numeric_value(xml, "wheel_speed_knee"),
        wheel_no_load_speed=_numeric_value(xml, "wheel_no_load_speed"),
        hop_speed_max=_numeric_value(xml, "hop_speed_max"),
    )


def safety_limits_for(safety: SafetyLimits, robot: RobotParams) -> SafetyLimits:
    """The safety limits ``robot`` runs under: ``sim15nm`` with the thesis's raised wheel torque
    limit (its drive's peak) and its wheels' speed up to the knee of their curve, every other
    variant as given."""
    if robot.variant == "sim15nm":
        return with_overrides(safety, {"wheel_torque_max": robot.wheel_torque_peak, "wheel_speed_max": robot.wheel_speed_knee})
    return safety


def planner_params_for(params: PlannerParams, robot: RobotParams) -> PlannerParams:
    """The planner's bounds within what ``robot`` does: its speed bound at most the robot's
    sustained hopping speed (``hop_speed_max``; faster, the wheels saturate)."""
    if params.v_max <= robot.hop_speed_max:
        return params
    return dataclasses.replace(params, v_max=robot.hop_speed_max)


@functools.lru_cache(maxsize=None)
def hopper_model(variant: str = DEFAULT_VARIANT) -> zdp.HopperModel:
    """The reduced hopper of :mod:`onboard.low_level.planning.zdp`: the sprung body and the foot apart.

    :class:`RobotParams` gives what it holds; the reduced stance model also needs the sprung
    body's own inertia and the foot's, which ``RobotParams`` lumps.
    """
    robot = robot_params(variant)
    r = _robot(variant)
    foot = r.joint_id(FOOT_JOINT)
    foot_joints = r.subtree(foot)
    sprung = r.inertia([j for j in r.subtree(r.joint_id(ROOT_JOINT)) if j not in foot_joints])
    unsprung = r.inertia(foot_joints)
    pivot_z = -(robot.leg_length - robot.foot_radius)  # contact sphere centre, torso frame
    i_s = _composite_about(sprung, sprung.lever)
    i_f = _composite_about(unsprung, np.array([0.0, 0.0, pivot_z]))
    return zdp.HopperModel(
        mass_sprung=float(sprung.mass),
        mass_foot=float(unsprung.mass),
        inertia_sprung=0.5 * float(i_s[0, 0] + i_s[1, 1]),
        inertia_foot=0.5 * float(i_f[0, 0] + i_f[1, 1]),
        spring_k=robot.spring_stiffness,
        spring_damping=robot.spring_damping,
        leg_rest=float(sprung.lever[2] - pivot_z),
        foot_com=float(unsprung.lever[2] - pivot_z),
        foot_radius=robot.foot_radius,
        travel=robot.foot_travel,
        gravity=robot.gravity,
    )


@dataclass(frozen=True)
class BodyShape:
    """One geom of the robot, for drawing it (``body_shapes``): torso frame, zero compression."""

    name: str
    kind: str  # MJCF geom type: "sphere", "capsule", "cylinder" or "box"
    size: tuple[float, ...]  # MJCF size: radius (, half-length or half-height) or box half-sizes [m]
    pos: Vec3  # centre in the torso frame [m]
    quat: tuple[float, float, float, float]  # orientation in the torso frame [w, x, y, z]; the geom's own z is its axis
    rgba: tuple[float, float, float, float]
    on_foot: bool  # moves with the foot: up by the compression along ``BodyGeometry.foot_axis``


@dataclass(frozen=True)
class BodyGeometry:
    shapes: tuple[BodyShape, ...]
    foot_axis: Vec3  # compression direction of the foot in the torso frame (unit)


_DRAWN_GEOMS = ("sphere", "capsule", "cylinder", "box")


def _euler_xyz(angles: np.ndarray) -> np.ndarray:
    """MuJoCo's default ``eulerseq="xyz"`` (intrinsic, radians, as ``compiler angle="radian"``)."""
    out = np.eye(3)
    for axis, a in zip(range(3), angles):
        c, s = math.cos(a), math.sin(a)
        r = np.eye(3)
        i, j = (axis + 1) % 3, (axis + 2) % 3  # cyclic, so that each is a right-handed rotation
        r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
        out = out @ r
    return out


def _mat_quat(rot: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion [w, x, y, z] of a rotation matrix (Shepperd's method)."""
    m = rot
    tr = float(m[0, 0] + m[1, 1] + m[2, 2])
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = (0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s)
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        v = [0.0, 0.0, 0.0]
        v[i] = 0.25 * s
        v[j] = (m[j, i] + m[i, j]) / s
        v[k] = (m[k, i] + m[i, k]) / s
        q = ((m[k, j] - m[j, k]) / s, *v)
    return tuple(float(x) for x in q)  # type: ignore[return-value]


@functools.lru_cache(maxsize=None)
def body_shapes(variant: str = DEFAULT_VARIANT) -> BodyGeometry:
    """Every drawable geom of the robot (collision and visual) in the torso frame, foot extended.

    For viewers (``archer view``): read from the same MJCF as :func:`robot_params`, without MuJoCo.
    """
    r = _robot(variant)
    xml, model = r.xml, r.model
    defaults = _Defaults(xml)
    foot = r.joint_id(FOOT_JOINT)
    torso_inv = r.body_placement(TORSO).inverse()
    shapes = []
    for body, cls in _walk_bodies(xml.find("worldbody")):
        placement = torso_inv * r.body_placement(body.get("name"))
        frame = model.frames[model.getFrameId(body.get("name"), pin.BODY)]
        on_foot = foot in model.supports[frame.parentJoint]
        for i, geom in enumerate(body.findall("geom")):
            attrs = defaults.attrs(geom, cls)
            kind = attrs.get("type", "sphere")
            if kind not in _DRAWN_GEOMS:
                raise ValueError(f"geom {geom.get('name')!r} of type {kind!r} cannot be drawn (only {', '.join(_DRAWN_GEOMS)})")
            size = _floats(attrs["size"])
            if "euler" in attrs:
                centre, grot = _floats(attrs.get("pos", "0 0 0")), _euler_xyz(_floats(attrs["euler"]))
            else:
                centre, grot = _geom_pose(attrs)
            if "fromto" in attrs:  # the half-length is the ends' distance, not a size entry
                ends = _floats(attrs["fromto"])
                size = np.array([size[0], 0.5 * float(np.linalg.norm(ends[3:] - ends[:3]))])
            rgba = tuple(float(v) for v in _floats(attrs.get("rgba", "0.5 0.5 0.5 1")))
            shapes.append(BodyShape(
                name=geom.get("name") or f"{body.get('name')}_{i}", kind=kind, size=tuple(float(v) for v in size),
                pos=_vec3(placement.act(centre)), quat=_mat_quat(placement.rotation @ grot),
                rgba=rgba, on_foot=bool(on_foot)))  # type: ignore[arg-type]
    slide = _named(xml, "joint", FOOT_JOINT, defaults)
    axis = _floats(slide.get("axis", "0 0 1"))
    foot_body_rot = (torso_inv * r.data.oMi[foot]).rotation
    foot_axis = foot_body_rot @ (axis / np.linalg.norm(axis))
    return BodyGeometry(shapes=tuple(shapes), foot_axis=_vec3(foot_axis))


DEPTH_CAMERA_SITE = "depth_camera"
# The camera's optical frame (x right, y down, z forward) in its MJCF site frame (x forward, y left, z up).
SITE_FROM_OPTICAL = ((0.0, 0.0, 1.0), (-1.0, 0.0, 0.0), (0.0, -1.0, 0.0))


@dataclass(frozen=True)
class CameraMount:
    """The depth camera's optical frame on the torso: the extrinsic of the robot's camera."""

    pos_from_com: Vec3  # optical centre from the whole robot's CoM, body frame [m] (the estimate's position is the CoM)
    quat: tuple[float, float, float, float]  # optical -> body [w, x, y, z]


@functools.lru_cache(maxsize=None)
def camera_mount(variant: str = DEFAULT_VARIANT) -> CameraMount:
    """The MJCF site ``depth_camera`` (a child of the torso) as the camera's extrinsic."""
    xml = load_xml(variant)
    defaults = _Defaults(xml)
    for body, cls in _walk_bodies(xml.find("worldbody")):
        for site in body.findall("site"):
            if site.get("name") != DEPTH_CAMERA_SITE:
                continue
            if body.get("name") != TORSO:
                raise ValueError(f"site {DEPTH_CAMERA_SITE!r} must be on the torso, not on {body.get('name')!r}")
            attrs = defaults.attrs(site, cls)
            rot = _euler_xyz(_floats(attrs["euler"])) if "euler" in attrs else _geom_pose(attrs)[1]
            pos = _floats(attrs.get("pos", "0 0 0")) - np.array(robot_params(variant).com_offset_body)
            return CameraMount(pos_from_com=_vec3(pos), quat=_mat_quat(rot @ np.array(SITE_FROM_OPTICAL)))
    raise ValueError(f"robot variant {variant!r} has no site {DEPTH_CAMERA_SITE!r}")
