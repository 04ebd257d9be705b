"""The hopping leg as the state estimator sees it: the CoM relative to the foot, the touchdown
impact and the spring's push (thesis 5.5, lines 2751-2755: projectile dynamics in flight, the
foot pinned in stance; the impact map of ch. 2's hybrid model).

Part of :class:`~onboard.estimation.estimator.StateEstimator`, which owns the state and passes
the attitude (``rot``: R row-major, body to world), the body rate [rad/s, body] and the foot's
compression and rate [m, m/s, along body +z] in; everything here is pure arithmetic on the
robot's geometry (:class:`RobotGeometry`):

- leg kinematics: the CoM velocity relative to the foot sphere's contact point (rolling) or its
  centre, and the CoM's position above the contact point (the odometry's anchor);
- the impact map: the ground stops the foot, the CoM loses the foot's share of momentum;
- without an accelerometer, the specific force the spring pushes the sprung body with.

Frames: world z up; body = torso frame, origin at the point the pose sensor reports, z up
along the leg. The foot slides along body z, so compression ``s`` moves the foot sphere up by
``s`` and the CoM by ``mu s`` (``mu``: the foot's share of the mass).
"""

from __future__ import annotations

from typing import Protocol

from onboard.geometry.quaternion import Vec3

FOOT_RANGE_MARGIN_M = 0.01  # [m] foot compression reading tolerated outside its travel
FOOT_EXTENDED_M = 0.001  # [m] below this compression the spring (~12 N) no longer holds the foot down

Rot = tuple[float, float, float, float, float, float, float, float, float]  # R, row-major


class RobotGeometry(Protocol):
    """What the estimator needs of the robot (``sim_twin.model.RobotParams`` has it)."""

    gravity: float  # [m/s^2]
    total_mass: float  # [kg]
    foot_mass: float  # unsprung mass [kg]
    com_offset_body: tuple[float, float, float]  # CoM from the torso origin, foot extended [m, body]
    leg_length: float  # torso origin to the foot's lowest point, foot extended [m]
    foot_radius: float  # contact sphere [m]
    foot_travel: float  # maximum compression [m]
    spring_stiffness: float  # leg spring [N/m]
    spring_damping: float  # [N s/m]


class LegModel:
    """The leg's kinematics, impact map and spring, from the robot's geometry."""

    def __init__(self, robot: RobotGeometry) -> None:
        mu = robot.foot_mass / robot.total_mass
        self.mu_foot = mu
        self.mu_sprung = 1.0 - mu
        c0 = tuple(float(v) for v in robot.com_offset_body)
        self.com_offset: Vec3 = (c0[0], c0[1], c0[2])  # CoM from the torso origin, foot extended [m, body]
        self.foot_travel = robot.foot_travel
        self.foot_radius = robot.foot_radius
        # the spring's push per metre of compression and per m/s of its rate, on the sprung body [m/s^2]
        m_sprung = robot.total_mass - robot.foot_mass
        self.spring_sf = (robot.spring_stiffness / m_sprung, robot.spring_damping / m_sprung)
        # CoM relative to the foot sphere's centre at zero compression [m, body]
        self.r_cf0 = (c0[0], c0[1], c0[2] + robot.leg_length - robot.foot_radius)

    def in_range(self, s: float) -> bool:
        """Whether a foot compression reading [m] lies within the travel (and a margin)."""
        return -FOOT_RANGE_MARGIN_M <= s <= self.foot_travel + FOOT_RANGE_MARGIN_M

    def com_from_contact(self, r: Rot, s: float) -> Vec3:
        """The CoM from the foot's contact point [m, world]: the lever to the foot sphere's centre, then its radius."""
        bx, by, bz = self.r_cf0
        bz -= self.mu_sprung * s
        return (r[0] * bx + r[1] * by + r[2] * bz, r[3] * bx + r[4] * by + r[5] * bz,
                r[6] * bx + r[7] * by + r[8] * bz + self.foot_radius)

    def velocity(self, r: Rot, omega: Vec3, s: float, sd: float, rolling: bool) -> Vec3:
        """CoM velocity [m/s, world] relative to the foot sphere's contact point
        (``rolling``) or to the sphere's centre, from attitude, body rate and the foot."""
        wx, wy, wz = omega
        k = self.mu_sprung
        bx, by, bz = self.r_cf0
        bz -= k * s
        # CoM - sphere centre in world, plus the sphere radius up to the contact point
        lx = r[0] * bx + r[1] * by + r[2] * bz
        ly = r[3] * bx + r[4] * by + r[5] * bz
        lz = r[6] * bx + r[7] * by + r[8] * bz
        if rolling:
            lz += self.foot_radius
        ox = r[0] * wx + r[1] * wy + r[2] * wz
        oy = r[3] * wx + r[4] * wy + r[5] * wz
        oz = r[6] * wx + r[7] * wy + r[8] * wz
        d = -k * sd  # d/dt of the body-z offset
        return (
            oy * lz - oz * ly + r[2] * d,
            oz * lx - ox * lz + r[5] * d,
            ox * ly - oy * lx + r[8] * d,
        )

    def lever_rate2(self, omega: Vec3, sd: float) -> float:
        """How fast the lever to the foot turns and stretches, squared: ``(|w| |r| + |r'|)^2`` as the
        leg velocity's variance per unit attitude variance."""
        wx, wy, wz = omega
        bx, by, bz = self.r_cf0
        return (wx * wx + wy * wy + wz * wz) * (bx * bx + by * by + bz * bz) + (self.mu_sprung * sd) ** 2

    def impact(self, r: Rot, omega: Vec3, free_foot: tuple[float, float], com_velocity: Vec3) -> Vec3:
        """Impact map: the CoM's velocity jump [m/s, world] when the ground stops the foot, from the
        foot's compression and rate (``free_foot``) at the last reading before it hit."""
        # the foot's motion relative to the body just before it hit (now the spring is compressing)
        rx, ry, rz = self.velocity(r, omega, free_foot[0], free_foot[1], False)
        vx, vy, vz = com_velocity
        m = self.mu_foot
        # foot velocity = CoM velocity - (CoM relative to the foot)'
        return (-m * (vx - rx), -m * (vy - ry), -m * (vz - rz))

    def spring_specific_force(self, s: float, sd: float) -> float:
        """The specific force along the leg [m/s^2, body z] the spring pushes the sprung body with
        in stance (no accelerometer to read it)."""
        k, c = self.spring_sf
        return max(0.0, k * s + c * sd)  # the spring only pushes
