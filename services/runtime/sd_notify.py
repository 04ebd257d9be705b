"""systemd's notify protocol, spoken directly (no libsystemd binding needed).

A service of ``Type=notify`` sends newline-separated ``KEY=VALUE`` assignments as
one datagram to the AF_UNIX socket named by ``$NOTIFY_SOCKET`` (a leading ``@``
means the Linux abstract namespace). The runtime sends:

- ``READY=1`` once ``setup()`` has returned, so units ordered ``After=`` it start
  only when its subscriptions and publishers exist;
- ``WATCHDOG=1`` every half ``$WATCHDOG_USEC``, but only while
  :meth:`services.runtime.service.Service.progress` says the service makes progress: a
  wedged event loop or a stalled hard-rate thread stops the pings and systemd (or
  :mod:`services.runtime.supervisor`) kills and restarts the service;
- ``STATUS=...``, a one-line summary shown by ``systemctl status``;
- ``STOPPING=1`` on the way out.

Without ``$NOTIFY_SOCKET`` (a shell, a test, lockstep) every call is a no-op.
"""

from __future__ import annotations

import asyncio
import os
import socket
from collections.abc import Mapping
from typing import Protocol



class Counts(Protocol):
    def get(self, name: str) -> int: ...


class Service(Protocol):
    """What the notifier reads of a service (:class:`services.runtime.service.Service`); a
    protocol, so that the service base imports this module and not the other way round."""

    state: str
    counters: Counts
    last_error: str

    def rates_hz(self) -> dict[str, float]: ...

    def progress(self) -> bool: ...


SOCKET_ENV = "NOTIFY_SOCKET"
WATCHDOG_USEC_ENV = "WATCHDOG_USEC"
WATCHDOG_PID_ENV = "WATCHDOG_PID"
STATUS_PERIOD_S = 2.0  # STATUS refresh when no watchdog asks for faster pings
STATUS_MAX_CHARS = 200  # systemctl shows one line; keep it readable


def socket_address(value: str) -> str | bytes:
    """``$NOTIFY_SOCKET`` as a ``socket.connect`` address (``@name`` is abstract)."""
    if value.startswith("@"):
        return b"\0" + value[1:].encode()
    return value


class Notifier:
    """Sends notify datagrams to the service manager; inert when there is none."""

    def __init__(self, env: Mapping[str, str] | None = None) -> None:
        env = os.environ if env is None else env
        path = env.get(SOCKET_ENV, "")
        self._address: str | bytes | None = socket_address(path) if path else None
        self.watchdog_s: float | None = None
        usec = env.get(WATCHDOG_USEC_ENV, "")
        pid = env.get(WATCHDOG_PID_ENV, "")
        # WATCHDOG_PID names the process the manager expects pings from; a child
        # that inherited the environment must not answer for its parent.
        if usec.isdigit() and int(usec) > 0 and (not pid or pid == str(os.getpid())):
            self.watchdog_s = int(usec) / 1e6
        self._sock: socket.socket | None = None

    @property
    def enabled(self) -> bool:
        return self._address is not None

    def notify(self, **fields: str | int) -> bool:
        """Send ``KEY=value`` lines (``notify(READY=1, STATUS="ok")``); True if sent."""
        if self._address is None:
            return False
        payload = "\n".join(f"{k}={v}" for k, v in fields.items()).encode()
        try:
            if self._sock is None:
                # Non-blocking: a manager that lags (its queue holds ~10 datagrams)
                # costs a dropped ping, never a stalled event loop.
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC | socket.SOCK_NONBLOCK)
            self._sock.sendto(payload, self._address)
        except OSError:
            return False  # manager gone or behind; the service itself keeps running
        return True

    def ready(self, status: str = "") -> bool:
        return self.notify(READY=1, STATUS=status) if status else self.notify(READY=1)

    def watchdog(self) -> bool:
        return self.notify(WATCHDOG=1)

    def status(self, text: str) -> bool:
        return self.notify(STATUS=text[:STATUS_MAX_CHARS].replace("\n", " "))

    def stopping(self) -> bool:
        return self.notify(STOPPING=1)

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


def status_line(service: Service) -> str:
    """``running; rx.state 999 Hz, tick 1000 Hz; errors 0; last error: ...``

    Built from the cheap parts of the status only: ``status_extra`` may compute
    percentiles over a loop's history, too costly to run every second beside a
    1 kHz loop.
    """
    rates = ", ".join(f"{name} {hz:.0f} Hz" for name, hz in sorted(service.rates_hz().items()))
    parts = [service.state]
    if rates:
        parts.append(rates)
    parts.append(f"errors {service.counters.get('errors')}")
    if service.last_error:
        parts.append(f"last error: {service.last_error}")
    return "; ".join(parts)


async def keep_alive(service: Service, notifier: Notifier | None = None) -> None:
    """READY now, then WATCHDOG while ``service.progress()`` holds; STOPPING when cancelled.

    Runs as a task on the service's event loop: if that loop is blocked, no ping
    goes out either, which is the point.
    """
    notifier = notifier or Notifier()
    if not notifier.enabled:
        return
    period = min(notifier.watchdog_s / 2, STATUS_PERIOD_S) if notifier.watchdog_s else STATUS_PERIOD_S
    notifier.ready(status_line(service))
    try:
        while True:
            await asyncio.sleep(period)
            if notifier.watchdog_s is not None and service.progress():
                notifier.watchdog()
            notifier.status(status_line(service))
    finally:
        notifier.stopping()
        notifier.close()
