"""How the twin turns a :class:`TorqueCommand` into motor torques, as the hardware would.

Shared by the lockstep runner and the real-time twin service. In order:

1. no command, a command not ``armed``, older than ``SafetyLimits.command_stale_s``, or with a
   non-finite value: zero torque (the drives' own watchdog); each reason is counted;
2. clamp to ``SafetyLimits`` (``wheel_torque_max``, ``foot_torque_max``);
3. the wheel motors' speed-torque curve (:meth:`RobotParams.wheel_torque_available`) and the foot
   drive's peak torque, i.e. what the motor physically delivers at its current speed.

The torques go to the MJCF actuators ``wheel_x/y/z`` and ``foot_motor`` through ``data.ctrl``.
"""

from __future__ import annotations

import math

import mujoco

from onboard.contracts.messages import TorqueCommand
from onboard.contracts.params import SafetyLimits
from robot_description import params as rd

NS = 1_000_000_000
AT_LIMIT = 0.999  # a wheel command within 0.1 % of the available torque counts as saturated


class Actuation:
    """Applies torque commands to one model; counts what it refused or clipped."""

    def __init__(self, model: mujoco.MjModel, robot: rd.RobotParams, safety: SafetyLimits) -> None:
        self.robot = robot
        self.safety = safety
        self._wheel_act = [int(model.actuator(n).id) for n in rd.WHEEL_ACTUATORS]
        self._foot_act = int(model.actuator(rd.FOOT_ACTUATOR).id)
        acts = self._wheel_act + [self._foot_act]
        # one slice write per tick when the actuators are contiguous (they are in the MJCF)
        self._acts = slice(acts[0], acts[0] + 4) if acts == list(range(acts[0], acts[0] + 4)) else acts
        self._wheel_dof = [int(model.joint(n).dofadr[0]) for n in rd.WHEEL_JOINTS]
        self._stale_ns = int(safety.command_stale_s * NS)
        self._wheel_max = min(safety.wheel_torque_max, robot.wheel_torque_peak)
        self._foot_max = min(safety.foot_torque_max, robot.foot_torque_peak)
        self.counters: dict[str, int] = {"applied": 0, "no_command": 0, "disarmed": 0, "stale": 0, "non_finite": 0}
        self.wheel_ticks = 0  # wheel-ticks applied (3 per applied command)
        self.wheel_saturated = 0  # wheel-ticks asking for all the torque there is (limit or motor curve)
        self.last_applied = (0.0, 0.0, 0.0, 0.0)  # wheel x, y, z, foot [N m]

    def _zero(self, data: mujoco.MjData, reason: str) -> None:
        self.counters[reason] += 1
        data.ctrl[self._acts] = 0.0
        self.last_applied = (0.0, 0.0, 0.0, 0.0)

    def apply(self, cmd: TorqueCommand | None, now_ns: int, data: mujoco.MjData, received_ns: int | None = None) -> None:
        """Set ``data.ctrl`` from ``cmd`` at time ``now_ns``.

        The command's age is measured from ``received_ns`` when given (a command from another
        process: only our own clock is trusted), else from its ``stamp_ns`` (lockstep: one clock).
        """
        if cmd is None:
            return self._zero(data, "no_command")
        if not cmd.armed:
            return self._zero(data, "disarmed")
        if now_ns - (cmd.stamp_ns if received_ns is None else received_ns) > self._stale_ns:
            return self._zero(data, "stale")
        wt = cmd.wheel_torque
        ft = cmd.foot_torque
        if not (math.isfinite(wt[0]) and math.isfinite(wt[1]) and math.isfinite(wt[2]) and math.isfinite(ft)):
            return self._zero(data, "non_finite")
        lim = self._wheel_max
        qvel = data.qvel.tolist()
        robot = self.robot
        knee = robot.wheel_speed_knee
        out = [0.0, 0.0, 0.0, 0.0]
        for i in range(3):
            want = wt[i]
            avail = lim
            speed = qvel[self._wheel_dof[i]]
            if want * speed > 0.0 and (speed > knee or speed < -knee):  # driving past the knee: motor curve
                avail = abs(robot.wheel_torque_available(speed, lim if want > 0.0 else -lim))
            tau = avail if want > avail else -avail if want < -avail else want
            # A controller that clamps to the same limits before sending still saturates.
            if want >= avail * AT_LIMIT or want <= -avail * AT_LIMIT:
                self.wheel_saturated += 1
            out[i] = tau
        fl = self._foot_max
        out[3] = fl if ft > fl else -fl if ft < -fl else ft
        data.ctrl[self._acts] = out
        self.wheel_ticks += 3
        self.counters["applied"] += 1
        self.last_applied = (out[0], out[1], out[2], out[3])

    @property
    def saturation_fraction(self) -> float:
        return self.wheel_saturated / self.wheel_ticks if self.wheel_ticks else 0.0
