"""Emulated Teensy on a pseudo-terminal, as the real one behaves on its USB serial port.

It streams a SENSORS frame every millisecond from its own clock, applies TORQUE and
ATTITUDE frames (the attitude PD runs here, as on the Teensy), rejects non-finite
commands, clamps torques at the drives' current limit, and zeroes every motor when
no command frame arrived for 100 ms (the real Teensy's watchdog), reporting it with
a STATUS frame and a sensor flag that stays set, torque off, until a disarmed
command arrives. Faults to inject: corrupted or dropped outgoing
frames, garbage bytes, and unplugging the port (optionally plugging it back).

The host opens :attr:`TeensyEmulator.port`, a symlink to the current pty (as udev's
``/dev/serial/by-id`` links), so that a re-plugged port has the same name.
"""

from __future__ import annotations

import logging
import math
import os
import tempfile
import threading
import time
import tty
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from drivers.elmo.emulator import InertiaLoad, MotorModel
from drivers.teensy import protocol as p
from onboard.geometry import quaternion as quat
from onboard.contracts.params import HardwareParams

log = logging.getLogger("archer.drivers.teensy.emulator")

WATCHDOG_S = 0.100  # the real Teensy's command timeout
SENSOR_PERIOD_S = 0.001
GRAVITY = 9.81  # [m/s^2] what the accelerometer reads at rest
READ_CHUNK = 65536
IDENTITY = (1.0, 0.0, 0.0, 0.0)


@dataclass
class BodyState:
    """What the IMU and the foot sensors see. Static unless a twin writes it."""

    quat: tuple[float, float, float, float] = IDENTITY
    gyro: tuple[float, float, float] = (0.0, 0.0, 0.0)
    accel: tuple[float, float, float] = (0.0, 0.0, GRAVITY)
    foot_pos: float = 0.0
    foot_vel: float = 0.0
    contact: bool = True


@dataclass
class Injection:
    corrupt: int = 0  # outgoing frames still to corrupt (one byte flipped)
    drop: int = 0  # outgoing frames still to drop
    garbage: bytes = b""  # bytes to write once, before the next frame
    replug_at: float | None = None
    counts: dict[str, int] = field(default_factory=dict)



class TeensyEmulator:
    def __init__(
        self,
        params: HardwareParams | None = None,
        gear_ratios: Sequence[float] = (1.0, 1.0, 1.0, 1.0),
        motors: list[MotorModel] | None = None,
        body: BodyState | None = None,
        link_dir: str | None = None,
    ) -> None:
        self.params = params or HardwareParams()
        n = len(self.params.node_ids)
        if n != 4:
            raise ValueError("the Teensy emulator serves three wheels and the foot")
        self.motors: list[MotorModel] = motors or [InertiaLoad() for _ in range(n)]
        self.body = body or BodyState()
        self.clamp = [
            self.params.current_max[i] * self.params.torque_constant[i] * gear_ratios[i] for i in range(n)
        ]  # [N m] at the joint: the drive's current clamp through the gearbox
        self.gains = p.Gains((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
        self.applied = [0.0] * n  # joint torques applied now [N m]
        self.armed = False
        self.watchdog_tripped = False
        self.fault_flag = False
        self.last_cmd_seq = 0
        self.last_cmd_s = -math.inf
        self.attitude: p.AttitudeCmd | None = None
        self.decoder = p.FrameDecoder()
        self.inject = Injection()
        self.counts = {"commands": 0, "rejected": 0, "heartbeats": 0, "sensors": 0, "tx_dropped": 0, "watchdog_trips": 0, "refused_while_tripped": 0}
        self.on_step: Callable[[float, list[float]], None] | None = None  # the twin hook
        self._lock = threading.Lock()
        self._seq = 0
        self._status_count = 0
        self._dir = link_dir or tempfile.mkdtemp(prefix="archer-teensy-")
        self.port = os.path.join(self._dir, "ttyTEENSY0")
        self._master = -1
        self._slave = -1
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="teensy-emulator", daemon=True)
        self.error: BaseException | None = None
        self._plug()

    # --- the port ----------------------------------------------------------------------

    def _plug(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no line discipline: bytes pass unchanged
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        tmp = self.port + ".new"
        if os.path.lexists(tmp):
            os.unlink(tmp)
        os.symlink(os.ttyname(slave), tmp)
        os.replace(tmp, self.port)
        self.decoder = p.FrameDecoder()

    def _unplug(self) -> None:
        if self._master >= 0:
            os.close(self._master)
            os.close(self._slave)
            self._master = self._slave = -1
        if os.path.lexists(self.port):
            os.unlink(self.port)

    @property
    def plugged(self) -> bool:
        return self._master >= 0

    def unplug(self, replug_after_s: float | None = None) -> None:
        """The USB cable comes out (and goes back in after ``replug_after_s``)."""
        with self._lock:
            self._unplug()
            self.inject.replug_at = None if replug_after_s is None else time.monotonic() + replug_after_s

    # --- fault injection -------------------------------------------------------------------

    def corrupt_next(self, n: int) -> None:
        with self._lock:
            self.inject.corrupt += n

    def drop_next(self, n: int) -> None:
        with self._lock:
            self.inject.drop += n

    def send_garbage(self, data: bytes) -> None:
        with self._lock:
            self.inject.garbage += data

    # --- lifecycle -------------------------------------------------------------------------------

    def start(self) -> TeensyEmulator:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(2.0)
        with self._lock:
            self._unplug()
        try:
            os.rmdir(self._dir)
        except OSError:
            pass

    def __enter__(self) -> TeensyEmulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # --- behaviour ----------------------------------------------------------------------------

    def _status(self, code: p.StatusCode) -> None:
        self._status_count += 1
        self._write(p.make_status(self._next_seq(), code, self._status_count))

    def _next_seq(self) -> int:
        self._seq = (self._seq + 1) % p.SEQ_MODULO
        return self._seq

    def _write(self, frame: bytes) -> None:
        if self._master < 0:
            return
        inj = self.inject
        if inj.garbage:
            frame = inj.garbage + frame
            inj.garbage = b""
        if inj.drop > 0:
            inj.drop -= 1
            return
        if inj.corrupt > 0:
            inj.corrupt -= 1
            mid = len(frame) // 2
            flipped = frame[mid] ^ 0x5A or 0x01  # never a zero: the delimiter must stay
            frame = frame[:mid] + bytes((flipped,)) + frame[mid + 1 :]
        try:
            os.write(self._master, frame)
        except BlockingIOError:
            self.counts["tx_dropped"] += 1
        except OSError:
            self.counts["tx_dropped"] += 1

    def _clamp(self, joint: int, torque: float) -> float:
        limit = self.clamp[joint]
        return max(-limit, min(limit, torque))

    def _apply_torque(self, cmd: p.TorqueCmd) -> None:
        if not self._may_arm(cmd.armed):
            return
        self.armed = cmd.armed
        self.attitude = None
        values = (*cmd.wheel_torque, cmd.foot_torque)
        self.applied = [self._clamp(i, v) if cmd.armed else 0.0 for i, v in enumerate(values)]

    def _attitude_torques(self) -> list[float]:
        """The Teensy's PD: torque = -kp * vec(q_des^-1 q) - kd * (w - w_des) + ff."""
        cmd = self.attitude
        assert cmd is not None
        qd = cmd.quat_des
        err = quat.mul(quat.conj(qd), self.body.quat)
        sign = 1.0 if err[0] >= 0 else -1.0  # the shorter way round
        out = []
        for k in range(3):
            tau = -self.gains.kp[k] * sign * err[k + 1] - self.gains.kd[k] * (self.body.gyro[k] - cmd.omega_des[k]) + cmd.torque_ff[k]
            out.append(self._clamp(k, tau))
        out.append(self._clamp(3, cmd.foot_torque))
        return out

    def _on_frame(self, frame: p.RawFrame, now: float) -> None:
        try:
            if frame.frame_type == p.FrameType.TORQUE:
                self._apply_torque(p.parse_torque(frame.payload))
            elif frame.frame_type == p.FrameType.ATTITUDE:
                cmd = p.parse_attitude(frame.payload)
                if not self._may_arm(cmd.armed):
                    self.last_cmd_s = now
                    return
                self.armed = cmd.armed
                self.attitude = cmd if cmd.armed else None
                if not cmd.armed:
                    self.applied = [0.0] * 4
            elif frame.frame_type == p.FrameType.GAINS:
                self.gains = p.parse_gains(frame.payload)
                return
            elif frame.frame_type == p.FrameType.HEARTBEAT:
                p.parse_heartbeat(frame.payload)
                self.counts["heartbeats"] += 1
                return
            else:
                raise p.FrameError("payload", f"unknown type 0x{frame.frame_type:02X}")
        except p.FrameError:
            self.counts["rejected"] += 1
            self._status(p.StatusCode.COMMAND_REJECTED)
            return
        self.counts["commands"] += 1
        self.last_cmd_seq = frame.seq
        self.last_cmd_s = now

    def _may_arm(self, armed: bool) -> bool:
        """After a watchdog trip, torque stays off until a disarmed command was seen."""
        if not self.watchdog_tripped:
            return True
        if armed:
            self.counts["refused_while_tripped"] += 1
            return False
        self.watchdog_tripped = False
        return True

    def step(self, now: float, dt: float) -> None:
        """One millisecond of the Teensy's loop: read, watchdog, motors, sensor frame."""
        if self._master >= 0:
            while True:
                try:
                    data = os.read(self._master, READ_CHUNK)
                except BlockingIOError:
                    break
                except OSError:
                    break  # EIO while no host holds the port open
                if not data:
                    break
                for frame in self.decoder.feed(data):
                    self._on_frame(frame, now)
        if now - self.last_cmd_s > WATCHDOG_S and (self.armed or any(self.applied)):
            self.armed = False
            self.attitude = None
            self.applied = [0.0] * 4
            self.watchdog_tripped = True
            self.counts["watchdog_trips"] += 1
            self._status(p.StatusCode.COMMAND_TIMEOUT)
        if self.attitude is not None and self.armed:
            self.applied = self._attitude_torques()
        if self.on_step is not None:
            self.on_step(now, list(self.applied))
        else:
            for i, motor in enumerate(self.motors):
                motor.step(self.applied[i], dt)
        self._write(p.make_sensors(self._next_seq(), self.sample(now)))
        self.counts["sensors"] += 1

    def sample(self, now: float) -> p.Sensors:
        b = self.body
        flags = (p.SENSOR_CONTACT if b.contact else 0) | (p.SENSOR_ARMED if self.armed else 0)
        flags |= (p.SENSOR_WATCHDOG if self.watchdog_tripped else 0) | (p.SENSOR_FAULT if self.fault_flag else 0)
        m = self.motors
        return p.Sensors(
            t_us=int(now * 1e6),
            flags=flags,
            quat=b.quat,
            gyro=b.gyro,
            accel=b.accel,
            wheel_pos=(m[0].position, m[1].position, m[2].position),
            wheel_vel=(m[0].velocity, m[1].velocity, m[2].velocity),
            wheel_torque=(self.applied[0], self.applied[1], self.applied[2]),
            foot_pos=b.foot_pos,
            foot_vel=b.foot_vel,
            foot_motor_pos=m[3].position,
            last_cmd_seq=self.last_cmd_seq,
            crc_errors=self.decoder.rejected,
        )

    def _run(self) -> None:
        try:
            next_t = time.monotonic()
            last = next_t
            while not self._stop.is_set():
                now = time.monotonic()
                with self._lock:
                    if self._master < 0 and self.inject.replug_at is not None and now >= self.inject.replug_at:
                        self.inject.replug_at = None
                        self._plug()
                    self.step(now, min(0.01, now - last))
                last = now
                next_t += SENSOR_PERIOD_S
                delay = next_t - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                elif delay < -0.05:
                    next_t = time.monotonic()  # fell far behind: do not burst
        except BaseException as exc:  # surfaced to the owner through .error
            self.error = exc
            log.exception("Teensy emulator crashed")
