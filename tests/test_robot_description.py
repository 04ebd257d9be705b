"""The robot description reads the same numbers from the MJCF as MuJoCo does.

The robot's services read ``robot_description.params`` (Pinocchio and the XML, no MuJoCo);
the reference here is the reading of the MuJoCo-compiled model the stack used before, kept
as the test's oracle: every field of ``RobotParams`` and of the reduced hopper must agree.
"""

from __future__ import annotations

import dataclasses
import math

import mujoco
import numpy as np
import pytest

from onboard.low_level.planning import zdp
from robot_description import params as rd
from sim_twin import model as tm


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


def params_from_model(model: mujoco.MjModel, variant: str) -> rd.RobotParams:
    """Extract :class:`RobotParams` from a compiled model at its reference pose."""
    data = mujoco.MjData(model)
    data.qpos[:] = model.qpos0
    # Torso at the origin, upright: body-frame quantities read straight from world ones.
    root = model.joint(rd.ROOT_JOINT)
    adr = int(root.qposadr[0])
    data.qpos[adr:adr + 7] = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
    mujoco.mj_forward(model, data)

    torso = model.body(rd.TORSO).id
    foot = model.body(rd.FOOT).id
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
    for name in rd.WHEEL_JOINTS:
        j = model.joint(name)
        body = int(j.bodyid[0])
        wheel_axes.append(data.xmat[body].reshape(3, 3) @ j.axis)
    wheel_body = int(model.joint(rd.WHEEL_JOINTS[0]).bodyid[0])
    wheel_inertia_local = model.body_inertia[wheel_body]
    spin_axis_local = model.joint(rd.WHEEL_JOINTS[0]).axis
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

    slide = model.joint(rd.FOOT_JOINT)
    slide_dof = int(slide.dofadr[0])
    motor = model.joint(rd.FOOT_MOTOR_JOINT)
    tendon = model.tendon(rd.CABLE_TENDON)
    wrap = [(int(model.wrap_objid[model.tendon_adr[tendon.id] + k]), float(model.wrap_prm[model.tendon_adr[tendon.id] + k])) for k in range(int(model.tendon_num[tendon.id]))]
    coefs = {jid: coef for jid, coef in wrap}
    if coefs.get(slide.id) != 1.0 or motor.id not in coefs:
        raise ValueError("cable tendon must be foot_slide - r * foot_motor")

    return rd.RobotParams(
        variant=variant,
        gravity=float(-model.opt.gravity[2]),
        timestep=float(model.opt.timestep),
        total_mass=total_mass,
        foot_mass=foot_mass,
        sprung_mass=total_mass - foot_mass,
        torso_mass=float(model.body_mass[torso]),
        torso_inertia=rd._mat3(data.ximat[torso].reshape(3, 3) @ np.diag(model.body_inertia[torso]) @ data.ximat[torso].reshape(3, 3).T),
        wheel_mass=float(model.body_subtreemass[wheel_body]),
        wheel_spin_inertia=wheel_spin_inertia,
        wheel_axes=rd._mat3(np.array(wheel_axes)),
        com_offset_body=rd._vec3(com - data.xpos[torso]),
        inertia_com=rd._mat3(inertia),
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
        hop_speed_max=_numeric_value(model, "hop_speed_max"),
    )



def mujoco_hopper_model(variant: str) -> zdp.HopperModel:
    robot = rd.robot_params(variant)
    model = tm.load_model(variant)
    data = mujoco.MjData(model)
    data.qpos[:] = model.qpos0
    adr = int(model.joint(rd.ROOT_JOINT).qposadr[0])
    data.qpos[adr:adr + 7] = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]  # torso upright at the origin
    mujoco.mj_forward(model, data)
    torso = model.body(rd.TORSO).id
    foot = model.body(rd.FOOT).id

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




def _assert_same(ours: object, theirs: object) -> None:
    for f in dataclasses.fields(ours):
        a, b = getattr(ours, f.name), getattr(theirs, f.name)
        if isinstance(a, str):
            assert a == b, f.name
        else:
            assert np.allclose(a, b, rtol=1e-12, atol=1e-15), f"{f.name}: {a} != {b} (MuJoCo)"  # round-off of another summation order


@pytest.mark.parametrize("variant", rd.VARIANTS)
def test_robot_params_equal_mujoco_reading(variant: str) -> None:
    _assert_same(rd.robot_params(variant), params_from_model(tm.load_model(variant), variant))


@pytest.mark.parametrize("variant", rd.VARIANTS)
def test_hopper_model_equals_mujoco_reading(variant: str) -> None:
    _assert_same(rd.hopper_model(variant), mujoco_hopper_model(variant))


@pytest.mark.parametrize("variant", rd.VARIANTS)
def test_body_shapes_equal_mujoco_geoms(variant: str) -> None:
    """What `archer view` draws is where MuJoCo puts each geom of the robot (torso upright at the origin)."""
    model = tm.load_model(variant)
    data = mujoco.MjData(model)
    adr = int(model.joint(rd.ROOT_JOINT).qposadr[0])
    data.qpos[adr:adr + 7] = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
    mujoco.mj_forward(model, data)
    kinds = {mujoco.mjtGeom.mjGEOM_SPHERE: "sphere", mujoco.mjtGeom.mjGEOM_CAPSULE: "capsule",
             mujoco.mjtGeom.mjGEOM_CYLINDER: "cylinder", mujoco.mjtGeom.mjGEOM_BOX: "box"}
    foot = model.body(rd.FOOT).id
    geometry = rd.body_shapes(variant)
    ours = list(geometry.shapes)
    robot = [g for g in range(model.ngeom) if model.geom_bodyid[g] != 0]  # the world's geoms hang off body 0
    assert len(robot) == len(ours)
    for g in robot:
        kind = kinds[int(model.geom_type[g])]
        match = [s for s in ours if s.kind == kind and np.allclose(s.pos, data.geom_xpos[g], atol=1e-9)]
        assert len(match) == 1, (variant, g, kind)
        s = match[0]
        n = {"sphere": 1, "capsule": 2, "cylinder": 2, "box": 3}[kind]
        assert np.allclose(s.size[:n], model.geom_size[g][:n], atol=1e-12)
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, np.array(s.quat))
        ours_rot, theirs = rot.reshape(3, 3), data.geom_xmat[g].reshape(3, 3)
        if kind == "box":
            assert np.allclose(ours_rot, theirs, atol=1e-6), (variant, s.name)
        elif kind != "sphere":  # round about their axis: the axis, either way along it (MuJoCo turns fromto's over)
            assert abs(float(ours_rot[:, 2] @ theirs[:, 2])) == pytest.approx(1.0, abs=1e-6), (variant, s.name)
        assert s.on_foot == _is_descendant(model, int(model.geom_bodyid[g]), foot) or model.geom_bodyid[g] == foot
        ours.remove(s)
    assert np.allclose(geometry.foot_axis, [0.0, 0.0, 1.0])
