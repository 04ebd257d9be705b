"""A twin that is not the model: the twin's physics drawn, per seed, around the MJCF.

The stack keeps reading the nominal description (``robot_description``); only the twin's compiled
model, its actuation and its sensors change. A *profile* says, per factor, how far the real robot
may be from the MJCF; :func:`draw` turns it and a seed into one robot (a :class:`Draw`), and the
lockstep runner (and the real-time twin) apply that draw:

- :meth:`Draw.apply_model`: body masses, inertias and the torso's CoM, the spring's stiffness and
  damping, the cable's stretch, wheel bearing viscous drag and Coulomb friction, wheel and foot
  torque constants (actuator gear), contact friction and stiffness/damping of the foot's tip, the
  floor's slope;
- :meth:`Draw.twin_params`: each sensor's latency and rate;
- :meth:`Draw.actuation_robot`: the wheel motors' speed-torque curve;
- :attr:`Draw.actuator_delay_s`, :attr:`Draw.imu_misalignment`: a command delay the runner queues,
  a mount rotation the IMU reads through (:class:`sim_twin.sensors.SensorSuite`).

A profile is a TOML file, ``[factors]`` with one entry per factor: a number (that value, every
seed: a one-factor sweep) or a table ``{mean = M, spread = S, dist = "uniform" | "normal"}``
(uniform: M +- S; normal: std S), or a list of fixed values, one per draw (per wheel: what
``archer identify`` writes, beside an ``[identified]`` table this module ignores). Relative
factors (kind ``rel``) are fractions of the MJCF's value (0.1: +10 %), absolute ones are in the
factor's unit. Shipped profiles live in
``sim_twin/model_errors/NAME.toml``; ``--model-error`` also takes a path or an inline list
``name=value;name=value``.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np

from onboard.contracts.params import TwinParams
from robot_description import params as rd

PROFILES_DIR = Path(__file__).resolve().parent / "model_errors"
NOMINAL = "nominal"
_SEED_TAG = 0x4D45  # "ME": the draw's own stream, apart from the sensors' and the scenario's


@dataclass(frozen=True)
class FactorSpec:
    kind: str  # "rel": fraction of the MJCF's value; "abs": in ``unit``
    unit: str
    count: int  # independent draws (per wheel, per axis)
    what: str


# Every factor a profile may name. Order: the report's.
FACTORS: dict[str, FactorSpec] = {
    "mass_torso": FactorSpec("rel", "", 1, "torso mass"),
    "mass_wheels": FactorSpec("rel", "", 3, "each wheel's mass"),
    "mass_foot": FactorSpec("rel", "", 1, "foot (unsprung) mass"),
    "inertia_torso": FactorSpec("rel", "", 3, "torso principal inertias"),
    "inertia_wheels": FactorSpec("rel", "", 3, "each wheel's inertia"),
    "com_x": FactorSpec("abs", "m", 1, "whole-robot CoM off the spine, body x (the torso's CoM moved)"),
    "com_y": FactorSpec("abs", "m", 1, "whole-robot CoM off the spine, body y"),
    "com_z": FactorSpec("abs", "m", 1, "whole-robot CoM along the spine"),
    "spring_stiffness": FactorSpec("rel", "", 1, "foot spring stiffness"),
    "spring_damping": FactorSpec("abs", "N s/m", 1, "foot spring damping (losses)"),
    "cable_stretch": FactorSpec("rel", "", 1, "cable + mount compliance (tendon limit time constant)"),
    "wheel_viscous": FactorSpec("abs", "N m s/rad", 3, "wheel bearing viscous drag"),
    "wheel_coulomb": FactorSpec("abs", "N m", 3, "wheel bearing Coulomb friction"),
    "wheel_torque_constant": FactorSpec("rel", "", 3, "wheel torque constant (torque per commanded torque)"),
    "foot_torque_constant": FactorSpec("rel", "", 1, "foot drive torque constant"),
    "wheel_speed_curve": FactorSpec("rel", "", 1, "wheel speed-torque curve (knee and no-load speed)"),
    "actuator_delay": FactorSpec("abs", "s", 1, "extra command delay (drives, bus)"),
    "imu_misalign": FactorSpec("abs", "rad", 3, "IMU mount rotation (body x, y, z)"),
    "imu_latency": FactorSpec("abs", "s", 1, "extra IMU latency"),
    "joints_latency": FactorSpec("abs", "s", 1, "extra encoder/foot latency"),
    "pose_latency": FactorSpec("abs", "s", 1, "extra pose (mocap) latency"),
    "imu_rate": FactorSpec("rel", "", 1, "IMU rate"),
    "pose_rate": FactorSpec("rel", "", 1, "pose rate"),
    "contact_friction": FactorSpec("rel", "", 1, "foot-floor sliding friction"),
    "contact_timeconst": FactorSpec("rel", "", 1, "foot contact stiffness (solref time constant)"),
    "contact_dampratio": FactorSpec("rel", "", 1, "foot contact damping ratio"),
    "floor_slope": FactorSpec("abs", "rad", 1, "floor slope (direction drawn uniformly)"),
}
DISTS = ("uniform", "normal")
REL_FLOOR = -0.9  # a relative error never takes a value below 10 % of the MJCF's


@dataclass(frozen=True)
class Spread:
    mean: float = 0.0
    spread: float = 0.0
    dist: str = "uniform"
    values: tuple[float, ...] = ()  # fixed values, one per draw (per wheel, per axis): an identified robot


@dataclass(frozen=True)
class Profile:
    name: str
    factors: dict[str, Spread]


def _spread(name: str, value: object) -> Spread:
    if name not in FACTORS:
        raise ValueError(f"model error: unknown factor {name!r}; known: {', '.join(FACTORS)}")
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        s = Spread(float(value))
    elif isinstance(value, list):  # one fixed value per draw (archer identify writes the wheels' so)
        count = FACTORS[name].count
        if len(value) != count or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
            raise ValueError(f"model error {name}: a list of {count} numbers, got {value!r}")
        s = Spread(float(value[0]), values=tuple(float(v) for v in value))
        if not all(math.isfinite(v) for v in s.values):
            raise ValueError(f"model error {name}: values finite")
    elif isinstance(value, dict):
        extra = set(value) - {"mean", "spread", "dist"}
        if extra:
            raise ValueError(f"model error {name}: unknown keys {sorted(extra)} (mean, spread, dist)")
        s = Spread(float(value.get("mean", 0.0)), float(value.get("spread", 0.0)), str(value.get("dist", "uniform")))
    else:
        raise ValueError(f"model error {name}: a number or a table {{mean, spread, dist}}, got {value!r}")
    if s.dist not in DISTS:
        raise ValueError(f"model error {name}: dist {s.dist!r} not in {DISTS}")
    if not (math.isfinite(s.mean) and math.isfinite(s.spread) and s.spread >= 0.0):
        raise ValueError(f"model error {name}: mean and spread finite, spread >= 0")
    return s


def load_profile(text: str | None) -> Profile:
    """A profile by name (``sim_twin/model_errors/NAME.toml``), path to a TOML file, or inline
    ``name=value;name=value`` (fixed values). None or ``nominal``: no error at all."""
    if text is None or text == NOMINAL:
        return Profile(NOMINAL, {})
    path = PROFILES_DIR / f"{text}.toml"
    if not path.exists() and text.endswith(".toml"):
        path = Path(text)
    if path.exists():
        with open(path, "rb") as f:
            doc = tomllib.load(f)
        table = doc.get("factors", {})
        # [identified]: what archer identify measured, with its uncertainties (robot_description.identified)
        if not isinstance(table, dict) or set(doc) - {"factors", "identified"}:
            raise ValueError(f"model error profile {path}: one table [factors] (and [identified])")
        return Profile(path.stem, {k: _spread(k, v) for k, v in table.items()})
    if "=" not in text:
        known = sorted(p.stem for p in PROFILES_DIR.glob("*.toml"))
        raise ValueError(f"model error {text!r}: not a profile ({', '.join([NOMINAL, *known])}), a .toml file or name=value;...")
    factors = {}
    for item in filter(None, (p.strip() for p in text.split(";"))):
        name, _, value = item.partition("=")
        try:
            factors[name.strip()] = _spread(name.strip(), float(value))
        except ValueError as exc:
            raise ValueError(f"model error {item!r}: {exc}") from None
    return Profile(text, factors)


@dataclass(frozen=True)
class Draw:
    """One robot drawn from a profile: factor -> its drawn values (a tuple of ``count``)."""

    profile: str
    values: dict[str, tuple[float, ...]] = field(default_factory=dict)

    def get(self, name: str, i: int = 0) -> float:
        v = self.values.get(name)
        return v[i] if v is not None else 0.0

    def has(self, name: str) -> bool:
        return name in self.values

    @property
    def actuator_delay_s(self) -> float:
        return max(0.0, self.get("actuator_delay"))

    @property
    def imu_misalignment(self) -> tuple[float, float, float] | None:
        if not self.has("imu_misalign"):
            return None
        return self.get("imu_misalign", 0), self.get("imu_misalign", 1), self.get("imu_misalign", 2)

    def report(self) -> dict:
        """The drawn values, for the run's report (units in the factor table)."""
        out: dict = {"profile": self.profile}
        for name, vals in self.values.items():
            out[name] = [round(v, 7) for v in vals] if len(vals) > 1 else round(vals[0], 7)
        return out

    def _rel(self, name: str, i: int = 0) -> float:
        return 1.0 + max(REL_FLOOR, self.get(name, i))

    def apply_model(self, model: mujoco.MjModel) -> None:
        """Change the compiled twin in place (call :func:`finish_model` with its data after)."""
        if not self.values:
            return
        torso = int(model.body(rd.TORSO).id)
        foot = int(model.body(rd.FOOT).id)
        wheels = [int(model.body(n).id) for n in rd.WHEEL_JOINTS]
        model.body_mass[torso] *= self._rel("mass_torso")
        model.body_mass[foot] *= self._rel("mass_foot")
        model.body_inertia[foot] *= self._rel("mass_foot")  # a heavier foot of the same shape
        for i in range(3):
            model.body_inertia[torso, i] *= self._rel("inertia_torso", i)
        for k, b in enumerate(wheels):
            model.body_mass[b] *= self._rel("mass_wheels", k)
            model.body_inertia[b] *= self._rel("inertia_wheels", k)
        # the whole robot's CoM moves by the drawn offset: the torso's CoM by that times its share
        robot_mass = float(sum(model.body_mass[b] for b in range(model.nbody) if model.body_rootid[b] == model.body_rootid[torso]))
        share = robot_mass / float(model.body_mass[torso])
        model.body_ipos[torso] += (share * self.get("com_x"), share * self.get("com_y"), share * self.get("com_z"))
        fj = model.joint(rd.FOOT_JOINT)
        model.jnt_stiffness[int(fj.id)] *= self._rel("spring_stiffness")
        model.dof_damping[int(fj.dofadr[0])] += max(0.0, self.get("spring_damping"))
        if self.has("cable_stretch"):
            model.tendon_solref_lim[int(model.tendon(rd.CABLE_TENDON).id), 0] *= self._rel("cable_stretch")
        for k, name in enumerate(rd.WHEEL_JOINTS):
            dof = int(model.joint(name).dofadr[0])
            model.dof_damping[dof] += max(0.0, self.get("wheel_viscous", k))
            model.dof_frictionloss[dof] += max(0.0, self.get("wheel_coulomb", k))
        for k, name in enumerate(rd.WHEEL_ACTUATORS):
            model.actuator_gear[int(model.actuator(name).id), 0] *= self._rel("wheel_torque_constant", k)
        model.actuator_gear[int(model.actuator(rd.FOOT_ACTUATOR).id), 0] *= self._rel("foot_torque_constant")
        tip = int(model.geom(rd.FOOT).id)  # the foot's tip has priority in its contacts: its parameters rule
        model.geom_friction[tip, 0] *= self._rel("contact_friction")
        model.geom_solref[tip, 0] *= self._rel("contact_timeconst")
        model.geom_solref[tip, 1] *= self._rel("contact_dampratio")
        slope = self.get("floor_slope")
        if slope:
            heading = self.get("floor_slope", 1) if len(self.values["floor_slope"]) > 1 else 0.0
            axis = np.array([-math.sin(heading), math.cos(heading), 0.0])  # tilt about it: downhill along heading
            quat = np.zeros(4)
            mujoco.mju_axisAngle2Quat(quat, axis, slope)
            model.geom_quat[int(model.geom("floor").id)] = quat

    def twin_params(self, twin: TwinParams) -> TwinParams:
        """The sensors' latency and rate as drawn (on top of the run's twin parameters)."""
        if not self.values:
            return twin
        changes: dict = {}
        for sensor in ("imu", "joints", "pose"):
            if self.has(f"{sensor}_latency"):
                changes[f"{sensor}_latency_s"] = max(0.0, getattr(twin, f"{sensor}_latency_s") + self.get(f"{sensor}_latency"))
        for sensor in ("imu", "pose"):
            if self.has(f"{sensor}_rate"):
                changes[f"{sensor}_rate_hz"] = getattr(twin, f"{sensor}_rate_hz") * self._rel(f"{sensor}_rate")
        return dataclasses.replace(twin, **changes) if changes else twin

    def actuation_robot(self, robot: rd.RobotParams) -> rd.RobotParams:
        """The robot as the twin's motors are: the wheels' speed-torque curve as drawn."""
        if not self.has("wheel_speed_curve"):
            return robot
        s = self._rel("wheel_speed_curve")
        return dataclasses.replace(robot, wheel_speed_knee=robot.wheel_speed_knee * s, wheel_no_load_speed=robot.wheel_no_load_speed * s)


def finish_model(model: mujoco.MjModel, data: mujoco.MjData) -> None:
    """Recompute what MuJoCo derives from masses and inertias (after :meth:`Draw.apply_model`)."""
    mujoco.mj_setConst(model, data)


def draw(profile: Profile, seed: int) -> Draw:
    """One robot from ``profile`` for ``seed`` (its own random stream: the sensors' noise and the
    scenario are those of the same seed without a model error)."""
    if not profile.factors:
        return Draw(profile.name)
    rng = np.random.default_rng(np.random.SeedSequence([_SEED_TAG, seed]))
    values: dict[str, tuple[float, ...]] = {}
    for name, spec in FACTORS.items():  # the table's order: a profile's key order changes nothing
        s = profile.factors.get(name)
        if s is None:
            continue
        if s.values:
            vals = np.array(s.values)
        elif s.dist == "normal":
            vals = s.mean + s.spread * rng.standard_normal(spec.count)
        else:
            vals = s.mean + s.spread * rng.uniform(-1.0, 1.0, spec.count)
        values[name] = tuple(float(v) for v in vals)
        if name == "floor_slope":  # the downhill heading, drawn with it
            values[name] += (float(rng.uniform(-math.pi, math.pi)),)
    return Draw(profile.name, values)


def true_com_offset(model: mujoco.MjModel) -> tuple[float, float, float]:
    """Whole-robot CoM relative to the torso origin in the torso frame, foot extended, of ``model``
    (the twin's own, for the metrics: the stack's belief is ``RobotParams.com_offset_body``)."""
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    torso = int(model.body(rd.TORSO).id)
    root = model.body_rootid[torso]
    com = data.subtree_com[root] - data.xpos[torso]
    body = data.xmat[torso].reshape(3, 3).T @ com
    return float(body[0]), float(body[1]), float(body[2])


def truth_robot(model: mujoco.MjModel, robot: rd.RobotParams) -> rd.RobotParams:
    """``robot`` with the twin's own CoM offset and masses: what the metrics' truth reads."""
    foot = float(model.body_mass[int(model.body(rd.FOOT).id)])
    torso = int(model.body(rd.TORSO).id)
    total = float(sum(model.body_mass[b] for b in range(model.nbody) if model.body_rootid[b] == model.body_rootid[torso]))
    return dataclasses.replace(robot, com_offset_body=true_com_offset(model), foot_mass=foot, total_mass=total)
