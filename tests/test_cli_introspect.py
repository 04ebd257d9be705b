"""`archer topics`, `archer echo` and `archer status` against a live service."""

from __future__ import annotations

import pytest

import asyncio
import json
import subprocess
import sys
import threading
import time

from onboard.contracts import messages as m
from onboard.contracts.topics import TOPICS
from services.cli.main import main
from services.runtime.router import RouterService
from services.runtime.zenoh_session import open_session

NS = "archer/clitest"


def test_topics_json_lists_the_table(capsys):
    assert main(["topics", "--json", "--namespace", NS]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert {r["name"] for r in rows} == set(TOPICS)
    assert all(r["key"].startswith(NS + "/") for r in rows)


def test_echo_and_status_see_a_running_service(zenoh_router):
    service = RouterService(ns=NS, endpoint=zenoh_router)
    service.zenoh_mode = "peer"  # the test fixture already serves the endpoint
    # run_service() installs signal handlers, which only the main thread may do,
    # so the service's coroutine runs on a loop of its own thread here.
    loop = asyncio.new_event_loop()
    runner = threading.Thread(target=loop.run_until_complete, args=(service.run(),), daemon=True)
    runner.start()
    try:
        deadline = time.monotonic() + 10
        while service.state != "running":
            assert time.monotonic() < deadline
            time.sleep(0.05)
        status = subprocess.run(
            [sys.executable, "-m", "services.cli.main", "status", "--json", "--endpoint", zenoh_router, "--namespace", NS],
            capture_output=True, text=True, timeout=30,
        )
        assert status.returncode == 0, status.stderr
        assert json.loads(status.stdout)["router"]["state"] == "running"

        echo = subprocess.Popen(
            [sys.executable, "-m", "services.cli.main", "echo", "goal", "--count", "1", "--timeout", "20",
             "--endpoint", zenoh_router, "--namespace", NS],
            stdout=subprocess.PIPE, text=True,
        )
        publisher = open_session(zenoh_router, "peer")
        try:
            while echo.poll() is None:  # keep offering until the echo's subscription is up
                publisher.put(TOPICS["goal"].key(NS), m.encode(m.Goal(position=[1.5, -2.0])))
                time.sleep(0.1)
        finally:
            publisher.close()
        out = echo.stdout.read()
        assert echo.returncode == 0
        assert json.loads(out.splitlines()[0])["position"] == [1.5, -2.0]
    finally:
        service.request_stop()
        runner.join(10)
    assert not runner.is_alive()


# real time: loops at their rate, processes and Zenoh over loopback share two loaded cores
pytestmark = pytest.mark.timing_sensitive(reason="real-time loops, processes or Zenoh over loopback on a shared host")
