"""The geometric MPC as the mid level: state estimate and CoM reference in, setpoint out.

Per solve (``GeometricMpcParams.rate_hz``, 100 Hz as in the thesis):

1. the estimate becomes the MPC's manifold state: the torso position and velocity from the
   CoM's (the offset from the robot description), wheel angles zero (no term of the dynamics
   or the cost depends on them), the foot's rate zero in flight (the cable holds it);
2. the mode sequence from the predicted impact (ballistic to the last touchdown height, as if
   upright) or lift-off (the spring's oscillation), :func:`onboard.low_level.planning.geometric_mpc.mode_schedule`;
3. the target per knot: the reference sampled at the knot's time (held position when none),
   upright at the heading held since the first solve;
4. :meth:`GeometricMpc.solve`; an answer that failed its checks is counted and dropped (the
   low level then falls back to the ZDP once the last setpoint is stale), never published.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from onboard.low_level.planning import geometric_mpc as gm
from onboard.geometry import quaternion as qt
from onboard.contracts.reference import sample_reference
from onboard.contracts.messages import ComReference, MidLevelSetpoint, StateEstimate
from onboard.contracts.params import ControlParams, GeometricMpcParams
from onboard.estimation.phase import PhaseDetector

NS = 1_000_000_000
# (CoM minus torso origin [m, world], CoM velocity minus torso velocity [m/s]) at a manifold state
ComOffset = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


class GmpcMidLevel:
    """Holds the MPC, the phase, the held place and heading, and the rejection count."""

    def __init__(
        self,
        mpc: gm.GeometricMpc,
        com_offset: ComOffset,
        params: GeometricMpcParams,
        control: ControlParams,
        touchdown_height: float,
        stance_omega: float,
        gravity: float,
    ) -> None:
        self.mpc = mpc
        self.p = params
        self._com_offset = com_offset
        self._g = gravity
        self._stance_omega = stance_omega
        self.flight_time = 2.0 * math.sqrt(2.0 * control.hop_height / gravity)  # nominal hop [s]
        self.stance_time = math.pi / stance_omega
        self.phase = PhaseDetector(control.min_flight_s, control.min_stance_s, touchdown_height)
        self.lead_s = 1.0 / params.rate_hz  # the setpoint is tracked until the next solve arrives
        self.hold: tuple[float, float] | None = None
        self.yaw: float | None = None
        self.solves = 0
        self.rejected = 0
        self.last_status = ""
        self.last_solution: gm.GmpcSolution | None = None

    def manifold_state(self, s: StateEstimate, stance: bool) -> np.ndarray:
        """The estimate as the MPC's 21-number state (module docstring, step 1)."""
        x = np.zeros(gm.STATE_DIM + 1)
        x[3:7] = qt.normalize(s.quat)
        x[10] = s.foot_pos
        x[14:17] = s.omega
        x[17:20] = s.wheel_vel
        x[20] = s.foot_vel if stance else 0.0
        dp, dv = self._com_offset(x)  # position and linear velocity still zero: the offsets alone
        x[0:3] = np.asarray(s.position) - dp
        x[11:14] = np.asarray(s.velocity) - dv
        return x

    def _targets(self, now_ns: int, s: StateEstimate, ref: ComReference | None, knots: list[gm.Knot]) -> tuple[np.ndarray, np.ndarray]:
        """CoM positions and velocities at the knots' start times, and at the horizon's end."""
        times = [k.t for k in knots] + [knots[-1].t + knots[-1].h]
        pos = np.empty((len(times), 3))
        vel = np.zeros((len(times), 3))
        pos[:, 2] = s.position[2]  # the height is the hop regulator's
        if ref is None or ref.hold:
            if ref is not None:
                p0 = ref.segments[0].control_points[0]
                self.hold = (p0[0], p0[1])
            elif self.hold is None:
                self.hold = (s.position[0], s.position[1])
            pos[:, 0], pos[:, 1] = self.hold
            return pos, vel
        self.hold = None
        base = (now_ns - ref.t_ref_ns) / NS
        for i, t in enumerate(times):
            x, y, vx, vy = sample_reference(ref, base + t)
            pos[i, 0], pos[i, 1], vel[i, 0], vel[i, 1] = x, y, vx, vy
        return pos, vel

    def step(self, now_ns: int, s: StateEstimate, ref: ComReference | None) -> MidLevelSetpoint | None:
        """One solve; None when the estimate is unusable or the answer failed its checks."""
        self.phase.update(now_ns, s)
        stance = self.phase.phase != "flight"
        if not (s.valid and all(map(math.isfinite, (*s.position, *s.velocity, *s.quat, *s.omega, *s.wheel_vel, s.foot_pos, s.foot_vel)))):
            self.rejected += 1
            self.last_status = "estimate not usable"
            return None
        if self.yaw is None:
            self.yaw = qt.yaw_of(s.quat)
        x0 = self.manifold_state(s, stance)
        if stance:
            event = gm.time_to_liftoff(s.foot_pos, s.foot_vel, self._stance_omega, self._g, self.stance_time)
        else:
            event = gm.time_to_touchdown(s.position[2], s.velocity[2], self.phase.touchdown_height, self._g)
        knots = gm.mode_schedule(gm.STANCE if stance else gm.FLIGHT, event, self.p, self.flight_time, self.stance_time)
        com_pos, com_vel = self._targets(now_ns, s, ref, knots)
        offset = x0[0:3] - np.asarray(s.position)  # torso minus CoM, held over the horizon
        q0 = tuple(x0[3:7])
        z_ref = gm.reference_states(q0, com_pos + offset, com_vel, qt.from_axis_yaw((0.0, 0.0, 1.0), self.yaw))
        sol = self.mpc.solve(x0, knots, z_ref)
        self.solves += 1
        self.last_status = sol.status
        self.last_solution = sol
        if not sol.ok:
            self.rejected += 1
            return None
        q_d, w_d, u_ff = sol.setpoint(self.lead_s)
        times, quats, omegas, torques = sol.plan(self.p.setpoint_plan_s)
        # lists, as the message's schema says and as it arrives decoded in real time: the compiled
        # low level (setup.py) checks the types it reads
        return MidLevelSetpoint(stamp_ns=now_ns, quat_des=list(q_d), omega_des=list(w_d), torque_ff=list(u_ff),
                                qp_iterations=list(sol.qp_iterations), plan_t=list(times), plan_quat=[list(q) for q in quats],
                                plan_omega=[list(w) for w in omegas], plan_torque=[list(u) for u in torques])
