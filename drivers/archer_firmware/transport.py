"""UDP transport for the ARCHER firmware: one non-blocking socket, one configured peer.

The transport layer of the driver, used by both ends (the computer's device and the
board's emulator). :meth:`UdpLink.poll` returns every datagram waiting now (never
blocks), each stamped with the time it was read; :meth:`UdpLink.send` sends one
datagram to the peer without waiting. The board reads in its loop, as the firmware
does. The computer starts a reader thread (:meth:`UdpLink.start_reader`) that blocks
in ``recvfrom`` and stamps each datagram as it arrives, so that a reply's time (and
whether it was late) does not depend on when the control tick happens to poll. Datagrams from any other address or port are
dropped and counted as ``foreign``: on a robot's network only the configured peer
may command the board or feed the computer a state. Nothing here retries: UDP has no
connection to lose, a missing answer is the device layer's business.
"""

from __future__ import annotations

import logging
import select
import socket
import threading
from collections import deque
from collections.abc import Callable

log = logging.getLogger("archer.drivers.archer_firmware")

MAX_DATAGRAM = 2048  # larger than any valid packet, so an oversized one is seen whole and counted
RECV_BATCH = 64  # datagrams read per poll at most: a flood cannot stall the caller's tick
READER_QUEUE = 256  # datagrams the reader thread holds for poll(); the oldest go beyond
READER_WAKE_S = 0.1  # the reader thread notices close() this often


class UdpLink:
    def __init__(self, local: tuple[str, int], peer: tuple[str, int], clock: Callable[[], float]) -> None:
        """Bind ``local`` (port 0: a free one) and accept datagrams from ``peer`` only."""
        self.peer = (socket.gethostbyname(peer[0]), int(peer[1]))
        self._clock = clock
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self._sock.bind(local)
        except OSError:
            self._sock.close()
            raise
        self._sock.setblocking(False)
        self.local = self._sock.getsockname()
        self.rx = 0  # datagrams accepted from the peer
        self.foreign = 0  # datagrams from anyone else, dropped
        self.tx = 0
        self.tx_errors = 0  # the OS refused the send (buffer full, ICMP unreachable reported back)
        self.last_foreign: tuple[str, int] | None = None
        self.queue_dropped = 0  # datagrams the reader thread had to discard (poll() too rare)
        self._queue: deque[tuple[bytes, float]] = deque()
        self._reader: threading.Thread | None = None
        self._closed = threading.Event()

    def _accept(self, data: bytes, addr: tuple[str, int]) -> bool:
        if (addr[0], addr[1]) != self.peer:
            self.foreign += 1
            if addr != self.last_foreign:
                log.warning("datagram from an unexpected address dropped", extra={"fields": {"from": f"{addr[0]}:{addr[1]}"}})
            self.last_foreign = (addr[0], addr[1])
            return False
        self.rx += 1
        return True

    def start_reader(self, on_start: Callable[[], None] | None = None) -> None:
        """Read on a thread from now on, stamping each datagram as it arrives; ``on_start`` runs
        first on that thread (the caller's scheduling: a stamp taken late is a wrong stamp)."""
        if self._reader is not None:
            return
        self._reader = threading.Thread(target=self._read_forever, args=(on_start,), name="udp-reader", daemon=True)
        self._reader.start()

    def _read_forever(self, on_start: Callable[[], None] | None) -> None:
        if on_start is not None:
            on_start()
        while not self._closed.is_set():
            # select, then a non-blocking read: the socket stays non-blocking for send()
            readable, _, _ = select.select([self._sock], [], [], READER_WAKE_S)
            if not readable:
                continue
            try:
                data, addr = self._sock.recvfrom(MAX_DATAGRAM)
            except OSError:  # nothing after all, or an ICMP error for an earlier send
                continue
            stamp = self._clock()
            if self._accept(data, addr):
                if len(self._queue) >= READER_QUEUE:
                    self._queue.popleft()
                    self.queue_dropped += 1
                self._queue.append((data, stamp))

    def poll(self) -> list[tuple[bytes, float]]:
        """Datagrams from the peer waiting now, with the time each arrived (or was read)."""
        out: list[tuple[bytes, float]] = []
        if self._reader is not None:
            while self._queue:
                out.append(self._queue.popleft())
            return out
        for _ in range(RECV_BATCH):
            try:
                data, addr = self._sock.recvfrom(MAX_DATAGRAM)
            except BlockingIOError:
                break
            except ConnectionRefusedError:
                continue  # an earlier send hit a closed port (ICMP): nothing to read
            except OSError as exc:
                log.warning("udp receive failed", extra={"fields": {"error": str(exc)}})
                break
            if self._accept(data, addr):
                out.append((data, self._clock()))
        return out

    def send(self, data: bytes) -> bool:
        try:
            self._sock.sendto(data, self.peer)
        except OSError:  # buffer full, or the peer's port reported closed
            self.tx_errors += 1
            return False
        self.tx += 1
        return True

    def close(self) -> None:
        self._closed.set()
        if self._reader is not None:
            self._reader.join(2 * READER_WAKE_S + 1.0)
        self._sock.close()

    def summary(self) -> dict[str, float]:
        return {"rx": self.rx, "foreign": self.foreign, "tx": self.tx, "tx_errors": self.tx_errors, "queue_dropped": self.queue_dropped}
