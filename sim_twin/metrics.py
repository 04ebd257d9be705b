"""Run metrics computed from the physics (true CoM, true contacts, true tilt), never from the stack's belief.

Shared by the lockstep runner and the real-time twin service. Definitions:

- ``hops``: completed flights (lift-off then touchdown of the foot, airborne >= ``MIN_FLIGHT_S``);
- ``falls``: fall episodes. The robot is down while it tilts over ``SafetyLimits.tilt_max`` or any
  robot geom other than the foot touches the ground (floor or terrain); an episode begins when it
  goes down and ends when it has been up again for ``RECOVERY_S``. A run stops at the first fall
  unless it keeps going (``archer sim --keep-going``), so only then can this exceed 1;
  ``fall_time_s`` and ``fall_reason`` are the first fall's. In a scenario that flips
  (``Scenario.flip_requests_s``) a tilt is the manoeuvre only in a flight that starts while a
  request is pending (made, not yet turned, and at most ``FLIP_PENDING_S`` old): there it is a
  fall only on the ground (an upside-down landing); any other flight keeps the tilt bound;
- ``full_turns``, ``flight_turn_max_deg`` and ``flight_turns_deg`` (flip scenarios only): flights
  in which the body turned at least ``FULL_TURN`` about horizontal axes, the most any flight
  turned, and every flight's turn past ``TURN_REPORTED`` (so each flip's angle can be read),
  from the true body rate;
- ``recoveries``: fall episodes that ended (the robot was back up, by itself or by a push);
- ``collisions``: contact episodes between the robot and an obstacle, whoever moved; each is put down at
  its first contact to the one that moved into the other (``collisions_by_robot``: the velocity of the
  robot's touching point toward the obstacle along the contact normal is at least the obstacle's toward
  the robot;
  ``collisions_by_obstacle`` otherwise: a mover of the scenario, ``Scenario.velocities``, came at it);
  ``collision_events`` lists each with its time, who moved, the robot's tilt at that contact and the
  seconds since an obstacle last came at it, so a robot knocked over by one mover and falling into
  another can be read apart from one that walked into it (movers only);
- ``keep_out_touchdowns``: touchdowns with the foot on ground the scenario keeps the robot off (a
  sidewalk's grass, ``Scenario.keep_out``; no geom, so no contact says so), where it has any;
- tracking errors: horizontal distance between the true CoM and the active reference evaluated at
  the same time, at every touchdown (``rms_/max_tracking_error_m``, the issue-4 definition) and over
  the whole run sampled every ``TRACE_EVERY`` ticks (``*_continuous_m``);
- ``goal_reached``: the final CoM is within the goal tolerance of the target (the goal, or the
  start for in-place scenarios) and the robot did not fall;
- ``torque_saturation_fraction``: wheel-ticks whose commanded torque reached or exceeded what the
  limits and the motor curve allow (:class:`sim_twin.actuation.Actuation`), whoever clamped it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import mujoco
import numpy as np

from onboard.contracts import messages as m
from onboard.contracts.params import SafetyLimits
from robot_description import params as rd
from sim_twin import scenarios as sc
from sim_twin.actuation import Actuation
from sim_twin.stack import TruthEstimator

NS = 1_000_000_000
MIN_FLIGHT_S = 0.08  # [s] an airborne spell shorter than this (apex < 8 mm) is a chatter, not a hop
FULL_TURN = 0.9 * 2.0 * math.pi  # [rad] a flight turning the body this far counts as a flip
TURN_REPORTED = 0.25 * math.pi  # [rad] flights turning further are listed one by one
# [s] a flip request not turned by then was refused or dropped (the low level gives up after
# control.flip_pump_hops hops of about 0.6 s): later flights keep the tilt bound
FLIP_PENDING_S = 8.0
RECOVERY_S = 0.5  # [s] up this long ends a fall: a fallen robot rocking on its housing is one fall
TRACE_EVERY = 10  # ticks between trace samples (plots, continuous tracking error)
HIT_REPORTED_S = 2.0  # [s] a collision this soon after an obstacle came at the robot says how soon


@dataclass
class Trace:
    t: list[float] = field(default_factory=list)
    com: list[tuple[float, float, float]] = field(default_factory=list)
    est: list[tuple[float, float, float]] = field(default_factory=list)
    ref: list[tuple[float, float]] = field(default_factory=list)
    wheel_vel: list[tuple[float, float, float]] = field(default_factory=list)
    torque: list[tuple[float, float, float, float]] = field(default_factory=list)
    tracking_error: list[float] = field(default_factory=list)
    impacts: list[tuple[float, float, float, float, float]] = field(default_factory=list)  # t, x, y, ref x, ref y


class ContactClassifier:
    """Which geoms are robot, foot, ground (floor / terrain) and obstacles."""

    def __init__(self, model: mujoco.MjModel) -> None:
        torso = model.body(rd.TORSO).id
        foot = model.body(rd.FOOT).id
        n = model.ngeom
        robot, feet, ground, obstacle = np.zeros(n, bool), np.zeros(n, bool), np.zeros(n, bool), np.zeros(n, bool)
        index = [-1] * n  # the obstacle's index in the scenario, from its name obstacle_<k>
        for g in range(n):
            chain = [int(model.geom_bodyid[g])]
            while chain[-1] != 0:
                chain.append(int(model.body_parentid[chain[-1]]))
            name = model.geom(g).name
            if torso in chain:
                robot[g] = True
                feet[g] = foot in chain
            elif name == "floor" or name.startswith(sc.TERRAIN_PREFIX):
                ground[g] = True
            elif name.startswith(sc.OBSTACLE_PREFIX):
                obstacle[g] = True
                tail = name[len(sc.OBSTACLE_PREFIX):]
                index[g] = int(tail) if tail.isdigit() else -1
        self.robot, self.foot, self.ground, self.obstacle = robot.tolist(), feet.tolist(), ground.tolist(), obstacle.tolist()
        self.obstacle_index = index
        self.body_of: list[int] = [int(b) for b in model.geom_bodyid]

    def classify(self, data: mujoco.MjData) -> tuple[bool, bool, bool]:
        """(foot on ground, other robot part on ground, robot touching an obstacle)."""
        foot_ground = body_ground = obstacle = False
        geoms = data.contact.geom
        rob, fo, gr, ob = self.robot, self.foot, self.ground, self.obstacle
        for k in range(data.ncon):
            a, b = int(geoms[k, 0]), int(geoms[k, 1])
            if rob[b] and not rob[a]:
                a, b = b, a
            if not rob[a]:
                continue
            if gr[b]:
                if fo[a]:
                    foot_ground = True
                else:
                    body_ground = True
            elif ob[b]:
                obstacle = True
        return foot_ground, body_ground, obstacle

    def obstacle_contacts(self, data: mujoco.MjData) -> list[tuple[float, float, int, int, int]]:
        """Each robot-obstacle contact: its horizontal normal from the robot toward the obstacle (unit;
        zero for a vertical one), the obstacle's index in the scenario, the robot's body that touches
        and the contact's index in ``data.contact``."""
        out = []
        geoms = data.contact.geom
        frames = data.contact.frame
        for k in range(data.ncon):
            a, b = int(geoms[k, 0]), int(geoms[k, 1])
            sign = 1.0  # the frame's normal points from geom 1 to geom 2
            if self.robot[b] and not self.robot[a]:
                a, b, sign = b, a, -1.0
            if not (self.robot[a] and self.obstacle[b]):
                continue
            nx, ny = sign * float(frames[k, 0]), sign * float(frames[k, 1])
            norm = math.hypot(nx, ny)
            if norm > 1e-9:
                nx, ny = nx / norm, ny / norm
            else:
                nx = ny = 0.0
            out.append((nx, ny, self.obstacle_index[b], self.body_of[a], k))
        return out


def reference_at(ref: m.ComReference, now_ns: int) -> tuple[float, float]:
    if ref.hold:
        p = ref.segments[0].control_points[0]
        return p[0], p[1]
    return sc.sample_reference(ref.segments, (now_ns - ref.t_ref_ns) / NS)


def _rms(values: list[float]) -> float | None:
    if not values:
        return None
    return round(math.sqrt(sum(v * v for v in values) / len(values)), 4)


class PhysicsMetrics:
    """Accumulates the metrics tick by tick; :meth:`summary` gives the figures."""

    def __init__(self, model: mujoco.MjModel, scenario: sc.Scenario, truth: TruthEstimator, safety: SafetyLimits) -> None:
        self.scenario = scenario
        self.truth = truth
        self.safety = safety
        self.contacts = ContactClassifier(model)
        self.model = model
        self._body_velocity = np.zeros(6)  # mj_objectVelocity's output, reused
        self.wheel_dof = [int(model.joint(n).dofadr[0]) for n in rd.WHEEL_JOINTS]
        self.qp_root = int(model.joint(rd.ROOT_JOINT).qposadr[0])
        self.qv_root = int(model.joint(rd.ROOT_JOINT).dofadr[0])
        self.cos_tilt_max = math.cos(safety.tilt_max)
        self.target = scenario.target()
        self.trace = Trace()
        self.ticks = 0
        self.hops = self.falls = self.recoveries = self.collisions = 0
        # ground the robot must not hop on (a sidewalk's grass): no geom to collide with, so its touchdowns are counted
        self._keep_out = [(np.array(p.A, dtype=float), np.array(p.b, dtype=float)) for p in (o.polytope() for o in scenario.keep_out)]
        self._foot_body = model.body(rd.FOOT).id
        self.keep_out_touchdowns = 0
        self.collisions_by_robot = self.collisions_by_obstacle = 0
        goal = scenario.goal()
        self._goal_tol = goal.tolerance if goal is not None else sc.GOAL_TOLERANCE
        self.goal_time = math.nan  # [s] when the CoM first came within the goal's tolerance (trace samples)
        self.fell = False  # at least once: what stops a run and fails its goal
        self.down = False  # in a fall episode now
        self._up_since = math.nan  # when a fallen robot was last seen up again
        self.fall_reason = ""
        self.fall_time = math.nan
        self.max_wheel = 0.0
        self.wheel_over_limit = 0
        self._on_ground = False
        self._airborne_since = 0.0
        self._aerial_turns = bool(scenario.flip_requests_s)  # the body turns over in flight on purpose
        self._pending: list[float] = sorted(scenario.flip_requests_s)  # requests not yet turned [s]
        self._turn_flight = False  # this flight started with a request pending: its tilt is the manoeuvre
        self._turned = 0.0  # [rad] the body turned about horizontal axes in this flight (flip scenarios)
        self.turn_max = 0.0  # [rad] the most of any flight
        self.full_turns = 0  # flights that turned the body at least FULL_TURN
        self.turns: list[float] = []  # [rad] every flight's turn past TURN_REPORTED
        self._t_prev = 0.0
        self._in_collision = False
        self.collision_events: list[dict] = []  # t_s, by ("robot" | "obstacle"), tilt_deg, since_hit_s (None: no hit within HIT_REPORTED_S)
        self._last_hit = -math.inf  # [s] the last contact an obstacle came into
        self._impact_err: list[float] = []
        self._cont_err: list[float] = []
        self._est_err: list[float] = []

    def traces_next_tick(self) -> bool:
        """Whether the next :meth:`update` samples the trace (and reads the estimate)."""
        return (self.ticks + 1) % TRACE_EVERY == 0

    def update(self, t: float, now_ns: int, data: mujoco.MjData, reference: m.ComReference | None,
               estimate: m.StateEstimate | None, applied: tuple[float, float, float, float]) -> None:
        """After the physics step at sim time ``t`` [s]; ``now_ns`` is the time base of ``reference``."""
        self.ticks += 1
        if data.ncon:
            foot_ground, body_ground, obstacle = self.contacts.classify(data)
        else:
            foot_ground = body_ground = obstacle = False
        if foot_ground and not self._on_ground:
            if self._airborne_since and t - self._airborne_since >= MIN_FLIGHT_S:
                self.hops += 1
            if self._keep_out:
                foot = data.xpos[self._foot_body, :2]
                if any(bool(np.all(a @ foot <= b)) for a, b in self._keep_out):
                    self.keep_out_touchdowns += 1
            if self._aerial_turns:
                self.turn_max = max(self.turn_max, self._turned)
                if self._turned >= TURN_REPORTED:
                    self.turns.append(self._turned)
                if self._turned >= FULL_TURN:
                    self.full_turns += 1
                    if self._pending and self._pending[0] <= t:
                        self._pending.pop(0)  # the oldest request was turned
                self._turned = 0.0
            if reference is not None:
                (px, py, _), _ = self.truth.com(data)
                rx, ry = reference_at(reference, now_ns)
                self._impact_err.append(math.hypot(px - rx, py - ry))
                self.trace.impacts.append((t, px, py, rx, ry))
            self._on_ground = True
        elif not foot_ground and self._on_ground:
            self._on_ground = False
            self._airborne_since = t
            if self._aerial_turns:
                while self._pending and t - self._pending[0] > FLIP_PENDING_S:
                    self._pending.pop(0)  # refused or dropped by the low level
                self._turn_flight = bool(self._pending) and self._pending[0] <= t
        elif not foot_ground and self._airborne_since == 0.0:
            self._airborne_since = t  # the initial drop: a flight start for timing
        qpos = data.qpos.tolist()
        qvel = data.qvel.tolist()
        qx, qy = qpos[self.qp_root + 4], qpos[self.qp_root + 5]
        cos_tilt = 1.0 - 2.0 * (qx * qx + qy * qy)
        tilted = cos_tilt < self.cos_tilt_max
        if obstacle and not self._in_collision:
            self.collisions += 1
            came = self._obstacle_came(data)
            if came:
                self.collisions_by_obstacle += 1
            else:
                self.collisions_by_robot += 1
            since = t - self._last_hit
            self.collision_events.append({"t_s": round(t, 3), "by": "obstacle" if came else "robot",
                                          "tilt_deg": round(math.degrees(math.acos(max(-1.0, min(1.0, cos_tilt)))), 1),
                                          "since_hit_s": round(since, 3) if since <= HIT_REPORTED_S else None})
            if came:
                self._last_hit = t
        self._in_collision = obstacle
        if self._aerial_turns:
            if not foot_ground and self._turn_flight:
                tilted = tilted and body_ground  # turning over in flight is the manoeuvre; landing so is a fall
            if not foot_ground:
                self._turned += self._horizontal_rate(qpos, qvel) * (t - self._t_prev)
            self._t_prev = t
        fallen_now = body_ground or tilted
        if fallen_now:
            self._up_since = math.nan
            if not self.down:
                self.down = True
                self.falls += 1
                if not self.fell:
                    self.fell = True
                    self.fall_time = t
                    self.fall_reason = "body on the ground" if body_ground else "tilt"
        elif self.down:
            if math.isnan(self._up_since):
                self._up_since = t
            elif t - self._up_since >= RECOVERY_S:
                self.down = False
                self.recoveries += 1
        mw = self.max_wheel
        for dof in self.wheel_dof:
            s = abs(qvel[dof])
            if s > mw:
                mw = s
        self.max_wheel = mw
        if mw > self.safety.wheel_speed_max:
            self.wheel_over_limit += 1

        if self.ticks % TRACE_EVERY == 0:
            tr = self.trace
            (px, py, pz), _ = self.truth.com(data)
            rx, ry = reference_at(reference, now_ns) if reference is not None else self.target
            err = math.hypot(px - rx, py - ry)
            self._cont_err.append(err)
            if math.isnan(self.goal_time) and math.hypot(px - self.target[0], py - self.target[1]) <= self._goal_tol:
                self.goal_time = t
            tr.t.append(t)
            tr.com.append((px, py, pz))
            if estimate is not None:
                sp = estimate.position
                self._est_err.append(math.dist((px, py, pz), sp))
                tr.est.append((sp[0], sp[1], sp[2]))
            tr.ref.append((rx, ry))
            tr.wheel_vel.append(tuple(qvel[d] for d in self.wheel_dof))
            tr.torque.append(applied)
            tr.tracking_error.append(err)

    def _obstacle_came(self, data: mujoco.MjData) -> bool:
        """Whether the obstacle moved into the robot: faster along a contact normal than the robot's
        touching point moved into it. The point's velocity, not the CoM's: a body tipping or swinging
        into an obstacle closes the gap while its CoM may move away (sliding-fast seed 1033 touched a
        slider with both CoMs moving apart). A tie (both still or separating) is the robot's."""
        vel = self.scenario.velocities
        spin = self._body_velocity
        robot_in = obstacle_in = 0.0
        for nx, ny, k, body, c in self.contacts.obstacle_contacts(data):
            mujoco.mj_objectVelocity(self.model, data, mujoco.mjtObj.mjOBJ_BODY, body, spin, 0)  # [w; v] at the body's origin
            wx, wy, wz, vx, vy, _ = spin.tolist()
            px, py, pz = data.contact.pos[c].tolist()
            ox, oy, oz = data.xpos[body].tolist()
            rx, ry, rz = px - ox, py - oy, pz - oz
            # the touching point: v + w x r
            robot_in = max(robot_in, (vx + wy * rz - wz * ry) * nx + (vy + wz * rx - wx * rz) * ny)
            if 0 <= k < len(vel):
                obstacle_in = max(obstacle_in, -(float(vel[k, 0]) * nx + float(vel[k, 1]) * ny))
        return obstacle_in > robot_in

    def _horizontal_rate(self, qpos: list[float], qvel: list[float]) -> float:
        """The true body rate about world-horizontal axes [rad/s] (the free joint's rate is in the body frame)."""
        w, x, y, z = qpos[self.qp_root + 3:self.qp_root + 7]
        wx, wy, wz = qvel[self.qv_root + 3:self.qv_root + 6]
        gx, gy = 2.0 * (x * z - w * y), 2.0 * (y * z + w * x)  # world z in the body frame: the rate about it is yaw
        gz = 1.0 - 2.0 * (x * x + y * y)
        about_up = wx * gx + wy * gy + wz * gz
        return math.sqrt(max(0.0, wx * wx + wy * wy + wz * wz - about_up * about_up))

    def summary(self, data: mujoco.MjData, actuation: Actuation) -> dict:
        (px, py, _), _ = self.truth.com(data)
        final_err = math.hypot(px - self.target[0], py - self.target[1])
        goal = self.scenario.goal()
        tol = goal.tolerance if goal is not None else sc.GOAL_TOLERANCE
        impact, cont = self._impact_err, self._cont_err
        return {
            "hops": self.hops,
            "falls": self.falls,
            "recoveries": self.recoveries,
            "fall_time_s": None if math.isnan(self.fall_time) else round(self.fall_time, 4),
            "fall_reason": self.fall_reason,
            "collisions": self.collisions,
            **({"keep_out_touchdowns": self.keep_out_touchdowns} if self._keep_out else {}),
            # who moved: only where obstacles move (a static world's collisions are all the robot's)
            **({"collisions_by_robot": self.collisions_by_robot, "collisions_by_obstacle": self.collisions_by_obstacle,
                "collision_events": self.collision_events}
               if self.scenario.movers else {}),
            # where the scenario has a goal to go to: when the CoM first came within its tolerance (the pace)
            **({"time_to_goal_s": None if math.isnan(self.goal_time) else round(self.goal_time, 3)} if goal is not None else {}),
            "goal_reached": bool(final_err <= tol and not self.fell),
            "final_goal_error_m": round(final_err, 4),
            "rms_tracking_error_m": _rms(impact),
            "max_tracking_error_m": round(max(impact), 4) if impact else None,
            "rms_tracking_error_continuous_m": _rms(cont),
            "max_tracking_error_continuous_m": round(max(cont), 4) if cont else None,
            "estimate_rms_error_m": _rms(self._est_err),
            "max_wheel_speed_rad_s": round(self.max_wheel, 3),
            "wheel_speed_over_limit_ticks": self.wheel_over_limit,
            "torque_saturation_fraction": round(actuation.saturation_fraction, 5),
            "commands_refused": {k: v for k, v in actuation.counters.items() if k != "applied" and v},
            "world": self.scenario.world_summary(),
            **({"full_turns": self.full_turns, "flight_turn_max_deg": round(math.degrees(self.turn_max), 1),
                "flight_turns_deg": [round(math.degrees(a), 1) for a in self.turns]}
               if self._aerial_turns else {}),
        }
