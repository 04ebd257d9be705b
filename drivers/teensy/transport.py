"""Serial transport for the Teensy link: non-blocking reads and writes, reconnect with backoff.

The transport layer of the Teensy driver. :meth:`SerialLink.poll` reads whatever
bytes are waiting (never blocks) and returns the frames they complete;
:meth:`SerialLink.send` writes one encoded frame without waiting. When the port
vanishes (USB unplugged, emulator gone) the link closes, counts a disconnect and
retries the open with exponential backoff, from ``reconnect_min_s`` up to
``reconnect_max_s``; the backoff resets once a valid frame arrives again.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import serial

from drivers.teensy.protocol import FrameDecoder, RawFrame

log = logging.getLogger("archer.drivers.teensy")

READ_CHUNK = 65536


def open_port(path: str) -> serial.Serial:
    """The port in raw, non-blocking mode (USB CDC ignores the baud rate)."""
    return serial.Serial(path, baudrate=2_000_000, timeout=0, write_timeout=0, exclusive=True)


class SerialLink:
    def __init__(
        self,
        port: str,
        reconnect_min_s: float,
        reconnect_max_s: float,
        opener: Callable[[str], serial.Serial] = open_port,
    ) -> None:
        if reconnect_min_s <= 0 or reconnect_max_s < reconnect_min_s:
            raise ValueError("need 0 < reconnect_min_s <= reconnect_max_s")
        self.port = port
        self.reconnect_min_s = reconnect_min_s
        self.reconnect_max_s = reconnect_max_s
        self._opener = opener
        self._serial: serial.Serial | None = None
        self._backoff = reconnect_min_s
        self._next_attempt = 0.0
        self.decoder = FrameDecoder()
        self.connects = 0
        self.disconnects = 0
        self.open_failures = 0
        self.tx_frames = 0
        self.tx_dropped = 0  # the OS buffer was full: the frame was not (completely) written
        self.rx_bytes = 0
        self.last_error = ""

    @property
    def connected(self) -> bool:
        return self._serial is not None

    def _lost(self, exc: Exception) -> None:
        self.last_error = f"{self.port}: {exc}"
        log.warning("serial link lost", extra={"fields": {"port": self.port, "error": str(exc)}})
        self.close()
        self.disconnects += 1

    def ensure_open(self, now: float) -> bool:
        """Open the port if closed and the backoff allows; True when connected."""
        if self._serial is not None:
            return True
        if now < self._next_attempt:
            return False
        try:
            self._serial = self._opener(self.port)
        except (serial.SerialException, OSError, ValueError) as exc:
            self.open_failures += 1
            self.last_error = f"{self.port}: {exc}"
            self._next_attempt = now + self._backoff
            self._backoff = min(self.reconnect_max_s, self._backoff * 2.0)
            return False
        self.connects += 1
        self.decoder = _continue_counts(self.decoder)
        log.info("serial link open", extra={"fields": {"port": self.port}})
        return True

    def poll(self, now: float) -> list[RawFrame]:
        """Frames completed by the bytes waiting now (reconnecting first if needed)."""
        if not self.ensure_open(now):
            return []
        assert self._serial is not None
        try:
            data = self._serial.read(READ_CHUNK)
        except (serial.SerialException, OSError, TypeError) as exc:
            # pyserial raises TypeError from inside read() when the fd was closed under it
            self._lost(exc)
            return []
        if not data:
            return []
        self.rx_bytes += len(data)
        frames = self.decoder.feed(data)
        if frames:
            self._backoff = self.reconnect_min_s
        return frames

    def send(self, frame: bytes, now: float) -> bool:
        if not self.ensure_open(now):
            return False
        assert self._serial is not None
        try:
            self._serial.write(frame)
        except serial.SerialTimeoutException:
            self.tx_dropped += 1
            return False
        except (serial.SerialException, OSError, TypeError) as exc:
            self._lost(exc)
            return False
        self.tx_frames += 1
        return True

    def close(self) -> None:
        if self._serial is not None:
            try:
                self._serial.close()
            except (serial.SerialException, OSError):
                pass
            self._serial = None
            self._next_attempt = 0.0  # the first retry goes at once, then backs off


def _continue_counts(old: FrameDecoder) -> FrameDecoder:
    """A fresh decoder (no half frame from the old port) that keeps the counters."""
    new = FrameDecoder()
    new.counts = old.counts
    return new
