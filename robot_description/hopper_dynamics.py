"""ARCHER's rigid-body dynamics per contact mode, for the geometric MPC (thesis section 5.3).

Pinocchio builds the tree from the same MJCF the twin compiles, with the free joint replaced
by three world-axis slides followed by a ball joint (body frame), so that the
generalized velocity is ``(p_dot, omega, theta_dot, l_dot)``: the CoM-free coordinates of
eq. 5.23 with ``omega`` in the Lie algebra. The spool joint is locked (the MPC plans the foot
as a passive degree of freedom, thesis lines 2230-2236).

Manifold state ``x`` (21 numbers): torso position [m, world], attitude quaternion
``[w, x, y, z]`` (body -> world), wheel angles [rad], foot compression ``l`` [m], then the
velocity ``(p_dot [m/s, world], omega [rad/s, body], theta_dot [rad/s], l_dot [m/s])``.
Perturbations are ``(dp, eta, dtheta, dl, dv)`` with ``q exp(eta)`` the perturbed attitude:
the Lie-algebra linearization of eqs. 5.18-5.22.

Modes (:data:`onboard.low_level.planning.geometric_mpc.FLIGHT`, ``STANCE``):

- flight: the cable holds the spring (``l_ddot = 0``, a joint lock enforced as a constraint);
- stance: the foot tip is pinned to the ground (3D point contact); the spring pushes the foot.

Jumps: ``touchdown`` (plastic impact of the foot tip, cable slack) and ``liftoff`` (the foot
reaches full extension and its stop locks it: plastic impact of the joint lock).
"""

from __future__ import annotations

import functools
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pinocchio as pin

from onboard.low_level.planning.geometric_mpc import FLIGHT, INPUT_DIM, LIFTOFF, STANCE, STATE_DIM, TOUCHDOWN
from robot_description.params import DEFAULT_VARIANT, FOOT_JOINT, FOOT_MOTOR_JOINT, ROOT_JOINT, TORSO, WHEEL_JOINTS, load_xml, robot_params

NV = STATE_DIM // 2  # velocity coordinates: 3 linear, 3 angular, 3 wheels, 1 foot
MANIFOLD_DIM = STATE_DIM + 1  # the quaternion takes four numbers for three directions
_WHEEL_V = slice(6, 9)
_SLIDES = ("gmpc_x", "gmpc_y", "gmpc_z")  # massless bodies and slides that carry the torso
_FOOT_V = 9
# Pinocchio's configuration from the manifold state: position, quaternion x y z w, wheels, foot
_PIN_Q = np.array([0, 1, 2, 4, 5, 6, 3, 7, 8, 9, 10])
# Pinocchio's constrained solvers: exact (no proximal regularization) in one iteration
_PROX = (1e-12, 1e-12, 0.0, 1)


def _pin_model(variant: str) -> pin.Model:
    """The MJCF's tree with the free joint split into three world-axis slides (on massless
    bodies) and a ball joint on the torso (Pinocchio's derivatives of a composite root joint
    disagree with finite differences of its own dynamics; separate joints agree)."""
    xml = load_xml(variant)
    world = xml.find("worldbody")
    torso = next(b for b in world if b.tag == "body" and b.get("name") == TORSO)
    free = torso.find("freejoint")
    if free is None or free.get("name") != ROOT_JOINT:
        raise ValueError("the torso must carry the MJCF free joint")
    torso.remove(free)
    torso.set("pos", "0 0 0")
    torso.insert(0, ET.Element("joint", name=ROOT_JOINT, type="ball"))
    world.remove(torso)
    parent = world
    for axis, name in zip(("1 0 0", "0 1 0", "0 0 1"), _SLIDES):  # one body each: Pinocchio would merge them
        body = ET.SubElement(parent, "body", name=f"{name}_body", pos="0 0 0")
        ET.SubElement(body, "inertial", pos="0 0 0", mass="0", diaginertia="0 0 0")
        ET.SubElement(body, "joint", name=name, type="slide", axis=axis, limited="false")
        parent = body
    parent.append(torso)
    with tempfile.TemporaryDirectory() as tmp:  # Pinocchio's MJCF parser reads files only
        path = Path(tmp) / "robot.xml"
        ET.ElementTree(xml).write(path)
        model = pin.buildModelFromMJCF(str(path))
    model = pin.buildReducedModel(model, [model.getJointId(FOOT_MOTOR_JOINT)], pin.neutral(model))
    names = [model.names[j] for j in range(1, model.njoints)]
    if names != [*_SLIDES, ROOT_JOINT, *WHEEL_JOINTS, FOOT_JOINT] or model.nv != NV:
        raise ValueError(f"unexpected joint tree {names}")
    model.gravity.linear = np.array([0.0, 0.0, -robot_params(variant).gravity])
    return model


class HopperDynamics:
    """Flows, jumps and their Lie-algebra Jacobians (the ``HybridDynamics`` of
    :mod:`onboard.low_level.planning.geometric_mpc`). Not thread-safe: one instance per MPC."""

    def __init__(self, variant: str = DEFAULT_VARIANT) -> None:
        robot = robot_params(variant)
        self.variant = variant
        self.model = _pin_model(variant)
        self.data = self.model.createData()
        self.spring_k = robot.spring_stiffness
        self.spring_c = robot.spring_damping
        self.wheel_torque_peak = robot.wheel_torque_peak
        foot = self.model.getJointId(FOOT_JOINT)
        contact = pin.RigidConstraintModel(pin.ContactType.CONTACT_3D, self.model, foot, pin.SE3.Identity(),
                                           pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
        self._contacts = pin.StdVec_RigidConstraintModel()
        self._contacts.append(contact)
        self._contact_data = pin.StdVec_RigidConstraintData()
        self._contact_data.append(contact.createData())
        self._prox = pin.ProximalSettings(*_PROX)
        pin.initConstraintDynamics(self.model, self.data, self._contacts, self._contact_data)
        self._select = np.zeros((NV, INPUT_DIM))  # wheel motor torques -> generalized forces
        self._select[_WHEEL_V, :] = np.eye(INPUT_DIM)
        self._lock = np.zeros(NV)  # the foot joint's row of the joint lock
        self._lock[_FOOT_V] = 1.0
        self._jac_template = np.zeros((STATE_DIM, STATE_DIM))
        self._jac_template[:NV, NV:] = np.eye(NV)

    # --- coordinates ---------------------------------------------------------------------------

    @staticmethod
    def configuration(x: np.ndarray) -> np.ndarray:
        """Pinocchio's ``q`` (quaternion ``x, y, z, w``) from the manifold state."""
        return x[_PIN_Q]

    @staticmethod
    def state(q: np.ndarray, v: np.ndarray) -> np.ndarray:
        return np.concatenate([q[0:3], q[6:7], q[3:6], q[7:11], v])

    def retract(self, x: np.ndarray, dz: np.ndarray) -> np.ndarray:
        """``x`` moved by the perturbation ``dz`` (20): ``q exp(eta)`` for the attitude."""
        q = pin.integrate(self.model, self.configuration(x), dz[:NV])
        return self.state(q, x[11:] + dz[NV:])

    def difference(self, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
        """The perturbation that takes ``x0`` to ``x1`` (inverse of :meth:`retract`)."""
        dq = pin.difference(self.model, self.configuration(x0), self.configuration(x1))
        return np.concatenate([dq, x1[11:] - x0[11:]])

    def com_offset(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(whole-robot CoM minus torso origin [m, world], CoM velocity minus ``p_dot`` [m/s])."""
        q = self.configuration(x)
        v = x[11:]
        com = pin.centerOfMass(self.model, self.data, q, v)
        return com - q[:3], self.data.vcom[0] - v[:3]

    # --- generalized forces --------------------------------------------------------------------

    def _tau(self, mode: str, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        tau = self._select @ u
        if mode == STANCE:  # the spring pushes the foot (in flight the cable holds it)
            tau[_FOOT_V] = -self.spring_k * x[10] - self.spring_c * x[11 + _FOOT_V]
        return tau

    # --- flows ---------------------------------------------------------------------------------

    def acceleration(self, mode: str, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Generalized acceleration in ``mode``."""
        q, v = self.configuration(x), x[11:]
        tau = self._tau(mode, x, u)
        if mode == STANCE:
            return pin.constraintDynamics(self.model, self.data, q, v, tau, self._contacts, self._contact_data, self._prox).copy()
        a_free = pin.aba(self.model, self.data, q, v, tau)
        return a_free - self._lock_column(q)[1] * a_free[_FOOT_V]

    def _lock_column(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(M^-1, M^-1 e / e' M^-1 e)``: the foot lock removes ``a_foot`` (or ``v_foot``)
        along that column, the response to the lock's force."""
        m_inv = pin.computeMinverse(self.model, self.data, q).copy()  # full and symmetric (the tests check B)
        return m_inv, m_inv[:, _FOOT_V] / m_inv[_FOOT_V, _FOOT_V]

    def flow(self, mode: str, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(z_dot, A, B)`` at ``x``, ``u``: eq. 5.20 for the attitude, plain Jacobians else.

        ``A`` is d z_dot / d(dp, eta, dtheta, dl, dv), ``B`` d z_dot / du. The MPC calls this
        for every knot of every SQP iteration: the numpy work around Pinocchio's is kept to a
        few whole-block operations (it was twice Pinocchio's own time).
        """
        q, v = x[_PIN_Q], x[11:]
        tau = np.zeros(NV)
        tau[_WHEEL_V] = u
        jac = self._jac_template.copy()  # p_dot = v, xi_dot = omega (eq. 5.19), theta_dot, l_dot
        lower = jac[NV:]  # d a / d(dq, dv)
        b = np.zeros((STATE_DIM, INPUT_DIM))
        if mode == STANCE:
            tau[_FOOT_V] = -self.spring_k * x[10] - self.spring_c * x[11 + _FOOT_V]  # the spring pushes the foot
            z_dot = np.concatenate([v, pin.constraintDynamics(self.model, self.data, q, v, tau, self._contacts, self._contact_data, self._prox)])
            da_dq, da_dv, da_dtau = pin.computeConstraintDynamicsDerivatives(
                self.model, self.data, self._contacts, self._contact_data, self._prox)[:3]
            lower[:, :NV] = da_dq
            lower[:, NV:] = da_dv
            # the spring's force on the foot joint: -k l - c l_dot
            foot = da_dtau[:, _FOOT_V]
            lower[:, _FOOT_V] -= self.spring_k * foot
            lower[:, NV + _FOOT_V] -= self.spring_c * foot
            b[NV:] = da_dtau[:, _WHEEL_V]
        elif mode == FLIGHT:  # the cable holds the spring
            # the lock's force enters as a generalized force: differentiate ABA there, then
            # project (the lock row is constant, so d a = P d a_free with P = I - col e')
            m_inv, col = self._lock_column(q)
            a_free = pin.aba(self.model, self.data, q, v, tau)
            z_dot = np.concatenate([v, a_free - col * a_free[_FOOT_V]])
            tau[_FOOT_V] -= a_free[_FOOT_V] / m_inv[_FOOT_V, _FOOT_V]  # the locked torque
            pin.computeABADerivatives(self.model, self.data, q, v, tau)
            lower[:, :NV] = self.data.ddq_dq
            lower[:, NV:] = self.data.ddq_dv
            lower -= col[:, None] * lower[_FOOT_V]  # broadcasting: np.outer's checks cost more than the product
            b[NV:] = m_inv[:, _WHEEL_V] - col[:, None] * m_inv[_FOOT_V, _WHEEL_V]
        else:
            raise ValueError(f"unknown mode {mode!r}")
        return z_dot, jac, b

    # --- jumps ---------------------------------------------------------------------------------

    def _jump_velocity(self, edge: str, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        if edge == TOUCHDOWN:
            return pin.impulseDynamics(self.model, self.data, q, v, self._contacts, self._contact_data, 0.0, self._prox).copy()
        if edge == LIFTOFF:
            return v - self._lock_column(q)[1] * v[_FOOT_V]
        raise ValueError(f"unknown jump {edge!r}")

    def jump(self, edge: str, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(x_plus, D)`` of eq. 5.22: the post-impact state and d z+ / d z- (the
        momentum transfer extended off the guard, as the thesis does)."""
        q, v = self.configuration(x), x[11:]
        v_plus = self._jump_velocity(edge, q, v)
        d = np.eye(STATE_DIM)
        if edge == TOUCHDOWN:
            pin.computeImpulseDynamicsDerivatives(self.model, self.data, self._contacts, self._contact_data, 0.0, self._prox)
            d[NV:, :NV] = self.data.ddq_dq
            d[NV:, NV:] = self.data.ddq_dv + np.eye(NV)  # Pinocchio gives d(v+ - v-)/dv- (checked by the tests)
        else:  # the lock's projection v+ = v - col(q) v_foot, col = w / w_foot with w = M^-1 e_foot
            m_inv, col = self._lock_column(q)
            d[NV:, NV:] -= col[:, None] * self._lock
            # and its change with the configuration: M w = e gives dw/dq = -M^-1 d(M w)/dq at w held,
            # d(M w)/dq = RNEA's dtau/dq at (q, 0, w) less gravity's (Pinocchio's, in the Lie algebra)
            w = m_inv[:, _FOOT_V]
            dmw = pin.computeRNEADerivatives(self.model, self.data, q, np.zeros(NV), w)[0].copy()
            dmw -= pin.computeGeneralizedGravityDerivatives(self.model, self.data, q)
            dw = -m_inv @ dmw
            dcol = (dw - col[:, None] * dw[_FOOT_V]) / w[_FOOT_V]
            d[NV:, :NV] = -dcol * v[_FOOT_V]
        return np.concatenate([x[:11], v_plus]), d


@functools.lru_cache(maxsize=None)
def stance_half_period(variant: str = DEFAULT_VARIANT) -> float:
    """Half the period [s] of the sprung body bouncing on the pinned foot: the nominal stance."""
    robot = robot_params(variant)
    return float(np.pi * np.sqrt(robot.sprung_mass / robot.spring_stiffness))
