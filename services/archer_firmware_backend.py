"""A ``hardware`` service backend for ARCHER's own flywheel-board firmware (UDP, attitude mode).

It follows the ``Backend`` protocol of :mod:`services.hardware`
(``hardware.backend = "archer-firmware"``). The board runs the attitude PD itself, so it
takes an :class:`~onboard.contracts.messages.AttitudeSetpoint` only; per tick:

- armed with a setpoint: one setpoint packet. The message's ``torque_ff`` is a wheel
  motor torque (our convention, :class:`~onboard.contracts.messages.AttitudeSetpoint`); the
  firmware wants a body torque, so it goes through the wheel axes. ``foot_torque`` is
  not sent: the foot board runs its hop cycle by itself;
- anything else (disarmed, torque mode, stale): the reset command
  (``archer_firmware.poll_disarmed``), which stops the motors at once and which the board
  answers with its state like any packet: the board never streams, and the estimator
  needs its IMU to arm on. With ``poll_disarmed`` False, or a latched fault: nothing, and
  the firmware's 100 ms watchdog turns the motors off.

What the board reports becomes ``joints`` (wheel speeds, foot contact, deflection and
rate) stamped with the reply's arrival. The firmware reports no wheel angles, wheel
torques, spool angle or accelerometer: those ``JointSensors`` fields are 0 (not
measurements). :meth:`imu` is the board's attitude and rates with ``accel_sensed``
False: the estimator models the specific force from the foot instead
(:mod:`onboard.estimation.estimator`) and says so in its covariance.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

from drivers.archer_firmware import codec
from drivers.archer_firmware.device import ArcherBoard
from drivers.archer_firmware.transport import UdpLink
from onboard.contracts import messages as msgs
from onboard.low_level.tracking.attitude_control import WheelAllocation
from onboard.contracts.params import ArcherFirmwareParams

NS = 1_000_000_000


class ArcherFirmwareBackend:
    def __init__(
        self, params: ArcherFirmwareParams, wheel_axes: Sequence[Sequence[float]], clock: Callable[[], float] = time.monotonic,
        on_reader_start: Callable[[], None] | None = None,
    ) -> None:
        """``on_reader_start`` runs first on the thread that reads and stamps the board's replies."""
        link = UdpLink((params.computer_host, params.computer_port), (params.board_host, params.board_port), clock)
        self.board = ArcherBoard(link, params)
        self.alloc = WheelAllocation.from_axes(wheel_axes)
        self.poll_disarmed = params.poll_disarmed
        self.torques_ignored = 0  # armed torque commands this firmware cannot take (ticks)
        self._on_reader_start = on_reader_start

    @property
    def faults(self) -> list[str]:
        return self.board.faults

    def open(self) -> None:
        self.board.open(self._on_reader_start)

    def exchange(self, now_s: float, torques: Sequence[float], armed: bool, attitude: msgs.AttitudeSetpoint | None) -> None:
        setpoint = None
        if armed and attitude is not None:
            q, w = attitude.quat_des, attitude.omega_des
            tau = self.alloc.body_torque(attitude.torque_ff)
            setpoint = codec.Setpoint((q[0], q[1], q[2], q[3]), (w[0], w[1], w[2]), tau)
        elif armed and any(torques):
            self.torques_ignored += 1
        self.board.exchange(now_s, setpoint)
        if setpoint is None and self.poll_disarmed and not self.board.faulted:
            self.board.reset(now_s)  # motors off, and the board's state comes back

    def joints(self) -> msgs.JointSensors | None:
        s = self.board.state
        if s is None or not self.board.fresh:
            return None
        return msgs.JointSensors(
            stamp_ns=int(self.board.state_rx_s * NS),
            wheel_pos=[0.0, 0.0, 0.0],
            wheel_vel=list(s.wheel_vel),
            wheel_torque=[0.0, 0.0, 0.0],
            foot_pos=s.foot_deflection,
            foot_vel=s.foot_deflection_rate,
            foot_contact=s.foot_contact,
        )

    def imu(self) -> msgs.ImuSample | None:
        s = self.board.state
        if s is None or not self.board.fresh:
            return None
        return msgs.ImuSample(stamp_ns=int(self.board.state_rx_s * NS), quat=list(s.quat), gyro=list(s.gyro),
                              accel=[0.0, 0.0, 0.0], accel_sensed=False)

    def board_attitude(self) -> tuple[float, codec.Quat, codec.Vec3] | None:
        """(arrival time [s], IMU attitude body -> world, body rates [rad/s]) of the newest state."""
        s = self.board.state
        return None if s is None else (self.board.state_rx_s, s.quat, s.gyro)

    def recover(self, now_s: float) -> None:
        self.board.recover(now_s)

    def summary(self) -> dict[str, float]:
        return {**self.board.summary(), "torques_ignored": float(self.torques_ignored)}

    def close(self) -> None:
        self.board.close()
