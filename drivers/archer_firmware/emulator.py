"""Emulated ARCHER flywheel board and foot board, as their firmware behaves on UDP.

:meth:`BoardEmulator.tick` is one millisecond of the board's loop, run from the
board's own clock (``archer emulate archer-firmware`` drives it with a
:class:`~services.runtime.realtime.DeadlineLoop`):

1. read every datagram waiting; from the configured peer only, 40 bytes, finite, a
   unit quaternion: a setpoint is stored, a reset packet stops the motors; each
   accepted packet is answered at once with the 13-float state. Anything else is
   dropped, counted and never answered nor applied;
2. no accepted packet for ``watchdog_s``: motors off (wheels and foot) until the
   next setpoint;
3. the attitude PD on the IMU: ``tau = -kp * s * vec(conj(q_des) q) - kd * (gyro -
   omega_des) + tau_ff`` (``s``: sign of the error's scalar part, the shorter way
   round), body torque to wheel motor torques by the wheel axes, to current at
   1/kt, clamped to +-current_max;
4. the foot board's hop cycle (:class:`FootBoard`);
5. the torques go to the plant: the twin (``on_step``) or stand-in inertias.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from enum import Enum

from drivers.archer_firmware import codec
from drivers.archer_firmware.transport import UdpLink
from drivers.elmo.emulator import InertiaLoad, MotorModel
from drivers.teensy.emulator import BodyState
from onboard.geometry import quaternion as quat
from onboard.low_level.tracking.attitude_control import WheelAllocation
from onboard.low_level.tracking.foot_control import FootPhysics
from onboard.contracts.params import ArcherFirmwareParams

ZERO4 = [0.0, 0.0, 0.0, 0.0]
IDENTITY_AXES = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


class FootPhase(Enum):
    IDLE = "idle"  # motors off: cable slack, no torque
    FLIGHT = "flight"  # wind the spring to the preload
    COMPRESSION = "compression"  # touchdown: cable released, the spring compresses
    THRUST = "thrust"  # the spring extends and pushes off


class FootBoard:
    """The foot board's own hop cycle, from its contact switch and deflection sensor.

    In flight the spool winds the spring to ``foot_preload_m``; at touchdown it
    unwinds past the fully extended foot so the cable is slack and the stored energy
    goes into the stance (compression, then thrust); at lift-off it winds again. The
    energy each hop gains makes up what the impact loses, so an upright robot hops in
    place by itself. The preload is scaled after each flight by the flight time the
    contact switch measured (apex rise ``g T^2 / 8``) towards ``foot_hop_height_m``:
    the hop's energy goes as the preload squared. Spool torque is the gearbox output
    [N m], positive winds.
    """

    def __init__(self, params: ArcherFirmwareParams, phys: FootPhysics) -> None:
        if phys.spool_radius <= 0 or phys.spring_k <= 0:
            raise ValueError("spool radius and spring stiffness must be positive")
        self.p = params
        self.phys = phys
        self.preload = min(params.foot_preload_m, phys.travel)
        self.phase = FootPhase.IDLE
        self.hops = 0  # lift-offs seen
        self.liftoff_s: float | None = None

    def _regulate(self, flight_s: float) -> None:
        """After a flight of ``flight_s``: the preload for the hop height (energy ~ preload^2)."""
        p = self.p
        rise = self.phys.gravity * flight_s * flight_s / 8.0
        if p.foot_hop_height_m <= 0.0 or flight_s < p.foot_min_flight_s:
            return
        scale = (p.foot_hop_height_m / rise) ** (0.5 * p.foot_hop_gain)
        self.preload = min(max(self.preload * scale, 0.0), self.phys.travel)

    def step(self, enabled: bool, contact: bool, deflection: float, rate: float, spool_pos: float, spool_vel: float,
             now_s: float | None = None) -> float:
        previous = self.phase
        if not enabled:
            self.phase = FootPhase.IDLE
            self.liftoff_s = None
            return 0.0
        if not contact:
            self.phase = FootPhase.FLIGHT
            if previous in (FootPhase.COMPRESSION, FootPhase.THRUST):
                self.hops += 1
                self.liftoff_s = now_s
        else:
            if previous == FootPhase.FLIGHT and self.liftoff_s is not None and now_s is not None:
                self._regulate(now_s - self.liftoff_s)  # touchdown: the flight just measured
                self.liftoff_s = None
            if previous != FootPhase.THRUST:
                self.phase = FootPhase.COMPRESSION if rate > 0.0 else FootPhase.THRUST
        r = self.phys.spool_radius
        if self.phase == FootPhase.FLIGHT:
            target = self.preload / r
            ff = r * self.phys.spring_k * min(max(deflection, 0.0), self.preload)  # hold the spring once the cable carries it
        else:
            target = -self.p.foot_release_slack_m / r  # slack before the spring starts to extend
            ff = 0.0
        return ff + self.p.foot_spool_kp * (target - spool_pos) - self.p.foot_spool_kd * spool_vel


class BoardEmulator:
    COUNTERS = ("setpoints", "resets", "replies", "length", "non_finite", "quaternion", "watchdog_trips")

    def __init__(
        self,
        params: ArcherFirmwareParams,
        foot: FootPhysics,
        local: tuple[str, int],
        peer: tuple[str, int],
        clock: Callable[[], float],
        wheel_axes: Sequence[Sequence[float]] = IDENTITY_AXES,
        motors: list[MotorModel] | None = None,
        body: BodyState | None = None,
    ) -> None:
        self.params = params
        self.link = UdpLink(local, peer, clock)
        self.alloc = WheelAllocation.from_axes(wheel_axes)
        self.foot = FootBoard(params, foot)
        self.motors: list[MotorModel] = motors or [InertiaLoad() for _ in range(4)]
        self.body = body or BodyState()
        self.on_step: Callable[[float, list[float]], None] | None = None  # the twin hook
        self.setpoint: codec.Setpoint | None = None
        self.motors_on = False
        self.last_packet_s = -math.inf
        self.applied = list(ZERO4)  # wheel 1, 2, 3, foot [N m] at the joints
        self.currents = [0.0, 0.0, 0.0]  # [A]
        self.counts = dict.fromkeys(self.COUNTERS, 0)
        self._last_tick: float | None = None

    # --- packets ----------------------------------------------------------------------

    def state(self) -> codec.BoardState:
        b, m = self.body, self.motors
        return codec.BoardState(
            wheel_vel=(m[0].velocity, m[1].velocity, m[2].velocity),
            gyro=b.gyro,
            quat=b.quat,
            foot_contact=b.contact,
            foot_deflection=b.foot_pos,
            foot_deflection_rate=b.foot_vel,
        )

    def _on_packet(self, data: bytes, now: float) -> None:
        try:
            packet = codec.unpack_setpoint(data)
        except codec.CodecError as exc:
            self.counts[exc.kind] += 1
            return
        if packet is None:
            self.counts["resets"] += 1
            self.setpoint = None
            self.motors_on = False
        else:
            self.counts["setpoints"] += 1
            self.setpoint = packet
            self.motors_on = True
        self.last_packet_s = now
        try:
            reply = codec.pack_state(self.state())
        except codec.CodecError:
            return  # a plant that went non-finite: say nothing rather than lie
        if self.link.send(reply):
            self.counts["replies"] += 1

    # --- the 1 kHz loop ------------------------------------------------------------------

    def body_torque(self) -> tuple[float, float, float]:
        """The firmware's PD on the IMU [N m], body frame."""
        sp = self.setpoint
        assert sp is not None
        err = quat.mul(quat.conj(sp.quat_des), self.body.quat)
        sign = 1.0 if err[0] >= 0.0 else -1.0
        p = self.params
        kp = (p.kp_tilt, p.kp_tilt, p.kp_yaw)
        kd = (p.kd_tilt, p.kd_tilt, p.kd_yaw)
        g = self.body.gyro
        return (
            -kp[0] * sign * err[1] - kd[0] * (g[0] - sp.omega_des[0]) + sp.torque_ff[0],
            -kp[1] * sign * err[2] - kd[1] * (g[1] - sp.omega_des[1]) + sp.torque_ff[1],
            -kp[2] * sign * err[3] - kd[2] * (g[2] - sp.omega_des[2]) + sp.torque_ff[2],
        )

    def _wheel_torques(self) -> list[float]:
        kt, i_max = self.params.torque_constant, self.params.current_max
        out = []
        for k, tau in enumerate(self.alloc.wheel_torques(self.body_torque())):
            current = max(-i_max, min(i_max, tau / kt))
            self.currents[k] = current
            out.append(current * kt)
        return out

    def tick(self, now: float) -> None:
        """One loop of the board at time ``now`` [s] of its own clock."""
        dt = 0.0 if self._last_tick is None else now - self._last_tick
        self._last_tick = now
        for data, _rx in self.link.poll():
            self._on_packet(data, now)
        if self.motors_on and now - self.last_packet_s > self.params.watchdog_s:
            self.motors_on = False
            self.setpoint = None
            self.counts["watchdog_trips"] += 1
        if self.motors_on and self.setpoint is not None:
            wheels = self._wheel_torques()
        else:
            wheels = [0.0, 0.0, 0.0]
            self.currents = [0.0, 0.0, 0.0]
        b, spool = self.body, self.motors[3]
        foot = self.foot.step(self.motors_on, b.contact, b.foot_pos, b.foot_vel, spool.position, spool.velocity, now)
        self.applied = [*wheels, foot]
        if self.on_step is not None:
            self.on_step(now, list(self.applied))
        else:
            for motor, torque in zip(self.motors, self.applied):
                motor.step(torque, dt)

    def summary(self) -> dict[str, float]:
        out: dict[str, float] = {k: float(v) for k, v in self.counts.items()}
        out.update({f"udp_{k}": float(v) for k, v in self.link.summary().items()})
        out["hops"] = float(self.foot.hops)
        return out

    def close(self) -> None:
        self.link.close()
