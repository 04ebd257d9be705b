"""The Teensy as a device: one command frame out per tick, the latest sensor frame in.

The device layer of the Teensy driver. :meth:`Teensy.exchange` reads every frame
that arrived, keeps the newest SENSORS frame, then sends exactly one command frame
(TORQUE or ATTITUDE by mode, disarmed zero torque while faulted) and, every
``HEARTBEAT_PERIOD_S``, a HEARTBEAT. ``make_*`` build frames without sending.

Faults latch until :meth:`Teensy.recover`: the port vanished, no SENSORS frame for
``link_timeout_s``, or the Teensy reports its own command watchdog or a drive fault
while the host was commanding. The Teensy itself zeroes its motors when no command
frame reaches it for 100 ms, so a dead host or a dead link is safe on both sides.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Literal

from drivers.faults import LatchedFaults
from drivers.teensy import protocol as p
from drivers.teensy.transport import SerialLink

log = logging.getLogger("archer.drivers.teensy")

HEARTBEAT_PERIOD_S = 0.1
ZERO3 = (0.0, 0.0, 0.0)

Mode = Literal["torque", "attitude"]


@dataclass
class TeensyStats:
    sensors: int = 0
    stale_ticks: int = 0  # ticks without a new SENSORS frame
    payload_errors: int = 0  # frames with a valid CRC but a payload of the wrong size or NaN
    unexpected: int = 0  # frame types the host does not consume
    status_events: int = 0
    faults_latched: int = 0
    recoveries: int = 0


class Teensy(LatchedFaults):
    device_name = "Teensy"
    fault_log = log

    def __init__(self, link: SerialLink, mode: Mode, link_timeout_s: float) -> None:
        if mode not in ("torque", "attitude"):
            raise ValueError(f"unknown Teensy mode {mode!r}")
        self.link = link
        self.mode = mode
        self.link_timeout_s = link_timeout_s
        self.sensors: p.Sensors | None = None
        self.sensors_rx_s = -1.0  # host time the newest SENSORS frame arrived
        self.fresh = False  # a new SENSORS frame arrived in the last exchange
        self.faults: list[str] = []
        self.last_status: tuple[p.StatusCode | int, int] | None = None
        self.stats = TeensyStats()
        self._seq = 0
        self._next_heartbeat_s = 0.0
        self._started_s: float | None = None
        self._disconnects_seen = 0

    # --- frames ---------------------------------------------------------------------

    def _next_seq(self) -> int:
        self._seq = (self._seq + 1) % p.SEQ_MODULO
        return self._seq

    def make_torque(self, cmd: p.TorqueCmd) -> bytes:
        return p.make_torque(self._next_seq(), cmd)

    def make_attitude(self, cmd: p.AttitudeCmd) -> bytes:
        return p.make_attitude(self._next_seq(), cmd)

    def make_gains(self, gains: p.Gains) -> bytes:
        return p.make_gains(self._next_seq(), gains)

    def make_heartbeat(self, now: float) -> bytes:
        return p.make_heartbeat(self._next_seq(), int(now * 1000))

    # --- faults -------------------------------------------------------------------------

    def recover(self, now: float) -> bool:
        """Recovery on command: clears the faults if the link is up and sensors are fresh."""
        self.stats.recoveries += 1
        if not self.link.connected or now - self.sensors_rx_s > self.link_timeout_s:
            self.latch("recovery refused: link down")
            return False
        self.faults.clear()
        self._disconnects_seen = self.link.disconnects
        return True

    # --- the cyclic exchange --------------------------------------------------------------

    def _receive(self, now: float) -> None:
        self.fresh = False
        for frame in self.link.poll(now):
            try:
                if frame.frame_type == p.FrameType.SENSORS:
                    self.sensors = p.parse_sensors(frame.payload)
                    self.sensors_rx_s = now
                    self.fresh = True
                    self.stats.sensors += 1
                    if self.sensors.flags & p.SENSOR_WATCHDOG:
                        self.latch("Teensy command watchdog tripped: commands did not arrive")
                    if self.sensors.flags & p.SENSOR_FAULT:
                        self.latch("Teensy reports a drive fault")
                elif frame.frame_type == p.FrameType.STATUS:
                    self._on_status(p.parse_status(frame.payload))
                elif frame.frame_type == p.FrameType.HEARTBEAT:
                    p.parse_heartbeat(frame.payload)
                else:
                    self.stats.unexpected += 1
            except p.FrameError:
                self.stats.payload_errors += 1

    def _on_status(self, status: tuple[p.StatusCode | int, int]) -> None:
        self.stats.status_events += 1
        self.last_status = status
        code = status[0]
        if code == p.StatusCode.COMMAND_TIMEOUT:
            self.latch("Teensy command watchdog tripped: commands did not arrive")
        elif code == p.StatusCode.DRIVE_FAULT:
            self.latch("Teensy reports a drive fault")
        elif code == p.StatusCode.IMU_FAULT:
            self.latch("Teensy reports an IMU fault")
        elif code == p.StatusCode.COMMAND_REJECTED:
            log.warning("Teensy rejected a command", extra={"fields": {"count": status[1]}})

    def exchange(self, now: float, torque: p.TorqueCmd | None = None, attitude: p.AttitudeCmd | None = None) -> None:
        """One tick: read, check the link, send one command frame (and a heartbeat when due)."""
        if self._started_s is None:
            self._started_s = now
        self._receive(now)
        if not self.fresh:
            self.stats.stale_ticks += 1
        if self.link.disconnects != self._disconnects_seen:
            self._disconnects_seen = self.link.disconnects
            self.latch(f"serial port vanished ({self.link.last_error})")
        since = self.sensors_rx_s if self.sensors_rx_s >= 0 else self._started_s
        if now - since > self.link_timeout_s:
            self.latch(f"no sensor frame for {self.link_timeout_s * 1000:.0f} ms")
        if self.mode == "attitude" and attitude is not None and not self.faulted:
            frame = self.make_attitude(attitude)
        elif torque is not None and not self.faulted:
            frame = self.make_torque(torque)
        else:
            frame = self.make_torque(p.TorqueCmd(ZERO3, 0.0, False))
        self.link.send(frame, now)
        if now >= self._next_heartbeat_s:
            self.link.send(self.make_heartbeat(now), now)
            self._next_heartbeat_s = now + HEARTBEAT_PERIOD_S

    def summary(self) -> dict[str, float]:
        s = self.stats
        d = self.link.decoder.counts
        return {
            "sensors": s.sensors,
            "stale_ticks": s.stale_ticks,
            "payload_errors": s.payload_errors,
            "unexpected": s.unexpected,
            "status_events": s.status_events,
            "faults_latched": s.faults_latched,
            "recoveries": s.recoveries,
            "crc_errors": d["crc"],
            "cobs_errors": d["cobs"],
            "oversize": d["oversize"],
            "gaps": d["gaps"],
            "missing": d["missing"],
            "rejected_frames": self.link.decoder.rejected,
            "tx_frames": self.link.tx_frames,
            "tx_dropped": self.link.tx_dropped,
            "connects": self.link.connects,
            "disconnects": self.link.disconnects,
            "connected": float(self.link.connected),
        }
