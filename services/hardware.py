"""The ``hardware`` service: torque commands to the motors, sensor frames to topics, at 1 kHz.

Subscribes ``torque_cmd`` (``attitude_cmd`` instead for a Teensy in attitude mode and for
ARCHER's own firmware, which runs the attitude PD on its board) into
latest-value slots. A :class:`~services.runtime.realtime.DeadlineLoop` thread then, every
tick: checks the command (its own watchdog: nothing newer than
``SafetyLimits.command_stale_s``, or not armed, means zero torque and disabled
drives), clamps it to ``SafetyLimits``, does one batched exchange with the hardware
(:class:`CanBackend`: ELMO drives over CANopen, one RPDO each and one SYNC;
:class:`TeensyBackend`: one frame to the Teensy;
:class:`~services.archer_firmware_backend.ArcherFirmwareBackend`: one UDP packet to
the flywheel board), and publishes ``joints`` (and ``imu`` when a Teensy or the
flywheel board provides it), stamped with the time the values were sampled.

Faults latch in the drivers (EMCY, lost heartbeat or feedback, bus-off, error
frames, vanished port): the motors get zero torque and a ``safety`` event is
published; an operator clears them by setting ``hardware.recover_request`` to a new
value through the parameter query. Drivers, counters and loop timing are in the
status (``archer status``).
"""

from __future__ import annotations

import asyncio
import math
import threading
import time
from collections.abc import Sequence
from typing import Any, Protocol

import can

from drivers.can_budget import LoadMeter
from drivers.elmo.device import DriveGroup, ElmoDrive, joint_drives
from drivers.elmo.transport import CanTransport
from drivers.socketcand import SocketcandBus
from drivers.teensy import protocol as tp
from drivers.teensy.device import Teensy
from drivers.teensy.transport import SerialLink
from onboard.contracts import messages as msgs
from onboard.contracts.params import HardwareParams, SafetyLimits
from services.runtime.realtime import DeadlineLoop, make_realtime_from
from services.runtime.service import LatestSlot, Service

NS = 1_000_000_000
STATUS_POLL_S = 0.2  # how often main() looks at the loop and the drivers
ZERO4 = (0.0, 0.0, 0.0, 0.0)


def gear_ratios() -> tuple[float, float, float, float]:
    """Joint gear ratios (wheels direct, foot through its gearbox), from the MJCF model."""
    from robot_description.params import robot_params  # the one source of physical parameters

    return (1.0, 1.0, 1.0, robot_params().foot_gear_ratio)


def bus_kwargs(params: HardwareParams) -> dict[str, Any]:
    """python-can ``can.Bus`` arguments for an interface other than socketcand (socketcan, pcan, ...)."""
    kwargs: dict[str, Any] = {"interface": params.can_interface, "channel": params.can_channel}
    if params.can_interface != "virtual":
        kwargs["bitrate"] = params.can_bitrate
    return kwargs


class Backend(Protocol):
    faults: list[str]

    def open(self) -> None: ...

    def exchange(self, now_s: float, torques: Sequence[float], armed: bool, attitude: msgs.AttitudeSetpoint | None) -> None: ...

    def joints(self) -> msgs.JointSensors | None: ...

    def imu(self) -> msgs.ImuSample | None: ...

    def recover(self, now_s: float) -> None: ...

    def summary(self) -> dict[str, float]: ...

    def close(self) -> None: ...


class CanBackend:
    """ELMO drives on a CAN bus; the host is the CANopen master."""

    def __init__(self, params: HardwareParams, safety: SafetyLimits, gears: Sequence[float], bus: can.BusABC | None = None) -> None:
        self.params = params
        self.safety = safety
        self._bus = bus
        self._own_bus = bus is None
        self.meter = LoadMeter()
        self.group: DriveGroup | None = None
        self._drives = [ElmoDrive(j) for j in joint_drives(params, gears)]
        self._t0 = time.monotonic()
        self._sync_ns = 0  # when the SYNC whose feedback we hold was sent
        self._prev_sync_ns = 0

    @property
    def faults(self) -> list[str]:
        return self.group.faults if self.group is not None else ["not started"]

    def open(self) -> None:
        if self._bus is None:
            p = self.params
            try:
                if p.can_interface == "socketcand":
                    # same protocol as python-can's client, with one write per tick's batch
                    self._bus = SocketcandBus(p.can_channel, p.can_host, p.can_port)
                else:
                    self._bus = can.Bus(**bus_kwargs(p))
            except (OSError, can.CanError) as exc:
                where = f"socketcand {p.can_host}:{p.can_port}" if p.can_interface == "socketcand" else f"{p.can_interface} {p.can_channel}"
                raise ConnectionError(f"cannot open the CAN bus ({where}): {exc}") from None
        transport = CanTransport(self._bus, self.meter)
        self.group = DriveGroup(transport, self._drives, self.params, self.safety.heartbeat_timeout_s)
        self.group.start()
        self._t0 = time.monotonic()
        self.meter.reset()

    def exchange(self, now_s: float, torques: Sequence[float], armed: bool, attitude: msgs.AttitudeSetpoint | None) -> None:
        assert self.group is not None
        self.group.exchange(torques, armed)
        self._sync_ns, self._prev_sync_ns = int(now_s * NS), self._sync_ns

    def joints(self) -> msgs.JointSensors | None:
        """The drives' answer to the previous SYNC; None unless every drive answered it."""
        assert self.group is not None
        answered = self.group.sync_count - 1
        fb = [x.feedback for x in self._drives]
        if any(f.sync != answered for f in fb):
            return None
        return msgs.JointSensors(
            stamp_ns=self._prev_sync_ns,  # sampled by the drives at the previous SYNC
            wheel_pos=[fb[0].position, fb[1].position, fb[2].position],
            wheel_vel=[fb[0].velocity, fb[1].velocity, fb[2].velocity],
            wheel_torque=[fb[0].torque, fb[1].torque, fb[2].torque],
            foot_pos=0.0,
            foot_vel=0.0,
            foot_contact=False,
            foot_motor_pos=fb[3].position,
            foot_sensed=False,
        )

    def imu(self) -> msgs.ImuSample | None:
        return None  # the IMU hangs on the Teensy, not on the CAN bus

    def recover(self, now_s: float) -> None:
        assert self.group is not None
        self.group.recover()

    def applied_limits(self) -> list[float]:
        return [d.torque_limit for d in self._drives]

    def summary(self) -> dict[str, float]:
        if self.group is None:
            return {}
        out = self.group.summary()
        elapsed = time.monotonic() - self._t0
        out["bus_load"] = round(self.meter.load(elapsed, self.params.can_bitrate), 4)  # since the bus opened
        out["bus_bits"] = round(self.meter.bits)  # for the load over a window of the caller's choosing
        return out

    def close(self) -> None:
        if self.group is not None:
            self.group.stop()
        if self._bus is not None and self._own_bus:
            self._bus.shutdown()


class TeensyBackend:
    """A Teensy on a serial port that drives the motors and reads the IMU and the foot."""

    def __init__(self, params: HardwareParams, safety: SafetyLimits, opener: Any = None) -> None:
        if not params.serial_port:
            raise ValueError("hardware.serial_port is empty: which port is the Teensy on?")
        kwargs = {} if opener is None else {"opener": opener}
        link = SerialLink(params.serial_port, params.reconnect_min_s, params.reconnect_max_s, **kwargs)
        self.teensy = Teensy(link, params.teensy_mode, params.link_timeout_s)  # type: ignore[arg-type]

    @property
    def faults(self) -> list[str]:
        return self.teensy.faults

    def open(self) -> None:
        self.teensy.link.ensure_open(time.monotonic())

    def exchange(self, now_s: float, torques: Sequence[float], armed: bool, attitude: msgs.AttitudeSetpoint | None) -> None:
        if attitude is not None and armed:
            cmd = tp.AttitudeCmd(
                tuple(attitude.quat_des), tuple(attitude.omega_des), tuple(attitude.torque_ff), attitude.foot_torque, True  # type: ignore[arg-type]
            )
            self.teensy.exchange(now_s, attitude=cmd)
        else:
            self.teensy.exchange(now_s, torque=tp.TorqueCmd((torques[0], torques[1], torques[2]), torques[3], armed))

    def _stamp_ns(self) -> int:
        return int(self.teensy.sensors_rx_s * NS)

    def joints(self) -> msgs.JointSensors | None:
        s = self.teensy.sensors
        if s is None or not self.teensy.fresh:
            return None
        return msgs.JointSensors(
            stamp_ns=self._stamp_ns(),
            wheel_pos=list(s.wheel_pos),
            wheel_vel=list(s.wheel_vel),
            wheel_torque=list(s.wheel_torque),
            foot_pos=s.foot_pos,
            foot_vel=s.foot_vel,
            foot_contact=bool(s.flags & tp.SENSOR_CONTACT),
            foot_motor_pos=s.foot_motor_pos,
        )

    def imu(self) -> msgs.ImuSample | None:
        s = self.teensy.sensors
        if s is None or not self.teensy.fresh:
            return None
        return msgs.ImuSample(stamp_ns=self._stamp_ns(), quat=list(s.quat), gyro=list(s.gyro), accel=list(s.accel))

    def recover(self, now_s: float) -> None:
        self.teensy.recover(now_s)

    def summary(self) -> dict[str, float]:
        return self.teensy.summary()

    def close(self) -> None:
        self.teensy.exchange(time.monotonic(), torque=tp.TorqueCmd((0.0, 0.0, 0.0), 0.0, False))
        self.teensy.link.close()


class CommandGate:
    """The service's own watchdog and limits: what may reach the motors this tick.

    Pure bookkeeping on values the tick passes in, so it is tested without threads.
    """

    def __init__(self, safety: SafetyLimits) -> None:
        self.safety = safety
        self.stale_ns = int(safety.command_stale_s * NS)
        self.limits = (safety.wheel_torque_max,) * 3 + (safety.foot_torque_max,)
        self.tripped = True  # no command seen yet counts as stale
        self.trips = 0
        self.clamped = 0
        self.speed_limited = 0
        self.last_age_s = math.inf

    def gate(self, cmd: msgs.TorqueCommand | None, recv_ns: int, now_ns: int, wheel_vel: Sequence[float]) -> tuple[tuple[float, ...], bool, bool]:
        """(torques, armed, newly_tripped) for this tick."""
        if cmd is None:
            return ZERO4, False, False
        age = now_ns - recv_ns
        self.last_age_s = age / NS
        if age > self.stale_ns:
            newly = not self.tripped
            if newly:
                self.trips += 1
            self.tripped = True
            return ZERO4, False, newly
        self.tripped = False
        if not cmd.armed:
            return ZERO4, False, False
        raw = (*cmd.wheel_torque, cmd.foot_torque)
        out = []
        for i, tau in enumerate(raw):
            limit = self.limits[i]
            if abs(tau) > limit:
                self.clamped += 1
                tau = math.copysign(limit, tau)
            if i < 3 and abs(wheel_vel[i]) > self.safety.wheel_speed_max and tau * wheel_vel[i] > 0:
                self.speed_limited += 1  # never drive a wheel further past its speed limit
                tau = 0.0
            out.append(tau)
        return tuple(out), True, False


class HardwareService(Service):
    name = "hardware"
    params_sections = ("hardware", "safety", "archer_firmware")
    subscribes = ("torque_cmd", "attitude_cmd")

    def __init__(self, *args: Any, backend: Backend | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._backend_override = backend
        self.backend: Backend | None = None
        self.loop: DeadlineLoop | None = None
        self._recover = threading.Event()
        self._recover_value = self.params["hardware"].recover_request
        self._faults_reported = 0
        self._wheel_vel: list[float] = [0.0, 0.0, 0.0]
        self.safety: SafetyLimits = self.params["safety"]
        self.gate = CommandGate(self.safety)

    # --- what it subscribes ------------------------------------------------------------

    async def setup(self) -> None:
        hw: HardwareParams = self.params["hardware"]
        # from the one live commander only (Service.commands): forged commands never reach a drive
        self.torque_slot: LatestSlot = self.commands("torque_cmd")
        attitude = hw.backend == "archer-firmware" or (hw.backend == "teensy" and hw.teensy_mode == "attitude")
        self.attitude_slot: LatestSlot | None = self.commands("attitude_cmd") if attitude else None
        self.joints_pub = self.publisher("joints")
        self.imu_pub = self.publisher("imu")
        self.safety_pub = self.publisher("safety")
        if self._backend_override is not None:
            self.backend = self._backend_override
        elif hw.backend == "can":
            self.backend = CanBackend(hw, self.safety, gear_ratios())
        elif hw.backend == "teensy":
            self.backend = TeensyBackend(hw, self.safety)
        elif hw.backend == "archer-firmware":
            from services.archer_firmware_backend import ArcherFirmwareBackend
            from robot_description.params import robot_params  # the one source of physical parameters (as gear_ratios)

            # the replies' reader stamps arrivals: it runs with the exchange thread's scheduling
            self.backend = ArcherFirmwareBackend(self.params["archer_firmware"], robot_params().wheel_axes,
                                                 on_reader_start=self._make_loop_realtime)
        else:
            raise ValueError(f"hardware.backend must be 'can', 'teensy' or 'archer-firmware', not {hw.backend!r}")
        await asyncio.to_thread(self.backend.open)
        self.loop = DeadlineLoop(1.0 / hw.rate_hz, self._tick, name="hardware-loop", on_start=self._make_loop_realtime)

    def _make_loop_realtime(self) -> None:
        hw = self.params["hardware"]
        applied = make_realtime_from(hw.rt_priority, hw.cpu)
        self.log.info("exchange thread scheduling", extra={"fields": applied})

    def on_params_changed(self, section: str) -> None:
        value = self.params["hardware"].recover_request
        if section == "hardware" and value != self._recover_value:
            self._recover_value = value
            self._recover.set()

    # --- what it computes and publishes, every tick ------------------------------------------

    def _publish_safety(self, trip: str, value: float, limit: float) -> None:
        self.count(f"trip.{trip}")
        self.safety_pub.put(msgs.SafetyEvent(trip=trip, value=value, limit=limit, armed=False, count=self.counters.get(f"trip.{trip}")))

    def _tick(self, deadline: float) -> None:
        backend = self.backend
        assert backend is not None
        now_ns = self.clock.now_ns()
        if self._recover.is_set():
            self._recover.clear()
            self.log.info("recovery requested", extra={"fields": {"faults": list(backend.faults)}})
            backend.recover(now_ns / NS)  # blocking (reconfigures the drives): an operator action, motors off
            self._faults_reported = len(backend.faults)
        attitude = None
        if self.attitude_slot is None:
            slot = self.torque_slot.get()
        else:  # the board runs the PD: the watchdog and the limits apply to the setpoint's torques
            slot = self.attitude_slot.get()
            if slot is not None:
                attitude = slot[0]
                as_torque = msgs.TorqueCommand(wheel_torque=list(attitude.torque_ff), foot_torque=attitude.foot_torque, armed=attitude.armed)
                slot = (as_torque, slot[1])
        cmd, recv_ns = slot if slot is not None else (None, 0)
        torques, armed, tripped = self.gate.gate(cmd, recv_ns, now_ns, self._wheel_vel)
        if attitude is not None and armed:  # what reaches the board is the clamped feed-forward
            attitude = msgs.AttitudeSetpoint(stamp_ns=attitude.stamp_ns, quat_des=attitude.quat_des, omega_des=attitude.omega_des,
                                             torque_ff=list(torques[:3]), foot_torque=torques[3], armed=True, commander=attitude.commander)
        if tripped:
            self._publish_safety("command_stale", self.gate.last_age_s, self.safety.command_stale_s)
        backend.exchange(now_ns / NS, torques, armed, attitude if armed else None)
        self.rate("tick").tick()
        faults = backend.faults
        if len(faults) > self._faults_reported:
            for reason in faults[self._faults_reported :]:
                self.fail(reason)
                self.count("trip.hardware_fault")
                event = msgs.SafetyEvent(trip=f"hardware_fault: {reason}", value=float(len(faults)), limit=0.0, armed=False, count=self.counters.get("trip.hardware_fault"))
                self.safety_pub.put(event)
            self._faults_reported = len(faults)
        # the IMU first: the estimator integrates an IMU interval once the same sample's joint
        # frame arrives, and fuses the leg kinematics only at a current IMU sample
        imu = backend.imu()
        if imu is not None:
            self.imu_pub.put(imu)
        joints = backend.joints()
        if joints is not None:
            self._wheel_vel = joints.wheel_vel
            self.joints_pub.put(joints)

    # --- lifecycle ---------------------------------------------------------------------------------

    async def main(self) -> None:
        assert self.loop is not None
        self.loop.start()
        try:
            while not self.stopping.is_set():
                await asyncio.sleep(STATUS_POLL_S)
                if self.loop.error is not None:
                    self.fail(f"hardware loop crashed: {self.loop.error!r}")
                    self.state = "error"
                    raise RuntimeError("hardware loop crashed") from self.loop.error
                backend = self.backend
                self.state = "degraded" if backend is not None and backend.faults else "running"
        finally:
            self.loop.stop()

    async def teardown(self) -> None:
        if self.backend is not None:
            await asyncio.to_thread(self.backend.close)

    def progress(self) -> bool:
        return self.loop is not None and self.loop.progressing()

    def status_extra(self) -> dict[str, float]:
        out: dict[str, float] = {}
        if self.loop is not None:
            for key, value in self.loop.recorder.stats().as_dict().items():
                out[f"loop.{key}"] = float(value)
        if self.backend is not None:
            for key, value in self.backend.summary().items():
                out[f"hw.{key}"] = float(value)
            out["hw.faults"] = float(len(self.backend.faults))
        out["watchdog.trips"] = float(self.gate.trips)
        out["watchdog.clamped"] = float(self.gate.clamped)
        out["watchdog.speed_limited"] = float(self.gate.speed_limited)
        return out

