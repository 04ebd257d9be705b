"""Zero Dynamics Policy: LQR and the invariant subspace on known linear systems, the
reduced hopper's impact map, and its linearization checked against the twin."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest
import scipy.linalg

from onboard.low_level.planning import zdp, zdp_policy
from robot_description import params as rd
from robot_description.params import hopper_model
from sim_twin import model as tm


def augmented(a_zz, a_ze):
    n_z, n_eta = a_ze.shape
    a = np.zeros((n_eta + n_z, n_eta + n_z))
    a[n_eta:, :n_eta] = a_ze
    a[n_eta:, n_eta:] = a_zz
    b = np.zeros((n_eta + n_z, n_eta))
    b[:n_eta] = np.eye(n_eta)
    return a, b


def test_dlqr_solves_the_riccati_equation_and_stabilizes():
    h = 0.1
    a = np.array([[1.0, h], [0.0, 1.0]])  # double integrator
    b = np.array([[0.5 * h * h], [h]])
    q, r = np.diag([1.0, 0.1]), np.array([[0.01]])
    k, p = zdp.dlqr(a, b, q, r)
    residual = a.T @ p @ a - p - a.T @ p @ b @ np.linalg.solve(r + b.T @ p @ b, b.T @ p @ a) + q
    assert np.abs(residual).max() < 1e-9
    assert np.abs(np.linalg.eigvals(a - b @ k)).max() < 1.0


def test_invariant_subspace_of_a_scalar_system_matches_the_hand_solution():
    # z' = 2 z + eta, eta' = v. A deadbeat-like closed loop with known modes:
    # choose A_cl = [[-k1, -k2], [1, 2]] with eigenvalues 0.5 and 0.1.
    lam1, lam2 = 0.5, 0.1
    # characteristic polynomial: s^2 - (2 - k1) s + (k2 - 2 k1) = (s - lam1)(s - lam2)
    k1 = 2.0 - (lam1 + lam2)
    k2 = lam1 * lam2 + 2.0 * k1
    a_cl = np.array([[-k1, -k2], [1.0, 2.0]])
    s_eta, eigs = zdp.invariant_subspace_policy(a_cl, 1)
    # the slow eigenvector of A_cl: (lam1 - 2, 1) since its second row reads eta + 2 z = lam1 z
    assert s_eta[0, 0] == pytest.approx(lam1 - 2.0)
    assert eigs[0] == pytest.approx(lam1)


@pytest.mark.parametrize("seed", range(5))
def test_zdp_manifold_is_invariant_and_attractive_for_random_systems(seed):
    rng = np.random.default_rng(seed)
    n_z, n_eta = 4, 2
    a_zz = np.eye(n_z) + 0.3 * rng.standard_normal((n_z, n_z))
    a_ze = rng.standard_normal((n_z, n_eta))
    lin = zdp.linear_zdp(a_zz, a_ze, np.eye(n_eta), np.eye(n_z), 0.5 * np.eye(n_eta))
    a, b = augmented(a_zz, a_ze)
    a_cl = a - b @ lin.k_aug
    # invariance: a point on eta = S z maps to a point on it under the LQR closed loop
    for _ in range(10):
        z = rng.standard_normal(n_z)
        nxt = a_cl @ np.concatenate([lin.s_eta @ z, z])
        assert np.allclose(nxt[:n_eta], lin.s_eta @ nxt[n_eta:], atol=1e-8)
    # stable zero dynamics, equal to the slow closed-loop modes
    assert np.abs(lin.zero_dynamics_eigs).max() < 1.0
    slow = np.sort(np.abs(np.linalg.eigvals(a_cl)))[::-1][:n_z]
    assert np.allclose(np.sort(np.abs(lin.zero_dynamics_eigs)), np.sort(slow), atol=1e-8)
    # attractive: from anywhere, the distance to the manifold dies faster than the state
    x = rng.standard_normal(n_eta + n_z) * 3
    for _ in range(25):
        x = a_cl @ x
    off = np.linalg.norm(x[:n_eta] - lin.s_eta @ x[n_eta:])
    assert off <= 1e-6 * max(1.0, np.linalg.norm(x[n_eta:])) + 1e-9
    # and applying psi directly (eta_{k+1} = S z_{k+1}) stabilizes z
    z = rng.standard_normal(n_z)
    eta = lin.s_eta @ z
    for _ in range(200):
        z = a_zz @ z + a_ze @ eta
        eta = lin.s_eta @ z
    assert np.linalg.norm(z) < 1e-6


def test_repeated_modes_of_a_symmetric_system_are_handled():
    # two identical decoupled axes: repeated eigenvalues (ill-conditioned eigenvectors)
    a1 = np.array([[1.0, 0.35], [0.0, 1.15]])
    b1 = np.array([[0.9], [3.5]])
    a_zz = scipy.linalg.block_diag(a1, a1)[[0, 2, 1, 3]][:, [0, 2, 1, 3]]
    a_ze = np.zeros((4, 2))
    a_ze[[0, 2], 0] = b1[:, 0]
    a_ze[[1, 3], 1] = b1[:, 0]
    lin = zdp.linear_zdp(a_zz, a_ze, np.eye(2), np.diag([1.0, 1.0, 0.5, 0.5]), np.eye(2))
    s = lin.s_eta
    assert s[0, 0] == pytest.approx(s[1, 1]) and s[0, 2] == pytest.approx(s[1, 3])
    assert abs(s[0, 1]) < 1e-9 and abs(s[0, 3]) < 1e-9
    assert s[0, 0] < 0 and s[0, 2] < 0  # Raibert signs: foot placed towards the error


def test_linear_policy_clips_errors_and_tilt_by_norm():
    pol = zdp_policy.LinearPolicy.from_matrix(-np.array([[0.2, 0, 0.3, 0], [0, 0.2, 0, 0.3]]), 0.3, 0.6, 0.1)
    ax, ay = pol(3.0, 4.0, 0.0, 0.0)  # position error 5 m clipped to 0.3 m (direction kept)
    assert math.hypot(ax, ay) == pytest.approx(0.2 * 0.3)
    assert ay / ax == pytest.approx(4.0 / 3.0)
    ax, ay = pol(0.3, 0.0, 0.6, 0.0)
    assert math.hypot(ax, ay) == pytest.approx(math.sin(0.1))
    unclipped = zdp_policy.LinearPolicy.from_matrix(-np.array([[0.2, 0, 0.3, 0], [0, 0.2, 0, 0.3]]), 0.0, 0.0, 0.0)
    assert unclipped(2.0, 0.0, 0.0, 0.0) == pytest.approx((-0.4, 0.0))


# --- the reduced hopper --------------------------------------------------------------------


@pytest.fixture(scope="module")
def hopper() -> zdp.HopperModel:
    return hopper_model("indoor")


def test_hopper_model_is_read_from_the_mjcf(hopper):
    robot = rd.robot_params("indoor")
    assert hopper.mass == pytest.approx(robot.total_mass)
    assert hopper.mass_foot == pytest.approx(robot.foot_mass)
    assert hopper.spring_k == robot.spring_stiffness
    # the whole-robot CoM to foot-contact distance agrees with RobotParams
    assert hopper.foot_radius + hopper.com_to_pivot(0.0) == pytest.approx(robot.leg_length + robot.com_offset_body[2])


def test_periodic_preload_repeats_the_hop_and_no_preload_decays(hopper):
    h = 0.1
    vz = -math.sqrt(2 * hopper.gravity * h)
    d = zdp.periodic_preload(hopper, h)
    assert 0.0 < d < hopper.travel
    r = zdp.impact_map(hopper, np.zeros((1, 4)), vz, np.zeros((1, 2)), d)
    assert r.vz[0] == pytest.approx(vz, abs=2e-3)
    assert r.stance_time[0] == pytest.approx(math.pi * math.sqrt(hopper.mass_sprung / hopper.spring_k), rel=0.1)
    passive = zdp.impact_map(hopper, np.zeros((1, 4)), vz, np.zeros((1, 2)), 0.0)
    assert abs(passive.vz[0]) < abs(vz)  # the foot's impacts lose energy


def test_impact_map_is_translation_invariant_and_mirror_symmetric(hopper):
    d = zdp.periodic_preload(hopper, 0.1)
    z = np.array([[0.0, 0.0, 0.2, -0.1]])
    eta = np.array([[0.03, 0.05]])
    base = zdp.impact_map(hopper, z, -1.4, eta, d).z[0]
    shifted = zdp.impact_map(hopper, z + [1.0, -2.0, 0, 0], -1.4, eta, d).z[0]
    assert np.allclose(shifted - base, [1.0, -2.0, 0, 0], atol=1e-9)  # Assumption 5.9
    mirrored = zdp.impact_map(hopper, z * [1, 1, -1, -1], -1.4, -eta, d).z[0]
    assert np.allclose(mirrored, -base, atol=1e-9)  # point reflection of the horizontal plane


# --- linearization against the twin ----------------------------------------------------------


class TwinImpactMap:
    """One hop of the MuJoCo twin from a pre-impact state, with the foot cycle the low level
    runs (wound preload, released at touchdown) and no wheel torque: the ``Omega`` map."""

    def __init__(self, preload: float, hop_height: float):
        self.model = tm.load_model("indoor")
        self.robot = rd.robot_params("indoor")
        self.preload = preload
        self.vz = -math.sqrt(2 * self.robot.gravity * hop_height)
        m = self.model
        self.root_q = int(m.joint(rd.ROOT_JOINT).qposadr[0])
        self.root_v = int(m.joint(rd.ROOT_JOINT).dofadr[0])
        self.slide_q = int(m.joint(rd.FOOT_JOINT).qposadr[0])
        self.spool_q = int(m.joint(rd.FOOT_MOTOR_JOINT).qposadr[0])
        self.spool_v = int(m.joint(rd.FOOT_MOTOR_JOINT).dofadr[0])
        self.touch = int(m.sensor("foot_force").adr[0])
        self.foot_act = int(m.actuator(rd.FOOT_ACTUATOR).id)
        self.torso = m.body(rd.TORSO).id

    def com(self, data) -> tuple[np.ndarray, np.ndarray]:
        mujoco.mj_subtreeVel(self.model, data)
        return data.subtree_com[self.torso].copy(), data.subtree_linvel[self.torso].copy()

    def __call__(self, z: np.ndarray, eta: np.ndarray) -> np.ndarray:
        return np.array([self.one(zi, ei) for zi, ei in zip(z, eta, strict=True)])

    def one(self, z: np.ndarray, eta: np.ndarray) -> np.ndarray:
        m, r = self.model, self.robot
        data = mujoco.MjData(m)
        ax, ay = eta
        axis = np.array([ax, ay, math.sqrt(1 - ax * ax - ay * ay)])
        from onboard.geometry import quaternion as qt

        q = qt.from_axis_yaw(axis, 0.0)
        data.qpos[self.root_q + 3:self.root_q + 7] = q
        data.qpos[self.slide_q] = self.preload
        data.qpos[self.spool_q] = self.preload / r.spool_radius
        # place the foot's contact point 1 mm above the floor, then set the CoM state
        mujoco.mj_forward(m, data)
        foot_bottom = data.xpos[m.body(rd.FOOT).id][2] - r.foot_radius
        data.qpos[self.root_q + 2] -= foot_bottom - 1e-3
        mujoco.mj_forward(m, data)
        c, _ = self.com(data)
        data.qpos[self.root_q:self.root_q + 2] += z[:2] - c[:2]
        data.qvel[self.root_v:self.root_v + 3] = [z[2], z[3], self.vz]
        mujoco.mj_forward(m, data)
        k = r.spring_stiffness * r.spool_radius
        stance, done = False, False
        for _ in range(2000):
            contact = data.sensordata[self.touch] > 1.0
            if contact and not stance:
                stance = True
            elif stance and not contact and data.qpos[self.slide_q] < 1e-3:
                done = True
            if done and contact:
                break
            if stance and not done:  # released: unwind at full torque
                data.ctrl[self.foot_act] = -10.0
            else:  # hold / wind the preload
                err = self.preload / r.spool_radius - data.qpos[self.spool_q]
                data.ctrl[self.foot_act] = k * min(data.qpos[self.slide_q], self.preload) + 10.0 * err - 0.2 * data.qvel[self.spool_v]
            mujoco.mj_step(m, data)
        else:
            raise AssertionError("no second touchdown")
        c, v = self.com(data)
        return np.array([c[0], c[1], v[0], v[1]])


def test_reduced_linearization_agrees_with_the_twin(hopper):
    h = 0.1
    d = zdp.periodic_preload(hopper, h)
    a_red, b_red = zdp.linearize(zdp.reduced_step(hopper, h, d))
    twin = TwinImpactMap(d, h)
    a_tw, b_tw = zdp.linearize(twin, dz=(0.01, 0.01, 0.02, 0.02), deta=0.01)
    # the entries that carry the dynamics: velocity and position gain per hop
    for i, j in [(0, 2), (2, 2)]:
        assert a_tw[i, j] == pytest.approx(a_red[i, j], rel=0.08), (i, j)
    for i, j in [(0, 0), (2, 0)]:
        assert b_tw[i, j] == pytest.approx(b_red[i, j], rel=0.08), (i, j)
    # position is a pure translation in both
    assert a_tw[0, 0] == pytest.approx(1.0, abs=0.02)
    assert abs(a_tw[2, 0]) < 0.05
