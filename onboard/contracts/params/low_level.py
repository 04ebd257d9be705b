"""Parameters of the low level (``onboard.low_level``): the 1 kHz controller and the geometric MPC.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Literal



from onboard.contracts.params.base import Cpu, LOOP_HZ_MAX, Name, Request, RtPriority, _Section, above, within


@dataclass(frozen=True)
class ControlParams(_Section, section="control"):
    """The hard-rate low level (:mod:`onboard.low_level.controller`) and its ``control`` service.

    Attitude gains act on the body torque per body axis; the attitude error is a
    rotation vector (see :mod:`onboard.low_level.tracking.attitude_control`). Gain ceilings: with the
    body's ~0.054 kg m^2 about a horizontal axis, kp 500 N m/rad is a 15 Hz loop
    (far past what 1.6 N m wheels deliver) and kd 50 N m s/rad half the 1 kHz
    discrete damping limit 2 I / dt.
    """

    rate_hz: Annotated[float, within(100.0, LOOP_HZ_MAX)] = 1000.0  # control loop rate [Hz]
    auto_arm: bool = True  # arm on the first valid estimate (else wait for an arm request)
    robot: Name = "indoor"  # MJCF variant the parameters are read from (robot_description/models)
    # archer identify's file, the same as [estimator] identified: the CoM offset the estimate already
    # accounts for, which the balance observer starts from and does not count twice; "": the MJCF's
    identified: str = ""
    rt_priority: RtPriority = 80  # SCHED_FIFO priority of the loop process (0: leave the scheduler alone)
    cpu: Cpu = -1  # CPU the loop process is pinned to (-1: no pinning)
    tube_period_s: Annotated[float, above(0.0, 60.0)] = 0.5  # publish the measured tube this often [s]
    # "torque": wheel and foot torques (torque_cmd); "attitude": the hardware runs the attitude PD and
    # the foot's hop cycle itself, the loop publishes attitude setpoints (attitude_cmd) and no foot command
    output: Literal["torque", "attitude"] = "torque"
    arm_request: Request = 0  # operator command: set a new value to arm (after a latched disarm)
    disarm_request: Request = 0  # operator command: set a new value to disarm
    # flight: quaternion PD (thesis 2201-2216)
    kp_tilt: Annotated[float, within(0.0, 500.0)] = 40.0  # [N m/rad] roll and pitch
    kd_tilt: Annotated[float, within(0.0, 50.0)] = 3.0  # [N m s/rad]
    kp_yaw: Annotated[float, within(0.0, 500.0)] = 2.0  # [N m/rad]
    kd_yaw: Annotated[float, within(0.0, 50.0)] = 0.25  # [N m s/rad]
    attitude_log: bool = False  # error map: False = 2 Im(q_d^-1 q) (thesis default), True = Log
    # ground: flywheel spin-down u = -gamma * wheel speed (thesis 2723-2731)
    spin_down_gamma: Annotated[float, within(0.0, 1.0)] = 0.03  # [N m s/rad]
    yaw_rate_max: Annotated[float, within(0.0, 10.0)] = 1.0  # [rad/s] the heading follows the reference's yaw (the planner points the camera) at most this fast
    # foot: hop-height regulator (preload in flight, release at touchdown)
    hop_height: Annotated[float, above(0.0, 0.5)] = 0.12  # CoM rise from touchdown to apex [m] (higher: fewer hops per metre, less wheel momentum)
    hop_gain: Annotated[float, within(0.0, 1.0)] = 0.5  # fraction of the hop-energy error corrected per hop
    loss_adapt: Annotated[float, within(0.0, 1.0)] = 0.2  # per-hop gain of the energy-loss estimate
    preload_max: Annotated[float, within(0.0, 0.1)] = 0.05  # [m] spring compression the cable may hold (the spring travels 0.1 m)
    spool_kp: Annotated[float, within(0.0, 1000.0)] = 10.0  # spool position gain [N m/rad]
    spool_kd: Annotated[float, within(0.0, 50.0)] = 0.2  # spool damping [N m s/rad]
    release_slack: Annotated[float, within(0.0, 0.1)] = 0.015  # at release unwind to this much cable [m] past the extended foot
    # phases
    min_flight_s: Annotated[float, within(0.0, 1.0)] = 0.05  # ignore a touchdown earlier than this after lift-off [s]
    min_stance_s: Annotated[float, within(0.0, 1.0)] = 0.02  # ignore a lift-off earlier than this after touchdown [s]
    # Zero Dynamics Policy (thesis 2377-2777)
    policy: Literal["zdp", "lqr", "raibert", "mlp"] = "zdp"  # "zdp" (eq. 5.44, clipped), "lqr" (plain gain, unclipped), "raibert", "mlp"
    zdp_q_pos: Annotated[float, within(0.0, 1e4)] = 1.0  # LQR state weight on position error [1/m^2]
    zdp_q_vel: Annotated[float, within(0.0, 1e4)] = 0.5  # on velocity error [s^2/m^2]
    zdp_q_tilt: Annotated[float, within(0.0, 1e4)] = 2.0  # on the impact attitude [1/rad^2]
    zdp_r: Annotated[float, above(0.0, 1e4)] = 2.0  # on the attitude command [1/rad^2] (positive: the LQR needs R > 0)
    raibert_kp: Annotated[float, within(0.0, 10.0)] = 0.25  # eq. 5.48 gains: tilt per position error [rad/m]
    raibert_kd: Annotated[float, within(0.0, 10.0)] = 0.30  # tilt per velocity error [rad s/m]
    tilt_cmd_max: Annotated[float, within(0.0, 0.5)] = 0.12  # clip on the commanded impact tilt [rad]
    # the lean that holds the reduced model's hop map at the reference's speed (v = a v + b eta, so
    # eta = (1 - a) v / b, against the motion: a > 1), added to the policy's. Its error law alone leans
    # back only from an error, so it cruised ~5 cm ahead of a moving reference (setpoint), which the
    # tube measures and the planner pays for (docs/model_error.md, the cruise lean)
    cruise_feedforward: Annotated[float, within(0.0, 2.0)] = 1.0  # share of that lean (0: off)
    pos_err_max: Annotated[float, within(0.0, 10.0)] = 0.30  # clip on the position error the policy sees [m]
    vel_err_max: Annotated[float, within(0.0, 10.0)] = 0.60  # clip on the velocity error the policy sees [m/s]
    mlp_weights: Name = "zdp_mlp.npz"  # file under onboard/data/ for policy = "mlp"
    # tracking certificate
    tube_window: Annotated[int, within(1, 100_000)] = 100  # impacts in the published tube statistics
    # supervisor
    estimate_fault_disarm_s: Annotated[float, within(0.0, 1.0)] = 0.05  # a bad estimate for this long disarms (latched) [s]
    # the CoM estimate not valid while its attitude is: the low level holds the body upright and
    # hops in place (no position feedback) for at most this long, then disarms (latched) [s]
    attitude_only_max_s: Annotated[float, within(0.0, 5.0)] = 0.5
    arm_tilt_max: Annotated[float, within(0.0, math.pi / 2)] = 0.35  # refuse to arm beyond this tilt [rad]
    # mid level: "zdp" (the impact attitude of the policy above) or "geometric_mpc" (thesis 5.3: the
    # loop tracks the MPC's attitude, rate and feed-forward with the quaternion PD in both phases,
    # and falls back to the ZDP while no fresh, checked MPC answer is at hand)
    mid_level: Literal["zdp", "geometric_mpc"] = "zdp"
    mid_level_stale_s: Annotated[float, above(0.0, 1.0)] = 0.05  # [s] an MPC setpoint older than this is not tracked
    # the flip (thesis Fig. 5.13, onboard.low_level.tracking.flip): one full turn about a horizontal body axis in one flight
    flip_request: Request = 0  # operator command: set a new value to flip once (refused where the wheels cannot)
    flip_hop_height: Annotated[float, above(0.0, 0.5)] = 0.40  # [m] apex rise the hops are raised to for the turn's flight
    flip_axis_deg: Annotated[float, within(-180.0, 180.0)] = 45.0  # turn axis in the body's xy plane from body x [deg] (45: wheels x and y share it)
    flip_settle_s: Annotated[float, within(0.0, 0.5)] = 0.06  # [s] the turn ends this long before the predicted touchdown
    flip_torque_share: Annotated[float, above(0.0, 1.0)] = 0.7  # share of a wheel's torque limit the turn's feed-forward may take
    flip_pump_hops: Annotated[int, within(1, 50)] = 10  # hops to raise the flight before the request is dropped
    # the balance point (onboard.low_level.planning.balance): a disturbance observer on the hop map. A CoM
    # off the spine acts as a constant extra lean at impact that the ZDP's proportional law only answers
    # with a standing position error (~14x the offset); each pair of touchdowns observes that lean from the
    # policy's own linearized hop map, in the body's heading frame, standing or moving; the controller
    # cancels it and moves the position the policy sees by the CoM offset it implies
    balance_gain: Annotated[float, within(0.0, 1.0)] = 0.2  # share of each hop's innovation taken (0: off)
    balance_innovation_max: Annotated[float, above(0.0, 0.3)] = 0.03  # [rad] a push or a stumble moves the estimate by at most gain x this
    balance_tilt_max: Annotated[float, within(0.0, 0.3)] = 0.1  # [rad] bound on the observed lean (0.1: ~3.6 cm of CoM)
    balance_speed_max: Annotated[float, above(0.0, 3.0)] = 1.0  # [m/s] faster touchdowns are outside the hop map's linearization
    # the wheels' momentum governor (onboard.low_level.planning.momentum): the fastest wheel at each touchdown,
    # projected momentum_lookahead_hops on where it grew, caps the speed the ZDP steers to: from the robot's
    # nominal sustained speed (hop_speed_max) at momentum_wheel_share_lo of the wheels' speed limit
    # (SafetyLimits.wheel_speed_max: 600 rad/s indoor, 3000 for sim15nm's 15 N m wheels) down to
    # momentum_speed_min at momentum_wheel_share_hi. The nominal twin's setpoint and square peak at ~200 rad/s
    # of 600; datasheet robots at the same speed gained 60-170 rad/s a hop into the limit and fell (issue 26).
    # 0 for the low share: off
    momentum_wheel_share_lo: Annotated[float, within(0.0, 1.0)] = 0.25  # 150 rad/s indoor
    momentum_wheel_share_hi: Annotated[float, above(0.0, 1.0)] = 0.5833  # 350 rad/s indoor: room to slow before the motors' knee
    momentum_speed_min: Annotated[float, within(0.0, 1.0)] = 0.05  # [m/s]
    momentum_lead_s: Annotated[float, above(0.0, 2.0)] = 0.25  # [s] the position error the policy sees: this long at the cap (about a hop)
    momentum_lookahead_hops: Annotated[float, within(0.0, 20.0)] = 3.0  # a wheel that grew over the last hop counts as this many hops on
    momentum_cap_rise: Annotated[float, above(0.0, 1.0)] = 0.02  # [m/s] per hop the cap rises by, once the wheels slowed (it falls at once)
    # identification routine (onboard/low_level/tracking/excitation.py, archer identify): while hopping in
    # place, a known dither on every wheel's command and a heading swing, so that a recording tells each
    # wheel's torque constant from its drag. Off on the robot unless the lab runs the routine.
    identify: bool = False
    identify_torque: Annotated[float, within(0.0, 0.5)] = 0.2  # [N m] dither amplitude per wheel
    identify_yaw: Annotated[float, within(0.0, 1.5)] = 0.5  # [rad] heading swing amplitude
    identify_yaw_period_s: Annotated[float, above(0.0, 60.0)] = 5.0  # [s]
    # hot standby (services/control.py): a primary on this host whose armed command stream stopped this long
    # (a hang: its token outlives it by the link's lease) is killed, so that the standby takes over [s]; 0: never.
    # Above the worst stall of a loaded machine (~65 ms measured): a false fence costs a takeover and a restart
    standby_fence_s: Annotated[float, within(0.0, 1.0)] = 0.25


@dataclass(frozen=True)
class GeometricMpcParams(_Section, section="gmpc"):
    """The geometric MPC (:mod:`onboard.low_level.planning.geometric_mpc`, thesis section 5.3, Table 5.3).

    Weights are the diagonal of ``Q`` (also the terminal ``V``, as in the thesis) and ``R``;
    the vertical position and velocity are left to the hop-height regulator.
    """

    rate_hz: Annotated[float, above(0.0, 1000.0)] = 100.0  # solves per second (thesis: 100 Hz)
    # SCHED_FIFO priority of the MPC's process: below the control loop (80), the estimator (75) and the
    # hardware exchange (70); at normal priority on a loaded 2-core machine a 6 ms solve took 20 ms (p50)
    rt_priority: RtPriority = 60
    cpu: Cpu = -1  # CPU the MPC's process is pinned to (-1: no pinning)
    # [s] of the plan sent with each answer: the loop follows the plan at the time it acts, so an
    # answer that arrives late (a loaded machine: solves of 20 ms) still acts where it was meant to
    setpoint_plan_s: Annotated[float, above(0.0, 1.0)] = 0.1
    horizon: Annotated[int, within(2, 200)] = 20  # knots, jumps included (thesis: 20)
    sqp_iterations: Annotated[int, within(1, 10)] = 2  # thesis: 2
    flight_step_s: Annotated[float, above(0.0, 0.2)] = 0.04  # [s] flight knot
    stance_step_s: Annotated[float, above(0.0, 0.2)] = 0.01  # [s] stance knot (finer: the spring is stiff)
    min_step_s: Annotated[float, above(0.0, 0.05)] = 0.002  # [s] a mode remainder shorter than this joins the knot before
    # position and velocity: the thesis's Table 5.3 has 10 and 1; on the twin (sim15nm square, seed 0, 12 s)
    # 30 and 10 tracked to 0.033 m RMS against 0.33 m (it hopped, but drifted behind the reference)
    weight_position: Annotated[float, within(0.0, 1e6)] = 30.0  # horizontal position [1/m^2]
    weight_height: Annotated[float, within(0.0, 1e6)] = 0.0  # vertical position [1/m^2]
    weight_orientation: Annotated[float, within(0.0, 1e6)] = 10.0  # xi, the Lie-algebra attitude [1/rad^2] (thesis: 10)
    weight_velocity: Annotated[float, within(0.0, 1e6)] = 10.0  # horizontal velocity [s^2/m^2]
    weight_vertical_velocity: Annotated[float, within(0.0, 1e6)] = 0.0  # [s^2/m^2]
    weight_omega: Annotated[float, within(0.0, 1e6)] = 0.01  # body rate [s^2/rad^2] (thesis: 0.01)
    weight_wheel_speed: Annotated[float, within(0.0, 1e6)] = 1e-4  # keeps the wheels from spinning up [s^2/rad^2]
    weight_input: Annotated[float, above(0.0, 1e6)] = 0.001  # wheel torque [1/(N m)^2] (thesis: 0.001)
    weight_floor: Annotated[float, above(0.0, 1.0)] = 1e-8  # on unweighted states: keeps P positive definite
    # [rad] bound on the planned tilt (body z from vertical, linearized about the present attitude,
    # never tighter than the present tilt); 0: none (the thesis's problem has none)
    tilt_max_plan: Annotated[float, within(0.0, 1.5)] = 0.0
    # PIQP by default: on this QP (stiff stance rows, 420 equalities) OSQP needed 400-1300 ADMM
    # iterations and ~50 ms a solve against PIQP's 8 iterations and ~2.5 ms (measured, shared 2-core machine)
    # "condensed" (issue 29): the states eliminated through the dynamics, the 60-input QP and its box solved
    # by an active-set method (2-4 factorizations): the QP's 2.4 ms a solve with PIQP became ~0.5 ms and the
    # answers agree within the solvers' tolerances (tests/test_geometric_mpc.py); PIQP stays the cross-check
    # and takes the QP when the tilt rows are on (general inequalities)
    backend: Literal["osqp", "piqp", "condensed"] = "condensed"
    eps: Annotated[float, above(0.0, 1.0)] = 1e-5  # QP tolerance (absolute and relative)
    max_qp_iter: Annotated[int, within(1, 100_000)] = 4000  # per QP: bounds the solve time
    osqp_check_termination: Annotated[int, within(1, 1000)] = 10  # OSQP checks convergence this often
    residual_tol: Annotated[float, above(0.0, 1.0)] = 1e-3  # largest dynamics residual an answer may keep [state units]


# The thesis's Table 5.3 discretization (seed text lines 2257-2263: horizon 20, SQP iterations 2,
# dt_flight 0.01 s, dt_ground 0.001 s; run at 100 Hz, line 2219), as overrides of GeometricMpcParams
# (``with_overrides``; ``archer bench gmpc --thesis-settings``; ``[gmpc]`` in a config file). Not the
# stack's default: 20 knots of 10 ms see 0.2 s of a 0.31 s flight and 20 of 1 ms under a third of a
# 68 ms stance; on the twin (sim15nm, square, seeds 0-9) the MPC at these knots fell after 5-6 hops in
# 10 of 10 runs, with PIQP and with the condensed QP alike, where the default's knots hop 10 of 10
# (README, issue 29).
# min_step_s: half a stance knot (the default's 2 ms would merge the last two stance knots).
GMPC_THESIS_KNOTS: dict[str, int | float] = {"horizon": 20, "sqp_iterations": 2, "flight_step_s": 0.01, "stance_step_s": 0.001,
                                             "min_step_s": 0.0005}
