"""UDP transport for the ARCHER firmware: one non-blocking socket, one configured peer.

The transport layer of the driver, used by both ends (the computer's device and the
board's emulator). :meth:`UdpLink.poll` returns every datagram waiting now (never
blocks), each stamped with the time it was read; :meth:`UdpLink.send` sends one
datagram to the peer without waiting. Datagrams from any other address or port are
dropped and counted as ``foreign``: on a robot's network only the configured peer
may command the board or feed the computer a state. Nothing here retries: UDP has no
connection to lose, a missing answer is the device layer's business.
"""

from __future__ import annotations

import logging
import socket
from collections.abc import Callable

log = logging.getLogger("archer.drivers.archer_firmware")

MAX_DATAGRAM = 2048  # larger than any valid packet, so an oversized one is seen whole and counted
RECV_BATCH = 64  # datagrams read per poll at most: a flood cannot stall the caller's tick


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

    def poll(self) -> list[tuple[bytes, float]]:
        """Datagrams from the peer waiting now, with the time each was read."""
        out: list[tuple[bytes, float]] = []
        for _ in range(RECV_BATCH):
            try:
                data, addr = self._sock.recvfrom(MAX_DATAGRAM)
            except BlockingIOError:
                break
            except ConnectionRefusedError:
                self.tx_errors += 1  # an earlier send hit a closed port (ICMP): nothing to read
                continue
            except OSError as exc:
                log.warning("udp receive failed", extra={"fields": {"error": str(exc)}})
                break
            if (addr[0], addr[1]) != self.peer:
                self.foreign += 1
                if addr != self.last_foreign:
                    log.warning("datagram from an unexpected address dropped", extra={"fields": {"from": f"{addr[0]}:{addr[1]}"}})
                self.last_foreign = (addr[0], addr[1])
                continue
            self.rx += 1
            out.append((data, self._clock()))
        return out

    def send(self, data: bytes) -> bool:
        try:
            self._sock.sendto(data, self.peer)
        except (BlockingIOError, ConnectionRefusedError, OSError):
            self.tx_errors += 1
            return False
        self.tx += 1
        return True

    def close(self) -> None:
        self._sock.close()

    def summary(self) -> dict[str, float]:
        return {"rx": self.rx, "foreign": self.foreign, "tx": self.tx, "tx_errors": self.tx_errors}
