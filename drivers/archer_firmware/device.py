"""The flywheel board as a device: one setpoint out per tick, the latest state in.

The device layer of the driver. :meth:`ArcherBoard.exchange` reads every reply that
arrived, keeps the newest valid one with the time it was read, then sends at most one
packet: the setpoint, or nothing. The firmware has no "motors off" packet; silence
is how the computer stops the motors (its watchdog turns them off after 100 ms), so
nothing is sent while the caller has no setpoint or a fault is latched.

The board answers every packet it receives with one state, and only then. The
replies carry no sequence number, so they are matched to requests first in, first
out: a reply that arrived more than ``reply_late_s`` after its request is *late*
(the link's reader thread stamps arrivals, :meth:`UdpLink.start_reader`), a request
unanswered for ``reply_missing_s`` is *missing* (and forgotten), a reply with no
request waiting is *unsolicited*. While commanding, no valid reply for
``link_timeout_s`` latches a fault (the computer's watchdog) until :meth:`recover`.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

from drivers.archer_firmware import codec
from drivers.archer_firmware.transport import UdpLink
from drivers.faults import LatchedFaults
from onboard.contracts.params import ArcherFirmwareParams

log = logging.getLogger("archer.drivers.archer_firmware")

MAX_OUTSTANDING = 1024  # requests remembered at most (a dead board must not grow memory)


@dataclass
class BoardStats:
    requests: int = 0
    resets: int = 0
    replies: int = 0  # valid states
    late: int = 0
    missing: int = 0
    unsolicited: int = 0
    stale_ticks: int = 0  # ticks without a new state
    rejected_length: int = 0
    rejected_non_finite: int = 0
    rejected_quaternion: int = 0
    refused_setpoints: int = 0  # setpoints the caller gave that could not be encoded (NaN, not a unit quaternion)
    faults_latched: int = 0
    recoveries: int = 0


class ArcherBoard(LatchedFaults):
    device_name = "ARCHER flywheel board"
    fault_log = log

    def __init__(self, link: UdpLink, params: ArcherFirmwareParams) -> None:
        self.link = link
        self.params = params
        self.state: codec.BoardState | None = None
        self.state_rx_s = -1.0  # host time the newest state arrived
        self.fresh = False  # a new state arrived in the last exchange
        self.faults: list[str] = []
        self.stats = BoardStats()
        self._outstanding: deque[float] = deque(maxlen=MAX_OUTSTANDING)  # send times of unanswered requests
        self._commanding_since: float | None = None

    def open(self, on_reader_start: Callable[[], None] | None = None) -> None:
        """Stamp replies as they arrive (a reader thread) instead of when a tick polls;
        ``on_reader_start`` runs first on that thread (its scheduling)."""
        self.link.start_reader(on_reader_start)

    # --- receiving --------------------------------------------------------------------

    def _receive(self, now: float) -> None:
        self.fresh = False
        for data, rx_s in self.link.poll():
            try:
                state = codec.unpack_state(data)
            except codec.CodecError as exc:
                self._count_rejection(exc.kind)
                continue
            if self._outstanding:
                sent = self._outstanding.popleft()
                if rx_s - sent > self.params.reply_late_s:
                    self.stats.late += 1
            else:
                self.stats.unsolicited += 1
            self.state, self.state_rx_s, self.fresh = state, rx_s, True
            self.stats.replies += 1
        while self._outstanding and now - self._outstanding[0] > self.params.reply_missing_s:
            self._outstanding.popleft()
            self.stats.missing += 1

    def _count_rejection(self, kind: str) -> None:
        name = f"rejected_{kind}"
        setattr(self.stats, name, getattr(self.stats, name) + 1)

    # --- sending ------------------------------------------------------------------------

    def _send(self, packet: bytes, now: float) -> None:
        if self.link.send(packet):
            self._outstanding.append(now)

    def reset(self, now: float) -> None:
        """Send the firmware's reset command (it is answered like any packet)."""
        self.stats.resets += 1
        self._send(codec.RESET_PACKET, now)

    def recover(self, now: float) -> bool:
        """Clears the faults; the link is judged again from the next setpoint on."""
        self.stats.recoveries += 1
        self.faults.clear()
        self._commanding_since = None
        return True

    def exchange(self, now: float, setpoint: codec.Setpoint | None) -> None:
        """One tick: read the replies, check the link, send the setpoint (or nothing)."""
        self._receive(now)
        if not self.fresh:
            self.stats.stale_ticks += 1
        if setpoint is None or self.faulted:
            self._commanding_since = None
            return
        if self._commanding_since is None:
            self._commanding_since = now
        since = max(self.state_rx_s, self._commanding_since)
        if now - since > self.params.link_timeout_s:
            self.latch(f"no reply from the board for {self.params.link_timeout_s * 1000:.0f} ms")
            return  # silence: the board's own watchdog turns the motors off
        try:
            packet = codec.pack_setpoint(setpoint)
        except codec.CodecError:
            self.stats.refused_setpoints += 1
            return
        self.stats.requests += 1
        self._send(packet, now)

    def summary(self) -> dict[str, float]:
        out: dict[str, float] = {k: float(v) for k, v in vars(self.stats).items()}
        out.update({f"udp_{k}": float(v) for k, v in self.link.summary().items()})
        out["outstanding"] = float(len(self._outstanding))
        return out

    def close(self) -> None:
        self.link.close()
