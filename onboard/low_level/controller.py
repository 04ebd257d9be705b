"""The composed hard-rate low level: ZDP + quaternion PD + spin-down + foot + supervisor.

Interface (used by the ``control`` service and by the twin's lockstep runner):

    ctrl = LowLevelController(control_params, robot, hopper, safety_limits, mlp_weights)
    cmd = ctrl.step(now_ns, state, reference, joints)   # -> TorqueCommand, every 1 ms
    ctrl.drain_phase_events()   # -> list[PhaseEvent]  (touchdown, bottom, liftoff, apex)
    ctrl.drain_safety_events()  # -> list[SafetyEvent] (every trip, to log and publish)
    ctrl.tube(stamp_ns)         # -> TrackingTube      (the measured certificate)
    ctrl.request_arm(); ctrl.disarm(now_ns)
    ctrl.retune(control_params, safety_limits)  # new gains and limits, between two ticks
    sp = ctrl.step_attitude(now_ns, state, reference)  # -> AttitudeSetpoint (ControlParams.output = "attitude")

``robot_description.controller.build_controller(variant, ...)`` builds one from the MJCF (the
robot's parameters and the reduced hopper model) and the policy weights file; use
it rather than the constructor. ``step`` takes the clock time ``now_ns`` [ns], the
latest :class:`~onboard.contracts.messages.StateEstimate`, the latest
:class:`~onboard.contracts.messages.ComReference` (None: hop in place) and the latest
:class:`~onboard.contracts.messages.JointSensors` (the cable spool angle; None: the foot
motor is left unpowered and the hop decays). It never raises on bad data: the
supervisor turns it into a safe command and a counted event.

Per tick:

1. supervisor: estimate fresh and finite, upright, armed? else zero torque; only its
   attitude valid (``Supervisor.attitude_only``, e.g. an IMU gap): step 3's flight
   attitude is upright at the held heading (no position feedback) for the
   supervisor's bound;
2. phase detection; at touchdown the impact error to the reference is recorded in
   the tube and the preload released; at apex the hop-energy loss is learnt;
3. flight: predict the impact (ballistic to the last touchdown height), sample the
   reference there (Corollary 5.8), evaluate the policy ``eta = psi(z - z_ref)``,
   turn it into a desired attitude (leg axis + held heading) and run the quaternion
   PD on the wheels; wind the spring preload;
   stance: spin the wheels down; keep the cable slack;
4. supervisor: clamp to the limits.

Attitude mode (``ControlParams.output = "attitude"``, :meth:`LowLevelController.step_attitude`):
the hardware runs the quaternion PD itself (ARCHER's flywheel board) and the foot's hop
cycle (its foot board), so the tick stops at the desired attitude: in flight the ZDP's
(step 3, the same policy) at zero rate; in stance the estimated attitude and rate, so
that the board's PD adds nothing to the spin-down sent as the wheels' feed-forward (as
step 3's stance: holding a tilted landing attitude against gravity on the foot ran the
wheels away, 600 rad/s in 4 s on the twin); upright until the first flight (balancing
while it stands); no foot command. Phases come from the estimate's contact, i.e. the foot board's
contact reports. The firmware's PD takes the gains as they are set on the board.

Frames: world z up; ``eta`` is the world-frame horizontal part of the body z axis at
impact (the foot lands at ``-leg * axis`` from the CoM).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol, cast

import numpy as np

from onboard.low_level.tracking import attitude_control as ac
from onboard.geometry import quaternion as qt
from onboard.low_level.planning import zdp, zdp_policy
from onboard.low_level.planning.balance import BalancePoint
from onboard.low_level.planning.momentum import MomentumGovernor
from onboard.low_level.tracking.excitation import heading_swing, wheel_dither
from onboard.low_level.tracking.flip import FlipLimits, FlipManoeuvre
from onboard.low_level.tracking.foot_control import FootPhysics, HopRegulator
from onboard.contracts.messages import (AttitudeSetpoint, ComReference, JointSensors, MidLevelSetpoint, PhaseEvent, SafetyEvent, StateEstimate,
                              TorqueCommand, TrackingTube)
from onboard.low_level.planning.mlp import Mlp
from onboard.contracts.params import ControlParams, SafetyLimits, restart_changes
from onboard.estimation.phase import PhaseDetector
from onboard.low_level.tracking.supervisor import Supervisor
from onboard.contracts.tube import TubeMonitor
from onboard.contracts.reference import sample_reference

NS = 1_000_000_000
POLICIES = ("zdp", "lqr", "raibert", "mlp")
SPOOL_VEL_FILTER = 0.3  # first-order filter weight of the differenced spool speed (1 kHz)


class RobotLike(Protocol):
    """The fields of ``sim_twin.model.RobotParams`` the low level reads."""

    wheel_axes: tuple[tuple[float, float, float], ...]
    total_mass: float
    gravity: float
    spring_stiffness: float
    spool_radius: float
    foot_travel: float
    wheel_torque_peak: float
    foot_torque_peak: float
    inertia_com: tuple[tuple[float, float, float], ...]
    wheel_spin_inertia: float
    com_offset_body: tuple[float, float, float]
    hop_speed_max: float


@dataclass(frozen=True)
class PolicyDesign:
    """What the constructor derives from the reduced model (kept for reports/tests)."""

    preload_nominal: float  # periodic in-place hop preload [m]
    loss_nominal: float  # energy loss per hop [J]
    linear: zdp.LinearZdp  # linearization, LQR and S_eta


def design_policy(params: ControlParams, hopper: zdp.HopperModel) -> PolicyDesign:
    """Linearize the reduced impact map at the in-place hop and build the ZDP."""
    d = zdp.periodic_preload(hopper, params.hop_height)
    a_zz, a_ze = zdp.linearize(zdp.reduced_step(hopper, params.hop_height, d))
    q_eta = np.eye(2) * params.zdp_q_tilt
    q_z = np.diag([params.zdp_q_pos, params.zdp_q_pos, params.zdp_q_vel, params.zdp_q_vel])
    r = np.eye(2) * params.zdp_r
    lin = zdp.linear_zdp(a_zz, a_ze, q_eta, q_z, r)
    return PolicyDesign(d, 0.5 * hopper.spring_k * d * d, lin)


def _quat(q: Sequence[float]) -> qt.Quat:
    """A setpoint's quaternion (a list decoded, a tuple in lockstep) as the tuple the attitude code takes."""
    return q[0], q[1], q[2], q[3]


def _vec3(v: Sequence[float]) -> ac.Vec3:
    return v[0], v[1], v[2]


def _setpoint_sound(sp: MidLevelSetpoint) -> bool:
    """Every number finite and the plan's lists of matching lengths, times non-decreasing."""
    n = len(sp.plan_t)
    if len(sp.plan_quat) != n or len(sp.plan_omega) != n or len(sp.plan_torque) != max(0, n - 1) or n == 1:
        return False
    if any(b < a for a, b in zip(sp.plan_t, sp.plan_t[1:])):
        return False
    values = [*sp.quat_des, *sp.omega_des, *sp.torque_ff, *sp.plan_t]
    for row in (*sp.plan_quat, *sp.plan_omega, *sp.plan_torque):
        values.extend(row)
    return all(map(math.isfinite, values)) and all(qt.is_finite(q) for q in (sp.quat_des, *sp.plan_quat))


def turn_toward(angle: float, target: float, max_step: float) -> float:
    """``angle`` [rad] moved toward ``target`` the short way round, by at most ``max_step``."""
    d = (target - angle + math.pi) % (2.0 * math.pi) - math.pi
    return angle + max(-max_step, min(max_step, d))


class LowLevelController:
    """See the module docstring."""

    def __init__(
        self,
        params: ControlParams,
        robot: RobotLike,
        hopper: zdp.HopperModel,
        safety: SafetyLimits | None = None,
        mlp_weights: Mapping[str, np.ndarray] | None = None,
    ) -> None:
        if params.policy not in POLICIES:
            raise ValueError(f"unknown policy {params.policy!r}; known: {', '.join(POLICIES)}")
        self.robot = robot
        self.hopper = hopper
        self.design = design_policy(params, hopper)
        self.alloc = ac.WheelAllocation.from_axes(robot.wheel_axes)
        self._zero3 = (0.0, 0.0, 0.0)
        if params.policy == "mlp":
            if mlp_weights is None:
                raise ValueError("policy 'mlp' needs the weights (ControlParams.mlp_weights)")
            self._mlp = Mlp(mlp_weights)
            if (self._mlp.n_in, self._mlp.n_out) != (4, 2):
                raise ValueError(f"ZDP network must map 4 -> 2, got {self._mlp.n_in} -> {self._mlp.n_out}")
        safety = safety or SafetyLimits()
        self.flip = FlipManoeuvre(self._flip_limits(safety), params)
        lin = self.design.linear  # the hop map's velocity row, whatever policy flies: the observer's model
        self.balance = BalancePoint(float(lin.a_zz[2, 2]), float(lin.a_zeta[2, 0]), hopper.com_to_pivot(self.design.preload_nominal),
                                    params.balance_gain, params.balance_innovation_max, params.balance_tilt_max, params.balance_speed_max,
                                    robot.com_offset_body[0], robot.com_offset_body[1])
        limit = safety.wheel_speed_max  # the governor's bounds are shares of it
        self.momentum = MomentumGovernor(robot.hop_speed_max, params.momentum_wheel_share_lo * limit, params.momentum_wheel_share_hi * limit,
                                         params.momentum_speed_min, params.momentum_lead_s, params.momentum_lookahead_hops,
                                         params.momentum_cap_rise)
        self._tune(params, safety)

        self.supervisor = Supervisor(self.safety, params)
        touchdown_h = hopper.touchdown_height(self.design.preload_nominal)
        self.phase = PhaseDetector(params.min_flight_s, params.min_stance_s, touchdown_h)
        self.foot = HopRegulator(
            params,
            FootPhysics(robot.total_mass, robot.gravity, robot.spring_stiffness, robot.spool_radius, robot.foot_travel),
            self.design.loss_nominal,
        )
        self.tube_monitor = TubeMonitor(params.tube_window)
        self._phase_events: list[PhaseEvent] = []
        self._g = robot.gravity
        self._yaw_ref = 0.0
        self._yaw_home = 0.0  # the heading it armed with (the identification routine swings about it)
        self._arm_ns = 0
        self._hold: tuple[float, float] | None = None  # hop-in-place point [m]
        self._was_armed = False
        self._flown = False  # attitude mode: a flight since it armed
        self._spool_prev: tuple[int, float] | None = None
        self._spool_vel = 0.0
        # telemetry (read by the runner and the service status)
        self.q_des: qt.Quat = qt.IDENTITY
        self.eta: tuple[float, float] = (0.0, 0.0)
        self.predicted_impact: tuple[float, float, float] = (0.0, 0.0, 0.0)  # time to impact [s], CoM x, y [m]
        self.reference_at_impact: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
        self.last_impact_error = math.nan  # [m]
        self.holding = True
        self.armed_ticks = 0  # ticks that commanded torque
        self.saturated_ticks = 0  # of those, ticks whose wheel command hit the torque limit
        self.mid_level_ticks = 0  # armed ticks that tracked the geometric MPC's setpoint
        self.mid_level_fallback_ticks = 0  # mid_level = "geometric_mpc", but no fresh, finite setpoint: the ZDP's
        self._mid_checked: MidLevelSetpoint | None = None  # the last setpoint checked, and its verdict
        self._mid_ok = False
        self._lifted_off = False  # a lift-off this tick: the flip decides once the flight is predicted

    def _tune(self, params: ControlParams, safety: SafetyLimits) -> None:
        """What the gains and limits set directly: cheap enough for between two ticks."""
        self.p = params
        self.safety = safety
        self._kp = (params.kp_tilt, params.kp_tilt, params.kp_yaw)
        self._kd = (params.kd_tilt, params.kd_tilt, params.kd_yaw)
        # the controllers saturate at what the actuators deliver; the supervisor's
        # clamps are the safety net behind them, and trip only on a real violation
        self._wheel_max = min(safety.wheel_torque_max, self.robot.wheel_torque_peak)
        self._foot_max = min(safety.foot_torque_max, self.robot.foot_torque_peak)
        self.flip.configure(self._flip_limits(safety), params)
        if hasattr(self, "balance"):  # built after the first _tune
            self.balance.configure(params.balance_gain, params.balance_innovation_max, params.balance_tilt_max, params.balance_speed_max)
            limit = safety.wheel_speed_max  # the governor's bounds are shares of it
            self.momentum.configure(params.momentum_wheel_share_lo * limit, params.momentum_wheel_share_hi * limit, params.momentum_speed_min,
                                    params.momentum_lead_s, params.momentum_lookahead_hops, params.momentum_cap_rise)
        lin = self.design.linear
        self._cruise_lean = params.cruise_feedforward * (1.0 - float(lin.a_zz[2, 2])) / float(lin.a_zeta[2, 0])  # [rad per m/s]
        if params.policy == "zdp":
            self._linear = zdp_policy.LinearPolicy.from_matrix(lin.s_eta, params.pos_err_max, params.vel_err_max, params.tilt_cmd_max)
        elif params.policy == "lqr":  # the plain gain, nothing clipped (thesis Fig. 5.22)
            self._linear = zdp_policy.LinearPolicy.from_matrix(-lin.k_lqr, 0.0, 0.0, 0.0)
        elif params.policy == "raibert":
            kp, kd = params.raibert_kp, params.raibert_kd
            s = -np.array([[kp, 0.0, kd, 0.0], [0.0, kp, 0.0, kd]])
            self._linear = zdp_policy.LinearPolicy.from_matrix(s, params.pos_err_max, params.vel_err_max, params.tilt_cmd_max)
        else:  # the network's inputs and output are clipped as the linear policies' are
            self._linear = zdp_policy.LinearPolicy.from_matrix(np.zeros((2, 4)), params.pos_err_max, params.vel_err_max, params.tilt_cmd_max)

    def _flip_limits(self, safety: SafetyLimits) -> FlipLimits:
        robot = self.robot
        i0, i1, i2 = robot.inertia_com
        return FlipLimits((_vec3(i0), _vec3(i1), _vec3(i2)), self.alloc.axes, robot.wheel_spin_inertia,
                          min(safety.wheel_torque_max, robot.wheel_torque_peak), safety.wheel_speed_max, robot.gravity)

    def retune(self, params: ControlParams, safety: SafetyLimits) -> None:
        """Take new gains and limits between two ticks, keeping every state (armed,
        phase, learnt hop loss, tube). A change of a field in
        :data:`onboard.contracts.params.NEEDS_RESTART` needs a new controller: ValueError."""
        rebuild = restart_changes("control", self.p, params)
        if rebuild:
            raise ValueError(f"{', '.join(rebuild)}: needs a new controller")
        self._tune(params, safety)
        self.supervisor.retune(safety, params)
        self.phase.set_dwell(params.min_flight_s, params.min_stance_s)
        self.foot.retune(params)

    # --- accessors -------------------------------------------------------------------

    def drain_phase_events(self) -> list[PhaseEvent]:
        out, self._phase_events = self._phase_events, []
        return out

    def drain_safety_events(self) -> list[SafetyEvent]:
        return self.supervisor.drain_events()

    def tube(self, stamp_ns: int = 0) -> TrackingTube:
        return self.tube_monitor.tube(stamp_ns)

    @property
    def armed(self) -> bool:
        return self.supervisor.armed

    @property
    def saturation_fraction(self) -> float:
        """Fraction of armed ticks whose wheel command was cut to the torque limit."""
        return self.saturated_ticks / self.armed_ticks if self.armed_ticks else 0.0

    def request_arm(self) -> None:
        self.supervisor.request_arm()

    def disarm(self, now_ns: int, reason: str = "disarm_request") -> None:
        self.supervisor.disarm(now_ns, reason)
        self.flip.cancel()

    def request_flip(self) -> bool:
        """One flip (:mod:`onboard.low_level.tracking.flip`); False if refused (``flip.last_refusal`` says why)."""
        if self.p.output == "attitude":  # the board runs its own PD on a fixed setpoint per message
            self.flip.refuse("attitude output: the hardware's PD tracks no planned turn")
            return False
        return self.flip.request()

    def policy(self, ex: float, ey: float, evx: float, evy: float) -> tuple[float, float]:
        """The impact attitude ``(a_x, a_y)`` for an impact-state error [m, m/s]."""
        if self.p.policy == "mlp":
            lp = self._linear
            ex, ey = zdp_policy.clip_norm(ex, ey, lp.pos_err_max)
            evx, evy = zdp_policy.clip_norm(evx, evy, lp.vel_err_max)
            ax, ay = self._mlp((ex, ey, evx, evy))
            return zdp_policy.clip_norm(ax, ay, math.sin(lp.tilt_max))
        return self._linear(ex, ey, evx, evy)

    # --- the tick ----------------------------------------------------------------------

    def _safe(self, now_ns: int) -> TorqueCommand:
        return TorqueCommand(stamp_ns=now_ns, wheel_torque=[0.0, 0.0, 0.0], foot_torque=0.0, armed=False)

    def safe_setpoint(self, now_ns: int) -> AttitudeSetpoint:
        return AttitudeSetpoint(stamp_ns=now_ns, quat_des=list(self.q_des), omega_des=[0.0, 0.0, 0.0],
                                torque_ff=[0.0, 0.0, 0.0], foot_torque=0.0, armed=False)

    def _check_and_arm(self, now_ns: int, state: StateEstimate) -> bool:
        """The supervisor's verdict on the estimate; on arming hold heading and place, upright."""
        sup = self.supervisor
        flip = self.flip
        if flip.state != "idle" or sup.tilt_exempt:  # ends with the turn, however it ended (a touchdown, a disarm)
            sup.tilt_exempt = flip.tilt_exempt(now_ns)
        if not sup.check_estimate(now_ns, state):
            self._was_armed = sup.armed
            if not sup.armed:
                flip.cancel()
            return False
        if not self._was_armed:  # just armed: hold heading and place
            flip.cancel()
            self._was_armed = True
            self._yaw_ref = qt.yaw_of(state.quat)
            self._yaw_home = self._yaw_ref
            self._arm_ns = now_ns
            self._hold = (state.position[0], state.position[1])
            self.q_des = qt.from_axis_yaw((0.0, 0.0, 1.0), self._yaw_ref)
            self._flown = False
            self.phase.reset()
            self.balance.reset()
            self.momentum.reset()
        return True

    def _phase_update(self, now_ns: int, state: StateEstimate, ref: ComReference | None) -> None:
        ev = self.phase.update(now_ns, state)
        if ev is not None:
            self._phase_events.append(ev)
            self._on_event(now_ns, ev, state, ref)

    def _flight_attitude(self, now_ns: int, state: StateEstimate, ref: ComReference | None) -> qt.Quat:
        """Predict the impact, sample the reference there, the policy's impact attitude (step 3);
        upright while the supervisor trusts the estimate's attitude only."""
        if self.supervisor.attitude_only:
            self.eta = (0.0, 0.0)
            self.q_des = qt.from_axis_yaw((0.0, 0.0, 1.0), self._yaw_ref)
            return self.q_des
        if self.p.identify:  # the identification routine swings the heading (tracking/excitation.py)
            swing = heading_swing((now_ns - self._arm_ns) / NS, self.p.identify_yaw, self.p.identify_yaw_period_s)
            self._yaw_ref = turn_toward(self._yaw_ref, self._yaw_home + swing, self.p.yaw_rate_max / self.p.rate_hz)
        elif ref is not None and ref.yaw is not None:
            self._yaw_ref = turn_toward(self._yaw_ref, ref.yaw, self.p.yaw_rate_max / self.p.rate_hz)
        g = self._g
        px, py, pz = state.position
        vx, vy, vz = state.velocity
        yaw = qt.yaw_of(state.quat)
        dx, dy = self.balance.offset(yaw)  # the CoM where the learnt balance point puts it
        px += dx
        py += dy
        z_td = self.phase.touchdown_height
        disc = vz * vz + 2.0 * g * (pz - z_td)
        t_imp = (vz + math.sqrt(disc)) / g if disc > 0.0 else max(vz / g, 0.0)
        self.foot.in_flight(pz + vz * vz / (2.0 * g) - z_td)  # ballistic apex rise
        xi, yi = px + vx * t_imp, py + vy * t_imp
        rx, ry, rvx, rvy = self._target(now_ns, state, ref, t_imp)
        self.predicted_impact = (t_imp, xi, yi)
        self.reference_at_impact = (rx, ry, rvx, rvy)
        ex, ey, gvx, gvy = self.momentum.target(xi - rx, yi - ry, rvx, rvy)
        ax, ay = self.policy(ex, ey, vx - gvx, vy - gvy)
        ax, ay = ax + self._cruise_lean * gvx, ay + self._cruise_lean * gvy
        bx, by = self.balance.lean(yaw)
        ax, ay = zdp_policy.clip_norm(ax + bx, ay + by, math.sin(self.p.tilt_cmd_max) if self.p.tilt_cmd_max > 0.0 else 0.999)
        self.eta = (ax, ay)
        az = math.sqrt(max(1e-6, 1.0 - ax * ax - ay * ay))
        self.q_des = qt.from_axis_yaw((ax, ay, az), self._yaw_ref)
        return self.q_des

    def step_attitude(self, now_ns: int, state: StateEstimate, reference: ComReference | None) -> AttitudeSetpoint:
        """One tick in attitude mode (module docstring): the setpoint for a PD that runs on the hardware."""
        if not self._check_and_arm(now_ns, state):
            return self.safe_setpoint(now_ns)
        sup = self.supervisor
        ref = sup.check_reference(now_ns, reference)
        self._phase_update(now_ns, state, ref)
        omega = [0.0, 0.0, 0.0]
        if self.phase.phase == "flight":
            q_des = self._flight_attitude(now_ns, state, ref)
            self._flown = True
            ff = self._zero3
        elif not self._flown:  # standing since it armed: upright
            q_des = self.q_des
            ff = self._zero3
        else:  # stance: the PD follows the estimate, the wheels spin down through the feed-forward
            q_des, omega = cast(qt.Quat, tuple(state.quat)), list(state.omega)
            ff = ac.spin_down(state.wheel_vel, self.p.spin_down_gamma)
            wm = self._wheel_max
            ff = (max(-wm, min(wm, ff[0])), max(-wm, min(wm, ff[1])), max(-wm, min(wm, ff[2])))
        self.armed_ticks += 1
        wheel, _ = sup.limit_command(now_ns, ff, 0.0, state.wheel_vel)
        return AttitudeSetpoint(stamp_ns=now_ns, quat_des=list(q_des), omega_des=omega,
                                torque_ff=[wheel[0], wheel[1], wheel[2]], foot_torque=0.0, armed=True)

    def _target(self, now_ns: int, s: StateEstimate, ref: ComReference | None, t_ahead: float) -> tuple[float, float, float, float]:
        if ref is None:
            if self._hold is None:
                self._hold = (s.position[0], s.position[1])
            self.holding = True
            return self._hold[0], self._hold[1], 0.0, 0.0
        self.holding = False
        if ref.hold:
            p = ref.segments[0].control_points[0]
            self._hold = (p[0], p[1])
            return p[0], p[1], 0.0, 0.0
        self._hold = None
        return sample_reference(ref, (now_ns - ref.t_ref_ns) / NS + t_ahead)

    def _mid_level_target(self, now_ns: int, sp: MidLevelSetpoint | None) -> tuple[qt.Quat, ac.Vec3, ac.Vec3] | None:
        """``(q_d, omega_d, wheel feed-forward)`` of a fresh, finite setpoint of the geometric MPC
        at ``now_ns``: along its plan (interpolated between knots), else its lead-time values.
        None: no such setpoint, the ZDP flies (counted either way)."""
        if self.p.mid_level != "geometric_mpc":
            return None
        if sp is None or not 0 <= now_ns - sp.stamp_ns <= self.p.mid_level_stale_s * NS:
            self.mid_level_fallback_ticks += 1
            return None
        if sp is not self._mid_checked:  # a new setpoint: every number checked once
            self._mid_checked, self._mid_ok = sp, _setpoint_sound(sp)
        if not self._mid_ok:
            self.mid_level_fallback_ticks += 1
            return None
        self.mid_level_ticks += 1
        ts = sp.plan_t
        if not ts:
            return _quat(sp.quat_des), _vec3(sp.omega_des), _vec3(sp.torque_ff)
        tau = (now_ns - sp.stamp_ns) / NS
        last = len(ts) - 1
        if tau >= ts[last]:  # the plan ran out: hold its end, no feed-forward planned for now
            return _quat(sp.plan_quat[last]), _vec3(sp.plan_omega[last]), self._zero3
        i = 0
        while i < last - 1 and tau >= ts[i + 1]:
            i += 1
        span = ts[i + 1] - ts[i]
        s = min(1.0, max(0.0, (tau - ts[i]) / span)) if span > 0.0 else 1.0
        qa, qb = sp.plan_quat[i], sp.plan_quat[i + 1]
        rot = qt.log(qt.mul(qt.conj(qa), qb))
        q = qt.mul(qa, qt.exp((s * rot[0], s * rot[1], s * rot[2])))
        wa, wb = sp.plan_omega[i], sp.plan_omega[i + 1]
        w = (wa[0] + s * (wb[0] - wa[0]), wa[1] + s * (wb[1] - wa[1]), wa[2] + s * (wb[2] - wa[2]))
        return q, w, _vec3(sp.plan_torque[i])

    def step(
        self,
        now_ns: int,
        state: StateEstimate,
        reference: ComReference | None,
        joints: JointSensors | None = None,
        mid_level: MidLevelSetpoint | None = None,
    ) -> TorqueCommand:
        sup = self.supervisor
        if not self._check_and_arm(now_ns, state):
            return self._safe(now_ns)

        # spool speed by differencing the encoder (the message carries no speed)
        spool_pos = math.nan
        if joints is not None and math.isfinite(joints.foot_motor_pos):
            spool_pos = joints.foot_motor_pos
            if self._spool_prev is not None and now_ns > self._spool_prev[0]:
                raw = (spool_pos - self._spool_prev[1]) * NS / (now_ns - self._spool_prev[0])
                self._spool_vel += SPOOL_VEL_FILTER * (raw - self._spool_vel)
            self._spool_prev = (now_ns, spool_pos)

        ref = sup.check_reference(now_ns, reference)
        self._phase_update(now_ns, state, ref)

        stance = self.phase.phase != "flight"
        flip = self.flip
        if not stance:  # the ZDP's impact attitude (the fallback), and the hop regulator's apex
            if flip.state != "idle":
                self.foot.hop_height = self.p.flip_hop_height if flip.raising_hop else self.p.hop_height
            self._flight_attitude(now_ns, state, ref)
            if self._lifted_off:
                self._lifted_off = False
                flip.on_liftoff(now_ns, self.predicted_impact[0], self._yaw_ref)
        target = flip.target(now_ns) if flip.state == "turning" else None
        if target is not None:  # the flip's turn: its plan's attitude, rate and body torque
            self.q_des, omega_des, body_ff = target
            u = ac.pd_torque(state.quat, state.omega, self.q_des, omega_des, body_ff, self._kp, self._kd, self.p.attitude_log)
            wheel = self.alloc.wheel_torques(u)
        elif (target := self._mid_level_target(now_ns, mid_level)) is not None:  # thesis 5.3: the PD on the MPC's plan, both phases
            self.q_des, omega_des, wheel_ff = target
            ff = self.alloc.body_torque(wheel_ff)
            u = ac.pd_torque(state.quat, state.omega, self.q_des, omega_des, ff, self._kp, self._kd, self.p.attitude_log)
            wheel = self.alloc.wheel_torques(u)
        elif not stance:
            u = ac.pd_torque(state.quat, state.omega, self.q_des, self._zero3, self._zero3, self._kp, self._kd, self.p.attitude_log)
            wheel = self.alloc.wheel_torques(u)
        else:
            wheel = ac.spin_down(state.wheel_vel, self.p.spin_down_gamma)
        if math.isfinite(spool_pos):
            foot = self.foot.spool_torque(stance, state.foot_pos, spool_pos, self._spool_vel)
            foot = max(-self._foot_max, min(self._foot_max, foot))
        else:
            foot = 0.0
        if self.p.identify:  # the identification routine's known dither, both phases (tracking/excitation.py)
            d0, d1, d2 = wheel_dither((now_ns - self._arm_ns) / NS, self.p.identify_torque)
            wheel = (wheel[0] + d0, wheel[1] + d1, wheel[2] + d2)
        wm = self._wheel_max
        w0, w1, w2 = wheel
        if w0 > wm or w0 < -wm or w1 > wm or w1 < -wm or w2 > wm or w2 < -wm:
            self.saturated_ticks += 1
            wheel = (max(-wm, min(wm, w0)), max(-wm, min(wm, w1)), max(-wm, min(wm, w2)))
        self.armed_ticks += 1
        wheel, foot = sup.limit_command(now_ns, wheel, foot, state.wheel_vel)
        return TorqueCommand(stamp_ns=now_ns, wheel_torque=[wheel[0], wheel[1], wheel[2]], foot_torque=foot, armed=True)

    def _on_event(self, now_ns: int, ev: PhaseEvent, s: StateEstimate, ref: ComReference | None) -> None:
        com_valid = not self.supervisor.attitude_only  # else no impact error, no hop-energy learning from the CoM
        if ev.event == "touchdown":
            yaw = qt.yaw_of(s.quat)
            lean = qt.body_z(s.quat)  # the lean it lands with, whoever commanded it (the ZDP, the geometric MPC)
            self.balance.on_touchdown(s.velocity[0], s.velocity[1], lean[0], lean[1], yaw, com_valid and self.flip.state == "idle")
            self.momentum.on_touchdown(s.wheel_vel[0], s.wheel_vel[1], s.wheel_vel[2], self.flip.state == "idle")
            if com_valid:
                rx, ry, _, _ = self._target(now_ns, s, ref, 0.0)
                dx, dy = self.balance.offset(yaw)
                ex, ey = s.position[0] + dx - rx, s.position[1] + dy - ry
                err = math.hypot(ex, ey)
                self.last_impact_error = err
                self.tube_monitor.record_impact(err, qt.angle_between(s.quat, self.q_des))
            self.foot.on_touchdown(s.foot_pos)
            self.flip.on_touchdown()
            if self.flip.state == "idle":
                self.foot.hop_height = self.p.hop_height
        elif ev.event == "liftoff":
            self._lifted_off = True
        elif ev.event == "apex" and com_valid:
            self.foot.on_apex(s.position[2] - self.phase.touchdown_height)
