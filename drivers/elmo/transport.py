"""CAN transport: moves :class:`~drivers.elmo.codec.Frame` objects over a python-can bus.

The transport layer of the ELMO driver. It sends a batch of frames per call and
drains received frames without waiting (:meth:`CanTransport.poll`), or waits for one
(:meth:`CanTransport.recv`, for SDO during configuration). It also watches the bus
itself: an error frame (SocketCAN error classes, as python-can reports them) or a
failed send latches a fault that only :meth:`CanTransport.clear_fault` clears, so a
glitching bus never silently resumes torque.
"""

from __future__ import annotations

import logging
import time
import can

from drivers.can_budget import LoadMeter
from drivers.elmo.codec import Frame

log = logging.getLogger("archer.drivers.can")

# SocketCAN error classes (linux/can/error.h), carried in an error frame's identifier.
CAN_ERR_TX_TIMEOUT = 0x001
CAN_ERR_LOSTARB = 0x002
CAN_ERR_CRTL = 0x004
CAN_ERR_PROT = 0x008
CAN_ERR_TRX = 0x010
CAN_ERR_ACK = 0x020
CAN_ERR_BUSOFF = 0x040
CAN_ERR_BUSERROR = 0x080
CAN_ERR_RESTARTED = 0x100

ERROR_CLASS_NAMES = {
    CAN_ERR_TX_TIMEOUT: "tx-timeout",
    CAN_ERR_LOSTARB: "lost-arbitration",
    CAN_ERR_CRTL: "controller",
    CAN_ERR_PROT: "protocol-violation",
    CAN_ERR_TRX: "transceiver",
    CAN_ERR_ACK: "no-ack",
    CAN_ERR_BUSOFF: "bus-off",
    CAN_ERR_BUSERROR: "bus-error",
    CAN_ERR_RESTARTED: "restarted",
}
# Classes that are information, not a fault: arbitration is normal, a restart is the recovery.
BENIGN_ERROR_CLASSES = CAN_ERR_LOSTARB | CAN_ERR_RESTARTED


def error_classes(error_id: int) -> list[str]:
    return [name for bit, name in ERROR_CLASS_NAMES.items() if error_id & bit]


def make_error_frame(error_class: int) -> can.Message:
    """An error frame as SocketCAN reports it (used by the emulators to inject faults)."""
    return can.Message(arbitration_id=error_class, is_error_frame=True, is_extended_id=True, data=bytes(8))


class BusGone(Exception):
    """The bus interface itself failed (socket closed, adapter unplugged)."""


class CanTransport:
    """Frames in and out of one python-can bus, with bus-fault latching and counters."""

    def __init__(self, bus: can.BusABC, meter: LoadMeter | None = None) -> None:
        self.bus = bus
        self.meter = meter
        self.fault = ""  # latched; "" when healthy
        self.tx_frames = 0
        self.rx_frames = 0
        self.tx_errors = 0
        self.error_frames = 0
        self.bus_off = 0
        self.broken = False  # the interface failed (not just the bus): no recovery by clearing

    # --- faults ------------------------------------------------------------------

    def _latch(self, reason: str) -> None:
        if not self.fault:
            self.fault = reason
            log.error(f"CAN fault latched: {reason}", extra={"fields": {"reason": reason}})

    def clear_fault(self) -> None:
        """Recovery on command: forget the latched fault."""
        self.fault = ""

    def _on_error_frame(self, msg: can.Message) -> None:
        self.error_frames += 1
        classes = msg.arbitration_id & 0x1FFFFFFF
        if classes & CAN_ERR_BUSOFF:
            self.bus_off += 1
        if classes & ~BENIGN_ERROR_CLASSES:
            self._latch("CAN error frame: " + ",".join(error_classes(classes)))

    # --- moving frames -------------------------------------------------------------

    def send(self, frame: Frame) -> bool:
        try:
            self.bus.send(can.Message(arbitration_id=frame.can_id, data=frame.data, is_extended_id=False))
        except (can.CanError, OSError) as exc:
            self.tx_errors += 1
            self._latch(f"CAN send failed: {exc}")
            return False
        self.tx_frames += 1
        if self.meter is not None:
            self.meter.add(frame.can_id, frame.data)
        return True

    def send_batch(self, frames: list[Frame]) -> int:
        """Send ``frames`` in order, in one write where the interface can; returns how many went out."""
        send_many = getattr(self.bus, "send_many", None)
        if send_many is None:
            sent = 0
            for frame in frames:
                if not self.send(frame):
                    break
                sent += 1
            return sent
        try:
            send_many([can.Message(arbitration_id=f.can_id, data=f.data, is_extended_id=False) for f in frames])
        except (can.CanError, OSError) as exc:
            self.tx_errors += 1
            self._latch(f"CAN send failed: {exc}")
            return 0
        self.tx_frames += len(frames)
        if self.meter is not None:
            for f in frames:
                self.meter.add(f.can_id, f.data)
        return len(frames)

    def _accept(self, msg: can.Message | None) -> Frame | None:
        if msg is None:
            return None
        if msg.is_error_frame:
            self._on_error_frame(msg)
            return None
        if msg.is_extended_id or msg.is_remote_frame:
            return None  # CANopen here uses 11-bit data frames only
        self.rx_frames += 1
        data = bytes(msg.data)
        if self.meter is not None:
            self.meter.add(msg.arbitration_id, data)
        return Frame(msg.arbitration_id, data)

    def _recv_msg(self, timeout: float) -> can.Message | None:
        """The next message, None on timeout; raises :class:`BusGone` when the bus broke."""
        try:
            return self.bus.recv(timeout)
        except (can.CanError, OSError, ValueError) as exc:
            self.broken = True
            self._latch(f"CAN receive failed: {exc}")
            raise BusGone(str(exc)) from None

    def poll(self) -> list[Frame]:
        """All frames received so far, without waiting (none once the bus broke)."""
        out: list[Frame] = []
        while True:
            try:
                msg = self._recv_msg(0.0)
            except BusGone:
                return out
            if msg is None:
                return out
            frame = self._accept(msg)
            if frame is not None:
                out.append(frame)

    def recv(self, timeout_s: float) -> Frame | None:
        """The next data frame, waiting at most ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while True:
            remaining = deadline - time.monotonic()
            try:
                msg = self._recv_msg(max(0.0, remaining))
            except BusGone:
                return None
            if msg is None:
                if remaining <= 0:
                    return None
                continue
            frame = self._accept(msg)
            if frame is not None:
                return frame

    def shutdown(self) -> None:
        self.bus.shutdown()
