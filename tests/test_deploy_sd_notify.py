"""The notify protocol against a real AF_UNIX datagram socket, as systemd listens on one."""

from __future__ import annotations

import asyncio
import os
import socket
import threading
import time

import pytest

from services.runtime.service import Service
from services.runtime.sd_notify import Notifier, socket_address

WATCHDOG_USEC = 100_000  # pings every 50 ms
READY_TIMEOUT_S = 10.0


class ManagerSocket:
    """The service manager's end: a thread collects datagrams as ``{key: value}`` dicts."""

    def __init__(self, address: str) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(socket_address(address))
        self.sock.settimeout(0.05)
        self.messages: list[dict[str, str]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._collect, daemon=True)
        self._thread.start()

    def _collect(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                continue
            self.messages.append(dict(line.split("=", 1) for line in data.decode().splitlines()))

    def count(self, key: str) -> int:
        return sum(1 for m in list(self.messages) if key in m)

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.sock.close()


@pytest.mark.parametrize("abstract", [False, True])
def test_notifier_sends_datagrams(tmp_path, abstract):
    address = f"@archer-test-{os.getpid()}-{time.monotonic_ns()}" if abstract else str(tmp_path / "notify")
    manager = ManagerSocket(address)
    try:
        notifier = Notifier({"NOTIFY_SOCKET": address, "WATCHDOG_USEC": str(WATCHDOG_USEC)})
        assert notifier.enabled and notifier.watchdog_s == pytest.approx(0.1)
        assert notifier.ready("up")
        assert notifier.watchdog()
        assert notifier.status("line one\nline two")
        notifier.close()
        time.sleep(0.2)
        assert manager.messages == [{"READY": "1", "STATUS": "up"}, {"WATCHDOG": "1"}, {"STATUS": "line one line two"}]
    finally:
        manager.close()


def test_notifier_is_inert_without_a_manager_and_ignores_a_parents_watchdog():
    assert not Notifier({}).enabled and not Notifier({}).ready()
    other_pid = {"NOTIFY_SOCKET": "/nonexistent", "WATCHDOG_USEC": "1000", "WATCHDOG_PID": str(os.getpid() + 1)}
    assert Notifier(other_pid).watchdog_s is None
    assert not Notifier({"NOTIFY_SOCKET": "/nonexistent/socket"}).ready()  # no manager: no crash


class StallingService(Service):
    """Makes progress until told to stall, as a hard-rate thread that stopped ticking."""

    name = "stalling"
    stalled = False

    def progress(self) -> bool:
        return not self.stalled


def test_runtime_pings_ready_then_watchdog_only_while_progressing(tmp_path, monkeypatch, zenoh_router):
    address = str(tmp_path / "notify")
    manager = ManagerSocket(address)
    monkeypatch.setenv("NOTIFY_SOCKET", address)
    monkeypatch.setenv("WATCHDOG_USEC", str(WATCHDOG_USEC))
    monkeypatch.delenv("WATCHDOG_PID", raising=False)

    async def scenario() -> None:
        service = StallingService(ns="archer/test", endpoint=zenoh_router)
        task = asyncio.create_task(service.run())
        try:
            deadline = time.monotonic() + READY_TIMEOUT_S  # opening the session takes a while under load
            while not manager.messages and time.monotonic() < deadline:
                await asyncio.sleep(0.02)
            assert manager.messages[0]["READY"] == "1" and manager.messages[0]["STATUS"].startswith("running")
            pings_at_ready = manager.count("WATCHDOG")
            await asyncio.sleep(0.5)
            assert manager.count("WATCHDOG") - pings_at_ready >= 5  # ~10 expected in 0.5 s
            service.stalled = True
            await asyncio.sleep(0.1)  # a ping already scheduled may still go out
            pings_before, statuses_before = manager.count("WATCHDOG"), manager.count("STATUS")
            await asyncio.sleep(0.4)
            assert manager.count("WATCHDOG") == pings_before  # stalled: no ping
            assert manager.count("STATUS") > statuses_before  # the status still refreshes
        finally:
            service.stopping.set()
            await asyncio.wait_for(task, 5.0)
        await asyncio.sleep(0.2)
        assert manager.messages[-1] == {"STOPPING": "1"}

    try:
        asyncio.run(asyncio.wait_for(scenario(), 30))
    finally:
        manager.close()


class CostlyStatus(Service):
    name = "costly"
    extra_calls = 0

    def status_extra(self) -> dict[str, float]:
        self.extra_calls += 1
        return {}


def test_the_status_line_leaves_status_extra_alone():
    """systemd's STATUS goes out every second: it must not run a service's costly extras."""
    from services.runtime.sd_notify import status_line

    service = CostlyStatus(ns="archer/test")
    service.rate("tick").tick()
    service.fail("boom")
    assert status_line(service) == "starting; tick 0 Hz; errors 1; last error: boom"
    assert service.extra_calls == 0


# real time: loops at their rate, processes and Zenoh over loopback share two loaded cores
pytestmark = pytest.mark.timing_sensitive(reason="real-time loops, processes or Zenoh over loopback on a shared host")
